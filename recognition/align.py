"""Camera-roll histogram, roll alignment and ICP: from a VFH match to a full 6-DoF pose.

VFH is invariant to rotation about the line of sight through the cluster centroid (the camera
roll). The camera roll histogram (Aldoma et al., 2011) recovers it: rotate each cluster so that its
centroid lies on +z, histogram the direction of the normals projected on the xy plane (weighted by
the projected length), and circularly cross-correlate the scene's histogram with the model view's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from recognition.vfh import ROLL_BINS


def rotation_between(a: np.ndarray, b: np.ndarray, half_turn_axis: np.ndarray | None = None) -> np.ndarray:
    """Smallest rotation R (3, 3) with R @ a/|a| = b/|b| (Rodrigues).

    When a and b are opposite every axis normal to them will do: the half turn is about
    half_turn_axis (unit, normal to a; default x, which suits a = -z).
    """
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        axis, s = np.asarray(half_turn_axis if half_turn_axis is not None else (1.0, 0.0, 0.0), dtype=np.float64), 0.0
    else:
        axis = axis / s
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def align_to_z(direction: np.ndarray) -> np.ndarray:
    """Smallest rotation R (3, 3) with R @ direction/|direction| = +z."""
    return rotation_between(direction, np.array([0.0, 0.0, 1.0]))


def roll_histogram(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Camera roll histogram (90 bins of 4 deg) of a cluster in its camera frame, summing to 1."""
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    ok = np.all(np.isfinite(n), axis=1)
    R = align_to_z(p[ok].mean(axis=0))
    m = n[ok] @ R.T
    angle = np.arctan2(m[:, 1], m[:, 0])
    weight = np.hypot(m[:, 0], m[:, 1])
    index = np.clip(np.floor((angle + np.pi) / (2 * np.pi) * ROLL_BINS).astype(int), 0, ROLL_BINS - 1)
    hist = np.bincount(index, weight, minlength=ROLL_BINS)
    total = hist.sum()
    return hist / total if total > 0 else hist


def roll_candidates(scene_hist: np.ndarray, view_hist: np.ndarray, peaks: int = 3, ratio: float = 0.7) -> list[float]:
    """Roll angles (rad) that turn the view's histogram into the scene's, best first.

    The circular cross-correlation (by FFT) is searched for local maxima at least ``ratio`` of the
    best; each is refined to sub-bin precision with a parabola through its neighbours.
    """
    corr = np.real(np.fft.ifft(np.fft.fft(scene_hist) * np.conj(np.fft.fft(view_hist))))
    left, right = np.roll(corr, 1), np.roll(corr, -1)
    is_peak = (corr >= left) & (corr > right) & (corr >= ratio * corr.max())
    order = [int(k) for k in np.argsort(-corr) if is_peak[k]][:peaks]
    step = 2 * np.pi / ROLL_BINS
    out = []
    for k in order:
        denom = left[k] - 2 * corr[k] + right[k]
        offset = 0.5 * (left[k] - right[k]) / denom if denom < 0 else 0.0
        out.append((k + offset) * step)
    return out or [0.0]


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def view_to_scene(scene_centroid: np.ndarray, view_centroid: np.ndarray, roll: float) -> np.ndarray:
    """camera_T_view (4, 4): puts a model view's cloud (in its virtual camera) onto the scene cluster.

    Both clusters are turned so that their centroids lie on +z, the view is rolled by ``roll`` about
    z, and the centroids are made to coincide.
    """
    A_s, A_v = align_to_z(scene_centroid), align_to_z(view_centroid)
    R = A_s.T @ rot_z(roll) @ A_v
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(scene_centroid) - R @ np.asarray(view_centroid)
    return T


@dataclass(frozen=True)
class IcpResult:
    """camera_T_object (4, 4); fitness = inlier fraction of the visible model points (0..1); RMSE m."""

    camera_T_object: np.ndarray
    fitness: float
    rmse_m: float


def visible_points(model_points: np.ndarray, model_normals: np.ndarray, camera_T_object: np.ndarray) -> np.ndarray:
    """Model points (object frame) whose normal faces the camera at this pose: a cheap visibility cull."""
    R, t = camera_T_object[:3, :3], camera_T_object[:3, 3]
    p_cam = model_points @ R.T + t
    n_cam = model_normals @ R.T
    return model_points[np.einsum("ij,ij->i", n_cam, -p_cam) > 0]


def refine_icp(
    model_points: np.ndarray,
    model_normals: np.ndarray,
    scene: o3d.geometry.PointCloud,
    camera_T_object: np.ndarray,
    max_distance_m: float,
    iterations: int = 30,
    max_shift_m: float = np.inf,
) -> IcpResult:
    """Point-to-plane ICP of the camera-facing model points onto the scene (which must have normals).

    The visible set is chosen at the initial pose, refined, then chosen again at the refined pose for
    the final score, so that the fitness counts the surface the camera should actually see. A result
    that moved more than max_shift_m from the start (ICP sliding off a degenerate cluster) scores 0.
    """
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    pose = np.asarray(camera_T_object, dtype=np.float64)
    for distance in (2.0 * max_distance_m, max_distance_m):  # coarse then fine
        src = _cloud(visible_points(model_points, model_normals, pose))
        if len(src.points) < 3:
            return IcpResult(pose, 0.0, float("inf"))
        pose = o3d.pipelines.registration.registration_icp(src, scene, distance, pose, est, crit).transformation
    start = np.asarray(camera_T_object, dtype=np.float64)
    if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:3, 3] - start[:3, 3]) > max_shift_m:
        return IcpResult(start, 0.0, float("inf"))
    src = _cloud(visible_points(model_points, model_normals, pose))
    ev = o3d.pipelines.registration.evaluate_registration(src, scene, max_distance_m, pose)
    return IcpResult(np.asarray(pose), float(ev.fitness), float(ev.inlier_rmse) if ev.fitness > 0 else float("inf"))


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
