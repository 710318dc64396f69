"""Offline re-solve of MCAP logs: a synthetic log with known answers, and a truncated one."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from cellsight.config import CellConfig
from cellsight.evaluation.resolve_report import peek_config, run_resolve
from cellsight.evaluation.synthetic import NoiseSettings, ViewBiases, frame_observations, observations_msg
from cellsight.record import Recorder
from cellsight.scenario_config import cell_config_of
from drivers.replay import replay
from drivers.sim.scenario import CameraMotion, CameraSpec, MarkerSpec, ObjectMotion, ObjectSpec, Scenario
from estimator.config import KeyframeConfig
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.geometry import invert_pose
from schemas.log import LogWriter, read_log
from schemas.spec import PoseSpec
from tests.helpers import assert_pose_close, wait_until

CELL = "res"


def scene() -> Scenario:
    wall = lambda i, x, role="static": MarkerSpec(  # noqa: E731
        id=i, role=role, side_m=0.25, pose=PoseSpec(position=(x, 2.0, 1.0), normal=(0.0, -1.0, 0.0))
    )
    return Scenario(
        markers=[wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2, "anchor")],
        cameras=[
            CameraSpec(id="a", pose=PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.3, 2.0, 1.0))),
            CameraSpec(id="b", pose=PoseSpec(position=(0.6, 0.0, 1.2), look_at=(0.3, 2.0, 1.0))),
        ],
    )


def write_log(
    path: Path, s: Scenario, seconds: float, flip_rate: float = 0.05, view_biases: bool = False
) -> CellConfig:
    """A log of ``s`` seen by its cameras at 30 Hz, with ground truth at 10 Hz; ``view_biases``:
    each view carries a bias as the estimator's factor model allows for (``ViewBiases``)."""
    cfg = cell_config_of(s, base=CellConfig.model_validate({"cell": {"name": CELL}}))
    e = cfg.estimator
    biases = ViewBiases(e.max_fused, np.radians(e.view_rotation_sigma_deg)) if view_biases else None
    specs = {mk.id: mk for mk in s.markers}
    w = LogWriter(path, chunk_size=64 * 1024, metadata={"config": cfg.to_toml()})
    rng = np.random.default_rng(1)
    t0 = 1_700_000_000_000_000_000
    for k in range(int(seconds * 30)):
        stamp, t = t0 + int(k * 1e9 / 30), k / 30
        for cam in s.cameras:
            obs = frame_observations(s, cam.id, t, stamp, rng, NoiseSettings(flip_rate=flip_rate))
            if biases is not None:
                camera_T_world = invert_pose(cam.world_T_camera(t))
                obs = [biases.apply(o, camera_T_world @ s.world_T_marker(specs[o.marker_id], t), rng) for o in obs]
            w.write(keys.markers(CELL, cam.id), observations_msg(cam.id, stamp, obs), stamp)
            if k % 3 == 0:
                truth = [codec.StampedPose("world", cam.id, stamp, cam.world_T_camera(t))]
                w.write(keys.truth(CELL, "cameras"), codec.poses_to_msg(stamp, truth), stamp)
        if k % 3 == 0 and s.objects:
            moving = [
                codec.StampedPose("world", f"marker_{mk.id}", stamp, s.world_T_marker(mk, t))
                for mk in s.markers
                if mk.role == "object"
            ]
            w.write(keys.truth(CELL, "marker_poses"), codec.poses_to_msg(stamp, moving), stamp)
    w.close()
    return cfg


