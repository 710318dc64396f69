"""SE(3) maths on numpy arrays: the one home for rotations, poses and their differences.

Conventions (docs/architecture.md section 3): poses are 4x4 float64 ``parent_T_child``; quaternions are
(x, y, z, w); 6x6 covariances are ROS order (x, y, z, rx, ry, rz) unless a name says gtsam.
Nothing here knows about messages or the bus (that is ``codec``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

# Index map between ROS order (x y z rx ry rz) and gtsam's Pose3 tangent order (rx ry rz x y z).
ROS_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])


# ---------------------------------------------------------------- rotations


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a 3x3 rotation matrix."""
    return quats_from_matrices(np.asarray(R, dtype=np.float64)[None])[0]


def quats_from_matrices(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) as (x, y, z, w), w >= 0, of rotation matrices (N, 3, 3) (Shepperd's method).

    Each quaternion comes from the largest of w, x, y, z (the trace when positive, else the
    largest diagonal entry), so no division is by a small number.
    """
    R = np.asarray(R, dtype=np.float64)
    d0, d1, d2 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    a01, a10, a02, a20, a12, a21 = R[:, 0, 1], R[:, 1, 0], R[:, 0, 2], R[:, 2, 0], R[:, 1, 2], R[:, 2, 1]
    trace = d0 + d1 + d2
    big = np.where(trace > 0, 3, np.argmax(np.stack([d0, d1, d2], axis=1), axis=1))
    s = 2.0 * np.sqrt(np.maximum(1.0 + np.stack([d0 - d1 - d2, d1 - d0 - d2, d2 - d0 - d1, trace], axis=1), 1e-300))
    s = np.take_along_axis(s, big[:, None], axis=1)[:, 0]
    # Row k: the quaternion computed from component k (x, y, z, w) being the largest.
    cand = np.stack(
        [
            np.stack([0.25 * s, (a01 + a10) / s, (a02 + a20) / s, (a21 - a12) / s], -1),
            np.stack([(a01 + a10) / s, 0.25 * s, (a12 + a21) / s, (a02 - a20) / s], -1),
            np.stack([(a02 + a20) / s, (a12 + a21) / s, 0.25 * s, (a10 - a01) / s], -1),
            np.stack([(a21 - a12) / s, (a02 - a20) / s, (a10 - a01) / s, 0.25 * s], -1),
        ],
        axis=1,
    )
    q = cand[np.arange(len(R)), big]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, 3:] < 0, -q, q)


def matrices_from_quats(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 4) quaternions (x, y, z, w), normalised first."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    xx, yy, zz, xy, xz, yz, xw, yw, zw = x * x, y * y, z * z, x * y, x * z, y * z, x * w, y * w, z * w
    R = np.empty((len(q), 3, 3))  # filled in place: nested np.stack cost more than the arithmetic
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = 1 - 2 * (yy + zz), 2 * (xy - zw), 2 * (xz + yw)
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = 2 * (xy + zw), 1 - 2 * (xx + zz), 2 * (yz - xw)
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = 2 * (xz - yw), 2 * (yz + xw), 1 - 2 * (xx + yy)
    return R


def matrix_from_quat(q: Iterable[float]) -> np.ndarray:
    """3x3 rotation matrix of a quaternion (x, y, z, w); the quaternion is normalised first."""
    return matrices_from_quats(np.asarray(list(q), dtype=np.float64).reshape(1, 4))[0]


def rotation_angles(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angles (rad) of R_a^T R_b over stacks (..., 3, 3), broadcast: how far apart rotations are.

    atan2 of the axis part and the trace part: accurate for tiny angles too, where the arccos of
    the trace alone loses half the digits (1e-8 rad reads as 0).
    """
    D = np.einsum("...ji,...jk->...ik", R_a, R_b)
    s = 0.5 * np.linalg.norm(
        np.stack([D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], -1), axis=-1
    )
    c = 0.5 * (np.trace(D, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(s, c)


def rotations_within(R_a: np.ndarray, R_b: np.ndarray, max_rad: float) -> np.ndarray:
    """Whether R_a^T R_b turns by less than ``max_rad`` (< pi), over stacks (..., 3, 3), broadcast:
    its trace above 1 + 2 cos(max_rad), without the angle itself (cheap on large pair tables)."""
    return np.einsum("...ji,...ji->...", R_a, R_b) > 1.0 + 2.0 * np.cos(max_rad)


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (rad) of R_a^T R_b for two rotations (3, 3)."""
    return float(rotation_angles(np.asarray(R_a, np.float64), np.asarray(R_b, np.float64)))


def rotation_between(a: np.ndarray, b: np.ndarray, half_turn_axis: np.ndarray | None = None) -> np.ndarray:
    """Smallest rotation R (3, 3) with R @ a/|a| = b/|b|; batched over leading axes: a and b
    (..., 3) broadcast, R (..., 3, 3).

    With v = a x b and c = a . b (unit a, b): R = c I + [v]x + v v^T / (1 + c). When a and b are
    opposite every axis normal to them will do: the half turn is about half_turn_axis (unit, normal
    to a, (..., 3)); by default about the coordinate axis most normal to a, made normal to it (x for
    a = -z).
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.sqrt(np.sum(a * a, axis=-1, keepdims=True))
    b = b / np.sqrt(np.sum(b * b, axis=-1, keepdims=True))
    a, b = np.broadcast_arrays(a, b)
    v = np.cross(a, b)
    c = np.sum(a * b, axis=-1)
    # 1 + c as |a + b|^2 / 2: accurate to the last bits however close to opposite a and b are. Nearer
    # than ~1e-8 rad to opposite, the half turn is closer than the formula's own rounding.
    one_plus_c = 0.5 * np.sum((a + b) ** 2, axis=-1)
    opposite = one_plus_c < 1e-16
    R = v[..., :, None] * v[..., None, :] / np.where(opposite, 1.0, one_plus_c)[..., None, None]
    R += c[..., None, None] * np.eye(3)
    R += skew(v)
    if np.any(opposite):
        if half_turn_axis is None:  # the coordinate axis most normal to a, made normal to it
            e = np.eye(3)[np.argmin(np.abs(a[opposite]), axis=-1)]
            h = e - np.sum(e * a[opposite], axis=-1, keepdims=True) * a[opposite]
            h /= np.linalg.norm(h, axis=-1, keepdims=True)
        else:
            h = np.broadcast_to(np.asarray(half_turn_axis, dtype=np.float64), v.shape)[opposite]
        R[opposite] = 2.0 * h[..., :, None] * h[..., None, :] - np.eye(3)
    return R


def angle_between(u: np.ndarray, v: np.ndarray) -> float:
    """Angle (rad) between two 3-vectors (atan2 form: accurate near 0 and pi)."""
    return math.atan2(float(np.linalg.norm(np.cross(u, v))), float(np.dot(u, v)))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x (..., 3, 3) of vectors (..., 3)."""
    S = np.zeros(v.shape + (3,))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def rpy_matrix(roll: float | np.ndarray, pitch: float | np.ndarray, yaw: float | np.ndarray) -> np.ndarray:
    """Rotation Rz(yaw) Ry(pitch) Rx(roll), angles in radians: (3, 3), or (..., 3, 3) for arrays of angles."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rx, Ry, Rz = (np.zeros(np.broadcast(roll, pitch, yaw).shape + (3, 3)) for _ in range(3))
    Rx[..., 0, 0], Rx[..., 1, 1], Rx[..., 1, 2], Rx[..., 2, 1], Rx[..., 2, 2] = 1.0, cr, -sr, sr, cr
    Ry[..., 0, 0], Ry[..., 0, 2], Ry[..., 1, 1], Ry[..., 2, 0], Ry[..., 2, 2] = cp, sp, 1.0, -sp, cp
    Rz[..., 0, 0], Rz[..., 0, 1], Rz[..., 1, 0], Rz[..., 1, 1], Rz[..., 2, 2] = cy, -sy, sy, cy, 1.0
    return Rz @ Ry @ Rx


def look_at_matrix(position: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Optical-frame rotation (x right, y down, z forward) of a camera at ``position`` facing ``target``."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight up or down: any right vector will do
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def normal_matrix(normal: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Marker-frame rotation with z along ``normal`` and y toward ``up`` (default world z, else y)."""
    z = np.asarray(normal, float) / np.linalg.norm(normal)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = np.asarray(up, float) - np.dot(up, z) * z
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


# ---------------------------------------------------------------- poses


def make_pose(R: np.ndarray | None = None, t: Iterable[float] | None = None) -> np.ndarray:
    """4x4 pose from a 3x3 rotation (default identity) and a translation in metres (default 0)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(list(t), dtype=np.float64)
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 pose without a general matrix inverse."""
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def invert_poses(T: np.ndarray) -> np.ndarray:
    """``invert_pose`` over a stack (..., 4, 4)."""
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti = np.zeros(T.shape)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def interpolate_pose(a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    """The pose a fraction ``f`` (0..1) of the way from ``a`` to ``b`` (4, 4): position linear,
    rotation along the geodesic (quaternion slerp)."""
    qa, qb = quat_from_matrix(a[:3, :3]), quat_from_matrix(b[:3, :3])
    if qa @ qb < 0:  # the short way round
        qb = -qb
    angle = math.acos(min(1.0, float(qa @ qb)))
    if angle < 1e-12:
        q = qa
    else:
        q = (math.sin((1 - f) * angle) * qa + math.sin(f * angle) * qb) / math.sin(angle)
    return make_pose(matrix_from_quat(q), (1 - f) * a[:3, 3] + f * b[:3, 3])


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    """The rigid transform T (4, 4) minimising sum |T src_i - dst_i|^2 over (N, 3) point pairs;
    None with fewer than three or (nearly) collinear points, where a rotation about the line is free."""
    if len(src) < 3:
        return None
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, S, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    if S[1] < 1e-4 * max(S[0], 1e-12):
        return None
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_pose(R, cd - R @ cs)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(position error mm, rotation error deg) of an estimate against a reference (4, 4 each)."""
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1000), math.degrees(
        rotation_angle(T_est[:3, :3], T_true[:3, :3])
    )


# ---------------------------------------------------------------- covariances


def cov_ros_to_gtsam(cov: np.ndarray) -> np.ndarray:
    """Reorder 6x6 covariances (..., 6, 6) from ROS (x y z rx ry rz) to gtsam Pose3 tangent (rx ry rz x y z)."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.shape[-2:] != (6, 6):
        cov = cov.reshape(6, 6)
    return cov[..., ROS_TO_GTSAM, :][..., ROS_TO_GTSAM]


def cov_gtsam_to_ros(cov: np.ndarray) -> np.ndarray:
    """Inverse of ``cov_ros_to_gtsam`` (the permutation is its own inverse)."""
    return cov_ros_to_gtsam(cov)


def covariance_in_frame(cov: np.ndarray, R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """Pose covariances (..., 6, 6, ROS order) of a pose whose rotation is ``R_from`` (..., 3, 3),
    re-expressed in the frame of ``R_to`` at the same point: the same uncertainty in the camera
    frame, body-frame perturbations turned by R_to^T R_from. For an IPPE observation whose other
    branch is taken: the front-end gave its covariance in the frame of the pose it chose."""
    Q = np.swapaxes(R_to, -1, -2) @ R_from
    B = np.zeros(Q.shape[:-2] + (6, 6))
    B[..., :3, :3] = Q
    B[..., 3:, 3:] = Q
    return B @ cov @ np.swapaxes(B, -1, -2)


def position_sigma(cov: np.ndarray) -> float:
    """Largest standard deviation (m) of the position block of a 6x6 ROS-order pose covariance."""
    return math.sqrt(max(float(np.linalg.eigvalsh(np.asarray(cov)[:3, :3]).max()), 0.0))


def mahalanobis_sq(d: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis length d^T cov^-1 d of differences d (..., k) under covariances (..., k, k)."""
    d = np.asarray(d, dtype=np.float64)
    return np.einsum("...i,...i->...", d, np.linalg.solve(cov, d[..., None])[..., 0])


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Tangent vector (..., 6) in ROS order (x y z rx ry rz) taking ``T_a`` to ``T_b`` (..., 4, 4) in
    a's own frame: translation R_a^T (t_b - t_a), rotation the axis-angle of R_a^T R_b."""
    RaT = np.swapaxes(T_a[..., :3, :3], -1, -2)
    D = RaT @ T_b[..., :3, :3]
    w = 0.5 * np.stack(
        [D[..., 2, 1] - D[..., 1, 2], D[..., 0, 2] - D[..., 2, 0], D[..., 1, 0] - D[..., 0, 1]], axis=-1
    )  # sin(angle) x axis
    s = np.sqrt(np.einsum("...i,...i->...", w, w))
    angle = np.arctan2(s, 0.5 * (np.trace(D, axis1=-2, axis2=-1) - 1.0))
    scale = np.where(s > 1e-300, angle / np.maximum(s, 1e-300), 1.0)
    t = (RaT @ (T_b[..., :3, 3] - T_a[..., :3, 3])[..., None])[..., 0]
    return np.concatenate([t, w * scale[..., None]], axis=-1)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) of axis-angle vectors w (..., 3) (rad), Rodrigues' formula."""
    w = np.asarray(w, dtype=np.float64)
    angle = np.sqrt(np.einsum("...i,...i->...", w, w))[..., None, None]
    K = skew(w)
    small = angle < 1e-8  # series terms: sin(a)/a -> 1, (1 - cos(a))/a^2 -> 1/2
    a = np.where(small, 1.0, angle)
    return (
        np.eye(3) + np.where(small, 1.0, np.sin(a) / a) * K + np.where(small, 0.5, (1.0 - np.cos(a)) / a**2) * (K @ K)
    )


def pose_retract(T_a: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Poses (..., 4, 4) ``T_a`` moved by tangent vectors ``d`` (..., 6) in ROS order in a's own
    frame, the inverse of ``pose_difference``: rotation R_a exp(d_rot), translation t_a + R_a d_t."""
    R = so3_exp(d[..., 3:])
    out = np.array(T_a, dtype=np.float64, copy=True)
    out[..., :3, :3] = T_a[..., :3, :3] @ R
    out[..., :3, 3] = T_a[..., :3, 3] + (T_a[..., :3, :3] @ d[..., :3, None])[..., 0]
    return out
