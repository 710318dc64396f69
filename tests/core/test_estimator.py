"""The estimator core on small synthetic scenes with known answers (gtsam test style).

Observations come from ``cellsight.evaluation.synthetic``: true poses plus noise drawn from the marker
front-end's covariance model. Tolerances are a few sigma of the expected accuracy.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest

from cellsight.evaluation.synthetic import NoiseSettings, estimator_config, flip, frame_observations
from drivers.markers import covariance_model
from drivers.sim.scenario import CameraMotion, CameraSpec, MarkerSpec, Scenario
from estimator.estimate import CameraState, through_camera
from estimator.graph import Estimator
from estimator.observation import Observation, ObservationRows
from estimator.pairs import Pair, fold_rows
from schemas.codec import CameraInfo
from schemas.geometry import make_pose, rotation_angle, rpy_matrix
from schemas.spec import PoseSpec
from tests.helpers import assert_pose_close

RATE = 30.0


SIDE_M = 0.25  # the demo cell's wall markers


def wall(mid: int, x: float, role: str = "static") -> MarkerSpec:
    """A marker on the far wall (y = 2), facing the cameras at y = 0."""
    return MarkerSpec(id=mid, role=role, side_m=SIDE_M, pose=PoseSpec(position=(x, 2.0, 1.0), normal=(0.0, -1.0, 0.0)))


def camera(cid: str, x: float, look_x: float, motion: list[CameraMotion] | None = None) -> CameraSpec:
    return CameraSpec(id=cid, pose=PoseSpec(position=(x, 0.0, 1.2), look_at=(look_x, 2.0, 1.0)), motion=motion or [])


def run(
    scenario: Scenario,
    seconds: float,
    est: Estimator | None = None,
    start_s: float = 0.0,
    seed: int = 0,
    noise: NoiseSettings = NoiseSettings(),
    update_every: int = 3,
) -> Estimator:
    """Feed every camera at 30 Hz for ``seconds`` and update every few frames."""
    est = est or Estimator(estimator_config(scenario))
    rng = np.random.default_rng(seed)
    n0, n1 = int(round(start_s * RATE)), int(round((start_s + seconds) * RATE))
    for k in range(n0, n1):
        t = k / RATE
        stamp = int(round(t * 1e9))
        for cam in scenario.cameras:
            est.add_frame(cam.id, stamp, frame_observations(scenario, cam.id, t, stamp, rng, noise))
        if k % update_every == 0:
            est.update(stamp)
    est.update(stamp + 1)
    return est


def check_camera(est: Estimator, scenario: Scenario, cid: str, t: float, pos_mm: float, rot_deg: float) -> None:
    """Within the absolute bounds, and consistent with the estimator's own covariance (chi2 6 dof, 99.9 %)."""
    ce = est.estimate(int(t * 1e9)).cameras[cid]
    assert ce.state is CameraState.LOCALIZED, f"{cid} is {ce.state}"
    truth = scenario.camera(cid).world_T_camera(t)
    assert_pose_close(ce.pose.T, truth, pos_mm / 1000, rot_deg, cid)
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(ce.pose.T).between(gtsam.Pose3(truth)))  # (rot, trans), body frame
    err = np.concatenate([xi[3:], xi[:3]])  # ROS order
    nees = float(err @ np.linalg.solve(ce.pose.covariance, err))
    assert nees < 22.5, f"{cid}: error is {np.sqrt(nees):.1f} sigma of the reported covariance"