def test_resolve_recovers_the_cameras_and_writes_the_report(tmp_path: Path) -> None:
    s = scene()
    log = tmp_path / "log.mcap"
    write_log(log, s, 5.0)
    cfg = peek_config(log)
    assert cfg is not None and len(cfg.estimator.anchors) == 2  # the anchors come from the log itself
    run = run_resolve(log, tmp_path / "out", cfg)
    segs = {seg.camera_id: seg for seg in run.result.segments}
    assert set(segs) == {"a", "b"} and run.result.unanchored == []
    for cid, seg in segs.items():
        assert_pose_close(seg.world_T_camera, s.camera(cid).world_T_camera(0.0), 0.005, 0.1, cid)
    for name in (
        "resolved.mcap",
        "report.html",
        "top_view.png",
        "residuals.png",
        "outliers.png",
        "online_vs_offline.png",
        "errors_vs_truth.png",
        "resolve.json",
        "config.toml",
    ):
        assert (tmp_path / "out" / name).stat().st_size > 0, name
    assert 'src="errors_vs_truth.png"' in (tmp_path / "out" / "report.html").read_text()  # the log has ground truth
    tum = (tmp_path / "out" / "trajectories" / "a.tum").read_text().splitlines()
    assert len(tum) >= 140 and len(tum[0].split()) == 8  # t x y z qx qy qz qw, one per frame
    figures = json.loads((tmp_path / "out" / "resolve.json").read_text())
    assert figures["cameras"]["a"]["offline_vs_truth_mm_deg"][0] < 5.0


def test_reading_the_log_in_a_child_process_gives_the_same_solution(tmp_path: Path) -> None:
    """``cellsight resolve`` reads the log in a child process while it solves: the same blocks in
    the same order, so the same answer to the last bit, the same messages handed on, the same report."""
    s = scene()
    log = tmp_path / "log.mcap"
    cfg = write_log(log, s, 3.0)
    runs = {bg: run_resolve(log, tmp_path / f"out_{bg}", cfg, background=bg) for bg in (True, False)}
    a, b = runs[True], runs[False]
    assert [s.camera_id for s in a.result.segments] == [s.camera_id for s in b.result.segments]
    for sa, sb in zip(a.result.segments, b.result.segments):
        np.testing.assert_array_equal(sa.world_T_camera, sb.world_T_camera)
    assert a.result.observations == b.result.observations > 0
    assert a.read.messages == b.read.messages and a.read.metadata == b.read.metadata
    assert a.evidence.truth_cameras.stamps == b.evidence.truth_cameras.stamps  # truth reached the evaluation too


