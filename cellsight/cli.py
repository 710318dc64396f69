"""The ``cellsight`` command. Commands parse, call library code and print; errors become exit
codes in one place, ``EXIT_CODES``, applied to every command by the top-level group.

Imports of heavy components happen inside the commands so that ``--help`` is instant.
Exit codes: 0 ok, 1 nothing received / a run or check failed, 2 bad configuration or input,
3 bus error.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import click
import typer
from typer.core import TyperGroup

from cellsight.errors import CellsightError, ConfigError, RunError
from cellsight.transport_flags import CellOpt, ConnectOpt, ListenOpt, TransportFlags, ZenohConfigOpt, transport_options
from drivers.errors import DriverError  # noqa: E402  (the packages' exception roots: small modules)
from estimator.errors import EstimatorError  # noqa: E402
from recognition.errors import RecognitionError  # noqa: E402
from schemas.errors import BusError, SchemaError  # noqa: E402

#: Exception -> exit code, first match wins: the one place errors become exit codes.
EXIT_CODES: tuple[tuple[type[BaseException], int], ...] = (
    (BusError, 3),  # the zenoh session could not be opened or used
    (RunError, 1),  # a cell or a recording could not run to the end
    (ConfigError, 2),
    (SchemaError, 2),  # bad keys, undecodable payloads or logs
    (DriverError, 2),  # no device, bad scenario or image
    (RecognitionError, 2),  # bad cloud, mesh or model database
    (EstimatorError, 2),
    (CellsightError, 1),
    (OSError, 2),  # a file that cannot be read or written
    (ValueError, 2),  # a flag value pydantic refused (e.g. --mode)
)


def exit_code(exc: BaseException) -> int | None:
    """The exit code ``EXIT_CODES`` gives an exception, None for one it does not know (a bug)."""
    return next((code for kind, code in EXIT_CODES if isinstance(exc, kind)), None)


class _Commands(TyperGroup):
    """The top-level group: runs the command and turns a known error into its message and exit code."""

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except click.exceptions.ClickException:
            raise
        except Exception as exc:
            code = exit_code(exc)
            if code is None:
                raise
            raise _fail(str(exc), code) from None


app = typer.Typer(
    cls=_Commands, help="cellsight: self-aligning multi-camera work-cell monitoring.", no_args_is_help=True
)
config_app = typer.Typer(help="Check and show cell configurations.", no_args_is_help=True)
bus_app = typer.Typer(help="Look at the zenoh bus.", no_args_is_help=True)
app.add_typer(config_app, name="config")
app.add_typer(bus_app, name="bus")
security_app = typer.Typer(help="The secure deployment profile: mutual TLS and access control.", no_args_is_help=True)
app.add_typer(security_app, name="security")

RECOGNITION_NICE = 5
VerboseOpt = Annotated[bool, typer.Option("--verbose", "-v", help="debug logging")]
DurationOpt = Annotated[Optional[float], typer.Option(help="stop after this many seconds")]
CameraIdOpt = Annotated[
    str, typer.Option("--camera", help="camera id (a [[cameras]] entry of the cell config, or any id)")
]


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

    # Wrapped at a terminal's width only on a terminal: a path in an error must stay one string
    # for whoever reads the output (a log, a test, grep).
    return Console(stderr=True, soft_wrap=not sys.stderr.isatty())


def _fail(message: str, code: int) -> typer.Exit:
    _stderr().print(f"[bold red]error:[/] {message}", highlight=False)
    return typer.Exit(code)


def _load(config_file: Path | None):
    """Cell config from a file (None: defaults)."""
    from cellsight.config import load_config

    return load_config(config_file)


def _load_cell(cell_config: Path | None, scenario: Path | None = None):
    """The cell config, completed from the scenario (built-in demo when neither is given)."""
    from cellsight.scenario_config import complete

    cfg = _load(cell_config)
    if scenario is not None:
        cfg = cfg.model_copy(update={"cell": cfg.cell.model_copy(update={"scenario": scenario}), "cameras": []})
    return complete(cfg)


def _drive(
    cfg, publish_images: bool, camera: str, make_source, transport: TransportFlags, duration: float | None
) -> None:
    """Serve one camera on the bus until its source ends, ``duration`` or Ctrl-C / SIGTERM.
    ``make_source(bus)`` gives the frame source (a ROS 2 camera's reads the same session)."""
    from drivers.service import DriverService, use_opencv_threads

    use_opencv_threads(cfg.markers.opencv_threads)
    stop = _stop_event()
    with _bus(cfg, None, transport) as bus:
        DriverService(bus, make_source(bus), camera, cfg.markers, publish_images=publish_images).run(stop, duration)


def _camera_section(cell_config: Path | None, camera: str, source: str, verbose: bool):
    """A driver command's start: logging set up, the cell config, and its section of ``camera``
    (or a default one of the given source)."""
    from drivers.config import CameraConfig

    _setup_logging(verbose)
    cfg = _load(cell_config)
    return cfg, next((c for c in cfg.cameras if c.id == camera), None) or CameraConfig(id=camera, source=source)


def _stop_event():
    """An event set by Ctrl-C or SIGTERM, so long-running commands shut down cleanly."""
    import signal
    import threading

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _bus(cell_cfg, cell: str | None, transport: TransportFlags):
    """A bus session from the cell config's transport with the command's flags on top."""
    from schemas.bus import Bus

    return Bus(transport.apply(cell_cfg.transport), cell or cell_cfg.cell.name, cell_cfg.wire)


# ---------------------------------------------------------------- config


@config_app.command("check")
def config_check(file: Annotated[Path, typer.Argument(help="cell config TOML")]) -> None:
    """Validate a cell config; print it with defaults filled in, or say what is wrong (exit 2)."""
    cfg = _load(file)
    typer.echo(cfg.to_toml())
    _stderr().print(f"[green]{file}: ok[/] ({len(cfg.cameras)} cameras, {len(cfg.estimator.anchors)} anchors)")


@config_app.command("show")
def config_show(
    file: Annotated[Optional[Path], typer.Argument(help="cell config TOML (default: built-in)")] = None,
) -> None:
    """Print the effective configuration (defaults + file + CELLSIGHT__* environment) as TOML."""
    typer.echo(_load(file).to_toml())


@config_app.command("docs")
def config_docs() -> None:
    """Print every configuration section and field with its default, as Markdown (docs/configuration.md)."""
    from cellsight.config_docs import markdown

    typer.echo(markdown(), nl=False)


# ---------------------------------------------------------------- security


@security_app.command("init")
def security_init(
    directory: Annotated[Path, typer.Argument(help="new directory for the CA, certificates and zenoh configs")],
    cell: CellOpt = None,
    listen: Annotated[str, typer.Option("--listen", help="the router's TLS endpoint")] = "tls/127.0.0.1:7447",
    host: Annotated[
        Optional[list[str]],
        typer.Option(
            "--host", help="name or address clients reach the router by (repeatable; default 127.0.0.1 and localhost)"
        ),
    ] = None,
    ros2_domain: Annotated[
        Optional[int],
        typer.Option(
            "--ros2-domain",
            min=0,
            max=232,
            help="let this ROS 2 domain's rmw_zenoh traffic through ([ros2] enabled); default: none",
        ),
    ] = None,
) -> None:
    """Make a certificate authority, certificates for the router and each role, and their zenoh configs.

    Then: `cellsight router --config DIR/router.json5`, and each process with `--config DIR/ROLE.json5`
    (driver, estimator, recognition, recorder, viewer; a ROS 2 robot's zenoh router or node uses
    robot.pem / robot.key). Keep DIR/ca.key offline once done.
    """
    from schemas.security import EDGE_LISTEN, PUBLISH, PUBLISH_ROS2, write_profile

    profile = write_profile(
        directory, cell or "demo", listen, tuple(host) if host else ("127.0.0.1", "localhost"), ros2_domain
    )
    typer.echo(f"router:      cellsight router --config {profile.router_config}")
    for role, path in profile.role_configs.items():
        topics = PUBLISH[role] + (
            [f"ROS 2 {ros2_domain}/{t}" for t in PUBLISH_ROS2.get(role, [])] if ros2_domain is not None else []
        )
        typer.echo(
            f"{role + ':':12} --config {path}   publishes: {', '.join(topics) or 'nothing (subscribe and query only)'}"
        )
    typer.echo(
        f'edge host:   [cell] router_config = "{profile.edge_router_config}", its drivers --config {profile.role_configs["driver"]} '
        f"--connect {EDGE_LISTEN}   publishes: what a driver may"
    )


# ---------------------------------------------------------------- bus


@bus_app.command("echo")
@transport_options
def bus_echo(
    key: Annotated[str, typer.Argument(help="key expression, e.g. cellsight/demo/cam1/markers or cellsight/demo/**")],
    once: Annotated[bool, typer.Option("--once", help="print one message and exit")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object per line")] = False,
    timeout: Annotated[Optional[float], typer.Option(help="give up after this many seconds (exit 1)")] = None,
    cell_config: Annotated[Optional[Path], typer.Option("--cell-config", help="cell config TOML")] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Subscribe, decode and print messages, like ``ros2 topic echo``."""
    from cellsight.echo import format_message

    _setup_logging(verbose)
    cfg = _load(cell_config)
    with _bus(cfg, None, transport) as bus:
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
@transport_options
def bus_list(
    duration: Annotated[float, typer.Option(help="seconds to listen")] = 2.0,
    cell: CellOpt = None,
    cell_config: Annotated[Optional[Path], typer.Option("--cell-config", help="cell config TOML")] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Live keys of a cell with their message rates, and the liveliness tokens held."""
    from rich.console import Console
    from rich.table import Table

    from cellsight.echo import sample_rates

    _setup_logging(verbose)
    cfg = _load(cell_config)
    with _bus(cfg, cell, transport) as bus:
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


@app.command("router")
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

    _setup_logging(verbose)
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


FoxgloveOpt = Annotated[
    bool, typer.Option("--foxglove", help="serve the live bus to the Foxglove app over WebSocket (loopback)")
]
FoxglovePortOpt = Annotated[int, typer.Option(help="WebSocket port of the Foxglove live view")]
CellConfigOpt = Annotated[
    Optional[Path], typer.Option("--cell-config", help="cell config TOML (default: the simulated demo cell)")
]
ScenarioOpt = Annotated[
    Optional[Path], typer.Option("--scenario", help="simulated cell scenario TOML (default: built-in demo cell)")
]
driver_app = typer.Typer(help="Sensor driver processes.", no_args_is_help=True)
sim_app = typer.Typer(help="The simulated work cell.", no_args_is_help=True)
markers_app = typer.Typer(help="The marker front-end on single images.", no_args_is_help=True)
app.add_typer(driver_app, name="driver")
app.add_typer(sim_app, name="sim")
app.add_typer(markers_app, name="markers")
model_app = typer.Typer(help="Recognition model databases.", no_args_is_help=True)
app.add_typer(model_app, name="model")
export_app = typer.Typer(help="Logs in other tools' formats.", no_args_is_help=True)
app.add_typer(export_app, name="export")


@driver_app.command("sim")
@transport_options
def driver_sim(
    camera: Annotated[str, typer.Option("--camera", help="camera id in the scenario")],
    scenario: ScenarioOpt = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    epoch_ns: Annotated[
        Optional[int], typer.Option(help="Unix time (ns) of scenario time 0; share it between cameras")
    ] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one simulated camera: render, detect markers, publish every camera key (plus truth/)."""
    from drivers.sim.scenario import load_scenario
    from drivers.sim.source import SimSource

    _setup_logging(verbose)
    cfg = _load_cell(cell_config, scenario)
    cam = next((c for c in cfg.cameras if c.id == camera), None)
    if cam is None:
        raise _fail(f"camera {camera!r} is not in the cell; cameras: {[c.id for c in cfg.cameras]}", 2)
    source = SimSource(load_scenario(cfg.cell.scenario), camera, epoch_ns=epoch_ns, prerender=cam.prerender_frames)
    _drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)


@driver_app.command("openni2")
@transport_options
def driver_openni2(
    camera: Annotated[
        str, typer.Option("--camera", help="camera id (a [[cameras]] entry of the cell config, or any id with --uri)")
    ],
    uri: Annotated[
        Optional[str],
        typer.Option("--uri", help="device URI, 'Dummy', a .oni file; default: the camera's uri in the config"),
    ] = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one OpenNI2 sensor (Kinect v1, Xtion, .oni file): frames and marker observations on the bus."""
    from drivers.config import CameraConfig
    from drivers.openni2 import OpenNI2Source
    from schemas.codec import CameraInfo

    _setup_logging(verbose)
    cfg = _load(cell_config)
    cam = next((c for c in cfg.cameras if c.id == camera), None)
    if cam is None:
        if uri is None:
            raise _fail(f"camera {camera!r} is not in the cell config; give --uri to run it anyway", 2)
        cam = CameraConfig(id=camera, source="openni2", uri=uri)
    info = None
    if cam.intrinsics is not None:
        i = cam.intrinsics
        info = CameraInfo(cam.width, cam.height, [[i.fx, 0, i.cx], [0, i.fy, i.cy], [0, 0, 1]], list(i.distortion))
    source = OpenNI2Source(
        camera,
        uri if uri is not None else cam.uri,
        width=cam.width,
        height=cam.height,
        rate_hz=cam.rate_hz,
        info=info,
        lib_dir=cam.openni2_path,
    )
    _drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)
    # libOpenNI2's native shutdown segfaults once a frame has been read (seen with the plain
    # bindings and Debian's Dummy device too), which would turn every clean stop into a crash
    # for the supervisor: everything of ours is closed and flushed, so leave without it.
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(0)


@driver_app.command("realsense")
@transport_options
def driver_realsense(
    camera: CameraIdOpt,
    serial: Annotated[
        Optional[str],
        typer.Option("--serial", help="device serial number (default: the config's, else the first device)"),
    ] = None,
    bag: Annotated[
        Optional[Path], typer.Option("--bag", help="play a RealSense recording (.bag or .db3) instead of a device")
    ] = None,
    record_to: Annotated[
        Optional[Path], typer.Option("--record-to", help="also record the device to this .db3 file")
    ] = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one Intel RealSense D4xx (or play its recording): frames and marker observations on the bus."""
    from drivers.realsense import RealSenseSource

    cfg, cam = _camera_section(cell_config, camera, "realsense", verbose)
    recording = bag if bag is not None else cam.recording
    source = RealSenseSource(
        camera,
        serial=serial or cam.serial or None,
        recording=recording,
        width=cam.width,
        height=cam.height,
        rate_hz=cam.rate_hz,
        record_to=record_to,
    )
    _drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)


@driver_app.command("ros2")
@transport_options
def driver_ros2(
    camera: CameraIdOpt,
    color: Annotated[
        Optional[str],
        typer.Option("--color", help="colour image topic (default: the config's, else realsense2_camera's)"),
    ] = None,
    depth: Annotated[Optional[str], typer.Option("--depth", help="depth image topic, aligned to colour")] = None,
    info: Annotated[Optional[str], typer.Option("--info", help="the colour camera's CameraInfo topic")] = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one ROS 2 camera (its topics on this zenoh router, rmw_zenoh): marker observations and frames on the bus."""
    from drivers.ros2_topics import Ros2TopicsSource
    from schemas.ros2 import ros2_types

    cfg, cam = _camera_section(cell_config, camera, "ros2", verbose)

    def topics(bus):  # subscribes on the driver's own session
        return Ros2TopicsSource(
            camera,
            bus.session,
            ros2_types(cfg.ros2.distro),
            color=color or cam.color_topic,
            depth=depth or cam.depth_topic,
            info=info or cam.info_topic,
            domain_id=cfg.ros2.domain_id,
            rate_hz=cam.rate_hz,
        )

    _drive(cfg, cam.publish_images, camera, topics, transport, duration)


@app.command("estimator")
@transport_options
def estimator_cmd(
    cell_config: CellConfigOpt = None,
    scenario: ScenarioOpt = None,
    state_file: Annotated[Optional[Path], typer.Option(help="persist the map here and restore it on start")] = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run the estimator daemon: marker observations in, camera and marker poses out."""
    from estimator.service import EstimatorService

    _setup_logging(verbose)
    cfg = _load_cell(cell_config, scenario)
    est_cfg = cfg.estimator if state_file is None else cfg.estimator.model_copy(update={"state_file": state_file})
    stop = _stop_event()
    with _bus(cfg, None, transport) as bus:
        EstimatorService(bus, est_cfg, cfg.ros2).run(stop, duration)


@app.command("recognition")
@transport_options
def recognition_cmd(
    cell_config: CellConfigOpt = None,
    scenario: ScenarioOpt = None,
    models: Annotated[
        Optional[Path],
        typer.Option(
            "--models", help="model database folder (default: [recognition] models, or built from the scenario)"
        ),
    ] = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run the recognition worker: depth frames and camera poses in, object poses in world frame out."""
    from cellsight.model_build import models_for
    from recognition.worker import RecognitionWorker

    _setup_logging(verbose)
    cfg = _load_cell(cell_config, scenario)
    # Recognition is the heaviest and least urgent work of a cell: drivers and the estimator go first.
    os.nice(RECOGNITION_NICE)
    db = models_for(cfg, models)
    stop = _stop_event()
    with _bus(cfg, None, transport) as bus:
        RecognitionWorker(bus, cfg.recognition, db, cfg.ros2).run(stop, duration)


@model_app.command("build")
def model_build(
    out: Annotated[Path, typer.Option("--out", help="database folder to write")],
    scenario: Annotated[Optional[Path], typer.Option("--scenario", help="every object of this scenario TOML")] = None,
    demo: Annotated[bool, typer.Option("--demo", help="every object of the built-in demo cell")] = False,
    mesh: Annotated[
        Optional[list[str]],
        typer.Option("--mesh", help="ID=FILE: a mesh (PLY/OBJ/STL), metres; coloured by its vertex colours or texture"),
    ] = None,
    cloud: Annotated[
        Optional[list[str]],
        typer.Option("--cloud", help="ID=FILE: a point cloud (PCD/PLY), metres, captured from its origin"),
    ] = None,
    points: Annotated[
        Optional[list[str]],
        typer.Option("--points", help="ID=FILE: points over the whole surface (PLY/PCD/XYZ), metres, object frame"),
    ] = None,
    recording: Annotated[
        Optional[list[str]],
        typer.Option("--recording", help="ID=LOG.mcap: a camera walking round the object on the --board"),
    ] = None,
    board: Annotated[
        Optional[Path],
        typer.Option("--board", help="marker board TOML of the recordings (see drivers/sim/capture_board.toml)"),
    ] = None,
    distance: Annotated[
        Optional[list[float]],
        typer.Option(
            help="virtual camera distance for the views of --mesh and --points models and the scenario's, m; repeat for "
            "several (default: 2.0 and 0.8)"
        ),
    ] = None,
    scale: Annotated[
        float, typer.Option(help="metres per unit of the --mesh, --cloud and --points files (0.001: millimetres)")
    ] = 1.0,
    cell_config: CellConfigOpt = None,
) -> None:
    """Build a recognition model database (views from a tessellated sphere; descriptors as configured)."""
    from rich.progress import Progress

    from cellsight.model_build import VIEWS_PER_OBJECT, build_database, load_board
    from drivers.sim.scenario import load_scenario
    from recognition.models import VIEW_DISTANCES_M

    def pairs(items: list[str] | None, what: str) -> dict[str, Path]:
        out_ = {}
        for item in items or []:
            oid, sep, path = item.partition("=")
            if not sep or not oid or not path:
                raise _fail(f"--{what} {item!r}: write it as ID=FILE", 2)
            out_[oid] = Path(path)
        return out_

    meshes, clouds, recordings = pairs(mesh, "mesh"), pairs(cloud, "cloud"), pairs(recording, "recording")
    surfaces = pairs(points, "points")
    if not (scenario or demo or meshes or clouds or surfaces or recordings):
        raise _fail(
            "nothing to build: give --demo, --scenario FILE, --mesh ID=FILE, --cloud ID=FILE, --points ID=FILE or --recording ID=LOG",
            2,
        )
    cfg = _load(cell_config)
    sc = load_scenario(scenario) if (scenario or demo) else None
    board_cfg = load_board(board) if board else None
    distances = tuple(distance) if distance else VIEW_DISTANCES_M
    if not all(d > 0 for d in distances):
        raise _fail(f"--distance {list(distances)}: each must be positive", 2)
    rendered = len(distances) * ((len(sc.objects) if sc else 0) + len(meshes) + len(surfaces))
    total = VIEWS_PER_OBJECT * (rendered + len(clouds) + len(recordings))
    with Progress(console=_stderr(), transient=True) as bar:
        task = bar.add_task("rendering and describing views", total=total)
        db = build_database(
            cfg.recognition.descriptor,
            scenario=sc,
            meshes=meshes,
            clouds=clouds,
            points=surfaces,
            recordings=recordings,
            board=board_cfg,
            distances_m=distances,
            scale=scale,
            progress=lambda: bar.advance(task),
        )
    db.save(out)
    for oid, mdl in sorted(db.models.items()):
        colour = "in colour" if mdl.colours is not None else "no colour: verified on depth alone"
        typer.echo(
            f"{oid}: {len(mdl.views)} views, {len(mdl.points)} model points, diameter {mdl.diameter_m:.3f} m ({mdl.source}, {colour})"
        )
    typer.echo(f"wrote {out}/")


@app.command("recognize")
def recognize_cmd(
    models: Annotated[Path, typer.Option("--models", help="model database folder (cellsight model build)")],
    scene: Annotated[
        Path, typer.Option("--scene", help="scene: PCD/PLY cloud (m), or 16-bit depth image (mm); see --scale")
    ],
    rgb: Annotated[
        Optional[Path],
        typer.Option(
            "--rgb", help="colour image registered to a depth image scene (same size): verification then judges colour"
        ),
    ] = None,
    fx: Annotated[Optional[float], typer.Option(help="depth image focal length x, px (default Kinect v1)")] = None,
    fy: Annotated[Optional[float], typer.Option(help="depth image focal length y, px")] = None,
    cx: Annotated[Optional[float], typer.Option(help="depth image principal point x, px")] = None,
    cy: Annotated[Optional[float], typer.Option(help="depth image principal point y, px")] = None,
    scale: Annotated[
        Optional[float],
        typer.Option(
            help="metres per unit of the scene (default: 1 for a cloud, 0.001 for a depth image in mm; 0.0001 for 0.1 mm depth)"
        ),
    ] = None,
    standing: Annotated[
        bool,
        typer.Option(
            "--standing",
            help="every object stands on its base on the table or floor: "
            "take that plane as level ([recognition] level_support)",
        ),
    ] = False,
    picture: Annotated[
        Optional[Path],
        typer.Option(
            "--picture",
            help="write the scene (its colour, else its depth) with each object found drawn on it: its "
            "visible points, outline, axes, id and fitness (.png or .jpg)",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
    cell_config: CellConfigOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Recognise the database's objects in one scene and print their poses in the camera frame."""
    from cellsight.recognize_cmd import recognize_file
    from recognition.models import ModelDatabase

    _setup_logging(verbose)
    cfg = _load(cell_config)
    db = ModelDatabase.load(models)
    update = {"descriptor": db.descriptor} | ({"level_support": True} if standing else {})
    result = recognize_file(
        scene,
        db,
        cfg.recognition.model_copy(update=update),
        picture=picture,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        scale=scale,
        rgb=rgb,
    )
    typer.echo(result.to_json() if as_json else result.to_text())
    if not result.detections:
        raise typer.Exit(1)


@sim_app.command("snapshot")
def sim_snapshot(
    out: Annotated[Path, typer.Option("--out", help="folder for <camera>_rgb.png and <camera>_depth.png")],
    scenario: ScenarioOpt = None,
    time_s: Annotated[float, typer.Option("--time", help="scenario time in seconds")] = 1.0,
) -> None:
    """Render every camera once and write RGB and false-colour depth PNGs to look at."""
    from cellsight.pictures import write_snapshot
    from drivers.sim.scenario import load_scenario

    written = write_snapshot(load_scenario(scenario), out, time_s)
    for p in written:
        typer.echo(str(p))


@markers_app.command("detect")
def markers_detect(
    image: Annotated[Path, typer.Argument(help="image file (PNG, JPEG)")],
    dictionary: Annotated[
        str, typer.Option("--dict", help="OpenCV dictionary name or a .yml file")
    ] = "DICT_APRILTAG_36h11",
    camera_info: Annotated[
        Optional[Path],
        typer.Option(
            "--camera-info", help="OpenCV YAML with camera_matrix and distortion_coefficients (default: Kinect v1)"
        ),
    ] = None,
    size: Annotated[float, typer.Option("--size", help="marker side length in metres")] = 0.15,
    depth: Annotated[Optional[Path], typer.Option("--depth", help="registered 16-bit depth PNG in millimetres")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
    annotate: Annotated[
        Optional[Path], typer.Option("--annotate", help="write the image with markers and axes drawn")
    ] = None,
) -> None:
    """Detect markers in one image and print ids, corners and poses."""
    from cellsight.detect import detect_file

    result = detect_file(image, dictionary, camera_info, size, depth, annotate)
    typer.echo(result.to_json() if as_json else result.to_text())


@app.command("record")
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
        Optional[list[str]], typer.Option("--keys", help="key expressions to record (default: the whole cell)")
    ] = None,
    max_image_hz: Annotated[Optional[float], typer.Option(help="record images at most this often per camera")] = None,
    duration: DurationOpt = None,
    cell: CellOpt = None,
    cell_config: CellConfigOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Record bus traffic to MCAP (lz4 chunks, Foxglove schemas embedded) until Ctrl-C / SIGTERM."""
    from cellsight.record import Recorder

    _setup_logging(verbose)
    cfg = _load(cell_config)
    stop = _stop_event()
    with _bus(cfg, cell, transport) as bus:
        rec = Recorder(bus, out, keys_, max_image_hz, {"config": cfg.to_toml()})
        stop.wait(duration)
        rec.close()
    parts = ", ".join(str(p) for p in rec.parts)
    refused = sum(rec.refused.values())
    _stderr().print(f"{parts}: {rec.messages} messages ({rec.thinned} images thinned, {refused} refused)")
    for (key, reason), n in sorted(rec.refused.items()):
        _stderr().print(f"[yellow]refused:[/] {n} on {key} ({reason})")
    for gap in rec.gaps:
        _stderr().print(f"[yellow]gap:[/] nothing from {gap.camera} for {gap.seconds:.1f} s (marked in the log)")
    if rec.failures:
        raise _fail(
            f"recording interrupted {len(rec.failures)} time(s), {rec.lost} messages not recorded; last error: {rec.failures[-1]}",
            1,
        )
    if refused:
        raise _fail(f"{refused} messages refused (malformed or implausible, listed above); the log holds the rest", 1)


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

    stop = _stop_event()
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
                _stderr().print(f"Foxglove live view: open ws://127.0.0.1:{bridge.port} in the Foxglove app")
        if live_view is not None and board is not None:
            live_view.update(board.table())

    try:
        if live:
            with Live(refresh_per_second=2, console=_stderr()) as live_view:
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


@app.command("run")
def run_cmd(
    cell_config: Annotated[
        Optional[Path], typer.Argument(help="cell config TOML (default: the simulated demo cell)")
    ] = None,
    out: Annotated[
        Optional[Path], typer.Option("--out", help="run folder: config used, logs, state, recording")
    ] = None,
    record: Annotated[bool, typer.Option("--record/--no-record", help="record the cell to OUT/log.mcap")] = False,
    max_image_hz: Annotated[Optional[float], typer.Option(help="when recording: images per camera per second")] = 2.0,
    duration: Annotated[
        Optional[float], typer.Option(help="stop after this many seconds (default: until Ctrl-C)")
    ] = None,
    foxglove: FoxgloveOpt = False,
    foxglove_port: FoxglovePortOpt = 8765,
    verbose: VerboseOpt = False,
) -> None:
    """Run a cell: router, one driver per camera, estimator, recognition (and recorder), supervised."""
    _setup_logging(verbose)
    cfg = _load_cell(cell_config)
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
    _stderr().print(f"run folder: {run_dir}")


@app.command("demo")
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
    from cellsight.report import write_report
    from cellsight.scenario_config import demo_config

    _setup_logging(verbose)
    cfg = demo_config()
    if duration > 0:
        from drivers.sim.scenario import load_scenario

        scenario_len = load_scenario(cfg.cell.scenario).duration_s
        if duration > scenario_len:
            raise _fail(f"--duration {duration:g} is longer than the demo scenario ({scenario_len:g} s)", 2)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "log.mcap"
    _run(cfg, out, duration, log_path, max_image_hz, sys.stderr.isatty(), foxglove_port if foxglove else None)
    summary = write_report(log_path, cfg.cell.name, out)
    from rich.console import Console
    from rich.markdown import Markdown

    Console().print(Markdown((out / "summary.md").read_text()))
    typer.echo(f"wrote {out}/: log.mcap, config.toml, summary.json, summary.md, top_view.png, errors.png")
    if not summary.log_complete:
        _stderr().print("[yellow]warning:[/] the log was not complete; the summary covers what was readable")


@app.command("status")
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

    cfg = _load(cell_config)
    with _bus(cfg, cell, transport) as bus:
        board = StatusBoard(bus)
        time.sleep(duration)
        Console(width=140).print(board.table(bus.alive()))
        board.close()


@app.command("replay")
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

    _setup_logging(verbose)
    if not log_file.is_file():
        raise _fail(f"{log_file}: no such log file", 2)
    if not rate > 0:
        raise _fail(f"--rate must be positive, got {rate}", 2)
    cfg = _load(cell_config)
    stop = _stop_event()
    with _bus(cfg, None, transport) as bus:
        result = replay(bus, log_file, rate, all_keys, stop)
    _stderr().print(f"{log_file}: {result.published} messages republished, {result.skipped} recorded estimates skipped")
    for (key, reason), n in sorted(result.read.refused.items()):
        _stderr().print(f"[yellow]skipped:[/] {n} messages on {key} ({reason})")
    if result.read.stopped_early:
        _stderr().print(f"[yellow]warning:[/] the log is {result.read.stopped_early}; republished what came before")


@app.command("resolve")
def resolve_cmd(
    log_file: Annotated[Path, typer.Argument(help="MCAP log (cellsight record / demo / replay)")],
    out: Annotated[
        Optional[Path], typer.Option("--out", help="output folder (default: LOG's name + _resolved)")
    ] = None,
    config: Annotated[
        Optional[Path],
        typer.Option("--config", help="cell config with the anchors (default: the one embedded in the log)"),
    ] = None,
    verbose: VerboseOpt = False,
) -> None:
    """Re-solve a log in batch: resolved.mcap, TUM trajectories, report.html with figures."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TimeRemainingColumn

    from cellsight.resolve_report import peek_config, run_resolve

    _setup_logging(verbose)
    if not log_file.is_file():
        raise _fail(f"{log_file}: no such log file", 2)
    from schemas.log import ReadReport

    peeked = ReadReport()
    cfg = _load(config) if config is not None else peek_config(log_file, peeked)
    if cfg is None and peeked.stopped_early:
        raise _fail(
            f"{log_file} is cut or damaged {peeked.stopped_early.removeprefix('cut or damaged ')}, before its cell config: "
            "nothing to solve there; give --config with the anchors to solve what precedes the damage",
            2,
        )
    if cfg is None:
        raise _fail(
            f"{log_file} has no embedded cell config (not written by cellsight record?): give --config with the anchors",
            2,
        )
    if not cfg.estimator.anchors:
        from cellsight.scenario_config import complete

        cfg = complete(cfg)
    out = out or log_file.with_name(log_file.stem + "_resolved")
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        DownloadColumn(),
        TimeRemainingColumn(),
        console=_stderr(),
    ) as bar:
        task = bar.add_task("reading and solving", total=log_file.stat().st_size)
        run = run_resolve(log_file, out, cfg, lambda done, total: bar.update(task, completed=done))
    r = run.result
    typer.echo(
        f"{out}/: {r.frames} frames, {r.observations} observations, {len(r.segments)} segments, {len(r.markers)} markers"
        + (f", {r.object_links} object-marker instants linking cameras" if r.object_links else "")
    )
    if r.moving_frames_left_out:
        typer.echo(
            f"  {r.moving_frames_left_out} moving frames left out: the still views fit {r.moving_frames_scale:.3g} times better "
            "than the moving ones, each against its covariances (keyframes.max_inflation)"
        )
    for cam, c in run.figures.cameras.items():
        off, on = c.offline_vs_truth_mm_deg, c.online_vs_truth_mm_deg
        if off is not None:
            moving = f"; {c.moving_frames} moving frames solved" if c.moving_frames else ""
            paired = (
                f" (RMS at the same instants {c.paired.offline_mm_deg_rms[0]:.2f} / {c.paired.online_mm_deg_rms[0]:.2f} mm)"
                if c.paired
                else ""
            )
            typer.echo(
                f"  {cam}: offline {off[0]:.2f} mm / {off[1]:.3f} deg vs truth"
                + (f", online {on[0]:.2f} mm / {on[1]:.3f} deg" if on else "")
                + paired
                + moving
            )
    for child, o in run.figures.object_markers.items():
        off = o.offline_vs_truth_mm_deg
        typer.echo(
            f"  {child}: {o.poses} poses" + (f", offline {off[0]:.2f} mm / {off[1]:.2f} deg vs truth" if off else "")
        )
    for (key, reason), n in sorted(run.read.refused.items()):
        _stderr().print(
            f"[yellow]skipped:[/] {n} messages on {key} ({reason}), as a running cell would have refused them"
        )
    if run.read.stopped_early:
        _stderr().print(
            f"[yellow]warning:[/] the log is {run.read.stopped_early}; resolved from the {run.read.messages} messages before it"
        )
    if r.frames == 0:
        raise _fail(f"{log_file}: no marker frames to solve (nothing written to {out} is a solution)", 1)


@export_app.command("ros2")
def export_ros2(
    log_file: Annotated[Path, typer.Argument(help="MCAP log (cellsight record / demo, or resolve's resolved.mcap)")],
    out: Annotated[Path, typer.Option("--out", help="new folder for the ROS 2 bag")],
    distro: Annotated[str, typer.Option(help="ROS 2 message definitions: jazzy or humble")] = "jazzy",
) -> None:
    """Write a log as a ROS 2 bag (MCAP storage, CDR): tf, camera poses, observations, images."""
    from rich.progress import BarColumn, DownloadColumn, Progress

    from cellsight.export_ros2 import export_bag

    if not log_file.is_file():
        raise _fail(f"{log_file}: no such log file", 2)
    with Progress("[progress.description]{task.description}", BarColumn(), DownloadColumn(), console=_stderr()) as bar:
        task = bar.add_task("exporting", total=log_file.stat().st_size)
        result = export_bag(log_file, out, distro, lambda done, total: bar.update(task, completed=done))
    for topic, n in sorted(result.messages.items()):
        typer.echo(f"{n:8d}  {topic}")
    typer.echo(f"wrote {result.bag}/ (ros2 bag play {result.bag})")
    if result.read.stopped_early:
        _stderr().print(
            f"[yellow]warning:[/] the log ended early ({result.read.stopped_early}); exported what was readable"
        )


@app.command("compare")
def compare_cmd(
    a: Annotated[Path, typer.Argument(help="first solved log (resolved.mcap, or a recording with estimates)")],
    b: Annotated[Path, typer.Argument(help="second solved log")],
    min_mm: Annotated[float, typer.Option(help="smallest position change that counts as moved")] = 1.0,
    min_deg: Annotated[float, typer.Option(help="smallest rotation change that counts as moved")] = 0.05,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
) -> None:
    """How much each camera and marker moved between two solved logs, with a verdict against its uncertainty."""
    import json as json_

    from rich.console import Console
    from rich.table import Table

    from cellsight.compare import compare, newest_poses

    for f in (a, b):
        if not f.is_file():
            raise _fail(f"{f}: no such log file", 2)
    (pa, _), (pb, _) = newest_poses(a), newest_poses(b)
    if not pa or not pb:
        raise _fail(f"{a if not pa else b}: holds no estimate/cameras or estimate/markers (resolve it first)", 2)
    changes = compare(pa, pb, min_mm, min_deg)
    if as_json:
        typer.echo(json_.dumps([c.__dict__ for c in changes]))
        return
    t = Table(title=f"{a} -> {b}")
    for col in ("frame", "position (mm)", "rotation (deg)", "sigmas", "verdict"):
        t.add_column(col, no_wrap=True)
    for c in changes:
        style = "bold red" if c.verdict == "moved" else ""
        t.add_row(
            c.frame,
            f"{c.position_mm:.2f}",
            f"{c.rotation_deg:.3f}",
            "-" if c.sigmas is None else f"{c.sigmas:.1f}",
            f"[{style}]{c.verdict}[/]" if style else c.verdict,
        )
    Console(width=120).print(t)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
