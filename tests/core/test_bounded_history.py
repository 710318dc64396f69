"""Bounded history: camera segments that ended are marginalised into marker factors.

Small synthetic cells fed observations directly (true camera_T_marker plus Gaussian noise of a
stated sigma), so a thousand moves run in seconds. Known answers: the graph of a camera moved
1,000 times is no larger than after 10 moves; a folded segment constrains the markers exactly as
keeping it does (``keep_history=True``, the offline solve's mode), and dropping it would not.
"""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cellsight.evaluation.synthetic import ViewBiases
from estimator.config import AnchorConfig, EstimatorConfig
from estimator.estimate import CameraState
from estimator.graph import Estimator, marker_symbol
from estimator.observation import Observation
from schemas.geometry import invert_pose, look_at_matrix, make_pose, quat_from_matrix, rpy_matrix
from schemas.spec import PoseSpec
from tests.helpers import assert_pose_close

RATE = 30
SIGMA_M, SIGMA_RAD = 0.002, 0.01  # per observation: 2 mm, 0.6 deg
COV = np.diag([SIGMA_M**2] * 3 + [SIGMA_RAD**2] * 3)


def marker(x: float, z: float = 1.0) -> np.ndarray:
    """A marker on the wall y = 2, facing -y."""
    return make_pose(rpy_matrix(np.pi / 2, 0.0, 0.0), [x, 2.0, z])


MARKERS = {0: marker(0.0), 1: marker(0.6), 2: marker(1.2), 3: marker(0.3, 1.5)}


def cam_pose(x: float, jitter: np.ndarray | None = None) -> np.ndarray:
    T = make_pose(look_at_matrix(np.array([x, 0.0, 1.2]), np.array([x, 2.0, 1.0])), [x, 0.0, 1.2])
    return T if jitter is None else T @ jitter


def config(fold_after_s: float = 0.0, **kw: float) -> EstimatorConfig:
    T = MARKERS[0]
    anchor = AnchorConfig(
        marker_id=0, world_T_marker=PoseSpec(position=tuple(T[:3, 3]), quaternion=tuple(quat_from_matrix(T[:3, :3])))
    )
    return EstimatorConfig(anchors=[anchor], fold_after_s=fold_after_s, view_rotation_sigma_deg=0.0, **kw)


def frame(
    cid: str, stamp: int, world_T_camera: np.ndarray, seen: list[int], rng: np.random.Generator
) -> list[Observation]:
    out = []
    for mk in seen:
        T = invert_pose(world_T_camera) @ MARKERS[mk]
        noisy = T @ make_pose(rpy_matrix(*(rng.normal(size=3) * SIGMA_RAD)), rng.normal(size=3) * SIGMA_M)
        out.append(Observation(cid, stamp, mk, noisy, COV))
    return out


class Cell:
    """Cameras at fixed poses, one of which (``a``) can be moved; 30 Hz, an update every 3 frames."""

    def __init__(self, est: Estimator, seed: int = 0, biases: ViewBiases | None = None) -> None:
        self.est, self.rng, self.k = est, np.random.default_rng(seed), 0
        self.biases = biases  # each view's bias on top of the frames' noise (none: noise alone)
        self.poses = {"a": cam_pose(0.3), "b": cam_pose(0.9)}
        self.seen = {"a": [0, 1, 2, 3], "b": [0, 1, 2, 3]}

    def run(self, seconds: float) -> None:
        for _ in range(int(seconds * RATE)):
            stamp = self.k * 1_000_000_000 // RATE
            for cid, T in self.poses.items():
                obs = frame(cid, stamp, T, self.seen[cid], self.rng)
                if self.biases is not None:
                    obs = [self.biases.apply(o, invert_pose(T) @ MARKERS[o.marker_id], self.rng) for o in obs]
                self.est.add_frame(cid, stamp, obs)
            if self.k % 3 == 0:
                self.est.update(stamp)
            self.k += 1

    def move_a(self, step: int) -> None:
        """Bump camera a by 3 cm and 1 deg, alternating direction, and let it settle (0.5 s)."""
        sign = 1.0 if step % 2 else -1.0
        self.poses["a"] = cam_pose(0.3, make_pose(rpy_matrix(0.0, np.radians(sign), 0.0), [0.03 * sign, 0.0, 0.0]))
        self.run(0.5)

    def now(self) -> int:
        return self.k * 1_000_000_000 // RATE


