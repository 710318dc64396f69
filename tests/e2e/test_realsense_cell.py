"""Two RealSense cameras (recordings made through librealsense's software device, played back in
real time by the driver) under ``cellsight run``: both localise, as sensors of any other kind."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from cellsight.scenario_config import cell_config_of
from drivers.config import CameraConfig
from drivers.realsense import write_recording
from drivers.sim.scenario import load_scenario
from drivers.sim.source import SimSource
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from tests.conftest import free_port
from tests.helpers import stop_launcher, wait_until

CELL = "rs"
SECONDS = 4.0


def test_two_realsense_cameras_localize_under_cellsight_run(tmp_path: Path) -> None:
    scenario = load_scenario()
    cameras = []
    for cam in ("cam1", "cam2"):
        source = SimSource(scenario, cam, epoch_ns=0, realtime=False)
        frames = [source.read() for _ in range(int(SECONDS * 30))]
        write_recording(tmp_path / f"{cam}.db3", frames, serial=f"rs-{cam}")
        cameras.append(CameraConfig(id=cam, source="realsense", recording=Path(f"{cam}.db3")))
    port = free_port()
    cfg = cell_config_of(scenario).model_copy(deep=True)
    cfg = cfg.model_copy(update={"cameras": cameras})
    cfg.cell.name, cfg.cell.scenario = CELL, None
    cfg.transport.connect = [f"tcp/127.0.0.1:{port}"]
    cfg.recognition.enabled = False
    (tmp_path / "cell.toml").write_text(cfg.to_toml())
    states: dict[str, int] = {}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cellsight.cli",
            "run",
            str(tmp_path / "cell.toml"),
            "--out",
            str(tmp_path / "run"),
            "--duration",
            str(SECONDS + 20),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_until(lambda: (tmp_path / "run" / "processes.json").exists(), 30, "the launcher to start the cell")
        with Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), CELL) as bus:
            bus.subscribe(
                keys.estimate_status(CELL),
                m.EstimatorStatus,
                callback=lambda r: states.update({c.camera_id: c.state for c in r.msg.cameras}),
            )
            wait_until(
                lambda: states.get("cam1") == m.CameraState.LOCALIZED and states.get("cam2") == m.CameraState.LOCALIZED,
                SECONDS + 15,
                f"both RealSense cameras localized (states: {states})",
            )
    finally:
        stop_launcher(proc, tmp_path / "run")
    manifest = (tmp_path / "run" / "processes.json").read_text()
    assert manifest.count('"realsense"') == 2, manifest  # the launcher started the RealSense driver for both