def test_object_markers_are_placed_over_time_through_the_solved_cameras(tmp_path: Path) -> None:
    """A marker on a box sliding 0.3 m back and forth, seen by both cameras: resolved.mcap carries
    it on the daemon's key at <= 10 Hz, each pose through the solved camera with the smaller
    uncertainty, within a few mm of the truth at its stamp (single frames at ~2 m: a depth-refined
    observation is good to ~1 mm; the camera adds its own few mm), inside its reported covariance."""
    s = scene()
    s.objects = [
        ObjectSpec(
            id="box",
            pose=PoseSpec(position=(0.3, 1.7, 0.9)),
            motion=ObjectMotion(kind="slide", offset=(0.3, 0.0, 0.0), period_s=4.0),
        )
    ]
    s.markers.append(
        MarkerSpec(
            id=7,
            role="object",
            object="box",
            side_m=0.15,
            pose=PoseSpec(position=(0.0, -0.05, 0.1), normal=(0.0, -1.0, 0.0)),
        )
    )
    log = tmp_path / "log.mcap"
    write_log(log, s, 5.0, flip_rate=0.0)
    run = run_resolve(log, tmp_path / "out", peek_config(log))
    assert 7 not in run.result.markers  # an object marker never joins the map
    poses = [
        p
        for lm in read_log(tmp_path / "out" / "resolved.mcap")
        if lm.key == keys.estimate_markers(CELL)
        for p in codec.poses_from_msg(lm.msg).values()
        if p.child == "marker_7"
    ]
    stamps = np.array([p.stamp_ns for p in poses])
    assert 40 <= len(poses) <= 51 and np.diff(stamps).min() > 0  # ~10 Hz over 5 s, in time order
    t0 = 1_700_000_000_000_000_000
    errors = [
        np.linalg.norm(p.T[:3, 3] - s.world_T_marker(s.markers[-1], (p.stamp_ns - t0) / 1e9)[:3, 3]) for p in poses
    ]
    assert np.median(errors) < 0.004 and max(errors) < 0.012, (np.median(errors), max(errors))
    # The covariance tells the truth about the error (camera's uncertainty carried through the lever
    # arm): most positions inside their 95 % ellipsoid (chi-square, 3 dof), none absurdly wide.
    nees = []
    for p in poses:
        e = p.T[:3, 3] - s.world_T_marker(s.markers[-1], (p.stamp_ns - t0) / 1e9)[:3, 3]
        R = p.T[:3, :3]  # the covariance is in the marker frame
        nees.append(float(e @ R @ np.linalg.solve(p.covariance[:3, :3], R.T @ e)))
    assert np.mean(np.array(nees) < 7.81) >= 0.8, sorted(nees)
    assert np.median([np.sqrt(np.trace(p.covariance[:3, :3])) for p in poses]) < 0.01
    figures = json.loads((tmp_path / "out" / "resolve.json").read_text())
    # both cameras render at the same stamps: the box's marker linked them at every 0.2 s instant
    assert figures["object_links"] == run.result.object_links >= 20
    figures = figures["object_markers"]["marker_7"]
    assert figures["poses"] == len(poses) and figures["offline_vs_truth_mm_deg"][0] < 4.0
    assert len((tmp_path / "out" / "trajectories" / "marker_7.tum").read_text().splitlines()) == len(poses)
    from cellsight.compare import newest_poses

    newest, _ = newest_poses(tmp_path / "out" / "resolved.mcap")  # what compare weighs: not the moving box
    assert {"a", "b", "marker_0"} <= set(newest) and "marker_7" not in newest


def test_truncated_log_is_resolved_from_what_is_readable(tmp_path: Path) -> None:
    s = scene()
    log = tmp_path / "log.mcap"
    write_log(log, s, 5.0)
    data = log.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # mid-chunk, no summary, no footer
    cfg = peek_config(cut)
    run = run_resolve(cut, tmp_path / "out", cfg)
    assert run.read.stopped_early is not None
    assert 0 < run.result.frames < 2 * 150
    assert not json.loads((tmp_path / "out" / "resolve.json").read_text())["log_complete"]
    for seg in run.result.segments:
        assert_pose_close(seg.world_T_camera, s.camera(seg.camera_id).world_T_camera(0.0), 0.01, 0.2, seg.camera_id)


def test_corrupt_chunk_stops_reading_with_a_warning(tmp_path: Path) -> None:
    s = scene()
    log = tmp_path / "log.mcap"
    write_log(log, s, 3.0)
    data = bytearray(log.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 200] = bytes(200)  # garbage in a chunk: its CRC no longer matches
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    run = run_resolve(bad, tmp_path / "out", peek_config(bad))
    assert run.read.stopped_early is not None and run.result.frames > 0


