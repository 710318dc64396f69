"""Online moving frames: a camera's frames while it moves join the daemon's graph as poses of their own.

The wall cell of ``test_bounded_history`` (anchor 0 and markers 1-3 on the wall y = 2, cameras a
and b): camera a pans 0.4 m along the wall in a second and a half, then stands still. Known
answers: the move's frames enter once a's new segment is in the graph, each where a was at its
stamp (within the cell's noise); they tighten the markers a saw on the way; the graph keeps at
most ``max_live`` of them however often a pans; they are weighed by how the static pairs fit.
"""

from __future__ import annotations

import gtsam
import numpy as np

from cellsight.evaluation.synthetic import ViewBiases
from estimator.config import KeyframeConfig
from estimator.graph import Estimator, marker_symbol
from schemas.geometry import cov_ros_to_gtsam, make_pose, rpy_matrix
from tests.core.test_bounded_history import COV, RATE, Cell, cam_pose, config
from tests.helpers import assert_pose_close

PAN_S = 1.5


def pan(cell: Cell, x0: float, x1: float) -> dict[int, np.ndarray]:
    """Move camera a from x0 to x1 (turning 5 deg on the way and back) over PAN_S, then hold it
    still for 2 s; returns its true pose at each frame stamp of the pan (ns -> world_T_camera)."""
    truth = {}
    frames = int(PAN_S * RATE)
    for i in range(1, frames + 1):
        s = i / frames
        cell.poses["a"] = cam_pose(
            x0 + (x1 - x0) * s, make_pose(rpy_matrix(0.0, np.radians(5.0) * np.sin(np.pi * s), 0.0), [0.0, 0.0, 0.0])
        )
        truth[cell.now()] = cell.poses["a"]
        cell.run(1 / RATE)
    cell.run(2.0)
    return truth


def test_a_pans_frames_enter_where_the_camera_was_and_tighten_the_markers() -> None:
    results = {}
    for online in (True, False):
        cell = Cell(Estimator(config(keyframes=KeyframeConfig(online=online))), seed=4)
        cell.run(2.0)
        truth = pan(cell, 0.3, 0.7)
        results[online] = (cell.est, truth)
    est, truth = results[True]
    plain = results[False][0]
    assert plain.live_keyframes is None and plain.counters.keyframes == 0
    # 45 frames of the pan, one kept per 0.1 s (min_gap_s): ~15, less those that are not new views.
    assert KeyframeConfig().min_frames <= est.counters.keyframes <= PAN_S * 10 + 1
    assert len(est.live_keyframes.live) == est.counters.keyframes
    values = est.isam.calculateEstimate()
    for kf in est.live_keyframes.live:
        T, true = values.atPose3(kf.key).matrix(), truth[kf.stamp_ns]
        d = T[:3, :3].T @ (T[:3, 3] - true[:3, 3])  # gtsam's pose covariance is in the body frame, rotation first
        cov = est.isam.marginalCovariance(kf.key)[3:, 3:]
        assert d @ np.linalg.solve(cov, d) <= 16.27, f"frame at {kf.stamp_ns} ns is {1e3 * d} mm off"  # 3 dof, 99.9 %
    # The pan's views add information on the markers a saw (marker 3: seen by both, never an anchor).
    ratio = {
        mk: np.trace(est.isam.marginalCovariance(marker_symbol(mk))[3:, 3:])
        / np.trace(plain.isam.marginalCovariance(marker_symbol(mk))[3:, 3:])
        for mk in (1, 2, 3)
    }
    assert all(r < 0.95 for r in ratio.values()), ratio


FLOOR_DEG = 0.5  # the pairs' allowance for a view's bias in the weighing test


def _weighed_pan(biased: bool, max_inflation: float = 10.0, online: bool = True) -> Estimator:
    """a pans in the wall cell whose pairs allow for a ``FLOOR_DEG`` bias per view; its views
    carry such a bias (``ViewBiases``) or none."""
    cfg = config(keyframes=KeyframeConfig(online=online, max_inflation=max_inflation)).model_copy(
        update={"view_rotation_sigma_deg": FLOOR_DEG}
    )
    est = Estimator(cfg)
    cell = Cell(est, seed=0, biases=ViewBiases(cfg.max_fused, np.radians(FLOOR_DEG)) if biased else None)
    cell.run(2.0)
    pan(cell, 0.3, 0.7)
    return est