@pytest.mark.slow  # ~30 s: 1,000 moves at 30 Hz
def test_a_camera_moved_1000_times_leaves_the_graph_no_larger_than_after_10() -> None:
    cell = Cell(Estimator(config()))
    cell.run(1.0)
    sizes = {}
    for step in range(1, 1001):
        cell.move_a(step)
        if step in (10, 1000):
            cell.run(0.1)  # the last segment folded
            sizes[step] = (cell.est.factor_count(), cell.est.isam.calculateEstimate().size(), len(cell.est.pairs))
    assert cell.est.tracks["a"].segment >= 1000, f"only {cell.est.tracks['a'].segment} moves were detected"
    assert sizes[1000] <= sizes[10], f"(factors, variables, pairs) after 10 moves {sizes[10]}, after 1000 {sizes[1000]}"
    assert cell.est.history["a"].segments >= 999
    e = cell.est.estimate(cell.now())
    assert e.cameras["a"].state is CameraState.LOCALIZED
    # a's last segment is 0.5 s old (a few frames): its position sigma is ~5 mm, so a fixed mm bound
    # would test the noise draw. Its error must be what its own covariance allows (3 dof, 99.9 %).
    a = e.cameras["a"].pose
    d = a.T[:3, 3] - cell.poses["a"][:3, 3]
    assert d @ np.linalg.solve(a.covariance[:3, :3], d) <= 16.27, (
        f"a after 1000 moves: {1e3 * d} mm, sigmas {1e3 * np.sqrt(np.diag(a.covariance[:3, :3]))}"
    )
    assert_pose_close(a.T, cell.poses["a"], 0.01, 0.3, "a after 1000 moves")
    assert_pose_close(e.cameras["b"].pose.T, cell.poses["b"], 0.002, 0.2, "b after a's 1000 moves")


def test_a_folded_segment_still_constrains_the_markers_it_saw() -> None:
    """Marker 2 is seen by b and by a's first segment only; a then moves and stops seeing it.
    Folding that segment leaves marker 2's pose and covariance as keeping the segment does
    (within 2 % of a sigma, and of the covariance); dropping it loses a's views of marker 2: its
    covariance is then what b's views alone give, clearly larger. Markers relinearise at the
    cameras' threshold here: the default's slack (~0.1 sigma) would otherwise hide the fold's own."""
    results = {}
    for keep in (True, False):
        cell = Cell(Estimator(config(relinearize_threshold_markers=0.001), keep_history=keep), seed=3)
        cell.run(2.0)
        cell.seen["a"] = [0, 1, 3]
        cell.move_a(1)
        cell.run(1.0)
        assert cell.est.tracks["a"].segment == 1
        assert (("a", 0) in cell.est.camera_index) is keep  # folded unless kept
        # Both graphs hold every pair's final mean: a kept estimator's young segment entered the graph
        # at once, a folding one's after its pairs settled, so their factors were last refreshed at
        # different counts (0.13 sigma apart on marker 2), which is the refresh schedule, not the fold.
        cell.est.update(cell.now(), refresh_all=True)
        results[keep] = (cell.est.estimate(cell.now()).markers[2], cell.est)
    kept, folded = results[True][0], results[False][0]
    sigma = np.sqrt(np.diag(kept.covariance))
    d = gtsam.Pose3.Logmap(gtsam.Pose3(kept.T).between(gtsam.Pose3(folded.T)))
    assert np.all(np.abs(np.r_[d[3:], d[:3]]) <= 0.02 * sigma), (
        f"folded moved marker 2 by {np.r_[d[3:], d[:3]] / sigma} sigma"
    )
    np.testing.assert_allclose(np.diag(folded.covariance), np.diag(kept.covariance), rtol=0.02)
    # Drop a's first segment from the kept graph instead: marker 2 loses half its views.
    est = results[True][1]
    seg0 = gtsam.symbol("c", est.camera_index[("a", 0)])
    graph = gtsam.NonlinearFactorGraph()
    full = est.factor_graph()
    for i in range(full.size()):
        if seg0 not in full.at(i).keys():
            graph.add(full.at(i))
    values = gtsam.Values()
    for key in graph.keyVector():
        values.insert(key, est.values.atPose3(key))
    dropped = gtsam.Marginals(graph, gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()).marginalCovariance(
        marker_symbol(2)
    )
    kept_gtsam = est.isam.marginalCovariance(marker_symbol(2))
    assert np.trace(dropped[3:, 3:]) > 1.3 * np.trace(kept_gtsam[3:, 3:]), (
        "dropping the segment should cost marker 2 information"
    )


@pytest.mark.slow
def test_restart_from_the_persisted_map_after_many_moves() -> None:
    """The persisted state is the map (markers with covariances), bounded by the markers however
    often cameras moved; a new estimator seeded with it places both cameras on their first second."""
    cell = Cell(Estimator(config()))
    cell.run(1.0)
    for step in range(1, 101):
        cell.move_a(step)
    cell.run(0.2)
    saved = {mk: (p.T, p.covariance) for mk, p in cell.est.estimate(cell.now()).markers.items()}
    assert set(saved) == set(MARKERS)
    fresh = Estimator(config())
    fresh.seed_map({mk: v for mk, v in saved.items() if mk != 0})
    restarted = Cell(fresh, seed=9)
    restarted.poses = dict(cell.poses)
    restarted.k = cell.k
    restarted.run(1.0)
    e = fresh.estimate(restarted.now())
    for cid in ("a", "b"):
        assert_pose_close(e.cameras[cid].pose.T, cell.poses[cid], 0.002, 0.2, f"{cid} after restart")