def test_isam2_matches_batch_on_the_same_graph() -> None:
    """With relinearisation on every step, the incremental machinery (fused pair factors replaced
    in their slots) must give the batch optimum of the same graph. The production threshold
    (0.001 cameras, 0.005 markers) trades a little accuracy for speed: benchmarks.estimator_accuracy
    measures that."""
    s = Scenario(
        markers=[wall(0, 0.0, "anchor"), wall(1, 0.6), wall(2, 1.2)],
        cameras=[camera("a", 0.0, 0.4), camera("b", 1.2, 0.8)],
    )
    est = run(s, 2.0, Estimator(estimator_config(s, relinearize_threshold=1e-9, relinearize_threshold_markers=1e-9)))
    # One iSAM2 update is one reweighted Gauss-Newton step: Huber weights settle linearly, so
    # 100 steps (10 s of the daemon's 10 Hz updates) stand in for batch LM's inner iterations.
    est.relax(100)
    graph = est.factor_graph()
    initial = gtsam.Values()
    for key in est.values.keys():  # start the batch solve far from the answer
        initial.insert(key, est.values.atPose3(key) * gtsam.Pose3(gtsam.Rot3.Rz(0.05), np.array([0.05, -0.03, 0.02])))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    params.setMaxIterations(1000)
    batch = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    for key in est.values.keys():
        assert_pose_close(
            est.values.atPose3(key).matrix(), batch.atPose3(key).matrix(), 1e-5, 1e-3, gtsam.DefaultKeyFormatter(key)
        )


def test_case1_common_anchor() -> None:
    s = Scenario(markers=[wall(0, 0.6, "anchor")], cameras=[camera("a", 0.0, 0.6), camera("b", 1.2, 0.6)])
    est = run(s, 2.0)
    for cid in ("a", "b"):
        check_camera(est, s, cid, 2.0, pos_mm=10.0, rot_deg=0.3)


def test_case2_shared_non_anchor_marker() -> None:
    """a sees the anchor and marker 1; b sees only marker 1."""
    s = Scenario(
        markers=[wall(0, -1.4, "anchor"), wall(1, 0.3)], cameras=[camera("a", -0.6, -0.5), camera("b", 1.4, 1.6)]
    )
    s.cameras[1].pose = PoseSpec(position=(1.0, 1.0, 1.2), look_at=(0.3, 2.0, 1.0))
    obs_b = {o.marker_id for o in frame_observations(s, "b", 0.0, 0, np.random.default_rng(0), NoiseSettings())}
    assert obs_b == {1}, f"scene set-up: b should only see marker 1, sees {obs_b}"
    est = run(s, 2.0)
    check_camera(est, s, "a", 2.0, pos_mm=10.0, rot_deg=0.3)
    check_camera(est, s, "b", 2.0, pos_mm=15.0, rot_deg=0.5)


def test_case3a_chained_through_other_cameras() -> None:
    """c0 sees the anchor and m1; c1 sees m1 and m2; c2 sees only m2: placed through two links."""
    markers = [wall(0, -2.0, "anchor"), wall(1, -0.5), wall(2, 1.0)]
    cams = [
        CameraSpec(id="c0", pose=PoseSpec(position=(-1.25, 0.5, 1.2), look_at=(-1.25, 2.0, 1.0))),
        CameraSpec(id="c1", pose=PoseSpec(position=(0.25, 0.5, 1.2), look_at=(0.25, 2.0, 1.0))),
        CameraSpec(id="c2", pose=PoseSpec(position=(1.4, 0.5, 1.2), look_at=(1.4, 2.0, 1.0))),
    ]
    s = Scenario(markers=markers, cameras=cams)
    seen = {
        c.id: {o.marker_id for o in frame_observations(s, c.id, 0.0, 0, np.random.default_rng(0), NoiseSettings())}
        for c in cams
    }
    assert seen == {"c0": {0, 1}, "c1": {1, 2}, "c2": {2}}, f"scene set-up: {seen}"
    est = run(s, 2.0)
    for cid in ("c0", "c1", "c2"):
        check_camera(est, s, cid, 2.0, pos_mm=15.0, rot_deg=0.5)


