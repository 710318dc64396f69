"""A camera's folded past (bounded history): when a camera moves, the segment it left keeps its
pose variable as the camera's history and its pair factors fixed at their final means; the
previous history's factors move onto it through the estimated relative pose, fused per marker
where both saw it (``estimator.graph.Estimator._fold``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.geometry import pose_difference, pose_retract


@dataclass
class HistoryFactor:
    """One fixed factor of a camera's history: camera_T_marker (4x4) and its covariance (6x6, ROS
    order, marker frame)."""

    mean: np.ndarray
    covariance: np.ndarray
    slot: int | None = None  # iSAM2 factor index once in the graph


@dataclass
class History:
    """The folded past of one camera: fixed factors from the pose of its last ended segment
    (gtsam ``key``) to every marker its ended segments saw, by marker id."""

    key: int
    factors: dict[int, HistoryFactor]
    segments: int = 0  # segments folded into it


def fuse_measurements(a: list[HistoryFactor], b: list[HistoryFactor]) -> list[HistoryFactor]:
    """Information-weighted means of pairs of camera_T_marker measurements, a[i] and b[i] of one
    marker: one Gauss-Newton step from each ``a`` in its own frame (``pose_difference``: the
    tangent its covariance is in, to first order; the two measurements differ by millimetres).
    Covariances in the marker frame, where a pose's left composition leaves them unchanged. All
    pairs in one batch: a fold fuses every marker its camera saw before and after a move."""
    if not a:
        return []
    T_a, T_b = np.array([f.mean for f in a]), np.array([f.mean for f in b])
    info_a, info_b = (
        np.linalg.inv(np.array([f.covariance for f in a])),
        np.linalg.inv(np.array([f.covariance for f in b])),
    )
    cov = np.linalg.inv(info_a + info_b)
    step = np.einsum("sij,sjk,sk->si", cov, info_b, pose_difference(T_a, T_b))
    return [HistoryFactor(T, C) for T, C in zip(pose_retract(T_a, step), cov)]


def carried(
    old: History, factors: dict[int, HistoryFactor], here_T_old: np.ndarray
) -> tuple[dict[int, HistoryFactor], list[int]]:
    """A fold's history factors: the ended segment's own (``factors``, by marker id) and the
    previous history's moved onto the segment's pose through ``here_T_old`` (4, 4: the previous
    history's pose in the segment's frame), fused where both saw a marker (the moved or fused
    factor replaces the segment's own); and the iSAM2 slots they replace (the previous history's,
    and the segment's own where fused)."""
    moved = {mk: HistoryFactor(here_T_old @ f.mean, f.covariance) for mk, f in old.factors.items()}
    stale = [f.slot for f in old.factors.values() if f.slot is not None]
    both = [mk for mk in moved if mk in factors]
    stale += [factors[mk].slot for mk in both if factors[mk].slot is not None]
    moved.update(zip(both, fuse_measurements([factors[mk] for mk in both], [moved[mk] for mk in both])))
    return {**factors, **moved}, stale