def test_fused_measurement_is_the_information_weighted_mean() -> None:
    """Two measurements of one camera_T_marker a step d apart: with equal covariances the fused one
    lies half way (d / 2 from the first) with half the covariance; with the second a million
    times less certain, it stays on the first."""
    from estimator.history import HistoryFactor, fuse_measurements
    from schemas.geometry import pose_difference, pose_retract

    rng = np.random.default_rng(4)
    a = np.array([cam_pose(x) for x in rng.uniform(-1, 1, 5)])
    d = np.concatenate([rng.normal(scale=0.003, size=(5, 3)), rng.normal(scale=0.005, size=(5, 3))], axis=1)
    b = pose_retract(a, d)
    even = fuse_measurements([HistoryFactor(T, COV) for T in a], [HistoryFactor(T, COV) for T in b])
    np.testing.assert_allclose(pose_difference(a, np.array([f.mean for f in even])), d / 2, atol=1e-12)
    np.testing.assert_allclose(np.array([f.covariance for f in even]), np.broadcast_to(COV / 2, (5, 6, 6)), rtol=1e-9)
    lopsided = fuse_measurements([HistoryFactor(T, COV) for T in a], [HistoryFactor(T, 1e6 * COV) for T in b])
    np.testing.assert_allclose(pose_difference(a, np.array([f.mean for f in lopsided])), d * 1e-6, atol=1e-12)
    assert fuse_measurements([], []) == []


@pytest.mark.slow  # ~20 s: two 30 s runs of a 64-marker ring
def test_reordering_the_tree_changes_its_cost_not_the_answer() -> None:
    """The benchmark's ring cell (8 cameras, 64 markers), a camera bumped every 2 s for 30 s, with
    iSAM2's fill-in-triggered batch re-ordering off and at its most eager (any growth): the eager
    one re-orders more often and ends with a smaller Bayes tree, and every camera and marker ends
    where the other puts it (within a tenth of a millimetre and a hundredth of a degree: the two
    differ only in when they relinearise). A tiny cell would not do: there every update touches
    most of the tree, and iSAM2 re-orders it all anyway."""
    from benchmarks.estimator_scale import TICK_NS, Mover, Runner, ring_cell, tick_pools

    ends = {}
    for fill in (0.0, 1.01):
        markers, cams, anchors = ring_cell(8, 64)
        anchor_cfg = [
            AnchorConfig(
                marker_id=a,
                world_T_marker=PoseSpec(
                    position=tuple(markers[a][:3, 3]), quaternion=tuple(quat_from_matrix(markers[a][:3, :3]))
                ),
            )
            for a in anchors
        ]
        base = tick_pools(markers, cams, np.random.default_rng(0))
        pools = dict(base)
        mover = Mover(cams, base, pools, 20, np.random.default_rng(1))
        runner = Runner(Estimator(EstimatorConfig(anchors=anchor_cfg, reorder_fill=fill)), pools, 300)
        for k in range(300):
            if mover.due(k):
                mover.move()
            runner.step()
        est = runner.est
        ends[fill] = (est.counters.reorders, est.isam.treeNnz(), est.estimate(runner.tick * TICK_NS))
    (off_reorders, off_nnz, off), (on_reorders, on_nnz, on) = ends[0.0], ends[1.01]
    assert on_reorders > off_reorders and on_nnz < off_nnz, (on_reorders, off_reorders, on_nnz, off_nnz)
    for cid in off.cameras:
        assert_pose_close(on.cameras[cid].pose.T, off.cameras[cid].pose.T, 1e-4, 0.01, cid)
    for mk in off.markers:
        assert_pose_close(on.markers[mk].T, off.markers[mk].T, 1e-4, 0.01, f"marker {mk}")


@pytest.mark.slow
def test_a_camera_that_settles_only_for_moments_leaves_the_graph_bounded() -> None:
    """Camera a is moved 3 cm and 1 deg every 0.3-1.0 s (an arm pausing between moves): its segments
    end faster than they fold, several a camera by one update. The graph after 60 s of that must be no
    larger than after 15 s: a camera's history is one star, however its segments came and went."""
    cell = Cell(Estimator(config(fold_after_s=2.0)), seed=7)
    cell.run(2.0)
    rng, sizes, step = np.random.default_rng(7), {}, 0
    for until in (15.0, 60.0):
        while cell.now() < until * 1e9:
            step += 1
            sign = 1.0 if step % 2 else -1.0
            cell.poses["a"] = cam_pose(0.3, make_pose(rpy_matrix(0.0, np.radians(sign), 0.0), [0.03 * sign, 0.0, 0.0]))
            cell.run(rng.uniform(0.3, 1.0))
        sizes[until] = (cell.est.factor_count(), cell.est.isam.calculateEstimate().size())
    assert cell.est.history["a"].segments >= 40, f"only {cell.est.history['a'].segments} segments folded"
    assert sizes[60.0] <= sizes[15.0], f"(factors, variables) after 15 s {sizes[15.0]}, after 60 s {sizes[60.0]}"
