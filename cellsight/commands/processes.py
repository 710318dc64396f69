"""The processes of a cell, one command each: ``cellsight driver ...``, ``estimator``, ``recognition``."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    RECOGNITION_NICE,
    CameraIdOpt,
    CellConfigOpt,
    DurationOpt,
    ScenarioOpt,
    VerboseOpt,
    camera_section,
    drive,
    fail,
    load,
    load_cell,
    open_bus,
    setup_logging,
    stop_event,
)
from cellsight.transport_flags import TransportFlags, transport_options

driver_app = typer.Typer(help="Sensor driver processes.", no_args_is_help=True)


@driver_app.command("sim")
@transport_options
def driver_sim(
    camera: Annotated[str, typer.Option("--camera", help="camera id in the scenario")],
    scenario: ScenarioOpt = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    epoch_ns: Annotated[
        int | None, typer.Option(help="Unix time (ns) of scenario time 0; share it between cameras")
    ] = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one simulated camera: render, detect markers, publish every camera key (plus truth/)."""
    from drivers.sim.scenario import load_scenario
    from drivers.sim.source import SimSource

    setup_logging(verbose)
    cfg = load_cell(cell_config, scenario)
    cam = next((c for c in cfg.cameras if c.id == camera), None)
    if cam is None:
        raise fail(f"camera {camera!r} is not in the cell; cameras: {[c.id for c in cfg.cameras]}", 2)
    source = SimSource(load_scenario(cfg.cell.scenario), camera, epoch_ns=epoch_ns, prerender=cam.prerender_frames)
    drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)


@driver_app.command("openni2")
@transport_options
def driver_openni2(
    camera: Annotated[
        str, typer.Option("--camera", help="camera id (a [[cameras]] entry of the cell config, or any id with --uri)")
    ],
    uri: Annotated[
        str | None,
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

    setup_logging(verbose)
    cfg = load(cell_config)
    cam = next((c for c in cfg.cameras if c.id == camera), None)
    if cam is None:
        if uri is None:
            raise fail(f"camera {camera!r} is not in the cell config; give --uri to run it anyway", 2)
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
    drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)
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
        str | None,
        typer.Option("--serial", help="device serial number (default: the config's, else the first device)"),
    ] = None,
    bag: Annotated[
        Path | None, typer.Option("--bag", help="play a RealSense recording (.bag or .db3) instead of a device")
    ] = None,
    record_to: Annotated[
        Path | None, typer.Option("--record-to", help="also record the device to this .db3 file")
    ] = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one Intel RealSense D4xx (or play its recording): frames and marker observations on the bus."""
    from drivers.realsense import RealSenseSource

    cfg, cam = camera_section(cell_config, camera, "realsense", verbose)
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
    drive(cfg, cam.publish_images, camera, lambda _bus: source, transport, duration)


@driver_app.command("ros2")
@transport_options
def driver_ros2(
    camera: CameraIdOpt,
    color: Annotated[
        str | None,
        typer.Option("--color", help="colour image topic (default: the config's, else realsense2_camera's)"),
    ] = None,
    depth: Annotated[str | None, typer.Option("--depth", help="depth image topic, aligned to colour")] = None,
    info: Annotated[str | None, typer.Option("--info", help="the colour camera's CameraInfo topic")] = None,
    cell_config: CellConfigOpt = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run one ROS 2 camera (its topics on this zenoh router, rmw_zenoh): marker observations and frames on the bus."""
    from drivers.ros2_topics import Ros2TopicsSource
    from schemas.ros2 import ros2_types

    cfg, cam = camera_section(cell_config, camera, "ros2", verbose)

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

    drive(cfg, cam.publish_images, camera, topics, transport, duration)


@transport_options
def estimator_cmd(
    cell_config: CellConfigOpt = None,
    scenario: ScenarioOpt = None,
    state_file: Annotated[Path | None, typer.Option(help="persist the map here and restore it on start")] = None,
    duration: DurationOpt = None,
    transport: TransportFlags = TransportFlags(),
    verbose: VerboseOpt = False,
) -> None:
    """Run the estimator daemon: marker observations in, camera and marker poses out."""
    from estimator.service import EstimatorService

    setup_logging(verbose)
    cfg = load_cell(cell_config, scenario)
    est_cfg = cfg.estimator if state_file is None else cfg.estimator.model_copy(update={"state_file": state_file})
    stop = stop_event()
    with open_bus(cfg, None, transport) as bus:
        EstimatorService(bus, est_cfg, cfg.ros2).run(stop, duration)


@transport_options
def recognition_cmd(
    cell_config: CellConfigOpt = None,
    scenario: ScenarioOpt = None,
    models: Annotated[
        Path | None,
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

    setup_logging(verbose)
    cfg = load_cell(cell_config, scenario)
    # Recognition is the heaviest and least urgent work of a cell: drivers and the estimator go first.
    os.nice(RECOGNITION_NICE)
    db = models_for(cfg, models)
    stop = stop_event()
    with open_bus(cfg, None, transport) as bus:
        RecognitionWorker(bus, cfg.recognition, db, cfg.ros2).run(stop, duration)
