"""Camera resection against mapped markers (pure): a camera pose from markers whose poses are known.

    world_T_camera, covariance = resect(world_T_markers, marker_covs, camera_T_markers, pair_covs)

Each marker i gives a camera pose C_i = M_i Z_i^-1 (M_i = world_T_marker, Z_i = camera_T_marker).
In C's body tangent (gtsam order: rotation, translation) a perturbation of M_i or Z_i reaches C_i
through the adjoint of Z_i: Sigma_i = Ad(Z_i) (Sigma_M_i + Sigma_Z_i) Ad(Z_i)^T. The pose is the
robust (Huber) information-weighted mean of the C_i on SE(3), a few Gauss-Newton steps.

The reported covariance treats the observation noise as independent between markers and the
map's as fully correlated (the markers' estimates share anchors and cameras): the fused
observation covariance plus the mean of the transported map covariances: an upper bound, where
counting the map's errors as independent would understate what they share.
"""

from __future__ import annotations

import gtsam
import numpy as np

from schemas.geometry import ROS_TO_GTSAM, cov_gtsam_to_ros, mahalanobis_sq, skew

ITERATIONS = 3


def adjoints(T: np.ndarray) -> np.ndarray:
    """Adjoint maps (N, 6, 6) of poses T (N, 4, 4) in gtsam's tangent order (rotation, translation)."""
    R = T[:, :3, :3]
    A = np.zeros((len(T), 6, 6))
    A[:, :3, :3], A[:, 3:, :3], A[:, 3:, 3:] = R, skew(T[:, :3, 3]) @ R, R
    return A


def at_camera(camera_T_markers: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Covariances (N, 6, 6; ROS order, marker frame) of observations ``camera_T_markers`` (N, 4, 4)
    taken to the camera pose each implies: Ad(Z) Sigma Ad(Z)^T, gtsam order (rotation first)."""
    Ad = adjoints(np.asarray(camera_T_markers, np.float64))
    return Ad @ np.asarray(covs, np.float64)[np.ix_(range(len(Ad)), ROS_TO_GTSAM, ROS_TO_GTSAM)] @ np.swapaxes(Ad, 1, 2)


def implied_d2(
    world_T_camera: np.ndarray, world_T_markers: np.ndarray, camera_T_markers: np.ndarray, pair_covs: np.ndarray
) -> np.ndarray:
    """Squared Mahalanobis distances (N,) of each marker's implied camera pose M_i Z_i^-1 from
    ``world_T_camera`` (4, 4), under the observation's own covariance (``pair_covs`` (N, 6, 6), ROS
    order, marker frame) taken to the camera as ``resect`` does; the map taken as exact."""
    camera = gtsam.Pose3(world_T_camera)
    implied = np.asarray(world_T_markers, np.float64) @ np.linalg.inv(np.asarray(camera_T_markers, np.float64))
    r = np.array([gtsam.Pose3.Logmap(camera.between(gtsam.Pose3(c))) for c in implied])
    return mahalanobis_sq(r, at_camera(camera_T_markers, pair_covs) + 1e-12 * np.eye(6))


def resect(
    world_T_markers: np.ndarray,
    marker_covs: np.ndarray,
    camera_T_markers: np.ndarray,
    pair_covs: np.ndarray,
    huber_k: float = 1.345,
) -> tuple[np.ndarray, np.ndarray]:
    """world_T_camera (4, 4) and its covariance (6, 6; ROS order, camera frame) from N markers.

    ``world_T_markers`` (N, 4, 4) with ``marker_covs`` (N, 6, 6; ROS order, marker frame), the
    camera's fused observations ``camera_T_markers`` (N, 4, 4) with ``pair_covs`` (N, 6, 6; ROS
    order, marker frame). N >= 1.
    """
    Z = np.asarray(camera_T_markers, np.float64)
    C = np.asarray(world_T_markers, np.float64) @ np.linalg.inv(Z)  # each marker's camera pose
    S_obs, S_map = at_camera(Z, pair_covs), at_camera(Z, marker_covs)
    info = np.linalg.inv(S_obs + S_map + 1e-12 * np.eye(6))
    poses = [gtsam.Pose3(c) for c in C]
    # Start from the best-determined marker's camera pose: the mean of rotations could be a flip's.
    estimate = poses[int(np.argmin(np.trace(S_obs + S_map, axis1=1, axis2=2)))]
    weights = np.ones(len(Z))
    for _ in range(ITERATIONS):
        r = np.array([gtsam.Pose3.Logmap(estimate.between(p)) for p in poses])  # (N, 6)
        d2 = np.einsum("ni,nij,nj->n", r, info, r)
        weights = np.minimum(1.0, huber_k / np.sqrt(np.maximum(d2, 1e-18)))
        H = np.einsum("n,nij->ij", weights, info)
        delta = np.linalg.solve(H, np.einsum("n,nij,nj->i", weights, info, r))
        estimate = estimate.compose(gtsam.Pose3.Expmap(delta))
    w_obs = weights[:, None, None] * np.linalg.inv(S_obs + 1e-12 * np.eye(6))
    cov = np.linalg.inv(w_obs.sum(axis=0)) + np.einsum("n,nij->ij", weights, S_map) / weights.sum()
    return estimate.matrix(), cov_gtsam_to_ros(cov)