def test_case3b_no_anchor_is_unanchored_then_joins() -> None:
    """b sees only marker 2, which nobody else sees: unanchored, no world pose. Then a path appears:
    camera a slides 0.8 m along the wall (at t = 1 s) and sees the anchor and marker 2 together."""
    slide = CameraMotion(kind="slide", offset=(0.8, 0.0, 0.0), start_s=1.0, end_s=1.3)
    markers = [wall(0, -1.0, "anchor"), wall(2, 0.6)]
    cams = [
        CameraSpec(id="a", pose=PoseSpec(position=(-1.0, 0.5, 1.2), look_at=(-1.0, 2.0, 1.0)), motion=[slide]),
        CameraSpec(id="b", pose=PoseSpec(position=(1.4, 0.5, 1.2), look_at=(1.4, 2.0, 1.0))),
    ]
    s = Scenario(markers=markers, cameras=cams)
    seen = {
        (c, t): {o.marker_id for o in frame_observations(s, c, t, 0, np.random.default_rng(0), NoiseSettings())}
        for c in ("a", "b")
        for t in (0.0, 2.0)
    }
    assert seen == {("a", 0.0): {0}, ("a", 2.0): {0, 2}, ("b", 0.0): {2}, ("b", 2.0): {2}}, f"scene set-up: {seen}"
    est = run(s, 1.0)
    e = est.estimate(int(1e9))
    assert e.cameras["b"].state is CameraState.UNANCHORED and e.cameras["b"].pose is None
    assert 2 not in e.markers  # the unanchored component never entered the solver
    assert e.cameras["a"].state is CameraState.LOCALIZED
    est = run(s, 3.0, est, start_s=1.0)
    assert est.estimate(int(4e9)).cameras["a"].segment == 1
    check_camera(est, s, "a", 4.0, pos_mm=30.0, rot_deg=0.6)
    check_camera(est, s, "b", 4.0, pos_mm=30.0, rot_deg=0.6)


def test_bumped_camera_is_detected_and_reconverges_without_dragging_others() -> None:
    bump = CameraMotion(kind="bump", start_s=2.0, rotation_deg=(2.0, 0.0, 0.0), offset=(0.03, 0.0, 0.0))
    markers = [wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2, "anchor")]
    s = Scenario(markers=markers, cameras=[camera("a", 0.0, 0.3, [bump]), camera("b", 0.6, 0.3)])
    est = run(s, 2.0)
    before_b = est.estimate(int(2e9)).cameras["b"].pose.T
    est = run(s, 1.0, est, start_s=2.0)  # one second of data after the bump
    e = est.estimate(int(3e9))
    assert e.cameras["a"].segment == 1, "the bump did not start a new segment"
    check_camera(est, s, "a", 3.0, pos_mm=10.0, rot_deg=0.3)
    check_camera(est, s, "b", 3.0, pos_mm=10.0, rot_deg=0.3)
    assert_pose_close(e.cameras["b"].pose.T, before_b, 0.002, 0.05, "b moved when a was bumped")
    assert e.flagged_anchors == []  # a bumped camera is not a moved anchor


def test_a_move_whose_turn_cancels_its_shift_at_the_markers_is_caught() -> None:
    """30 mm sideways and turned back toward the markers: each marker moves under 1 cm in the
    camera's frame (the per-marker test's threshold), but together they are one rigid motion of
    the camera, which the fit of that motion sees."""
    bump = CameraMotion(kind="bump", start_s=2.0, rotation_deg=(0.0, -0.85, 0.0), offset=(0.03, 0.0, 0.0))
    markers = [wall(0, 0.0, "anchor"), wall(1, 0.15), wall(2, 0.3), wall(3, 0.45), wall(4, 0.6, "anchor")]
    s = Scenario(markers=markers, cameras=[camera("a", 0.0, 0.3, [bump]), camera("b", 0.6, 0.3)])
    before, after = s.camera("a").world_T_camera(1.0), s.camera("a").world_T_camera(3.0)
    shifts = [
        np.linalg.norm(
            (np.linalg.inv(after) @ s.world_T_marker(m, 3.0) - np.linalg.inv(before) @ s.world_T_marker(m, 1.0))[:3, 3]
        )
        for m in s.markers
    ]
    assert max(shifts) < Estimator(estimator_config(s)).config.bump_position_m, "not the case under test"
    est = run(s, 2.0)
    est = run(s, 2.0, est, start_s=2.0)
    assert est.estimate(int(4e9)).cameras["a"].segment == 1, "the move did not start a new segment"
    check_camera(est, s, "a", 4.0, pos_mm=10.0, rot_deg=0.3)


