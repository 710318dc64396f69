"""Recorder and replay on real zenoh sessions and real MCAP files."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cellsight.record import Recorder
from drivers.replay import replay
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.log import LogWriter, ReadReport, read_log
from tests.helpers import logged_messages, wait_until

CELL = "rr"


def status(i: int, camera: str = "cam1") -> m.DriverStatus:
    return m.DriverStatus(camera_id=camera, stamp_ns=1_000 + i, frames=i)


def test_recorder_writes_what_decodes_and_skips_garbage(client_transport: TransportConfig, tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    with Bus(client_transport, CELL) as rec_bus, Bus(client_transport, CELL) as pub_bus:
        rec = Recorder(rec_bus, path)
        pub = pub_bus.publisher(keys.status(CELL, "cam1"))
        raw = pub_bus.session.declare_publisher(keys.status(CELL, "cam1"))
        wait_until(lambda: (pub.put(status(0)), rec.messages > 0)[1], 5.0, "the recorder to subscribe")
        n0 = rec.messages
        for i in range(1, 51):
            pub.put(status(i))
            raw.put(b"\xff\xfe garbage")
        wait_until(lambda: rec.messages >= n0 + 50, 5.0, "50 messages recorded")
        rec.close()
    frames = [msg.frames for _, msg in logged_messages(path) if msg.frames > 0]
    assert frames == list(range(1, 51))
    assert rec.bad[keys.status(CELL, "cam1")] == 50


def test_recorder_keeps_what_a_faulty_producer_sent_and_the_reader_skips_it(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    """The recorder checks a payload against its key's schema only: a pose message with a NaN in it
    parses, so it is recorded as sent, and reading the log skips and counts it as every subscriber
    would."""
    path = tmp_path / "log.mcap"
    key = keys.estimate_cameras(CELL)
    good = codec.poses_to_msg(5, [codec.StampedPose("world", "cam1", 5, np.eye(4))])
    bad = m.PosesWithCovariance()
    bad.CopyFrom(good)
    bad.poses[0].pose.x = float("nan")
    with Bus(client_transport, CELL) as rec_bus, Bus(client_transport, CELL) as pub_bus:
        rec = Recorder(rec_bus, path)
        pub = pub_bus.publisher(key)
        wait_until(lambda: (pub.put(good), rec.messages > 0)[1], 5.0, "the recorder to subscribe")
        n0 = rec.messages
        pub.put(bad)
        pub.put(good)
        wait_until(lambda: rec.messages >= n0 + 2, 5.0, "both recorded")
        rec.close()
    assert not rec.bad
    report = ReadReport()
    read = [r.msg for r in read_log(path, report=report)]
    assert report.undecodable == 1 and len(read) == rec.messages - 1
    assert all(np.isfinite(msg.poses[0].pose.x) for msg in read)


@pytest.mark.slow
def test_replay_republishes_in_order_and_skips_estimates(client_transport: TransportConfig, tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    w = LogWriter(path)
    for i in range(30):
        t = 1_000_000_000 + i * 10_000_000
        w.write(keys.status(CELL, "cam1"), status(i), t)
        w.write(keys.estimate_status(CELL), m.EstimatorStatus(stamp_ns=t), t)
    w.close()
    with Bus(client_transport, CELL) as sub_bus, Bus(client_transport, CELL) as pub_bus:
        sub = sub_bus.subscribe(keys.everything(CELL), capacity=1000)
        time.sleep(0.5)
        result = replay(pub_bus, path, rate=10.0)
        wait_until(lambda: sub.received >= 30, 5.0, "the replayed messages")
        got = sub.drain()
    assert result.published == 30 and result.skipped == 30
    assert [g.msg.frames for g in got] == list(range(30))
    assert {g.key for g in got} == {keys.status(CELL, "cam1")}


@pytest.mark.slow
def test_recorder_killed_with_sigkill_leaves_a_readable_file(router_endpoint: str, tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cellsight.cli", "record", "--out", str(path), "--cell", CELL, "-e", router_endpoint],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with Bus(TransportConfig(connect=[router_endpoint]), CELL) as bus:
            pub = bus.publisher(keys.depth(CELL, "cam1"), frames=True)
            img = (np.arange(240 * 320) % 65536).astype(np.uint16).reshape(240, 320)
            deadline = time.monotonic() + 20
            # ~150 KB per frame: several 4 MB chunks are complete on disk before the kill.
            while time.monotonic() < deadline and (not path.exists() or path.stat().st_size < 3 * 4 * 1024 * 1024):
                pub.put(codec.image_to_msg(img, time.time_ns(), "cam1", "16UC1"))
                time.sleep(0.005)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(10)
    finally:
        proc.kill()
    report = ReadReport()
    n = sum(1 for _ in read_log(path, None, report))
    assert report.stopped_early is not None  # no footer: it was killed
    assert n >= 40, f"only {n} frames readable from a {path.stat().st_size} byte file"


def test_a_restarted_recorder_never_overwrites_a_recording(client_transport: TransportConfig, tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    with Bus(client_transport, CELL) as rec_bus:
        first = Recorder(rec_bus, path)
        first.close()
        kept = path.read_bytes()
        second = Recorder(rec_bus, path)
        second.close()
    assert first.parts == [path] and second.parts == [tmp_path / "log.1.mcap"]
    assert path.read_bytes() == kept


@pytest.mark.slow
def test_a_camera_falling_silent_is_marked_in_the_log(client_transport: TransportConfig, tmp_path: Path) -> None:
    """cam1 stops for ~1.5 s (a dropped link) and comes back; cam2 goes on throughout, and stops for
    good before the end: one gap each, cam1's within the silence, nothing for a camera that kept talking."""
    path = tmp_path / "log.mcap"
    with Bus(client_transport, CELL) as rec_bus, Bus(client_transport, CELL) as pub_bus:
        rec = Recorder(rec_bus, path, gap_after_s=0.5)
        cam1, cam2 = pub_bus.publisher(keys.status(CELL, "cam1")), pub_bus.publisher(keys.status(CELL, "cam2"))
        wait_until(lambda: (cam1.put(status(0)), rec.messages > 0)[1], 5.0, "the recorder to subscribe")

        def talk(seconds: float, *pubs) -> None:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                for pub in pubs:
                    pub.put(status(1, keys.parse(pub.key).camera))  # each camera's on its own key
                time.sleep(0.05)

        talk(0.5, cam1, cam2)
        silent_from = time.time_ns()
        talk(1.5, cam2)
        silent_to = time.time_ns()
        talk(0.5, cam1, cam2)
        talk(1.0, cam1)
        rec.close()
    report = ReadReport()
    for _ in read_log(path, report=report):
        pass
    gaps = report.gaps()
    assert [g.camera for g in gaps] == ["cam1", "cam2"]
    assert silent_from - 0.2e9 <= gaps[0].from_ns <= silent_from and silent_to <= gaps[0].to_ns <= silent_to + 0.2e9
    assert gaps[1].seconds >= 0.9  # silent from its last message to the end of the recording
    assert rec.gaps == gaps
