"""Faults (slow): processes SIGKILLed under ``cellsight run``'s supervisor, and a full disk.

A small simulated cell (two 320x240 cameras, a wall with an anchor and three markers) runs as
separate processes; the checks watch the estimator's status over zenoh, as an operator would.
The disk that fills is a small tmpfs (``small_disk``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cellsight.record import Recorder
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.log import ReadReport, read_log
from tests.conftest import free_port
from tests.helpers import stop_launcher, wait_until

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
    (tmp_path / "cell.toml").write_text(
        f'[cell]\nname = "faults"\nscenario = "scenario.toml"\n[transport]\nconnect = ["tcp/127.0.0.1:{port}"]\n'
    )
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cellsight.cli", "run", str(tmp_path / "cell.toml"), "--out", str(run_dir), "--record"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    states: list[tuple[float, dict[str, int]]] = []
    bus = None
    try:
        wait_until(lambda: (run_dir / "processes.json").exists(), 30, "the launcher to start the cell")
        bus = Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), "faults")
        bus.subscribe(
            keys.estimate_status("faults"),
            m.EstimatorStatus,
            callback=lambda r: states.append((time.monotonic(), {c.camera_id: c.state for c in r.msg.cameras})),
        )
        yield run_dir, states, proc, bus
    finally:
        stop_launcher(proc, run_dir)
        if bus is not None:
            bus.close()


def pid_of(run_dir: Path, name: str) -> int:
    return next(p["pid"] for p in json.loads((run_dir / "processes.json").read_text()) if p["name"] == name)


def localized(states, cam: str) -> bool:
    return bool(states) and states[-1][1].get(cam) == m.CameraState.LOCALIZED


def kill_once_localized(run_dir: Path, states, name: str) -> tuple[int, float]:
    """Wait until both cameras are localized, SIGKILL process ``name``: its pid and when (monotonic s)."""
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    pid = pid_of(run_dir, name)
    os.kill(pid, signal.SIGKILL)
    return pid, time.monotonic()


def zenoh_segments(pid: int) -> set[str]:
    """The zenoh shared-memory segments a process maps (its own pools and those it received from)."""
    return {line.split()[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines() if line.endswith(".zenoh")}


def test_killed_driver_goes_stale_and_recovers_after_restart(cell) -> None:
    """Also: the restarted driver sends plain bytes (``shm_driver_starts`` = 1) and makes no pool, so
    the router, which keeps every pool it has seen mapped (zenoh issue 2787), maps nothing new."""
    run_dir, states, _, _ = cell
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    router_before = zenoh_segments(pid_of(run_dir, "router"))
    old, killed = kill_once_localized(run_dir, states, "driver/a")
    wait_until(lambda: states[-1][1].get("a") == m.CameraState.STALE, 5, "camera a to go stale")
    stale_at = next(t for t, s in states if t > killed and s.get("a") == m.CameraState.STALE)
    assert stale_at - killed < 1.0, f"stale only {stale_at - killed:.2f} s after the kill"
    assert states[-1][1]["b"] == m.CameraState.LOCALIZED  # the other camera is unaffected
    wait_until(lambda: pid_of(run_dir, "driver/a") != old, 10, "the supervisor to restart the driver")
    wait_until(lambda: localized(states, "a"), 30, "camera a localized again")
    assert zenoh_segments(pid_of(run_dir, "driver/a")) == set(), "the restarted driver made a shared-memory pool"
    time.sleep(1.0)  # more frames of the new driver through the router
    new = zenoh_segments(pid_of(run_dir, "router")) - router_before
    # Another process's first large message (recognition's cloud) may come late on a slow machine:
    # its pool is that process's own, not one the restart made.
    others = set().union(
        *(
            zenoh_segments(p["pid"])
            for p in json.loads((run_dir / "processes.json").read_text())
            if p["name"] not in ("router", "driver/a")
        )
    )
    assert not new - others, (
        f"the router mapped {len(new - others)} new segments after the restart: {sorted(new - others)}"
    )


def test_killed_estimator_restarts_with_its_map_and_localizes_within_a_second(cell) -> None:
    run_dir, states, _, _ = cell
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 60, "both cameras localized")
    wait_until(lambda: (run_dir / "estimator_state.json").exists(), 15, "the estimator to save its map")
    _, killed = kill_once_localized(run_dir, states, "estimator")
    wait_until(lambda: any(t > killed + 0.3 for t, _ in states), 30, "status from the restarted estimator")
    first = next(t for t, _ in states if t > killed + 0.3)
    wait_until(lambda: localized(states, "a") and localized(states, "b"), 10, "cameras localized after the restart")
    back = next(
        t
        for t, s in states
        if t >= first and s.get("a") == m.CameraState.LOCALIZED and s.get("b") == m.CameraState.LOCALIZED
    )
    assert back - first < 1.0, f"localized {back - first:.2f} s after the restarted estimator's first status"
    log = (run_dir / "logs" / "estimator.log").read_text()
    assert "restored" in log, "the restarted estimator did not restore its map"


def test_killed_router_restarts_and_every_process_reconnects(cell) -> None:
    run_dir, states, _, bus = cell
    # Every process must have joined before the router goes: one that never connected exits and is
    # restarted (its first session cannot open), which is not what this test is about.
    wait_until(
        lambda: {"estimator", "recognition", "recorder", "driver"} <= {k.split("/")[3] for k in bus.alive()},
        60,
        "every process's liveliness token",
    )
    old, killed = kill_once_localized(run_dir, states, "router")
    wait_until(lambda: pid_of(run_dir, "router") != old, 10, "the supervisor to restart the router")
    wait_until(lambda: any(t > killed + 1.0 for t, _ in states), 30, "status over the restarted router")
    wait_until(
        lambda: localized(states, "a") and localized(states, "b"), 10, "both cameras localized after the restart"
    )
    restarted = {p["name"]: p["restarts"] for p in json.loads((run_dir / "processes.json").read_text())}
    assert restarted.pop("router") == 1
    assert not any(restarted.values()), f"processes restarted instead of reconnecting: {restarted}"


def _frame(i: int, rng: np.random.Generator) -> m.RawImage:
    """A 320x240 16-bit frame of noise (lz4 cannot shrink it: ~150 KB on disk), stamped i ns."""
    return codec.image_to_msg(rng.integers(0, 65536, (240, 320), dtype=np.uint16), 1 + i, "cam1", "16UC1")


def _stamps(path: Path) -> tuple[list[int], ReadReport]:
    report = ReadReport()
    return [x.publish_time_ns - 1 for x in read_log(path, None, report)], report


def test_recorder_on_a_full_disk_keeps_its_chunks_and_resumes_in_a_new_part(
    router_endpoint: str, small_disk: Path
) -> None:
    """16 MiB disk, 4 MiB taken: two 4 MiB chunks fit, the third fails. Freeing the 4 MiB lets the
    recorder start a second part; the first keeps every frame up to its last complete chunk."""
    filler = small_disk / "filler"
    filler.write_bytes(bytes(4 << 20))
    path, rng, sent = small_disk / "rec.mcap", np.random.default_rng(0), 0
    transport = TransportConfig(connect=[router_endpoint])
    with Bus(transport, "disk") as rec_bus, Bus(transport, "disk") as pub_bus:
        rec = Recorder(rec_bus, path, retry_s=0.5)
        pub = pub_bus.publisher(keys.depth("disk", "cam1"), frames=True)

        def publish_until(done, what: str) -> None:
            nonlocal sent
            deadline = time.monotonic() + 30
            while not done():
                assert time.monotonic() < deadline, f"timed out waiting for {what}"
                pub.put(_frame(sent, rng))
                sent += 1
                time.sleep(0.01)

        publish_until(lambda: rec.messages > 0, "the recorder to subscribe")
        publish_until(lambda: rec.failures, "the disk to fill")
        filler.unlink()
        publish_until(lambda: len(rec.parts) == 2 and rec.messages > 0, "a second part")
        resumed = sent
        publish_until(lambda: sent >= resumed + 20, "20 more frames")
        time.sleep(0.3)
        rec.close()
    assert "No space left" in rec.failures[0]
    first, report = _stamps(rec.parts[0])
    assert report.stopped_early is not None  # no footer: the part ended on the failed write
    assert len(first) >= 40, f"only {len(first)} frames kept of the two complete 4 MiB chunks"
    assert first == list(range(first[0], first[0] + len(first))), "frames missing inside the kept chunks"
    second, report = _stamps(rec.parts[1])
    assert report.stopped_early is None and len(second) >= 20
    assert second == list(range(second[0], second[0] + len(second))) and second[0] > first[-1]