@pytest.mark.parametrize("flip_rate", [0.0, 0.2])
@pytest.mark.slow
def test_a_moving_camera_is_posed_from_full_marker_poses(flip_rate: float) -> None:
    """While a camera moves it is posed frame by frame from the mapped markers. Six markers along a
    shallow arc (3 cm deep over 1.2 m, as a ring's are from inside): their centres leave a turn
    about the arc nearly free (fitted on centres: 44-118 mm median error here), their own
    rotations do not. One frame at 2 m poses the camera to ~7 mm median here, flips or not
    (a fifth of the observations on the wrong IPPE branch, each marker's branch chosen by the
    rotation most imply): the bounds are twice that and ~3x its worst."""

    def arc(mid: int, x: float, role: str) -> MarkerSpec:
        return MarkerSpec(
            id=mid,
            role=role,
            side_m=SIDE_M,
            pose=PoseSpec(position=(x, 2.0 - 0.03 * (x / 0.6) ** 2, 1.0), normal=(0.0, -1.0, 0.0)),
        )

    markers = [arc(i, x, "anchor" if i in (0, 5) else "static") for i, x in enumerate(np.linspace(-0.6, 0.6, 6))]
    sweep = CameraMotion(kind="sweep", amplitude_deg=5.0, period_s=2.0, start_s=2.0)
    s = Scenario(markers=markers, cameras=[camera("a", -0.3, 0.0), camera("b", 0.3, 0.0, [sweep])])
    est = Estimator(estimator_config(s))
    rng = np.random.default_rng(0)
    errors = []
    for k in range(int(4.0 * RATE)):
        t = k / RATE
        stamp = int(round(t * 1e9))
        for cam in s.cameras:
            est.add_frame(
                cam.id, stamp, frame_observations(s, cam.id, t, stamp, rng, NoiseSettings(flip_rate=flip_rate))
            )
        if k % 3 == 0:
            est.update(stamp)
            b = est.estimate(stamp, with_covariance=False).cameras["b"]
            if b.state is CameraState.MOVING and b.pose is not None:
                errors.append(np.linalg.norm(b.pose.T[:3, 3] - s.camera("b").world_T_camera(t)[:3, 3]))
    assert len(errors) >= 10, f"b was reported moving in {len(errors)} updates of its 2 s sweep"
    assert np.median(errors) < 0.015 and max(errors) < 0.06, (
        f"moving pose off by {np.median(errors) * 1e3:.0f} mm median, {max(errors) * 1e3:.0f} max"
    )


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.slow
def test_flips_are_absorbed(seed: int) -> None:
    """A fifth of the observations on the wrong IPPE branch (the same noise draws otherwise, and
    without depth, so positions are loose along the ray): each camera ends where it ends without
    flips, within a fraction of its own error (4-12 mm, 0.1-0.3 deg here)."""
    poses = []
    for flip_rate in (0.0, 0.2):
        s = Scenario(
            markers=[wall(0, 0.0, "anchor"), wall(1, 0.6), wall(2, 1.2)],
            cameras=[camera("a", 0.0, 0.6), camera("b", 1.2, 0.6)],
        )
        est = run(s, 3.0, seed=seed, noise=NoiseSettings(depth=False, flip_rate=flip_rate))
        for cid in ("a", "b"):
            check_camera(est, s, cid, 3.0, pos_mm=30.0, rot_deg=0.5)
        poses.append({cid: est.estimate(int(3e9)).cameras[cid].pose.T for cid in ("a", "b")})
    for cid in ("a", "b"):
        assert_pose_close(poses[1][cid], poses[0][cid], 0.003, 0.1, f"{cid} with flips against without")


