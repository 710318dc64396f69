"""What the estimator reports: per camera its state and world pose, the static markers' poses,
markers on objects posed through the camera that sees them best, and anchors that disagree with
their survey. Poses are world_T_child (4, 4); covariances 6x6 in ROS order (position first), in
the child's frame."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Generic, TypeVar

import numpy as np

K = TypeVar("K")
V = TypeVar("V")


class CameraState(Enum):
    LOCALIZED = 1
    UNANCHORED = 2
    MOVING = 3
    STALE = 4


@dataclass(frozen=True)
class PoseEstimate:
    """world_T_child (4x4) and its 6x6 covariance (ROS order, body frame; None if not computed)."""

    T: np.ndarray
    covariance: np.ndarray | None


@dataclass(frozen=True)
class CameraEstimate:
    camera_id: str
    state: CameraState
    segment: int
    last_stamp_ns: int
    markers_seen: int
    pose: PoseEstimate | None  # None for unanchored cameras: they have no world pose


@dataclass(frozen=True)
class Estimate:
    cameras: dict[str, CameraEstimate]
    markers: dict[int, PoseEstimate]  # static markers and anchors
    object_markers: dict[int, PoseEstimate]  # markers on objects, newest frame
    flagged_anchors: list[int]


class BestView(Generic[K, V]):
    """Of the sightings of one thing (an object marker at one instant) through several cameras,
    the one with the smallest position covariance (trace of its 3x3 block, m^2): cameras see an
    object at different distances and angles, and the best view is the one a robot should get."""

    def __init__(self) -> None:
        self._best: dict[K, tuple[float, V]] = {}

    def offer(self, key: K, covariance: np.ndarray, value: V) -> None:
        """Keep ``value`` for ``key`` if its covariance (6x6, ROS order) is the tightest so far."""
        score = float(np.trace(covariance[:3, :3]))
        if key not in self._best or score < self._best[key][0]:
            self._best[key] = (score, value)

    def keys(self) -> list[K]:
        return list(self._best)

    def pop(self, key: K) -> V:
        return self._best.pop(key)[1]


def through_camera(
    world_T_camera: np.ndarray, camera_cov: np.ndarray, camera_T_marker: np.ndarray, marker_cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """world_T_marker (..., 4, 4) and its covariance (..., 6, 6; ROS order, marker frame) from a
    camera pose with its covariance (camera frame) and an observation with its own (marker frame).

    The camera's uncertainty reaches the marker through the adjoint of marker_T_camera: a twist
    (v, w) of the camera is (R v + [p]x R w, R w) at the marker, R, p = marker_T_camera.
    Works on one pose or on stacks of them (leading dimensions broadcast).
    """
    R = np.swapaxes(camera_T_marker[..., :3, :3], -1, -2)
    p = -R @ camera_T_marker[..., :3, 3:4]
    px = np.zeros(R.shape)
    px[..., 0, 1], px[..., 0, 2], px[..., 1, 2] = -p[..., 2, 0], p[..., 1, 0], -p[..., 0, 0]
    px[..., 1, 0], px[..., 2, 0], px[..., 2, 1] = p[..., 2, 0], -p[..., 1, 0], p[..., 0, 0]
    A = np.zeros(R.shape[:-2] + (6, 6))
    A[..., :3, :3], A[..., :3, 3:], A[..., 3:, 3:] = R, px @ R, R
    return world_T_camera @ camera_T_marker, A @ camera_cov @ np.swapaxes(A, -1, -2) + marker_cov
