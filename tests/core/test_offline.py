"""The offline solve's pure core: batched folding, moving frames, object-marker links, the benchmark's bound."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from benchmarks.offline_vs_online import upper_bound_95
from cellsight.evaluation.synthetic import (
    NoiseSettings,
    demo,
    estimator_config,
    flip,
    frame_observations,
    observations_msg,
)
from drivers.sim.scenario import CameraMotion, CameraSpec, MarkerSpec, Scenario
from estimator.config import LinkConfig
from estimator.graph import Estimator, camera_symbol
from estimator.keyframes import MovingFrame, place_frame
from estimator.links import ObjectLinks, Sighting, add_links
from estimator.observation import observation_rows, observations_of
from schemas import codec
from schemas import messages as m
from schemas.geometry import invert_pose, make_pose, rotation_angle
from schemas.spec import PoseSpec
from tests.helpers import assert_pose_close


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


@pytest.mark.slow
def test_batched_frames_fold_in_like_one_at_a_time() -> None:
    """``Estimator.add_frames`` (the offline fast path) against ``add_frame`` per frame, on the demo
    cell with 5 % planar flips, cam1's tilt and cam2's bump (both brought forward to keep it short):
    same segments, same pairs, same means. The batched path gets each frame's markers in a shuffled
    order, as a detector lists them differently from frame to frame."""
    s = demo()
    s.camera("cam1").motion = [CameraMotion(kind="tilt", amplitude_deg=-10.0, start_s=2.0, end_s=4.0)]
    s.camera("cam2").motion = [
        CameraMotion(kind="bump", start_s=6.0, rotation_deg=(2.0, 0.0, 0.0), offset=(0.03, 0.0, 0.0))
    ]
    cfg = estimator_config(s)
    rng = np.random.default_rng(3)
    one, batched = Estimator(cfg), Estimator(cfg)
    pending: dict[str, list] = {c.id: [] for c in s.cameras}
    segments: dict[str, list] = {c.id: [] for c in s.cameras}
    for k in range(int(10.0 * 30)):
        t, stamp = k / 30, 1_000_000_000 + k * 1_000_000_000 // 30
        for cam in s.cameras:
            msg = observations_msg(
                cam.id, stamp, frame_observations(s, cam.id, t, stamp, rng, NoiseSettings(flip_rate=0.05))
            )
            one.add_frame(cam.id, stamp, observations_of(cam.id, stamp, observation_rows(codec.marker_arrays(msg))))
            shuffled = m.MarkerObservations()
            shuffled.CopyFrom(msg)
            del shuffled.markers[:]
            shuffled.markers.extend(msg.markers[i] for i in rng.permutation(len(msg.markers)))
            pending[cam.id].append(shuffled)
            if len(pending[cam.id]) == 30:
                msgs = pending.pop(cam.id)
                pending[cam.id] = []
                stamps = np.array([x.stamp_ns for x in msgs])
                segments[cam.id] += batched.add_frames(cam.id, stamps, observation_rows(codec.marker_batch(msgs)))
    assert {c: t.segment for c, t in one.tracks.items()} == {c: t.segment for c, t in batched.tracks.items()}
    assert one.tracks["cam2"].segment >= 1 and segments["cam2"][-1] == one.tracks["cam2"].segment  # the bump
    assert set(one.pairs) == set(batched.pairs)
    for key, pair in one.pairs.items():
        other = batched.pairs[key]
        assert abs(pair.n - other.n) <= max(1, pair.n // 100), (key, pair.n, other.n)
        if pair.n:
            # Means of hundreds of observations: the batch judges a few borderline ones against a
            # mean that is up to 30 frames older; 0.1 mm and 0.01 deg is far below the noise.
            assert_pose_close(pair.mean(exact=True), other.mean(exact=True), 1e-4, 0.01, what=str(key))


def _moving_frame(
    s: Scenario, world_T_camera: np.ndarray, flipped: set[int], outlier: int | None = None
) -> MovingFrame:
    """A frame of exact observations of every marker of ``s`` from ``world_T_camera``; rows in
    ``flipped`` carry the wrong IPPE branch as their choice, ``outlier`` is 60 mm off."""
    poses, alts = [], []
    for i, mk in enumerate(s.markers):
        T = invert_pose(world_T_camera) @ s.world_T_marker(mk, 0.0)
        if i == outlier:
            T = T.copy()
            T[:3, 3] += (0.06, 0.0, 0.0)
        poses.append(flip(T) if i in flipped else T)
        alts.append(T if i in flipped else flip(T))
    n = len(s.markers)
    return MovingFrame(
        "b",
        1,
        np.array([m.id for m in s.markers]),
        np.stack(poses),
        np.stack(alts),
        np.tile(np.eye(6) * 1e-6, (n, 1, 1)),
    )


def test_a_moving_frame_is_placed_by_the_markers_that_agree() -> None:
    """Two of four markers chose the mirrored IPPE branch and one more is 60 mm off: the frame's
    pose is the one the majority implies, each flip is taken back, the outlier is left out."""
    s = scene()
    s.markers.append(MarkerSpec(id=4, side_m=0.25, pose=PoseSpec(position=(0.3, 2.0, 1.6), normal=(0.0, -1.0, 0.0))))
    wTm = {mk.id: s.world_T_marker(mk, 0.0) for mk in s.markers}
    wTc = s.camera("b").world_T_camera(0.0)
    frame = _moving_frame(s, wTc, flipped={0, 2}, outlier=4)
    placed = place_frame(frame, wTm)
    assert placed is not None
    pose, kept, branches = placed.world_T_camera, placed.rows, placed.branches
    assert_pose_close(pose, wTc, 1e-9, 1e-6)
    assert kept == [0, 1, 2, 3]
    for j, k in zip(kept, branches):
        T = (frame.poses[j], frame.alternatives[j])[k]
        assert_pose_close(T, invert_pose(wTc) @ wTm[s.markers[j].id], 1e-9, 1e-6, f"marker {j}")
    assert branches == [1, 0, 1, 0]  # the flips taken back
    one = _moving_frame(s, wTc, flipped=set())
    assert (
        place_frame(MovingFrame("b", 1, one.ids[:1], one.poses[:1], one.alternatives[:1], one.covariances[:1]), wTm)
        is None
    )


def test_a_moving_frame_at_range_keeps_every_marker_its_noise_allows() -> None:
    """Eight wall markers 3 m away, single noisy frames (the front-end's covariance model, a fifth
    flipped): one marker's rotation noise puts the camera it implies 5-15 cm off, so agreement on
    implied positions would keep two or three (38 % here, 53 mm median error). Branches judged by
    rotation and the pose resected over all: every row's own covariance holds (a gate at 1 in 1,000
    keeps ~all), no flip is kept, and the camera lands at ~19 mm median here."""
    wall = lambda i, x: MarkerSpec(id=i, side_m=0.25, pose=PoseSpec(position=(x, 3.0, 1.0), normal=(0.0, -1.0, 0.0)))  # noqa: E731
    s = Scenario(
        markers=[wall(i, x) for i, x in enumerate(np.linspace(-0.9, 0.9, 8))],
        cameras=[CameraSpec(id="b", pose=PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.0, 3.0, 1.0)))],
    )
    wTm = {mk.id: s.world_T_marker(mk, 0.0) for mk in s.markers}
    wTc = s.camera("b").world_T_camera(0.0)
    rng = np.random.default_rng(0)
    kept, errors = [], []
    for i in range(50):
        obs = frame_observations(s, "b", 0.0, i, rng, NoiseSettings(flip_rate=0.2))
        frame = MovingFrame(
            "b",
            i,
            np.array([o.marker_id for o in obs]),
            np.stack([o.camera_T_marker for o in obs]),
            np.stack([o.alternative for o in obs]),
            np.stack([o.covariance for o in obs]),
        )
        placed = place_frame(frame, wTm)
        assert placed is not None, f"frame {i} not placed"
        pose, rows, branches = placed.world_T_camera, placed.rows, placed.branches
        kept.append(len(rows) / len(obs))
        errors.append(np.linalg.norm(pose[:3, 3] - wTc[:3, 3]))
        for j, k in zip(rows, branches):
            implied = wTm[int(frame.ids[j])] @ invert_pose((frame.poses[j], frame.alternatives[j])[k])
            assert np.degrees(rotation_angle(implied[:3, :3], wTc[:3, :3])) < 5.0, f"frame {i} marker {j}: a flip kept"
    assert np.mean(kept) > 0.95, f"kept {np.mean(kept):.0%} of the markers"
    assert np.median(errors) < 0.03, f"camera {np.median(errors) * 1e3:.0f} mm off (median)"


@pytest.mark.parametrize(("n", "t_table"), [(5, 2.132), (10, 1.833), (30, 1.699)])
def test_the_benchmarks_non_inferiority_bound_is_students_t(n: int, t_table: float) -> None:
    """offline_vs_online's one-sided 95 % bound on the mean against Student's t table (df = n - 1),
    to 1 %: the bound the README's non-inferiority claim rests on."""
    x = np.random.default_rng(n).normal(size=n)
    t = (upper_bound_95(x) - x.mean()) / (x.std(ddof=1) / np.sqrt(n))
    assert abs(t / t_table - 1) < 0.01, f"n={n}: t={t:.4f}, table {t_table}"