def test_a_flipped_observations_covariance_is_turned_to_the_branch_taken() -> None:
    """Without depth a marker's position is loose along the ray (the covariance's long axis). A
    front-end that reports the mirrored IPPE branch gives that pose's covariance in that pose's
    frame (``drivers.markers``); a pair that takes the true branch back must turn the covariance
    into it. Then its fused position covariance in the camera frame is the same whether 0 or 8 of
    20 exact observations came flipped, one by one (flips first: the young pair re-decides them)
    and batched, and in a pair that settled on the flip and swaps branches later. (Rotation
    blocks: the model's tilt axes differ between the branches; not compared.)"""
    info = CameraInfo.kinect_v1()
    T = make_pose(
        rpy_matrix(np.radians(-90.0 + 35.0), np.radians(20.0), 0.0), [0.4, -0.2, 2.5]
    )  # 35 and 20 deg off the ray
    F = flip(T)
    assert rotation_angle(T[:3, :3], F[:3, :3]) > np.radians(30.0)
    cov, cov_flipped = (covariance_model(P, SIDE_M, info, 0.5, None) for P in (T, F))
    reports = [
        (F, T, cov_flipped) if k % 5 in (0, 2) else (T, F, cov) for k in range(20)
    ]  # 8 flips, the first one of them

    def camera_frame(C: np.ndarray) -> np.ndarray:
        return T[:3, :3] @ C[:3, :3] @ T[:3, :3].T

    plain = Pair()
    for _ in range(20):
        plain.add_pose(T, F, cov)
    expected = camera_frame(plain.mean_covariance())
    one_by_one = Pair()
    for chosen, other, C in reports:
        assert one_by_one.add_pose(chosen, other, C)
    assert_pose_close(one_by_one.mean(exact=True), T, 1e-9, 1e-6, "the pair's mean")
    rows = ObservationRows(
        np.zeros(20, int),
        np.stack([r[0] for r in reports]),
        np.stack([r[1] for r in reports]),
        np.stack([r[2] for r in reports]),
        np.zeros(20, bool),
        np.arange(20),
    )
    batched = fold_rows(np.tile(T, (20, 1, 1)), np.zeros(20, int), 1, rows)
    # A pair that settled on the flip (20 of its first 30 flipped) and swaps branches later, when
    # most of its observations chose the other one: its sums turn with it.
    settled = Pair()
    for k in range(70):
        settled.add_pose(*((F, T, cov_flipped) if k < 20 else (T, F, cov)))
        if k == 29:
            assert rotation_angle(settled.mean(exact=True)[:3, :3], F[:3, :3]) < 1e-6, "settled on the flip"
    assert_pose_close(settled.mean(exact=True), T, 1e-9, 1e-6, "the settled pair's mean after the swap")
    for what, C in (
        ("one by one", one_by_one.mean_covariance()),
        ("batched", batched.sums[0, 21:].reshape(6, 6) / 20),
        ("swapped when settled", settled.mean_covariance()),
    ):
        got = camera_frame(C)
        assert np.abs(got - expected).max() <= 1e-9 * np.abs(expected).max(), f"{what}: {got} against {expected}"


def test_unknown_marker_is_counted_not_used() -> None:
    s = Scenario(markers=[wall(0, 0.6, "anchor")], cameras=[camera("a", 0.0, 0.6)])
    est = Estimator(estimator_config(s))
    T = s.camera("a").world_T_camera(0.0)
    bogus = Observation("a", 1, 99, np.linalg.inv(T) @ np.eye(4) @ np.diag([1, 1, 1, 1.0]), np.eye(6) * 1e-4)
    est.add_frame("a", 1, [bogus])
    est.update(1)
    assert est.counters.unknown_markers == 1 and 99 not in est.estimate(1).markers


