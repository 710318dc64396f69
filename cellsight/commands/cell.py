"""Running and recording a cell: ``run``, ``demo``, ``record``, ``replay``."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    CellConfigOpt,
    DurationOpt,
    FoxgloveOpt,
    FoxglovePortOpt,
    VerboseOpt,
    fail,
    load,
    load_cell,
    open_bus,
    setup_logging,
    stderr,
    stop_event,
)
from cellsight.transport_flags import CellOpt, TransportFlags, transport_options


@transport_options
def record(
    out: Annotated[
        Path,
        typer.Option(
            "--out",
            help="MCAP file to write (never overwritten: if it exists, the recording goes to NAME.1.mcap, NAME.2.mcap, ...)",
        ),
    ],
    keys_: Annotated[
        list[str] | None, typer.Option("--keys", help="key expressions to record (default: the whole cell)")
    ] = None,
    max_image_hz: Annotated[float | None, typer.Option(help="record images at most this often per camera")] = None,
    duration: DurationOpt = None,
    cell: CellOpt = None,
    cell_config: CellConfigOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Record bus traffic to MCAP (lz4 chunks, Foxglove schemas embedded) until Ctrl-C / SIGTERM."""
    from cellsight.record import Recorder

    setup_logging(verbose)
    cfg = load(cell_config)
    stop = stop_event()
    with open_bus(cfg, cell, transport) as bus:
        rec = Recorder(bus, out, keys_, max_image_hz, {"config": cfg.to_toml()})
        stop.wait(duration)
        rec.close()
    parts = ", ".join(str(p) for p in rec.parts)
    refused = sum(rec.refused.values())
    stderr().print(f"{parts}: {rec.messages} messages ({rec.thinned} images thinned, {refused} refused)")
    for (key, reason), n in sorted(rec.refused.items()):
        stderr().print(f"[yellow]refused:[/] {n} on {key} ({reason})")
    for gap in rec.gaps:
        stderr().print(f"[yellow]gap:[/] nothing from {gap.camera} for {gap.seconds:.1f} s (marked in the log)")
    if rec.failures:
        raise fail(
            f"recording interrupted {len(rec.failures)} time(s), {rec.lost} messages not recorded; last error: {rec.failures[-1]}",
            1,
        )
    if refused:
        raise fail(f"{refused} messages refused (malformed or implausible, listed above); the log holds the rest", 1)


def _run(
    cfg,
    run_dir: Path,
    duration: float | None,
    record: Path | None,
    max_image_hz: float | None,
    live: bool,
    foxglove_port: int | None = None,
) -> None:
    """Start the cell under the launcher with an optional live status table."""
    from rich.live import Live

    from cellsight.launch import run_cell
    from cellsight.status import StatusBoard
    from schemas.bus import Bus
    from schemas.errors import SchemaError

    stop = stop_event()
    board_bus = board = live_view = bridge = None

    def tick(sup) -> None:
        nonlocal board_bus, board, bridge
        if not live and foxglove_port is None:
            return  # nobody to show: no session, no decoding of the cell's messages
        if board_bus is None:
            try:  # the router comes up with the cell; join it once it is there
                board_bus = Bus(cfg.transport, cfg.cell.name)
            except SchemaError:
                return
            board = StatusBoard(board_bus) if live else None
            if foxglove_port is not None:
                from cellsight.live import FoxgloveBridge

                bridge = FoxgloveBridge(board_bus, foxglove_port)
                stderr().print(f"Foxglove live view: open ws://127.0.0.1:{bridge.port} in the Foxglove app")
        if live_view is not None and board is not None:
            live_view.update(board.table())

    try:
        if live:
            with Live(refresh_per_second=2, console=stderr()) as live_view:
                run_cell(
                    cfg, run_dir, duration_s=duration, record=record, max_image_hz=max_image_hz, stop=stop, on_tick=tick
                )
        else:
            run_cell(
                cfg, run_dir, duration_s=duration, record=record, max_image_hz=max_image_hz, stop=stop, on_tick=tick
            )
    finally:
        if bridge is not None:
            bridge.close()
        if board is not None:
            board.close()
        if board_bus is not None:
            board_bus.close()


