"""The estimator daemon over real zenoh sessions: publishing, map query, persisted state, bad input."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from cellsight.evaluation.synthetic import NoiseSettings, estimator_config, frame_observations, observations_msg
from drivers.sim.scenario import CameraSpec, MarkerSpec, Scenario
from estimator.service import ClockJumps, EstimatorService
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, Received, TransportConfig
from schemas.spec import PoseSpec
from tests.helpers import assert_pose_close, wait_until

CELL = "svc"


def scene() -> Scenario:
    wall = lambda i, x, role="static": MarkerSpec(  # noqa: E731
        id=i, role=role, side_m=0.25, pose=PoseSpec(position=(x, 2.0, 1.0), normal=(0.0, -1.0, 0.0))
    )
    return Scenario(
        markers=[wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2)],
        cameras=[CameraSpec(id="a", pose=PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.3, 2.0, 1.0)))],
    )


def feed(
    bus: Bus,
    s: Scenario,
    seconds: float,
    start_ns: int,
    garbage: bool = False,
    clock_step_ns: Callable[[str, int], int] | None = None,
) -> None:
    """Publish observations of every camera at 30 Hz (real time / 3 to keep the test short);
    ``clock_step_ns(camera, frame)`` sets how far that camera's clock is off at that frame."""
    pubs = {c.id: bus.publisher(keys.markers(CELL, c.id)) for c in s.cameras}
    raw = bus.session.declare_publisher(keys.markers(CELL, "a"))
    rng = np.random.default_rng(0)
    for k in range(int(seconds * 30)):
        stamp = start_ns + int(k * 1e9 / 30)
        for cam, pub in pubs.items():
            off = clock_step_ns(cam, k) if clock_step_ns else 0
            pub.put(observations_msg(cam, stamp + off, frame_observations(s, cam, 0.0, stamp, rng, NoiseSettings())))
        if garbage and k % 5 == 0:
            raw.put(b"\x0a\x03cam\x10" + bytes(rng.integers(0, 256, 40, dtype=np.uint8)))
        time.sleep(1 / 90)


def run_service(
    transport: TransportConfig,
    s: Scenario,
    state: Path,
    seconds: float,
    start_ns: int,
    garbage: bool = False,
    clock_step_ns: Callable[[str, int], int] | None = None,
) -> tuple[EstimatorService, list]:
    cfg = estimator_config(s, state_file=state, update_hz=20.0)
    statuses: list[m.EstimatorStatus] = []
    with Bus(transport, CELL) as svc_bus, Bus(transport, CELL) as client:
        svc = EstimatorService(svc_bus, cfg)
        client.subscribe(keys.estimate_status(CELL), m.EstimatorStatus, callback=lambda r: statuses.append(r.msg))
        stop = threading.Event()
        thread = threading.Thread(target=svc.run, args=(stop,))
        thread.start()
        try:
            time.sleep(0.5)  # routes
            feed(client, s, seconds, start_ns, garbage, clock_step_ns)
            wait_until(lambda: svc.estimator.counters.observations > 0, 5.0, "observations to arrive")
            time.sleep(0.3)
            replies = client.query(keys.estimate_map(CELL))
        finally:
            stop.set()
            thread.join(10)
    return svc, statuses, replies


def test_an_update_of_several_cameras_frames_is_what_each_camera_alone_gives(client_transport: TransportConfig) -> None:
    """The daemon validates an update's frames of every camera together and then splits them by
    camera: the same estimate as each camera's frames ingested on their own, and a malformed frame
    counted against its own camera only."""
    s = scene()
    s = s.model_copy(
        update={
            "cameras": s.cameras
            + [CameraSpec(id="b", pose=PoseSpec(position=(0.6, 0.0, 1.2), look_at=(0.3, 2.0, 1.0)))]
        }
    )
    rng = np.random.default_rng(3)
    updates = []
    for k in range(0, 60, 3):
        items = []
        for j in range(3):  # three frames of each camera an update, interleaved
            stamp = 10**18 + int((k + j) * 1e9 / 30)
            for cam in ("a", "b"):
                msg = observations_msg(cam, stamp, frame_observations(s, cam, 0.0, stamp, rng, NoiseSettings()))
                if cam == "a" and k == 30 and j == 1:
                    msg.markers[0].camera_T_marker.qw = 5.0  # not a unit quaternion
                items.append(Received(keys.markers(CELL, cam), msg, stamp))
        updates.append(items)
    with Bus(client_transport, CELL) as bus_together, Bus(client_transport, CELL) as bus_apart:
        together, apart = (
            EstimatorService(bus_together, estimator_config(s)),
            EstimatorService(bus_apart, estimator_config(s)),
        )
        for items in updates:
            together.ingest(items)
            for cam in ("a", "b"):
                apart.ingest([r for r in items if r.msg.camera_id == cam])
            for svc in (together, apart):  # at the newest stamp: the wall clock must not make them differ
                svc.estimator.update(svc.clock.stamp_ns)
        est_together, est_apart = (svc.estimator.estimate(svc.clock.stamp_ns) for svc in (together, apart))
    assert together.bad_frames == apart.bad_frames == {"a": 1}
    assert together.estimator.counters.observations == apart.estimator.counters.observations > 0
    for cam in ("a", "b"):
        assert est_together.cameras[cam].pose is not None
        np.testing.assert_allclose(est_together.cameras[cam].pose.T, est_apart.cameras[cam].pose.T, atol=1e-9)