def test_moved_anchor_is_flagged() -> None:
    markers = [wall(0, -0.6, "anchor"), wall(1, 0.0, "anchor"), wall(2, 0.6, "anchor"), wall(3, 1.2)]
    s = Scenario(markers=markers, cameras=[camera("a", 0.0, 0.3), camera("b", 0.6, 0.3)])
    cfg = estimator_config(s)
    s.markers[0].pose = PoseSpec(position=(-0.6, 2.0, 1.2), normal=(0.0, -1.0, 0.0))  # moved 20 cm up
    est = run(s, 2.0, Estimator(cfg))
    assert est.estimate(int(2e9)).flagged_anchors == [0]


def test_stale_camera() -> None:
    s = Scenario(markers=[wall(0, 0.6, "anchor")], cameras=[camera("a", 0.0, 0.6)])
    est = run(s, 1.0)
    assert est.estimate(int(1.0e9)).cameras["a"].state is CameraState.LOCALIZED
    assert est.estimate(int(3.0e9)).cameras["a"].state is CameraState.STALE


def test_time_going_backwards_is_ignored() -> None:
    s = Scenario(markers=[wall(0, 0.6, "anchor")], cameras=[camera("a", 0.0, 0.6)])
    est = run(s, 1.0)
    n = est.counters.observations
    est.add_frame("a", 1, frame_observations(s, "a", 0.0, 1, np.random.default_rng(1), NoiseSettings()))
    assert est.counters.observations == n and est.counters.rejected >= 1


@pytest.mark.parametrize("seconds", [2.0, 6.0])
def test_graph_stops_growing_for_static_cameras(seconds: float) -> None:
    s = Scenario(
        markers=[wall(0, 0.0, "anchor"), wall(1, 0.6), wall(2, 1.2)],
        cameras=[camera("a", 0.0, 0.6), camera("b", 1.2, 0.6)],
    )
    est = run(s, seconds)
    live = est.factor_graph().size()
    # One prior per anchor plus one factor per camera-marker pair, however long it runs.
    assert live == 1 + len(est.pairs)


@pytest.mark.slow
def test_settled_pairs_stop_costing_updates_without_moving_the_answer() -> None:
    """A settled pair's factor is rebuilt only when its mean moved ``refresh_sigma`` of the factor's
    sigma. Against rebuilding every ``refresh_s`` on the same observations: from 20 s to 40 s at most
    half the rebuilds (the mean's drift shrinks as 1/t, so the gaps grow as t^2), and each camera
    within the bound of least squares: a solution moves, in its own covariance's units, by at most
    the root-sum-square of its factors' whitened shifts, here refresh_sigma x sqrt(pairs)."""
    s = Scenario(
        markers=[wall(0, 0.0, "anchor"), wall(1, 0.6), wall(2, 1.2)],
        cameras=[camera("a", 0.0, 0.6), camera("b", 1.2, 0.6)],
    )
    rebuilt, estimators = {}, {}
    for name, cfg in (("lazy", estimator_config(s)), ("eager", estimator_config(s, refresh_sigma=0.0))):
        est = run(s, 20.0, Estimator(cfg))
        before = est.counters.factors_rebuilt
        estimators[name] = run(s, 20.0, est, start_s=20.0, seed=1)
        rebuilt[name] = est.counters.factors_rebuilt - before
    lazy, eager = estimators["lazy"], estimators["eager"]
    assert rebuilt["eager"] >= 15 * len(eager.pairs), rebuilt  # once a second per pair
    assert rebuilt["lazy"] <= rebuilt["eager"] / 2, rebuilt
    bound = lazy.config.refresh_sigma * np.sqrt(len(lazy.pairs))
    a, b = lazy.estimate(int(40e9)), eager.estimate(int(40e9))
    for cid in ("a", "b"):
        pa, pb = a.cameras[cid].pose, b.cameras[cid].pose
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(pb.T).between(gtsam.Pose3(pa.T)))  # (rot, trans), body frame
        err = np.concatenate([xi[3:], xi[:3]])  # ROS order, as the covariance
        assert float(np.sqrt(err @ np.linalg.solve(pb.covariance, err))) < bound, cid
        check_camera(lazy, s, cid, 40.0, 2.0, 0.1)


