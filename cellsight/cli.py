"""The ``cellsight`` command. Parses, calls library code, prints, maps errors to exit codes.

Imports of heavy components happen inside the commands so that ``--help`` is instant.
Exit codes: 0 ok, 1 nothing received / check failed, 2 bad configuration or input, 3 bus error.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from cellsight.transport_flags import CellOpt, ConnectOpt, ListenOpt, ModeOpt, ZenohConfigOpt, transport_from_flags

app = typer.Typer(help="cellsight: self-aligning multi-camera work-cell monitoring.", no_args_is_help=True)
config_app = typer.Typer(help="Check and show cell configurations.", no_args_is_help=True)
bus_app = typer.Typer(help="Look at the zenoh bus.", no_args_is_help=True)
app.add_typer(config_app, name="config")
app.add_typer(bus_app, name="bus")

VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="debug logging")]


def _setup_logging(verbose: bool) -> None:
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(name)s: %(message)s",
        handlers=[RichHandler(show_path=False, console=_stderr())],
        force=True,
    )


def _stderr():
    from rich.console import Console

    return Console(stderr=True)


def _fail(message: str, code: int) -> typer.Exit:
    _stderr().print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code)


def _load(config_file: Path | None):
    """Cell config from a file (None: defaults), turning errors into exit code 2."""
    from cellsight.config import load_config
    from cellsight.errors import ConfigError

    try:
        return load_config(config_file)
    except ConfigError as exc:
        raise _fail(str(exc), 2) from None


def _bus(cell_cfg, cell: str | None, mode, connect, listen, zenoh_config):
    from schemas.bus import Bus
    from schemas.errors import SchemaError

    try:
        transport = transport_from_flags(cell_cfg.transport, mode, connect, listen, zenoh_config)
        return Bus(transport, cell or cell_cfg.cell.name)
    except (SchemaError, ValueError) as exc:
        raise _fail(str(exc), 3) from None


# ---------------------------------------------------------------- config


@config_app.command("check")
def config_check(file: Annotated[Path, typer.Argument(help="cell config TOML")]) -> None:
    """Validate a cell config; print it with defaults filled in, or say what is wrong (exit 2)."""
    cfg = _load(file)
    typer.echo(cfg.to_toml())
    _stderr().print(f"[green]{file}: ok[/] ({len(cfg.cameras)} cameras, {len(cfg.estimator.anchors)} anchors)")


@config_app.command("show")
def config_show(file: Annotated[Optional[Path], typer.Argument(help="cell config TOML (default: built-in)")] = None) -> None:
    """Print the effective configuration (defaults + file + CELLSIGHT__* environment) as TOML."""
    typer.echo(_load(file).to_toml())


# ---------------------------------------------------------------- bus


@bus_app.command("echo")
def bus_echo(
    key: Annotated[str, typer.Argument(help="key expression, e.g. cellsight/demo/cam1/markers or cellsight/demo/**")],
    once: Annotated[bool, typer.Option("--once", help="print one message and exit")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object per line")] = False,
    timeout: Annotated[Optional[float], typer.Option(help="give up after this many seconds (exit 1)")] = None,
    cell_config: Annotated[Optional[Path], typer.Option("--cell-config", help="cell config TOML")] = None,
    mode: ModeOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    config: ZenohConfigOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Subscribe, decode and print messages, like ``ros2 topic echo``."""
    from cellsight.echo import format_message

    _setup_logging(verbose)
    cfg = _load(cell_config)
    with _bus(cfg, None, mode, connect, listen, config) as bus:
        sub = bus.subscribe(key, capacity=64, ring=True)
        deadline = None if timeout is None else time.monotonic() + timeout
        printed = 0
        try:
            while True:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                item = sub.get(timeout_s=0.2 if left is None else min(0.2, left))
                if item is None:
                    continue
                typer.echo(format_message(item.key, item.msg, as_json))
                sys.stdout.flush()
                printed += 1
                if once:
                    break
        except KeyboardInterrupt:
            pass
    if printed == 0:
        raise _fail(f"no message on {key} within {timeout} s", 1)


@bus_app.command("list")
def bus_list(
    duration: Annotated[float, typer.Option(help="seconds to listen")] = 2.0,
    cell: CellOpt = None,
    cell_config: Annotated[Optional[Path], typer.Option("--cell-config", help="cell config TOML")] = None,
    mode: ModeOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    config: ZenohConfigOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Live keys of a cell with their message rates, and the liveliness tokens held."""
    from rich.console import Console
    from rich.table import Table

    from cellsight.echo import sample_rates

    _setup_logging(verbose)
    cfg = _load(cell_config)
    with _bus(cfg, cell, mode, connect, listen, config) as bus:
        rates, bad = sample_rates(bus, duration)
        alive = bus.alive()
    table = Table(title=f"cell {bus.cell}: keys seen in {duration:g} s")
    for col in ("key", "type", "messages", "rate (Hz)", "malformed"):
        table.add_column(col)
    for key, (type_name, count) in sorted(rates.items()):
        table.add_row(key, type_name, str(count), f"{count / duration:.1f}", str(bad.get(key, 0)))
    console = Console()
    console.print(table)
    console.print("alive: " + (", ".join(alive) if alive else "(no liveliness tokens)"))


@app.command("router")
def router(
    listen: ListenOpt = None,
    config: ZenohConfigOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Run a zenoh router (default: tcp/127.0.0.1:7447, loopback only) until Ctrl-C."""
    from schemas.bus import DEFAULT_ROUTER, TransportConfig, open_session
    from schemas.errors import SchemaError

    _setup_logging(verbose)
    transport = TransportConfig.router(list(listen) if listen else [DEFAULT_ROUTER])
    if config is not None:
        transport = transport.model_copy(update={"zenoh_config": config})
    try:
        session = open_session(transport)
    except SchemaError as exc:
        raise _fail(str(exc), 3) from None
    logging.getLogger("cellsight.router").info("router listening on %s", ", ".join(transport.listen))
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()


def main() -> None:
    app()


if __name__ == "__main__":
    main()