def run_cmd(
    cell_config: Annotated[
        Path | None, typer.Argument(help="cell config TOML (default: the simulated demo cell)")
    ] = None,
    out: Annotated[Path | None, typer.Option("--out", help="run folder: config used, logs, state, recording")] = None,
    record: Annotated[bool, typer.Option("--record/--no-record", help="record the cell to OUT/log.mcap")] = False,
    max_image_hz: Annotated[float | None, typer.Option(help="when recording: images per camera per second")] = 2.0,
    duration: Annotated[float | None, typer.Option(help="stop after this many seconds (default: until Ctrl-C)")] = None,
    foxglove: FoxgloveOpt = False,
    foxglove_port: FoxglovePortOpt = 8765,
    verbose: VerboseOpt = False,
) -> None:
    """Run a cell: router, one driver per camera, estimator, recognition (and recorder), supervised."""
    setup_logging(verbose)
    cfg = load_cell(cell_config)
    run_dir = out or Path("runs") / time.strftime("run-%Y%m%d-%H%M%S")
    _run(
        cfg,
        run_dir,
        duration,
        run_dir / "log.mcap" if record else None,
        max_image_hz,
        sys.stderr.isatty(),
        foxglove_port if foxglove else None,
    )
    stderr().print(f"run folder: {run_dir}")


def demo(
    duration: Annotated[float, typer.Option(help="seconds of the demo cell's scenario to run")] = 30.0,
    out: Annotated[Path, typer.Option("--out", help="folder for the log, config, summary and pictures")] = Path(
        "runs/demo"
    ),
    max_image_hz: Annotated[float, typer.Option(help="images per camera per second in the log")] = 0.5,
    foxglove: FoxgloveOpt = False,
    foxglove_port: FoxglovePortOpt = 8765,
    verbose: VerboseOpt = False,
) -> None:
    """Run the built-in simulated cell for a while, then report its accuracy against ground truth."""
    from cellsight.evaluation.report import write_report
    from cellsight.scenario_config import demo_config

    setup_logging(verbose)
    cfg = demo_config()
    if duration > 0:
        from drivers.sim.scenario import load_scenario

        scenario_len = load_scenario(cfg.cell.scenario).duration_s
        if duration > scenario_len:
            raise fail(f"--duration {duration:g} is longer than the demo scenario ({scenario_len:g} s)", 2)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "log.mcap"
    _run(cfg, out, duration, log_path, max_image_hz, sys.stderr.isatty(), foxglove_port if foxglove else None)
    summary = write_report(log_path, cfg.cell.name, out)
    from rich.console import Console
    from rich.markdown import Markdown

    Console().print(Markdown((out / "summary.md").read_text()))
    typer.echo(f"wrote {out}/: log.mcap, config.toml, summary.json, summary.md, top_view.png, errors.png")
    if not summary.log_complete:
        stderr().print("[yellow]warning:[/] the log was not complete; the summary covers what was readable")


@transport_options
def replay_cmd(
    log_file: Annotated[Path, typer.Argument(help="MCAP log written by cellsight record / demo")],
    rate: Annotated[float, typer.Option(help="playback speed (2 = twice as fast)")] = 1.0,
    all_keys: Annotated[bool, typer.Option("--all", help="also republish recorded estimates, tf and objects")] = False,
    cell_config: CellConfigOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Republish a log with its original timing, so the estimator can be driven by a recording."""
    from drivers.replay import replay

    setup_logging(verbose)
    if not log_file.is_file():
        raise fail(f"{log_file}: no such log file", 2)
    if not rate > 0:
        raise fail(f"--rate must be positive, got {rate}", 2)
    cfg = load(cell_config)
    stop = stop_event()
    with open_bus(cfg, None, transport) as bus:
        result = replay(bus, log_file, rate, all_keys, stop)
    stderr().print(f"{log_file}: {result.published} messages republished, {result.skipped} recorded estimates skipped")
    for (key, reason), n in sorted(result.read.refused.items()):
        stderr().print(f"[yellow]skipped:[/] {n} messages on {key} ({reason})")
    if result.read.stopped_early:
        stderr().print(f"[yellow]warning:[/] the log is {result.read.stopped_early}; republished what came before")