def test_an_update_with_nothing_due_reports_its_own_cost() -> None:
    """The status publishes ``last_update_ms`` every tick; a tick with no factor due must report
    that call, not repeat the last update that rebuilt something (it did, and made the soak's
    static-cell p99 the duration of whichever rebuild came last)."""
    s = Scenario(markers=[wall(0, 0.0, "anchor"), wall(1, 0.6)], cameras=[camera("a", 0.0, 0.3)])
    est = run(s, 1.0)
    now = int(1.5e9)
    est.update(now, refresh_all=True)
    assert est.counters.last_update_rebuilt > 0
    assert est.counters.last_update_cpu_ms > 0.0  # building and solving is CPU work
    busy_ms = est.counters.last_update_ms
    est.update(now)  # the same instant: everything was just rebuilt
    assert est.counters.last_update_rebuilt == 0
    assert est.counters.last_update_ms != busy_ms and est.counters.last_update_ms >= 0.0


def test_biased_marker_rotations_do_not_turn_the_camera() -> None:
    """A static view's rotation bias repeats every frame (the README measured ~1 deg in-plane on the
    renderer with OpenCV's corners), so averaging cannot remove it. Here each of three anchors is seen turned by a fixed
    1.5 deg about one of its axes while positions stay unbiased (sigma ~1 mm at 2 m). With the
    view-rotation floor the camera is placed by where the anchors are: within 0.15 deg (1 mm
    over their 0.5-1.2 m spread is 0.05-0.1 deg; seeds 0-3 gave 0.03-0.07). Without it (0) the
    biased orientations, each trusted to ~0.1 deg, turn the camera by several times that
    (0.22-0.34 deg)."""
    marks = [
        MarkerSpec(id=i, role="anchor", side_m=SIDE_M, pose=PoseSpec(position=(x, 2.0, z), normal=(0.0, -1.0, 0.0)))
        for i, (x, z) in enumerate([(-0.6, 0.8), (0.0, 1.3), (0.6, 0.9)])
    ]  # not on one line: positions fix all 3 axes
    s = Scenario(markers=marks, cameras=[camera("a", 0.0, 0.0)])
    axes = {0: (1.0, 0.0, 0.0), 1: (0.0, 1.0, 0.0), 2: (0.0, 0.0, 1.0)}  # marker frame: tilt, tilt, in-plane
    bias = {mk: gtsam.Rot3.Rodrigues(np.radians(1.5) * np.array(ax)).matrix() for mk, ax in axes.items()}
    errors = {}
    for floor in (1.0, 0.0):
        est = Estimator(estimator_config(s, view_rotation_sigma_deg=floor))
        rng = np.random.default_rng(0)
        for k in range(60):
            stamp = int(k / RATE * 1e9)
            frame = []
            for o in frame_observations(s, "a", k / RATE, stamp, rng, NoiseSettings()):
                T = o.camera_T_marker.copy()
                T[:3, :3] = T[:3, :3] @ bias[o.marker_id]
                frame.append(Observation(o.camera_id, o.stamp_ns, o.marker_id, T, o.covariance, None, False))
            est.add_frame("a", stamp, frame)
            if k % 3 == 0:
                est.update(stamp)
        est.update(stamp + 1)
        pose = est.estimate(stamp).cameras["a"].pose
        errors[floor] = math.degrees(rotation_angle(pose.T[:3, :3], s.camera("a").world_T_camera(0.0)[:3, :3]))
    assert errors[1.0] < 0.15, errors
    assert errors[0.0] > 3 * errors[1.0], errors