def test_a_moves_frames_are_weighed_by_how_the_static_pairs_fit() -> None:
    """With views that carry the bias the pairs allow for, the pairs fit about as they claim and
    the pan's frames enter at their own covariances. With views that carry none, the pairs fit
    several times better than they claim (the frames as theirs claim): the frames enter with their
    covariances scaled by the ratio (``estimator.variance``), or past ``max_inflation`` not at all,
    and the estimate is then the one without moving frames."""
    biased = _weighed_pan(biased=True)
    fit = biased.static_fit()
    assert 0.27 < fit.factor < 2.35, fit  # chi-square of 18 dof over 18: inside in 99.8 % of cells whose model fits
    assert biased.counters.keyframe_inflation == 1.0 and biased.counters.keyframes >= KeyframeConfig().min_frames

    clean = _weighed_pan(biased=False)
    fit = clean.static_fit()
    assert fit.factor < 0.3, fit
    inflation = clean.counters.keyframe_inflation
    assert inflation > 2.0 and clean.counters.keyframes >= KeyframeConfig().min_frames, (inflation, clean.counters)
    own = cov_ros_to_gtsam(
        COV + np.diag([0.0] * 3 + [np.radians(FLOOR_DEG) ** 2] * 3)
    )  # a frame's factor: its observation's + the floor
    factors = clean.isam.getFactorsUnsafe()
    for kf in clean.live_keyframes.live:
        for f in kf.factors:
            np.testing.assert_allclose(factors.at(f.slot).noiseModel().noise().covariance(), own * inflation, rtol=1e-9)

    refused = _weighed_pan(biased=False, max_inflation=inflation / 2)
    plain = _weighed_pan(biased=False, online=False)
    assert refused.counters.keyframes == 0 and refused.counters.keyframes_refused >= KeyframeConfig().min_frames
    got, want = refused.isam.calculateEstimate(), plain.isam.calculateEstimate()
    assert got.size() == want.size()
    for key in want.keys():
        assert_pose_close(
            got.atPose3(key).matrix(), want.atPose3(key).matrix(), 1e-9, 1e-7, gtsam.DefaultKeyFormatter(key)
        )


def test_pans_leave_at_most_max_live_frames_in_the_graph() -> None:
    cell = Cell(Estimator(config(keyframes=KeyframeConfig(online=True, max_live=20))), seed=5)
    cell.run(2.0)
    for i in range(6):
        pan(cell, 0.3 if i % 2 == 0 else 0.7, 0.7 if i % 2 == 0 else 0.3)
    est = cell.est
    assert est.counters.keyframes > 40 and len(est.live_keyframes.live) <= 20
    held = [k for k in est.isam.calculateEstimate().keys() if gtsam.Symbol(k).chr() == ord("k")]
    assert len(held) == len(est.live_keyframes.live), "a dropped frame's variable must leave iSAM2 with its factors"


def test_a_camera_that_never_stops_enters_its_frames_after_the_lag() -> None:
    """Camera a slides to and fro along the wall at 0.3 m/s for 8 s without ever settling (a
    camera on an arm): with ``lag_s`` its frames enter while it moves, each where a was at its stamp, and at
    most ``max_live`` stay; with lag 0 none enter until it stops."""
    entered = {}
    for lag in (0.0, 1.0):
        cell = Cell(Estimator(config(keyframes=KeyframeConfig(online=True, lag_s=lag, max_live=30))), seed=6)
        cell.run(2.0)
        truth = {}
        for i in range(8 * RATE):
            travel = 0.3 * (i + 1) / RATE % 1.2  # 0.6 m out and back
            cell.poses["a"] = cam_pose(
                0.3 + min(travel, 1.2 - travel), make_pose(rpy_matrix(0.0, np.radians(3.0), 0.0), [0.0, 0.0, 0.0])
            )
            truth[cell.now()] = cell.poses["a"]
            cell.run(1 / RATE)
        assert cell.est.tracks["a"].moving and cell.est.tracks["a"].segment == 0, (
            "a must move all along for this test to mean anything"
        )
        entered[lag] = cell.est.counters.keyframes
        if lag == 0.0:
            continue
        est = cell.est
        assert len(est.live_keyframes.live) <= 30
        values = est.isam.calculateEstimate()
        for kf in est.live_keyframes.live:
            T, true = values.atPose3(kf.key).matrix(), truth[kf.stamp_ns]
            d = T[:3, :3].T @ (T[:3, 3] - true[:3, 3])
            cov = est.isam.marginalCovariance(kf.key)[3:, 3:]
            assert d @ np.linalg.solve(cov, d) <= 16.27, (
                f"frame at {kf.stamp_ns} ns is {1e3 * d} mm off"
            )  # 3 dof, 99.9 %
    assert entered[0.0] == 0
    # 8 s at one frame per 0.1 s (3 cm apart: new views), the last second still held: ~70
    assert entered[1.0] >= 60, entered


def test_a_moving_frames_factors_online_are_capped() -> None:
    """``max_markers_online``: a frame of a's pan holds factors to at most that many of its markers
    (at 64 cameras a frame's 32 doubled update p99); with 2 of the wall's 4, the pan's frames still
    enter where a was."""
    cell = Cell(Estimator(config(keyframes=KeyframeConfig(online=True, max_markers_online=2))), seed=4)
    cell.run(2.0)
    truth = pan(cell, 0.3, 0.7)
    est = cell.est
    assert est.counters.keyframes >= KeyframeConfig().min_frames
    values = est.isam.calculateEstimate()
    factors = est.isam.getFactorsUnsafe()
    for kf in est.live_keyframes.live:
        assert len(kf.factors) == 2, f"frame at {kf.stamp_ns} ns has {len(kf.factors)} factors"
        markers = {gtsam.Symbol(k).index() for f in kf.factors for k in factors.at(f.slot).keys() if k != kf.key}
        assert len(markers) == 2, f"frame at {kf.stamp_ns} ns: factors to {markers}"
        T = values.atPose3(kf.key).matrix()
        d = T[:3, :3].T @ (T[:3, 3] - truth[kf.stamp_ns][:3, 3])
        cov = est.isam.marginalCovariance(kf.key)[3:, 3:]
        assert d @ np.linalg.solve(cov, d) <= 16.27, f"frame at {kf.stamp_ns} ns is {1e3 * d} mm off"  # 3 dof, 99.9 %
