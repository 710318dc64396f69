"""``cellsight bus``, ``router`` and ``status``: looking at the zenoh bus and what runs on it."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    CellConfigOpt,
    VerboseOpt,
    fail,
    load,
    open_bus,
    setup_logging,
)
from cellsight.transport_flags import CellOpt, ConnectOpt, ListenOpt, TransportFlags, ZenohConfigOpt, transport_options

bus_app = typer.Typer(help="Look at the zenoh bus.", no_args_is_help=True)


@bus_app.command("echo")
@transport_options
def bus_echo(
    key: Annotated[str, typer.Argument(help="key expression, e.g. cellsight/demo/cam1/markers or cellsight/demo/**")],
    once: Annotated[bool, typer.Option("--once", help="print one message and exit")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object per line")] = False,
    timeout: Annotated[float | None, typer.Option(help="give up after this many seconds (exit 1)")] = None,
    cell_config: Annotated[Path | None, typer.Option("--cell-config", help="cell config TOML")] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Subscribe, decode and print messages, like ``ros2 topic echo``."""
    from cellsight.echo import format_message

    setup_logging(verbose)
    cfg = load(cell_config)
    with open_bus(cfg, None, transport) as bus:
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
        raise fail(f"no message on {key} within {timeout} s", 1)


@bus_app.command("list")
@transport_options
def bus_list(
    duration: Annotated[float, typer.Option(help="seconds to listen")] = 2.0,
    cell: CellOpt = None,
    cell_config: Annotated[Path | None, typer.Option("--cell-config", help="cell config TOML")] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Live keys of a cell with their message rates, and the liveliness tokens held."""
    from rich.console import Console
    from rich.table import Table

    from cellsight.echo import sample_rates

    setup_logging(verbose)
    cfg = load(cell_config)
    with open_bus(cfg, cell, transport) as bus:
        rates, bad = sample_rates(bus, duration)
        alive = bus.alive()
    table = Table(title=f"cell {bus.cell}: keys seen in {duration:g} s")
    table.add_column("key", no_wrap=True)
    for col in ("type", "messages", "rate (Hz)", "malformed"):
        table.add_column(col, no_wrap=True)
    for key, (type_name, count) in sorted(rates.items()):
        table.add_row(key, type_name, str(count), f"{count / duration:.1f}", str(bad.get(key, 0)))
    console = Console(width=max(Console().width, 140))
    console.print(table)
    console.print("alive: " + (", ".join(alive) if alive else "(no liveliness tokens)"))


def router(
    listen: ListenOpt = None,
    connect: ConnectOpt = None,
    config: ZenohConfigOpt = None,
    shared_memory: Annotated[
        bool,
        typer.Option(
            "--shared-memory/--no-shared-memory",
            help="pass frames between processes on this host through shared memory (off: a host that shares /dev/shm with another, e.g. a network namespace)",
        ),
    ] = True,
    verbose: VerboseOpt = False,
) -> None:
    """Run a zenoh router (default: tcp/127.0.0.1:7447, loopback only) until Ctrl-C; with --connect,
    peered with another router (an edge host's, with the cell's)."""
    from schemas.bus import DEFAULT_ROUTER, TransportConfig, open_session

    setup_logging(verbose)
    # A config file (the secure profile's router.json5) brings its own listen endpoints.
    transport = TransportConfig.router(
        list(listen) if listen else ([] if config else [DEFAULT_ROUTER]), list(connect or [])
    )
    transport = transport.model_copy(update={"zenoh_config": config, "shared_memory": shared_memory})
    session = open_session(transport)
    logging.getLogger("cellsight.router").info(
        "router listening on %s", ", ".join(transport.listen) or f"the endpoints of {config}"
    )
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()


@transport_options
def status(
    duration: Annotated[float, typer.Option(help="seconds to listen before printing")] = 2.0,
    cell: CellOpt = None,
    cell_config: CellConfigOpt = None,
    transport: TransportFlags = TransportFlags(),
) -> None:
    """Who is alive, driver rates and each camera's estimator state."""
    from rich.console import Console

    from cellsight.status import StatusBoard

    cfg = load(cell_config)
    with open_bus(cfg, cell, transport) as bus:
        board = StatusBoard(bus)
        time.sleep(duration)
        Console(width=140).print(board.table(bus.alive()))
        board.close()