def test_log_without_config_is_refused_with_a_clear_error(tmp_path: Path) -> None:
    log = tmp_path / "plain.mcap"
    LogWriter(log).close()
    out = subprocess.run(
        [sys.executable, "-m", "cellsight.cli", "resolve", str(log)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 2 and "--config" in out.stderr


def test_compare_finds_the_camera_that_moved_between_two_days(tmp_path: Path) -> None:
    from cellsight.compare import compare, newest_poses

    day1, day2 = scene(), scene()
    day2.cameras[1].pose = PoseSpec(position=(0.62, 0.0, 1.2), look_at=(0.3, 2.0, 1.0))  # b moved 2 cm
    for name, s in (("day1", day1), ("day2", day2)):
        write_log(tmp_path / f"{name}.mcap", s, 4.0)
        run_resolve(tmp_path / f"{name}.mcap", tmp_path / name, peek_config(tmp_path / f"{name}.mcap"))
    a, _ = newest_poses(tmp_path / "day1" / "resolved.mcap")
    b, _ = newest_poses(tmp_path / "day2" / "resolved.mcap")
    verdicts = {c.frame: c for c in compare(a, b)}
    assert verdicts["b"].verdict == "moved" and 15 < verdicts["b"].position_mm < 25
    assert verdicts["a"].verdict == "unchanged", verdicts["a"]
    assert all(verdicts[f"marker_{i}"].verdict == "unchanged" for i in (0, 1, 2, 3)), verdicts


def test_moving_camera_frames_are_solved_as_poses_of_their_own(tmp_path: Path) -> None:
    """Camera b slides 0.3 m between 2 and 3 s. Its frames in between join no segment; offline each
    kept one (>= 0.1 s apart, a new view) is a pose of its own, on estimate/cameras and in b's TUM
    trajectory. A single frame of 2-4 markers at ~2 m under the synthetic noise is good to ~15 mm:
    each error must lie inside its reported covariance (position NEES under 16.3, chi-square 3 dof
    99.9 %), the median under the median sigma. With ``max_frames`` 3 the kept frames still span
    the move; with keyframes off, or fewer frames than ``min_frames``, there are none. The views
    carry the biases the factor model allows for; in the same log without them the static pairs
    fit over ten times better than they claim and the frames are left out (``max_inflation``)."""
    s = scene()
    s.cameras[1].motion = [CameraMotion(kind="slide", offset=(0.3, 0.0, 0.0), start_s=2.0, end_s=3.0)]
    log = tmp_path / "log.mcap"
    write_log(log, s, 5.0, flip_rate=0.0, view_biases=True)
    cfg = peek_config(log)
    run = run_resolve(log, tmp_path / "out", cfg)
    frames = run.result.keyframes
    t0 = 1_700_000_000_000_000_000
    assert 5 <= len(frames) <= 12 and {k.camera_id for k in frames} == {"b"}, [
        (k.camera_id, k.stamp_ns) for k in frames
    ]
    errors, sigmas = [], []
    for k in frames:
        t = (k.stamp_ns - t0) / 1e9
        assert 2.0 <= t <= 3.5, t
        e = s.camera("b").world_T_camera(t)[:3, 3] - k.world_T_camera[:3, 3]
        R = k.world_T_camera[:3, :3]  # the covariance is in the camera (body) frame
        assert float(e @ R @ np.linalg.solve(k.covariance[:3, :3], R.T @ e)) < 16.27, (
            f"frame at {t:.2f} s off by {np.linalg.norm(e) * 1e3:.1f} mm"
        )
        errors.append(np.linalg.norm(e))
        sigmas.append(np.sqrt(np.trace(k.covariance[:3, :3])))
    assert np.median(errors) < np.median(sigmas), (np.median(errors), np.median(sigmas))
    assert np.diff([k.stamp_ns for k in frames]).min() >= 100_000_000
    tum = {float(line.split()[0]) for line in (tmp_path / "out" / "trajectories" / "b.tum").read_text().splitlines()}
    assert {round(k.stamp_ns / 1e9, 9) for k in frames} <= {round(x, 9) for x in tum}
    published = {
        p.stamp_ns
        for lm in read_log(tmp_path / "out" / "resolved.mcap")
        if lm.key == keys.estimate_cameras(CELL)
        for p in codec.poses_from_msg(lm.msg).values()
    }
    assert {k.stamp_ns for k in frames} <= published
    figures = json.loads((tmp_path / "out" / "resolve.json").read_text())["cameras"]["b"]
    assert figures["moving_frames"] == len(frames)
    # The log's truth is thinned to 10 Hz; interpolated along the straight slide it is exact.
    assert abs(figures["moving_frames_vs_truth_mm_deg"][0] - 1e3 * np.median(errors)) < 0.01
    few = cfg.model_copy(
        update={"estimator": cfg.estimator.model_copy(update={"keyframes": KeyframeConfig(max_frames=3, min_frames=1)})}
    )
    kept = sorted((k.stamp_ns - t0) / 1e9 for k in run_resolve(log, tmp_path / "few", few).result.keyframes)
    assert kept, "no moving frame survived the thinning"
    assert len(kept) <= 3 < len(frames), (kept, len(frames))  # bounded: fewer than without the bound
    assert kept[-1] - kept[0] >= 0.4, kept  # and still spread over the 1 s move, not its first frames
    off = cfg.model_copy(
        update={"estimator": cfg.estimator.model_copy(update={"keyframes": KeyframeConfig(enabled=False)})}
    )
    assert run_resolve(log, tmp_path / "off", off).result.keyframes == []
    sparse = cfg.model_copy(
        update={"estimator": cfg.estimator.model_copy(update={"keyframes": KeyframeConfig(min_frames=len(frames) + 1)})}
    )
    assert run_resolve(log, tmp_path / "sparse", sparse).result.keyframes == []  # a move with too few frames adds none
    assert run.figures.moving_frames_left_out == 0 and run.figures.moving_frames_covariance_scale == 1.0
    unbiased = tmp_path / "unbiased.mcap"
    write_log(unbiased, s, 5.0, flip_rate=0.0)
    left = run_resolve(unbiased, tmp_path / "unbiased", cfg)
    n_left = left.figures.moving_frames_left_out
    assert left.result.keyframes == [] and n_left >= KeyframeConfig().min_frames
    assert left.figures.moving_frames_covariance_scale > cfg.estimator.keyframes.max_inflation
    assert f"{n_left} moving frames left out" in (tmp_path / "unbiased" / "report.html").read_text()


def test_a_log_recorded_from_cellsight_replay_resolves_like_the_original(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    """Replay a log over zenoh (loopback router) into the recorder, then resolve the recording:
    every marker message survives the trip with its stamps, so the solve is the original's."""
    s = scene()
    original = tmp_path / "original.mcap"
    cfg = write_log(original, s, 3.0)
    recorded = tmp_path / "recorded.mcap"
    with Bus(client_transport, CELL) as rec_bus, Bus(client_transport, CELL) as pub_bus:
        rec = Recorder(rec_bus, recorded, metadata={"config": cfg.to_toml()})
        time.sleep(0.5)  # the recorder's subscription reaches the router
        result = replay(pub_bus, original, rate=5.0)
        wait_until(lambda: rec.messages >= result.published, 10.0, f"{result.published} replayed messages recorded")
        rec.close()
    assert result.published == sum(1 for _ in read_log(original, None))
    a = run_resolve(original, tmp_path / "a", cfg).result
    b = run_resolve(recorded, tmp_path / "b", peek_config(recorded)).result
    assert b.observations == a.observations and b.frames == a.frames
    segs = {(x.camera_id, x.segment): x for x in a.segments}
    assert sorted(segs) == sorted((x.camera_id, x.segment) for x in b.segments)
    for x in b.segments:
        assert_pose_close(
            x.world_T_camera, segs[(x.camera_id, x.segment)].world_T_camera, 1e-5, 1e-4, f"{x.camera_id}.{x.segment}"
        )


def test_a_log_from_the_openni2_driver_resolves_to_an_unanchored_camera(
    router_endpoint: str, client_transport: TransportConfig, tmp_path: Path
) -> None:
    """The real OpenNI2 runtime's Dummy device (blank images: frames but no markers) through the
    driver process and the recorder: resolve reads its frames and reports the camera unanchored,
    with the report written, instead of failing on a log with nothing to solve."""
    from cellsight.scenario_config import demo_config

    log = tmp_path / "openni2.mcap"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "cellsight.cli",
            "driver",
            "openni2",
            "--camera",
            "kinect",
            "--uri",
            "Dummy",
            "--duration",
            "30",
            "-e",
            router_endpoint,
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        with Bus(client_transport, "demo") as bus:
            rec = Recorder(bus, log)
            marker_msgs = bus.subscribe(keys.markers("demo", "kinect"), m.MarkerObservations, capacity=100)
            wait_until(lambda: marker_msgs.received >= 20, 30.0, "20 marker messages from the driver")
            rec.close()
    finally:
        proc.terminate()
        proc.wait(10)
    run = run_resolve(log, tmp_path / "out", demo_config())
    assert run.result.frames >= 15 and run.result.observations == 0
    assert run.result.segments == [] and run.result.unanchored == ["kinect"]
    figures = json.loads((tmp_path / "out" / "resolve.json").read_text())
    assert figures["log_complete"] and figures["unanchored"] == ["kinect"]
    assert (tmp_path / "out" / "report.html").stat().st_size > 0


def test_absurd_but_finite_observations_in_a_log_are_skipped_and_counted(tmp_path: Path) -> None:
    """Twenty observations at z = 1e6 m (the first at 1e300) among a camera's first frames made
    ``resolve`` die in iSAM2 (IndeterminateSystemException). They are what a running cell refuses,
    so the offline solve skips them too, says how many and why, and solves the rest as if they
    were not there."""
    s = scene()
    clean, dirty = tmp_path / "clean.mcap", tmp_path / "dirty.mcap"
    write_log(clean, s, 3.0)
    w = LogWriter(dirty, chunk_size=64 * 1024, metadata={"config": peek_config(clean).to_toml()})
    n = 0
    for lm in read_log(clean):
        if lm.key == keys.markers(CELL, "a") and n < 20:
            bad = m.MarkerObservations()
            bad.CopyFrom(lm.msg)
            bad.stamp_ns -= 1  # before the good frame: the camera's stamps keep going forward
            for o in bad.markers:
                o.camera_T_marker.z = 1e300 if n == 0 else 1e6
            w.write(lm.key, bad, lm.log_time_ns, bad.stamp_ns)
            n += 1
        w.write(lm.key, lm.msg, lm.log_time_ns, lm.publish_time_ns)
    w.close()
    a, b = (
        run_resolve(clean, tmp_path / "a", peek_config(clean)),
        run_resolve(dirty, tmp_path / "b", peek_config(dirty)),
    )
    assert b.read.refused == {(keys.markers(CELL, "a"), "out_of_bounds"): 20}
    assert b.result.frames == a.result.frames
    for sa, sb in zip(a.result.segments, b.result.segments):
        np.testing.assert_allclose(sb.world_T_camera, sa.world_T_camera, atol=1e-9)
    out = subprocess.run(
        [sys.executable, "-m", "cellsight.cli", "resolve", str(dirty), "--out", str(tmp_path / "c")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0 and "20 messages on cellsight/res/a/markers (out_of_bounds)" in out.stderr.replace(
        "\n", " "
    ), out.stderr


def test_a_log_cut_before_its_config_is_called_cut_and_an_empty_solve_exits_1(tmp_path: Path) -> None:
    """A log cut after a few bytes was reported as having "no embedded cell config"; a log with no
    marker frames exited 0 where the docs promise 1."""
    s = scene()
    log = tmp_path / "log.mcap"
    cfg = write_log(log, s, 1.0)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[:40])
    out = subprocess.run(
        [sys.executable, "-m", "cellsight.cli", "resolve", str(cut)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 2 and "cut or damaged at byte" in out.stderr and "no embedded" not in out.stderr, (
        out.stderr
    )
    empty = tmp_path / "empty.mcap"
    LogWriter(empty, metadata={"config": cfg.to_toml()}).close()
    out = subprocess.run(
        [sys.executable, "-m", "cellsight.cli", "resolve", str(empty), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 1 and "no marker frames" in out.stderr, (out.returncode, out.stderr)
