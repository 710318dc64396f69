"""Faults on a running cell (slow): processes SIGKILLed under ``cellsight run``'s supervisor.

A small simulated cell (two 320x240 cameras, a wall with an anchor and three markers) runs as
separate processes; the checks watch the estimator's status over zenoh, as an operator would.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from tests.conftest import free_port
from tests.helpers import wait_until

pytestmark = pytest.mark.slow

SCENARIO = """
name = "faults"
duration_s = 600.0
marker_side_m = 0.25
[[boxes]]
size = [4.0, 0.02, 2.0]
pose = { position = [0.0, 2.02, 1.0] }
[[markers]]
id = 0
role = "anchor"
pose = { position = [-0.6, 2.0, 1.0], normal = [0.0, -1.0, 0.0] }
[[markers]]
id = 1
pose = { position = [0.0, 2.0, 1.0], normal = [0.0, -1.0, 0.0] }
[[markers]]
id = 2
pose = { position = [0.6, 2.0, 1.0], normal = [0.0, -1.0, 0.0] }
[[markers]]
id = 3
pose = { position = [0.0, 2.0, 1.5], normal = [0.0, -1.0, 0.0] }
[[cameras]]
id = "a"
width = 320
height = 240
rate_hz = 15.0
pose = { position = [-0.4, 0.0, 1.2], look_at = [0.0, 2.0, 1.1] }
[[cameras]]
id = "b"
width = 320
height = 240
rate_hz = 15.0
pose = { position = [0.4, 0.0, 1.2], look_at = [0.0, 2.0, 1.1] }
"""


@pytest.fixture()
def cell(tmp_path: Path):
    port = free_port()
    (tmp_path / "scenario.toml").write_text(SCENARIO)
    (tmp_path / "cell.toml").write_text(f'[cell]\nname = "faults"\nscenario = "scenario.toml"\n[transport]\nconnect = ["tcp/127.0.0.1:{port}"]\n')
    run_dir = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "cellsight.cli", "run", str(tmp_path / "cell.toml"), "--out", str(run_dir), "--record"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
    states: list[tuple[float, dict[str, int]]] = []
    try:
        wait_until(lambda: (run_dir / "processes.json").exists(), 30, "the launcher to start the cell")
        bus = Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), "faults")
        bus.subscribe(keys.estimate_status("faults"), m.EstimatorStatus,
                      callback=lambda r: states.append((time.monotonic(), {c.camera_id: c.state for c in r.msg.cameras})))  # fmt: skip
        yield run_dir, states, proc
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
        bus.close()


def pid_of(run_dir: Path, name: str) -> int:
    return next(p["pid"] for p in json.loads((run_dir / "processes.json").read_text()) if p["name"] == name)


def localized(states, cam: str) -> bool:
    return bool(states) and states[-1][1].get(cam) == m.CameraState.LOCALIZED


def test_killed_driver_goes_stale_and_recovers_after_restart(cell) -> None:
    run_dir, states, _ = cell
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    old = pid_of(run_dir, "driver/a")
    os.kill(old, signal.SIGKILL)
    killed = time.monotonic()
    wait_until(lambda: states[-1][1].get("a") == m.CameraState.STALE, 5, "camera a to go stale")
    stale_at = next(t for t, s in states if t > killed and s.get("a") == m.CameraState.STALE)
    assert stale_at - killed < 1.0, f"stale only {stale_at - killed:.2f} s after the kill"
    assert states[-1][1]["b"] == m.CameraState.LOCALIZED  # the other camera is unaffected
    wait_until(lambda: pid_of(run_dir, "driver/a") != old, 10, "the supervisor to restart the driver")
    wait_until(lambda: localized(states, "a"), 30, "camera a localized again")


def test_killed_estimator_restarts_with_its_map_and_localizes_within_a_second(cell) -> None:
    run_dir, states, _ = cell
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    wait_until(lambda: (run_dir / "estimator_state.json").exists(), 15, "the estimator to save its map")
    os.kill(pid_of(run_dir, "estimator"), signal.SIGKILL)
    killed = time.monotonic()
    wait_until(lambda: any(t > killed + 0.3 for t, _ in states), 30, "status from the restarted estimator")
    first = next(t for t, _ in states if t > killed + 0.3)
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 10, "cameras localized after the restart")
    back = next(t for t, s in states if t >= first and s.get("a") == m.CameraState.LOCALIZED and s.get("b") == m.CameraState.LOCALIZED)
    assert back - first < 1.0, f"localized {back - first:.2f} s after the restarted estimator's first status"
    log = (run_dir / "logs" / "estimator.log").read_text()
    assert "restored" in log, "the restarted estimator did not restore its map"


def test_killed_router_restarts_and_every_process_reconnects(cell) -> None:
    run_dir, states, _ = cell
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    old = pid_of(run_dir, "router")
    os.kill(old, signal.SIGKILL)
    killed = time.monotonic()
    wait_until(lambda: pid_of(run_dir, "router") != old, 10, "the supervisor to restart the router")
    wait_until(lambda: any(t > killed + 1.0 for t, _ in states), 30, "status over the restarted router")
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 10, "both cameras localized after the restart")
    restarted = {p["name"]: p["restarts"] for p in json.loads((run_dir / "processes.json").read_text())}
    assert restarted.pop("router") == 1
    assert not any(restarted.values()), f"processes restarted instead of reconnecting: {restarted}"