def _sighting(cam: str, world_T_camera: np.ndarray, world_T_marker: np.ndarray, stamp_ns: int) -> Sighting:
    T = invert_pose(world_T_camera) @ world_T_marker
    return Sighting(cam, 0, stamp_ns, T, flip(T), np.diag([1e-6, 1e-6, 4e-6, 1e-4, 1e-4, 1e-4]))


def test_object_marker_instants_alone_place_a_camera() -> None:
    """Camera b sees no static marker: only an object marker that a (held by a prior) also sees,
    at four non-collinear places. The position-only links fix b's position and rotation; exact
    sightings give b back exactly (to the solver's tolerance). A sighting 5 ms off the instant
    (more than sync_ms / 2) is not an instant."""
    a_T = PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.3, 2.0, 1.0)).matrix()
    b_T = PoseSpec(position=(0.8, 0.1, 1.3), look_at=(0.3, 2.0, 1.0)).matrix()
    links = ObjectLinks(LinkConfig(min_gap_s=0.5, sync_ms=2.0))
    for i, (x, z) in enumerate([(0.0, 0.9), (0.4, 0.9), (0.4, 1.2), (0.0, 1.3)]):
        world_T_marker = PoseSpec(position=(x, 1.8, z), normal=(0.0, -1.0, 0.0)).matrix()
        stamp = i * 500_000_000
        links.add(7, _sighting("a", a_T, world_T_marker, stamp))
        links.add(7, _sighting("b", b_T, world_T_marker, stamp + (5_000_000 if i == 3 else 1_000_000)))
    assert [len(s) for _, s in links.groups()] == [2, 2, 2]  # the fourth instant has a only
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    ka, kb = camera_symbol(0), camera_symbol(1)
    graph.add(gtsam.PriorFactorPose3(ka, gtsam.Pose3(a_T), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    values.insert(ka, gtsam.Pose3(a_T))
    values.insert(
        kb, gtsam.Pose3(b_T).compose(gtsam.Pose3(gtsam.Rot3.RzRyRx(0.01, -0.01, 0.02), gtsam.Point3(0.02, -0.01, 0.01)))
    )
    added = add_links(
        graph, values, links, {("a", 0): ka, ("b", 0): kb}, 4, gtsam.noiseModel.mEstimator.Huber.Create(1.345)
    )
    assert added == 3
    solved = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    assert_pose_close(solved.atPose3(kb).matrix(), b_T, 1e-5, 1e-3, "camera b from the links alone")


def test_object_link_instants_stay_bounded_and_on_their_grid() -> None:
    """Past max_links the grid doubles: what is kept spans the whole log on the coarser grid."""
    links = ObjectLinks(LinkConfig(min_gap_s=0.1, max_links=10))
    T = make_pose(np.eye(3), np.array([0.0, 0.0, 2.0]))
    for i in range(100):  # 10 s at 0.1 s
        for cam in ("a", "b"):
            links.add(7, _sighting(cam, np.eye(4), T, i * 100_000_000))
    groups = links.groups()
    assert len(groups) <= 10 and links.gap_ns == 1_600_000_000
    stamps = [s[0].stamp_ns for _, s in groups]
    assert all(t % links.gap_ns == 0 for t in stamps) and stamps[0] == 0 and stamps[-1] >= 10e9 - 2 * links.gap_ns