@pytest.mark.slow
def test_camera_poses_follow_every_update_and_the_map_at_most_update_hz(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    s = scene()
    cfg = estimator_config(s, update_hz=5.0, max_update_hz=30.0)
    stamps: dict[str, list[float]] = {"cameras": [], "markers": [], "status": []}
    with Bus(client_transport, CELL) as svc_bus, Bus(client_transport, CELL) as client:
        svc = EstimatorService(svc_bus, cfg)
        for what, key, typ in (
            ("cameras", keys.estimate_cameras(CELL), m.PosesWithCovariance),
            ("markers", keys.estimate_markers(CELL), m.PosesWithCovariance),
            ("status", keys.estimate_status(CELL), m.EstimatorStatus),
        ):
            client.subscribe(key, typ, callback=lambda r, what=what: stamps[what].append(time.monotonic()))
        stop = threading.Event()
        thread = threading.Thread(target=svc.run, args=(stop,))
        thread.start()
        try:
            time.sleep(0.5)  # routes
            feed(client, s, 2.0, 10**18)  # 60 frames over ~0.7 s of wall time
            time.sleep(0.3)
        finally:
            stop.set()
            thread.join(10)
    span = stamps["cameras"][-1] - stamps["cameras"][0]
    # The map and status: at most 5 Hz (one more for the window's ends); camera poses with each
    # frame-triggered update, several times as often.
    for what in ("markers", "status"):
        assert len(stamps[what]) <= 5.0 * (span + 0.5) + 2, (what, len(stamps[what]), span)
    assert len(stamps["cameras"]) >= 2 * len(stamps["markers"]), {k: len(v) for k, v in stamps.items()}


@pytest.mark.slow
def test_daemon_publishes_answers_the_map_and_survives_garbage(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    s = scene()
    svc, statuses, replies = run_service(client_transport, s, tmp_path / "state.json", 2.0, 10**18, garbage=True)
    assert statuses and statuses[-1].cameras[0].state == m.CameraState.LOCALIZED
    # the camera's three pair factors were built at least once, and the count only grows
    rebuilt = [s.factors_rebuilt for s in statuses]
    assert rebuilt[-1] >= 3 and rebuilt == sorted(rebuilt), rebuilt
    assert sum(svc._sub.bad.values()) > 0, "the garbage was not seen (test set-up)"
    assert len(replies) == 1
    poses = codec.poses_from_msg(replies[0].msg.cameras)
    assert_pose_close(poses["a"].T, s.camera("a").world_T_camera(0.0), 0.02, 0.5, "camera a from the map query")
    assert {"marker_1", "marker_2", "marker_3"} <= set(codec.poses_from_msg(replies[0].msg.markers))


@pytest.mark.slow
def test_restart_restores_the_map(client_transport: TransportConfig, tmp_path: Path) -> None:
    s = scene()
    state = tmp_path / "state.json"
    run_service(client_transport, s, state, 2.0, 10**18)
    assert state.exists()
    # A fresh daemon whose config has no anchor left and whose camera sees only markers 1-3:
    # without the restored map it would be unanchored; with it, it is localised at once.
    s.markers = [mk for mk in s.markers if mk.id != 0]
    svc, statuses, _ = run_service(client_transport, s, state, 0.3, 10**18 + 10**15)
    assert svc.restored == 4  # markers 0-3 as saved
    assert statuses[-1].cameras[0].state == m.CameraState.LOCALIZED


@pytest.mark.slow
def test_corrupt_state_is_set_aside_not_trusted(client_transport: TransportConfig, tmp_path: Path) -> None:
    s = scene()
    state = tmp_path / "state.json"
    state.write_text('{"sha256": "0", "body": {"version": 1, "cell": "svc", "markers": {}}}')
    svc, statuses, _ = run_service(client_transport, s, state, 1.0, 10**18)
    assert svc.restored == 0
    assert list(tmp_path.glob("state.json.corrupt-*")), "the corrupt file was not kept aside"
    assert statuses[-1].cameras[0].state == m.CameraState.LOCALIZED  # started from the anchors


@pytest.mark.slow
def test_a_sensor_clock_that_jumps_is_taken_out_and_no_camera_goes_stale(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    """Camera a's clock steps an hour ahead after 1 s, then two hours back after 2 s (an NTP step
    each way); camera b's clock stays put. Both must stay localized throughout: without the
    correction the first step makes b stale (the daemon's clock follows a) and the second makes a
    stale (its frames go backwards and are refused)."""
    s = scene()
    s.cameras.append(CameraSpec(id="b", pose=PoseSpec(position=(0.6, 0.0, 1.2), look_at=(0.3, 2.0, 1.0))))
    hour = 3600 * 10**9
    step = lambda cam, k: 0 if cam == "b" or k < 30 else (hour if k < 60 else -hour)  # noqa: E731
    svc, statuses, _ = run_service(client_transport, s, tmp_path / "state.json", 3.0, 10**18, clock_step_ns=step)
    assert dict(svc.clock_jumps.jumps) == {"a": 2}
    assert len(statuses) > 20
    late = statuses[len(statuses) // 2 :]  # after the first jump (1 s of 3 s; statuses from 0.5 s on)
    for st_ in late:
        assert {c.camera_id: c.state for c in st_.cameras} == {
            "a": m.CameraState.LOCALIZED,
            "b": m.CameraState.LOCALIZED,
        }
    assert abs(late[-1].stamp_ns - (10**18 + 3 * 10**9)) < 2 * 10**9  # published on the timeline it started with


@pytest.mark.slow
def test_a_full_disk_keeps_the_saved_state_and_saving_resumes(
    client_transport: TransportConfig, small_disk: Path, caplog
) -> None:
    s = scene()
    state = small_disk / "state.json"
    run_service(client_transport, s, state, 1.0, 10**18)
    saved = state.read_bytes()
    filler = small_disk / "filler"
    with open(filler, "wb") as f:  # fill the disk to the last byte
        try:
            while True:
                f.write(bytes(1 << 16))
                f.flush()
        except OSError:
            pass
    svc, statuses, _ = run_service(client_transport, s, state, 1.0, 10**18 + 10**15)
    assert svc.save_failures >= 1 and "cannot save state" in caplog.text
    assert statuses[-1].cameras[0].state == m.CameraState.LOCALIZED  # it kept running
    assert state.read_bytes() == saved, "the saved state was damaged by the failed save"
    assert sorted(p.name for p in small_disk.iterdir()) == ["filler", "state.json"]  # no half-written copy left
    filler.unlink()
    svc, _, _ = run_service(client_transport, s, state, 0.3, 10**18 + 2 * 10**15)
    assert svc.restored == 4 and svc.save_failures == 0
    assert state.read_bytes() != saved  # saved again


def _corrected(jumps: ClockJumps, frames: list[tuple[int, int]]) -> list[int]:
    return [jumps.correct("a", stamp, arrival) for stamp, arrival in frames]


@pytest.mark.parametrize("stall_ms", [2000, 4990, 5010, 6000, 30000])
def test_a_late_frame_or_a_replay_at_another_rate_is_not_a_clock_jump(stall_ms: int) -> None:
    ms = 10**6
    jumps = ClockJumps(5000 * ms)
    # A driver stalled after stamping frames 9 and 10 (SIGSTOP, a long first detection): they
    # arrive late, by a little less and a little more than the stall; the next ones are captured
    # after it and arrive on time. Stalls near the jump threshold are the soak's case: two late
    # frames either side of it must not walk the reference down so that the on-time frame after
    # them reads as a step ahead.
    stall = stall_ms * ms
    late = {9: stall - 10 * ms, 10: stall + 40 * ms}
    stamps = [k * 33 * ms + (stall + 60 * ms if k > 10 else 0) for k in range(30)]
    arrivals = [k * 33 * ms + 20 * ms + (stall + 60 * ms if k > 10 else late.get(k, 0)) for k in range(30)]
    frames = list(zip(stamps, arrivals))
    assert _corrected(jumps, frames) == [s for s, _ in frames] and not jumps.jumps
    for wall_ms in (3, 66):  # 20 s of stamps replayed in 1.8 s (--rate 11) and in 40 s (--rate 0.5)
        replay = [(k * 33 * ms, k * wall_ms * ms) for k in range(600)]
        jumps = ClockJumps(5000 * ms)
        assert _corrected(jumps, replay) == [s for s, _ in replay] and not jumps.jumps


def test_a_clock_step_back_is_taken_out_once_it_persists() -> None:
    ms, hour = 10**6, 3600 * 10**9
    jumps = ClockJumps(5000 * ms, confirm_frames=5)
    frames = [(k * 33 * ms - (hour if k >= 10 else 0), k * 33 * ms) for k in range(30)]
    out = _corrected(jumps, frames)
    assert dict(jumps.jumps) == {"a": 1}
    assert out[14:] == [k * 33 * ms for k in range(14, 30)]  # back on its timeline from the 5th frame
    assert all(s < 0 for s in out[10:14])  # the first four still read an hour back (refused as backwards)