def test_object_marker_covariance_carries_the_camera_through_the_lever_arm() -> None:
    """Against gtsam's own Jacobian of a composition (d(wTc cTm)/d(wTc) = Ad(inv(cTm)), in its
    (rotation, translation) order): a camera's 0.1 deg rotation sigma shows at a marker 2 m away
    as ~3.5 mm, which the old sum of the two covariances left out."""
    rng = np.random.default_rng(3)
    cTm = gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3) * 0.5), np.array([0.3, -0.2, 2.0]))
    wTc = gtsam.Pose3(gtsam.Rot3.Rodrigues(rng.normal(size=3)), rng.normal(size=3))
    L = rng.normal(size=(6, 6)) * 1e-3
    cam_cov, obs_cov = L @ L.T, np.diag([1e-6] * 3 + [1e-5] * 3)
    T, cov = through_camera(wTc.matrix(), cam_cov, cTm.matrix(), obs_cov)
    H = cTm.inverse().AdjointMap()  # gtsam order (rx ry rz x y z)
    perm = [3, 4, 5, 0, 1, 2]
    cam_g = cam_cov[np.ix_(perm, perm)]  # ROS order -> gtsam order
    expected = (H @ cam_g @ H.T)[np.ix_(perm, perm)] + obs_cov
    np.testing.assert_allclose(T, wTc.compose(cTm).matrix(), atol=1e-12)
    np.testing.assert_allclose(cov, expected, rtol=1e-9, atol=1e-15)
    stacked_T, stacked = through_camera(wTc.matrix(), cam_cov, np.stack([cTm.matrix()] * 3), np.stack([obs_cov] * 3))
    np.testing.assert_allclose(stacked, np.stack([expected] * 3), rtol=1e-9, atol=1e-15)
    rot_only = np.diag([0.0] * 3 + [np.radians(0.1) ** 2] * 3)
    _, lever = through_camera(np.eye(4), rot_only, cTm.matrix(), np.zeros((6, 6)))
    assert 3.0 < 1000 * np.sqrt(np.trace(lever[:3, :3]) / 2) < 4.0  # ~2 m x 0.1 deg = 3.5 mm across two axes


def test_a_camera_bumped_within_its_first_frames_is_still_caught() -> None:
    """A camera bumped in its first frames (a slow camera under load: ~1 frame/s) has pairs of a
    few observations; they must still witness the move, or the moved frames fold into the first
    segment. A young pair's mean is uncertain by its observations' covariance over n, which the
    test adds; the bumped camera gets a new segment at its new pose."""
    bump = CameraMotion(kind="bump", start_s=0.1, rotation_deg=(2.0, 0.0, 0.0), offset=(0.03, 0.0, 0.0))
    markers = [wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2, "anchor")]
    s = Scenario(markers=markers, cameras=[camera("a", 0.0, 0.3, [bump]), camera("b", 0.6, 0.3)])
    # Kept history, so the first segment's pairs are still there to count (online, it is folded
    # once the new segment enters the graph); the motion test is the same either way.
    kept = run(s, 2.0, est=Estimator(estimator_config(s), keep_history=True))
    first = [p.n for ((cam, mk), p) in kept.pairs.items() if cam == ("a", 0)]
    assert first and max(first) <= 3, f"frames after the bump joined the first segment: {first} observations per pair"
    est = run(s, 2.0)
    assert est.estimate(int(2e9)).cameras["a"].segment == 1, "the bump in a's first frames did not start a new segment"
    check_camera(est, s, "a", 2.0, pos_mm=10.0, rot_deg=0.3)
    check_camera(est, s, "b", 2.0, pos_mm=10.0, rot_deg=0.3)
