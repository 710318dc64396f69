"""What every command shares: logging, the error console, loading the cell config, the bus, the
options several commands take. Heavy imports stay inside the functions so that ``--help`` is instant."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated

import typer

from cellsight.transport_flags import TransportFlags

RECOGNITION_NICE = 5
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="debug logging")]
DurationOpt = Annotated[float | None, typer.Option(help="stop after this many seconds")]
CameraIdOpt = Annotated[
    str, typer.Option("--camera", help="camera id (a [[cameras]] entry of the cell config, or any id)")
]

FoxgloveOpt = Annotated[
    bool, typer.Option("--foxglove", help="serve the live bus to the Foxglove app over WebSocket (loopback)")
]
FoxglovePortOpt = Annotated[int, typer.Option(help="WebSocket port of the Foxglove live view")]
CellConfigOpt = Annotated[
    Path | None, typer.Option("--cell-config", help="cell config TOML (default: the simulated demo cell)")
]
ScenarioOpt = Annotated[
    Path | None, typer.Option("--scenario", help="simulated cell scenario TOML (default: built-in demo cell)")
]


def setup_logging(verbose: bool) -> None:
    from rich.logging import RichHandler

    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(name)s: %(message)s",
        handlers=[RichHandler(show_path=False, console=stderr())],
        force=True,
    )


def stderr():
    from rich.console import Console

    # Wrapped at a terminal's width only on a terminal: a path in an error must stay one string
    # for whoever reads the output (a log, a test, grep).
    return Console(stderr=True, soft_wrap=not sys.stderr.isatty())


def fail(message: str, code: int) -> typer.Exit:
    stderr().print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code)


def load(config_file: Path | None):
    """Cell config from a file (None: defaults)."""
    from cellsight.config import load_config

    return load_config(config_file)


def load_cell(cell_config: Path | None, scenario: Path | None = None):
    """The cell config, completed from the scenario (built-in demo when neither is given)."""
    from cellsight.scenario_config import complete

    cfg = load(cell_config)
    if scenario is not None:
        cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"scenario": scenario}), "cameras": []})
    return complete(cfg)


def drive(
    cfg, publish_images: bool, camera: str, make_source, transport: TransportFlags, duration: float | None
) -> None:
    """Serve one camera on the bus until its source ends, ``duration`` or Ctrl-C / SIGTERM.
    ``make_source(bus)`` gives the frame source (a ROS 2 camera's reads the same session)."""
    from drivers.service import DriverService, use_opencv_threads

    use_opencv_threads(cfg.markers.opencv_threads)
    stop = stop_event()
    with open_bus(cfg, None, transport) as bus:
        DriverService(bus, make_source(bus), camera, cfg.markers, publish_images=publish_images).run(stop, duration)


def camera_section(cell_config: Path | None, camera: str, source: str, verbose: bool):
    """A driver command's start: logging set up, the cell config, and its section of ``camera``
    (or a default one of the given source)."""
    from drivers.config import CameraConfig

    setup_logging(verbose)
    cfg = load(cell_config)
    return cfg, next((c for c in cfg.cameras if c.id == camera), None) or CameraConfig(id=camera, source=source)


def stop_event():
    """An event set by Ctrl-C or SIGTERM, so long-running commands shut down cleanly."""
    import signal
    import threading

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def open_bus(cell_cfg, cell: str | None, transport: TransportFlags):
    """A bus session from the cell config's transport with the command's flags on top."""
    from schemas.bus import Bus

    return Bus(transport.apply(cell_cfg.transport), cell or cell_cfg.cell.name, cell_cfg.wire)
