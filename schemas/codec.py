"""Conversions between messages and numpy (poses, covariances, images, camera info, transforms) and
the validation of untrusted payloads. The maths itself is ``schemas.geometry``.

Conventions (docs/architecture.md section 3): poses are 4x4 float64 ``parent_T_child`` arrays; quaternions on
the wire are (x, y, z, w); 6x6 covariances on the wire are ROS order (x, y, z, rx, ry, rz) while
gtsam's Pose3 tangent is rotation first (rx, ry, rz, x, y, z). Every ``*_from_msg`` treats its
input as untrusted and raises ``DecodeError`` naming what was wrong.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np
from google.protobuf.message import DecodeError as _PbDecodeError
from google.protobuf.message import Message

from schemas import messages as m
from schemas.errors import DecodeError
from schemas.geometry import matrices_from_quats, quats_from_matrices
from schemas.limits import DEFAULT_LIMITS, WireLimits

Msg = TypeVar("Msg", bound=Message)
_EYE3, _LAST_ROW = np.eye(3), np.array([0.0, 0.0, 0.0, 1.0])


# ---------------------------------------------------------------- poses


def check_pose(T: np.ndarray, what: str = "pose", tol: float = 1e-6) -> np.ndarray:
    """Return ``T`` as float64 if it is a finite rigid 4x4 transform, else raise ``DecodeError``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise DecodeError(f"{what}: expected a 4x4 array, got shape {T.shape}")
    return check_poses(T[None], what, tol)[0]


def check_poses(T: np.ndarray, what: str = "pose", tol: float = 1e-6) -> np.ndarray:
    """Return ``T`` (N, 4, 4) as float64 if every pose is a finite rigid transform, else raise ``DecodeError``."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise DecodeError(f"{what}: expected (N, 4, 4) poses, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise DecodeError(f"{what}: contains NaN or inf", "not_finite")
    R = T[:, :3, :3]
    # Plain max-abs checks: np.allclose costs more than the rest of a pose's conversion.
    orthonormal = np.abs(np.einsum("nji,njk->nik", R, R) - _EYE3).max(axis=(1, 2)) <= tol
    if not (orthonormal.all() and (np.linalg.det(R) > 0).all() and np.abs(T[:, 3] - _LAST_ROW).max(initial=0.0) <= tol):
        raise DecodeError(f"{what}: not a rigid transform (rotation not orthonormal or bad last row)", "not_rigid")
    return T


def pose_to_msg(T: np.ndarray, out: m.Pose | None = None) -> m.Pose:
    """Fill (or create) a ``Pose`` message from a 4x4 ``parent_T_child``."""
    msg = out if out is not None else m.Pose()
    _fill_poses(check_pose(T, tol=1e-5)[None], [msg])
    return msg


def poses_to_msgs(T: np.ndarray, outs: Sequence[m.Pose]) -> None:
    """Fill each ``Pose`` message of ``outs`` from the matching pose of ``T`` (N, 4, 4), all checked
    and converted together (a frame's markers: per-pose numpy calls cost more than the maths)."""
    _fill_poses(check_poses(T, tol=1e-5), outs)


def _fill_poses(T: np.ndarray, outs: Sequence[m.Pose]) -> None:
    q = quats_from_matrices(T[:, :3, :3])
    for msg, t, qi in zip(outs, T[:, :3, 3].tolist(), q.tolist()):
        msg.x, msg.y, msg.z = t
        msg.qx, msg.qy, msg.qz, msg.qw = qi


def foxglove_pose(T: np.ndarray, out) -> None:
    """Fill a ``foxglove.Pose`` (position + orientation sub-messages) from a 4x4 pose."""
    p = pose_to_msg(T)
    out.position.x, out.position.y, out.position.z = p.x, p.y, p.z
    out.orientation.x, out.orientation.y, out.orientation.z, out.orientation.w = p.qx, p.qy, p.qz, p.qw


def pose_from_msg(msg: m.Pose, what: str = "pose", limits: WireLimits = DEFAULT_LIMITS) -> np.ndarray:
    """4x4 pose from a ``Pose`` message; rejects non-finite values, non-unit quaternions and
    positions beyond ``limits.max_position_m``."""
    t = np.array([[msg.x, msg.y, msg.z]])
    q = np.array([[msg.qx, msg.qy, msg.qz, msg.qw]])
    return _poses_from_arrays(t, q, [what], limits)[0]


# ---------------------------------------------------------------- covariances


def check_covariance(cov: np.ndarray, what: str = "covariance", limits: WireLimits | None = None) -> np.ndarray:
    """Return a 6x6 symmetric positive-definite covariance, else raise ``DecodeError``; with
    ``limits``, also one whose standard deviations are outside their bounds."""
    cov = np.asarray(cov, dtype=np.float64)
    if cov.size != 36:
        raise DecodeError(f"{what}: expected 36 values, got {cov.size}", "covariance")
    return _checked_covariances(cov.reshape(1, 36), [what], limits)[0]


def covariance_problems(rows: np.ndarray, limits: WireLimits | None = DEFAULT_LIMITS) -> list[tuple[int, str, str]]:
    """(row, what is wrong, reason) for each bad covariance of ``rows`` (N, 36), in row order:
    non-finite, not symmetric, not positive definite, then (with ``limits``) a standard deviation
    outside ``[min_sigma, max_sigma]`` (the first of these per row; the reason one of
    ``schemas.limits.REASONS``). Empty when all are good."""
    cov = rows.reshape(-1, 6, 6)
    finite = np.all(np.isfinite(rows), axis=1)
    c = np.where(finite[:, None, None], cov, np.eye(6))  # rows already flagged are checked as identity
    asym = np.abs(c - c.transpose(0, 2, 1)).max(axis=(1, 2)) > 1e-6 * np.abs(c).max(axis=(1, 2)) + 1e-12
    c = np.where(asym[:, None, None], np.eye(6), c)
    floor = 0.0 if limits is None else limits.min_sigma**2
    not_pd = too_sharp = np.zeros(len(c), bool)
    try:  # one batched factorisation: positive definite, and (with limits) no direction sharper than min_sigma
        np.linalg.cholesky(c - floor * np.eye(6))
    except np.linalg.LinAlgError:  # only then a per-row look
        smallest = np.linalg.eigvalsh(c).min(axis=1)
        not_pd, too_sharp = smallest <= 0, (smallest <= floor) & (smallest > 0)
        if not (not_pd | too_sharp).any():  # Cholesky failed: at least the least definite one
            (too_sharp if floor else not_pd)[int(np.argmin(smallest))] = True
    why = [
        (~finite, "contains NaN or inf", "not_finite"),
        (asym, "not symmetric", "covariance"),
        (not_pd, "not positive definite", "covariance"),
    ]
    if limits is not None:
        diag = np.einsum("nii->ni", c)
        too_wide = (diag[:, :3] > limits.max_sigma_m**2).any(axis=1) | (diag[:, 3:] > limits.max_sigma_rad**2).any(
            axis=1
        )
        bounds = f"[{limits.min_sigma:g}, {limits.max_sigma_m:g} m / {limits.max_sigma_rad:g} rad]"
        why.append((too_sharp | too_wide, f"a standard deviation outside {bounds}", "covariance"))
    bad = np.logical_or.reduce([mask for mask, _, _ in why])
    return [next((i, say, reason) for mask, say, reason in why if mask[i]) for i in np.flatnonzero(bad).tolist()]


def _checked_covariances(
    rows: np.ndarray, what: Sequence[str], limits: WireLimits | None = DEFAULT_LIMITS
) -> np.ndarray:
    """Covariances (N, 6, 6) from ``rows`` (N, 36); the first bad one raises ``DecodeError`` named by ``what``."""
    problems = covariance_problems(rows, limits)
    if problems:
        i, why, reason = problems[0]
        raise DecodeError(f"{what[i]}: {why}", reason)
    return rows.reshape(-1, 6, 6)


def covariance_to_list(cov: np.ndarray) -> list[float]:
    """Row-major 36 floats of a 6x6 covariance (ROS order expected)."""
    return np.asarray(cov, dtype=np.float64).reshape(36).tolist()


# ---------------------------------------------------------------- images

# encoding -> (dtype, channels)
IMAGE_ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "mono8": (np.dtype(np.uint8), 1),
    "16UC1": (np.dtype("<u2"), 1),
    "mono16": (np.dtype("<u2"), 1),
}


def stamp_to_timestamp(stamp_ns: int, ts) -> None:
    """Write integer nanoseconds into a ``google.protobuf.Timestamp``."""
    ts.seconds, ts.nanos = divmod(int(stamp_ns), 1_000_000_000)


def timestamp_to_stamp(ts) -> int:
    """Integer nanoseconds of a ``google.protobuf.Timestamp``."""
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def image_to_msg(image: np.ndarray, stamp_ns: int, frame_id: str, encoding: str) -> m.RawImage:
    """``RawImage`` from an (H, W, 3) uint8 colour or (H, W) uint16 depth (millimetres) array."""
    if encoding not in IMAGE_ENCODINGS:
        raise DecodeError(f"unsupported image encoding {encoding!r}; use one of {sorted(IMAGE_ENCODINGS)}")
    dtype, channels = IMAGE_ENCODINGS[encoding]
    image = np.ascontiguousarray(image, dtype=dtype)
    if image.ndim != (2 if channels == 1 else 3) or (channels > 1 and image.shape[2] != channels):
        raise DecodeError(f"image of shape {image.shape} does not match encoding {encoding!r}")
    h, w = image.shape[:2]
    msg = m.RawImage(frame_id=frame_id, width=w, height=h, encoding=encoding, step=w * channels * dtype.itemsize)
    stamp_to_timestamp(stamp_ns, msg.timestamp)
    msg.data = image.tobytes()
    return msg


def rgb_from_msg(msg: m.RawImage) -> np.ndarray:
    """A colour ``RawImage`` (rgb8 or bgr8) as (H, W, 3) uint8 in r, g, b order."""
    if msg.encoding not in ("rgb8", "bgr8"):
        raise DecodeError(f"colour encoding {msg.encoding!r}, expected rgb8 or bgr8")
    image = image_from_msg(msg)
    return image[..., ::-1] if msg.encoding == "bgr8" else image


def image_from_msg(msg: m.RawImage) -> np.ndarray:
    """Array view of a ``RawImage``: (H, W, C) for colour, (H, W) for single-channel encodings."""
    if msg.encoding not in IMAGE_ENCODINGS:
        raise DecodeError(f"unsupported image encoding {msg.encoding!r}")
    dtype, channels = IMAGE_ENCODINGS[msg.encoding]
    row = msg.width * channels * dtype.itemsize
    if msg.width == 0 or msg.height == 0:
        raise DecodeError(f"empty image {msg.width}x{msg.height}")
    if msg.step != row or len(msg.data) != row * msg.height:
        raise DecodeError(
            f"image {msg.width}x{msg.height} {msg.encoding}: step {msg.step} and {len(msg.data)} bytes "
            f"do not match the expected {row} and {row * msg.height}"
        )
    arr = np.frombuffer(msg.data, dtype=dtype)
    return arr.reshape(msg.height, msg.width) if channels == 1 else arr.reshape(msg.height, msg.width, channels)


# ---------------------------------------------------------------- camera info


@dataclass(frozen=True)
class CameraInfo:
    """Pinhole intrinsics in CameraInfo form. K (3, 3), D plumb_bob (5,), R (3, 3), P (3, 4)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))
    distortion_model: str = "plumb_bob"

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "D", np.asarray(self.D, dtype=np.float64).reshape(-1))
        if self.width <= 0 or self.height <= 0:
            raise DecodeError(f"camera info: image size {self.width}x{self.height} must be positive")
        if not np.all(np.isfinite(self.K)) or self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise DecodeError("camera info: K must be finite with positive focal lengths")
        if not np.all(np.isfinite(self.D)):
            raise DecodeError("camera info: D contains NaN or inf")

    @classmethod
    def kinect_v1(cls, width: int = 640, height: int = 480) -> CameraInfo:
        """Kinect v1 defaults (fx = fy = 525, cx = 319.5, cy = 239.5 at 640x480), scaled to size."""
        s = width / 640.0
        K = [[525.0 * s, 0, (319.5 + 0.5) * s - 0.5], [0, 525.0 * s, (239.5 + 0.5) * s - 0.5], [0, 0, 1]]
        return cls(width, height, np.array(K))

    @property
    def P(self) -> np.ndarray:
        return np.hstack([self.K, np.zeros((3, 1))])

    def to_msg(self, stamp_ns: int, frame_id: str) -> m.CameraCalibration:
        msg = m.CameraCalibration(
            frame_id=frame_id, width=self.width, height=self.height, distortion_model=self.distortion_model
        )
        stamp_to_timestamp(stamp_ns, msg.timestamp)
        msg.K.extend(self.K.reshape(9).tolist())
        msg.D.extend(self.D.tolist())
        msg.R.extend(np.eye(3).reshape(9).tolist())
        msg.P.extend(self.P.reshape(12).tolist())
        return msg

    @classmethod
    def from_msg(cls, msg: m.CameraCalibration) -> CameraInfo:
        if len(msg.K) != 9:
            raise DecodeError(f"camera info: K has {len(msg.K)} values, expected 9")
        return cls(
            int(msg.width), int(msg.height), np.array(msg.K), np.array(msg.D), msg.distortion_model or "plumb_bob"
        )


# ---------------------------------------------------------------- point clouds

#: foxglove.PackedElementField numeric types used here.
_FLOAT32, _UINT8 = 7, 1
#: One point: x, y, z float32 (m), then red, green, blue, alpha uint8: 16 bytes.
_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "u1", (4,))])
_POINT_FIELDS = (
    ("x", 0, _FLOAT32),
    ("y", 4, _FLOAT32),
    ("z", 8, _FLOAT32),
    ("red", 12, _UINT8),
    ("green", 13, _UINT8),
    ("blue", 14, _UINT8),
    ("alpha", 15, _UINT8),
)


def points_to_msg(stamp_ns: int, frame_id: str, xyz: np.ndarray, rgba: np.ndarray) -> m.PointCloud:
    """A ``foxglove.PointCloud`` of xyz (N, 3) metres in ``frame_id``, coloured by rgba (N, 4) uint8."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or np.shape(rgba) != (len(xyz), 4):
        raise ValueError(f"points must be (N, 3) with colours (N, 4), got {xyz.shape} and {np.shape(rgba)}")
    packed = np.empty(len(xyz), _POINT)
    packed["x"], packed["y"], packed["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    packed["rgba"] = rgba
    msg = m.PointCloud(frame_id=frame_id, point_stride=_POINT.itemsize, data=packed.tobytes())
    stamp_to_timestamp(stamp_ns, msg.timestamp)
    msg.pose.orientation.w = 1.0
    for name, offset, kind in _POINT_FIELDS:
        msg.fields.add(name=name, offset=offset, type=kind)
    return msg


def points_from_msg(msg: m.PointCloud) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3) float32, rgba (N, 4) uint8) of a cloud in the layout ``points_to_msg`` writes."""
    fields = tuple((f.name, f.offset, f.type) for f in msg.fields)
    if fields != _POINT_FIELDS or msg.point_stride != _POINT.itemsize:
        raise DecodeError(f"point cloud layout {fields} stride {msg.point_stride} is not x,y,z float32 + rgba uint8")
    if len(msg.data) % _POINT.itemsize:
        raise DecodeError(f"point cloud data is {len(msg.data)} bytes, not a multiple of {_POINT.itemsize}")
    packed = np.frombuffer(msg.data, _POINT)
    return np.stack([packed["x"], packed["y"], packed["z"]], axis=1), packed["rgba"].copy()


# ---------------------------------------------------------------- transforms and pose lists


def transforms_to_msg(stamp_ns: int, transforms: Iterable[tuple[str, str, np.ndarray]]) -> m.FrameTransforms:
    """``FrameTransforms`` from (parent_frame, child_frame, parent_T_child) triples."""
    msg = m.FrameTransforms()
    transforms = list(transforms)
    if not transforms:
        return msg
    # All poses checked and converted together: per-pose numpy calls cost more than the maths.
    poses = [np.asarray(T, dtype=np.float64) for _, _, T in transforms]
    for (_, child, _), T in zip(transforms, poses):
        if T.shape != (4, 4):
            raise DecodeError(f"transform {child}: expected a 4x4 array, got shape {T.shape}")
    T = check_poses(np.stack(poses), tol=1e-5)
    q = quats_from_matrices(T[:, :3, :3])
    for (parent, child, _), t, qi in zip(transforms, T[:, :3, 3].tolist(), q.tolist()):
        tr = msg.transforms.add(parent_frame_id=parent, child_frame_id=child)
        stamp_to_timestamp(stamp_ns, tr.timestamp)
        tr.translation.x, tr.translation.y, tr.translation.z = t
        tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = qi
    return msg


def transforms_from_msg(
    msg: m.FrameTransforms, limits: WireLimits = DEFAULT_LIMITS
) -> dict[tuple[str, str], np.ndarray]:
    """{(parent, child): parent_T_child} of a ``FrameTransforms``, each checked as ``pose_from_msg``
    checks one, all in one batch (a map's tf holds every marker, and subscribers read it at the
    estimator's rate)."""
    trs = msg.transforms
    t = np.array([(tr.translation.x, tr.translation.y, tr.translation.z) for tr in trs], dtype=np.float64).reshape(
        -1, 3
    )
    q = np.array(
        [(tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w) for tr in trs], dtype=np.float64
    ).reshape(-1, 4)
    T = _poses_from_arrays(t, q, [f"transform {tr.child_frame_id}" for tr in trs], limits)
    return {(tr.parent_frame_id, tr.child_frame_id): pose for tr, pose in zip(trs, T)}


def _poses_from_arrays(
    t: np.ndarray, q: np.ndarray, what: Sequence[str], limits: WireLimits = DEFAULT_LIMITS
) -> np.ndarray:
    """Poses (N, 4, 4) from translations (N, 3) and quaternions (N, 4; x y z w) as received, rejecting
    non-finite values, non-unit quaternions and positions beyond ``limits.max_position_m``: the first
    bad pose raises ``DecodeError`` named by ``what``."""
    finite = np.isfinite(t).all(axis=1) & np.isfinite(q).all(axis=1)
    norm = np.linalg.norm(np.where(finite[:, None], q, 1.0), axis=1)
    far = np.abs(np.where(finite[:, None], t, 0.0)).max(axis=1, initial=0.0) > limits.max_position_m
    bad = ~finite | (np.abs(norm - 1.0) > 1e-3) | far
    if bad.any():
        i = int(np.argmax(bad))
        if not finite[i]:
            raise DecodeError(f"{what[i]}: contains NaN or inf", "not_finite")
        if far[i]:
            raise DecodeError(
                f"{what[i]}: position {t[i].tolist()} beyond {limits.max_position_m:g} m", "out_of_bounds"
            )
        raise DecodeError(f"{what[i]}: quaternion norm {norm[i]:.4g} is not 1", "not_rigid")
    T = np.zeros((len(t), 4, 4))
    T[:, :3, :3] = matrices_from_quats(q) if len(q) else np.zeros((0, 3, 3))
    T[:, :3, 3], T[:, 3, 3] = t, 1.0
    return T


@dataclass(frozen=True)
class StampedPose:
    """``parent_T_child`` (4x4) with its 6x6 ROS-order covariance (None when unknown)."""

    parent: str
    child: str
    stamp_ns: int
    T: np.ndarray
    covariance: np.ndarray | None = None


def poses_to_msg(stamp_ns: int, poses: Iterable[StampedPose]) -> m.PosesWithCovariance:
    msg = m.PosesWithCovariance(stamp_ns=int(stamp_ns))
    poses = list(poses)
    for p in poses:
        item = msg.poses.add(parent_frame_id=p.parent, child_frame_id=p.child, stamp_ns=int(p.stamp_ns))
        if p.covariance is not None:
            item.covariance.extend(covariance_to_list(p.covariance))
    if poses:
        poses_to_msgs(np.stack([p.T for p in poses]), [item.pose for item in msg.poses])
    return msg


def poses_from_msg(msg: m.PosesWithCovariance, limits: WireLimits = DEFAULT_LIMITS) -> dict[str, StampedPose]:
    """{child_frame: StampedPose}; raises ``DecodeError`` on any bad pose or covariance."""
    items = msg.poses
    what = [f"pose of {item.child_frame_id!r}" for item in items]
    t = np.array([(i.pose.x, i.pose.y, i.pose.z) for i in items], dtype=np.float64).reshape(-1, 3)
    q = np.array([(i.pose.qx, i.pose.qy, i.pose.qz, i.pose.qw) for i in items], dtype=np.float64).reshape(-1, 4)
    T = _poses_from_arrays(t, q, what, limits)
    given = [k for k, item in enumerate(items) if len(item.covariance)]
    for k in given:
        if len(items[k].covariance) != 36:
            raise DecodeError(f"{what[k]}: expected 36 values, got {len(items[k].covariance)}", "covariance")
    rows = np.array([items[k].covariance for k in given], dtype=np.float64).reshape(-1, 36)
    covs = dict(zip(given, _checked_covariances(rows, [what[k] for k in given], limits)))
    return {
        item.child_frame_id: StampedPose(item.parent_frame_id, item.child_frame_id, item.stamp_ns, T[k], covs.get(k))
        for k, item in enumerate(items)
    }


# ---------------------------------------------------------------- untrusted payloads


@dataclass(frozen=True)
class MarkerArrays:
    """The observations of one or more ``MarkerObservations`` as arrays, one row per marker: ids (N,),
    camera_T_marker (N, 4, 4), quaternions as sent (N, 3, 4; x y z w): the chosen pose's, then the
    two planar-PnP (IPPE) candidates' (the chosen one's again where the driver sent none),
    covariances (N, 6, 6) in ROS order, ambiguous flags (N,) and the index (N,) of the message each
    row came from."""

    ids: np.ndarray
    poses: np.ndarray
    quaternions: np.ndarray
    covariances: np.ndarray
    ambiguous: np.ndarray
    frame: np.ndarray


def marker_arrays(msg: m.MarkerObservations, check: bool = True, limits: WireLimits = DEFAULT_LIMITS) -> MarkerArrays:
    """``marker_batch`` of one message."""
    return marker_batch([msg], check, limits)


def marker_batch(
    msgs: Sequence[m.MarkerObservations], check: bool = True, limits: WireLimits = DEFAULT_LIMITS
) -> MarkerArrays:
    """Validate every observation of the messages at once (batched numpy) and return them as arrays.

    ``check=False`` only converts: for messages already validated (``decode`` with
    ``semantic=True``). Raises ``DecodeError`` naming the first bad marker (``marker_problems``).
    """
    fields = marker_fields(msgs)
    if check and (problems := marker_problems(fields, limits)):
        _, why, reason = problems[0]
        raise DecodeError(why, reason)
    return fields.arrays()


@dataclass(frozen=True)
class MarkerFields:
    """Marker observations' fields as read, not yet checked, one row per marker: ``rows`` (N, 21:
    id, message index, ambiguous, side, corner values, covariance values, the chosen pose x y z qx
    qy qz qw, candidate_a's and candidate_b's quaternions, the chosen one's where none was sent)
    and ``covariances`` (N, 36; NaN where a marker did not send 36 values). Plain arrays: cheap to
    hand to another process, which checks and converts them (``marker_problems``, ``arrays``)."""

    rows: np.ndarray
    covariances: np.ndarray

    def arrays(self, keep: np.ndarray | None = None) -> MarkerArrays:
        """The rows (all, or those selected by ``keep``) as ``MarkerArrays``, unchecked."""
        r, cov = (self.rows, self.covariances) if keep is None else (self.rows[keep], self.covariances[keep])
        poses = np.zeros((len(r), 4, 4))
        poses[:, :3, :3] = matrices_from_quats(r[:, 9:13])
        poses[:, :3, 3] = r[:, 6:9]
        poses[:, 3, 3] = 1.0
        return MarkerArrays(
            r[:, 0].astype(np.int64),
            poses,
            r[:, 9:21].reshape(-1, 3, 4),
            cov.reshape(-1, 6, 6),
            r[:, 2] != 0,
            r[:, 1].astype(np.int64),
        )


def marker_fields(msgs: Sequence[m.MarkerObservations]) -> MarkerFields:
    """Every observation's fields, read in the one Python loop over the markers (every field read
    once; all checks and conversions come after, in numpy)."""
    rows, covs = [], []
    for i, msg in enumerate(msgs):
        for o in msg.markers:
            p = o.camera_T_marker
            a = o.candidate_a if o.HasField("candidate_a") else p
            b = o.candidate_b if o.HasField("candidate_b") else p
            cov = o.covariance
            rows.append(
                (
                    o.marker_id,
                    i,
                    o.ambiguous,
                    o.side_m,
                    len(o.corners_px),
                    len(cov),
                    p.x,
                    p.y,
                    p.z,
                    p.qx,
                    p.qy,
                    p.qz,
                    p.qw,
                    a.qx,
                    a.qy,
                    a.qz,
                    a.qw,
                    b.qx,
                    b.qy,
                    b.qz,
                    b.qw,
                )
            )
            covs.append(cov)
    r = np.array(rows, dtype=np.float64).reshape(-1, 21)
    if not np.all(r[:, 5] == 36):
        cov_a = np.array([list(c) if len(c) == 36 else [np.nan] * 36 for c in covs], dtype=np.float64).reshape(-1, 36)
    elif (cov_a := _packed_covariances(msgs, len(r))) is None:
        cov_a = np.fromiter(itertools.chain.from_iterable(covs), np.float64, 36 * len(r)).reshape(-1, 36)
    return MarkerFields(r, cov_a)


#: A marker's covariance on the wire: field 10, length-delimited, 288 bytes (36 packed doubles).
_COVARIANCE_HEADER = (0x52, 0xA0, 0x02)


def _packed_covariances(msgs: Sequence[m.MarkerObservations], n: int) -> np.ndarray | None:
    """The ``n`` markers' covariances (n, 36) straight from the messages' serialised bytes, where
    they are packed little-endian doubles: twice as fast as reading them value by value. Only when
    the header occurs exactly ``n`` times (once per marker, as protobuf writes it); None otherwise
    (a header's bytes inside other data), and the caller reads the values one by one."""
    buf = np.frombuffer(b"".join([msg.SerializeToString() for msg in msgs]), np.uint8)
    h0, h1, h2 = _COVARIANCE_HEADER
    hits = (
        np.flatnonzero((buf[:-2] == h0) & (buf[1:-1] == h1) & (buf[2:] == h2))
        if len(buf) > 2
        else np.zeros(0, np.int64)
    )
    if len(hits) != n or (n and hits[-1] + 3 + 288 > len(buf)):
        return None
    return buf[(hits + 3)[:, None] + np.arange(288)].view("<f8").reshape(-1, 36)


def marker_problems(f: MarkerFields, limits: WireLimits = DEFAULT_LIMITS) -> list[tuple[int, str, str]]:
    """(row, what is wrong, reason) for every bad row, the first problem of each, in row order:
    wrong corner count, covariance not 36 values, side not positive or too large, id too large,
    non-finite values, a position beyond the cell, a non-unit quaternion, a covariance non-finite /
    not symmetric / not positive definite / with a standard deviation out of bounds. ``reason`` is
    one of ``schemas.limits.REASONS``. Empty when all are good."""
    r, ids = f.rows, f.rows[:, 0].astype(np.int64)
    found: dict[int, tuple[str, str]] = {}

    def flag(mask: np.ndarray, reason: str, say) -> None:
        for i in np.flatnonzero(mask).tolist():
            found.setdefault(i, (say(i), reason))

    flag(r[:, 4] != 8, "malformed", lambda i: f"marker {ids[i]}: {int(r[i, 4])} corner values, expected 8")
    flag(r[:, 5] != 36, "covariance", lambda i: f"marker {ids[i]} covariance: expected 36 values, got {int(r[i, 5])}")
    flag(
        ~(r[:, 3] > 0) | ~np.isfinite(r[:, 3]),
        "out_of_bounds",
        lambda i: f"marker {ids[i]}: side length {r[i, 3]} must be positive",
    )
    flag(
        r[:, 3] > limits.max_marker_side_m,
        "out_of_bounds",
        lambda i: f"marker {ids[i]}: side length {r[i, 3]:g} m beyond {limits.max_marker_side_m:g} m",
    )
    flag(ids > limits.max_marker_id, "out_of_bounds", lambda i: f"marker id {ids[i]} beyond {limits.max_marker_id}")
    for name, values, quat in (
        ("camera_T_marker", r[:, 6:13], r[:, 9:13]),
        ("candidate_a", r[:, 13:17], r[:, 13:17]),
        ("candidate_b", r[:, 17:21], r[:, 17:21]),
    ):
        flag(
            ~np.all(np.isfinite(values), axis=1),
            "not_finite",
            lambda i, name=name: f"marker {ids[i]} {name}: contains NaN or inf",
        )
        with np.errstate(over="ignore", invalid="ignore"):  # 1e300 squared is inf: not a unit norm either way
            norms = np.linalg.norm(np.nan_to_num(quat), axis=1)
        flag(
            np.abs(norms - 1.0) > 1e-3,
            "not_rigid",
            lambda i, name=name, norms=norms: f"marker {ids[i]} {name}: quaternion norm {norms[i]:.4g} is not 1",
        )
    far = np.abs(np.nan_to_num(r[:, 6:9])).max(axis=1, initial=0.0) > limits.max_position_m
    flag(
        far,
        "out_of_bounds",
        lambda i: f"marker {ids[i]} camera_T_marker: position {r[i, 6:9].tolist()} beyond {limits.max_position_m:g} m",
    )
    for i, why, reason in covariance_problems(f.covariances, limits):
        found.setdefault(i, (f"marker {ids[i]} covariance: {why}", reason))
    return [(i, why, reason) for i, (why, reason) in sorted(found.items())]


def _has_unknown_fields(msg: Message, payload: bytes) -> bool:
    """True if ``msg``, parsed from ``payload``, or any sub-message carries fields our schema does
    not define; they are dropped from ``msg`` either way.

    The serialised size counts unknown fields at any depth, and dropping them is done by protobuf
    in C, recursively: ten times faster than walking the sub-messages in Python. When what is
    left serialises to exactly the payload's length, nothing was dropped (the common case, one
    size computation); otherwise the payload may just be encoded differently, and a fresh parse
    compares the sizes before and after dropping.
    """
    msg.DiscardUnknownFields()
    if msg.ByteSize() == len(payload):
        return False
    fresh = type(msg)()
    fresh.ParseFromString(payload)
    size = fresh.ByteSize()
    fresh.DiscardUnknownFields()
    return fresh.ByteSize() != size


def check_id(value: str, what: str) -> None:
    if not value or len(value) > 128 or not value.replace("_", "").replace("-", "").replace(".", "").isalnum():
        raise DecodeError(f"{what} {value[:40]!r} is not a valid id", "invalid_id")


def _check_count(n: int, what: str, limits: WireLimits) -> None:
    if n > limits.max_items:
        raise DecodeError(f"{what}: {n} items, more than {limits.max_items}", "too_many")


def _check_image_size(width: int, height: int, what: str, limits: WireLimits) -> None:
    if max(width, height) > limits.max_image_side_px:
        raise DecodeError(f"{what}: {width}x{height} pixels, a side beyond {limits.max_image_side_px}", "out_of_bounds")


def _validate(msg: Message, payload: bytes, semantic: bool, limits: WireLimits) -> None:
    """Semantic checks beyond protobuf's wire format, per message type."""
    # Fields our schema does not know mean garbage or a producer on another schema version.
    if _has_unknown_fields(msg, payload):
        raise DecodeError(f"{msg.DESCRIPTOR.full_name} carries fields this schema does not define")
    if not semantic:
        return
    if isinstance(msg, m.DriverStatus):
        check_id(msg.camera_id, "driver status camera_id")
        if not (0.0 <= msg.rate_hz <= 1e6):  # NaN fails too
            raise DecodeError(f"driver status rate_hz {msg.rate_hz} is not a frame rate", "out_of_bounds")
    elif isinstance(msg, m.EstimatorStatus):
        for cam in msg.cameras:
            check_id(cam.camera_id, "estimator status camera_id")
            if not (0.0 <= cam.position_sigma_m <= limits.max_sigma_m):
                raise DecodeError(
                    f"estimator status sigma {cam.position_sigma_m} of {cam.camera_id!r}", "out_of_bounds"
                )
    elif isinstance(msg, m.RawImage):
        _check_image_size(msg.width, msg.height, "image", limits)
        image_from_msg(msg)
    elif isinstance(msg, m.CameraCalibration):
        _check_image_size(msg.width, msg.height, "camera info", limits)
        CameraInfo.from_msg(msg)
    elif isinstance(msg, m.MarkerObservations):
        check_id(msg.camera_id, "marker observations camera_id")
        _check_image_size(msg.image_width, msg.image_height, "marker observations image", limits)
        marker_arrays(msg, limits=limits)
    elif isinstance(msg, m.PosesWithCovariance):
        poses_from_msg(msg, limits)
    elif isinstance(msg, m.FrameTransforms):
        transforms_from_msg(msg, limits)
    elif isinstance(msg, m.ObjectDetections):
        for det in msg.objects:
            check_id(det.object_id, "object id")
            pose_from_msg(det.world_T_object, f"object {det.object_id!r}", limits)
            if not (0.0 <= det.fitness <= 1.0 and 0.0 <= det.rmse_m <= limits.max_position_m):
                raise DecodeError(
                    f"object {det.object_id!r}: fitness {det.fitness} or rmse {det.rmse_m} m out of range",
                    "out_of_bounds",
                )
    elif isinstance(msg, m.Map):
        poses_from_msg(msg.cameras, limits)
        poses_from_msg(msg.markers, limits)


def decode(payload: bytes, msg_type: type[Msg], semantic: bool = True, limits: WireLimits = DEFAULT_LIMITS) -> Msg:
    """Parse and validate an untrusted payload; raise ``DecodeError`` saying what was wrong.

    ``semantic=False`` checks the wire format and the schema only, for a caller that validates
    the content of many messages at once (``marker_batch``).
    """
    msg, data = msg_type(), bytes(payload)
    try:
        msg.ParseFromString(data)
    except (_PbDecodeError, RuntimeError, ValueError) as exc:
        raise DecodeError(f"not a valid {msg_type.DESCRIPTOR.full_name}: {exc}") from exc
    _validate(msg, data, semantic, limits)
    return msg


# ---------------------------------------------------------------- what needs the key and the clock

#: Repeated fields whose length ``check_on_key`` bounds, per message type.
_ITEMS = {
    m.MarkerObservations: "markers",
    m.PosesWithCovariance: "poses",
    m.FrameTransforms: "transforms",
    m.ObjectDetections: "objects",
    m.EstimatorStatus: "cameras",
    m.SceneUpdate: "entities",
}
#: Messages a camera's driver sends, whose ``camera_id`` must be the camera of their key.
_CAMERA_OWNED = (m.MarkerObservations, m.DriverStatus)


def message_stamps(msg: Message) -> list[int]:
    """Every stamp a message carries (ns; 0 where a stamp was left unset): its own and its items'."""
    fields = msg.DESCRIPTOR.fields_by_name
    stamps = []
    if "stamp_ns" in fields:
        stamps.append(int(msg.stamp_ns))
    if "timestamp" in fields:
        stamps.append(timestamp_to_stamp(msg.timestamp))
    if isinstance(msg, m.PosesWithCovariance):
        stamps += [int(p.stamp_ns) for p in msg.poses]
    elif isinstance(msg, m.ObjectDetections):
        stamps += [int(o.stamp_ns) for o in msg.objects]
    elif isinstance(msg, m.EstimatorStatus):
        stamps += [int(c.last_stamp_ns) for c in msg.cameras]
    elif isinstance(msg, m.FrameTransforms):
        stamps += [timestamp_to_stamp(t.timestamp) for t in msg.transforms]
    elif isinstance(msg, m.Map):
        stamps += message_stamps(msg.cameras) + message_stamps(msg.markers) + message_stamps(msg.status)
    return stamps


def check_on_key(msg: Message, camera: str | None, now_ns: int, limits: WireLimits = DEFAULT_LIMITS) -> None:
    """What a message's own fields cannot show alone: a camera's message names the camera of the key
    it came on (``camera``, None for cell-wide keys), its stamps lie in the window of the receiver's
    clock ``now_ns`` (0 is an unset stamp; a camera's frames and statuses must carry one), and its
    lists are no longer than ``limits.max_items``. Raises ``DecodeError``; cheap, for every message."""
    if isinstance(msg, _CAMERA_OWNED) and msg.camera_id != camera:
        raise DecodeError(f"camera_id {msg.camera_id[:40]!r} on the key of camera {camera!r}", "id_mismatch")
    if (field_name := _ITEMS.get(type(msg))) is not None:
        _check_count(len(getattr(msg, field_name)), f"{msg.DESCRIPTOR.name}.{field_name}", limits)
    latest = now_ns + int(limits.max_stamp_ahead_s * 1e9)
    earliest = 1 if limits.max_stamp_age_s is None else now_ns - int(limits.max_stamp_age_s * 1e9)
    for stamp in message_stamps(msg):
        if stamp == 0 and not isinstance(msg, _CAMERA_OWNED):
            continue
        if not earliest <= stamp <= latest:
            ahead = (stamp - now_ns) / 1e9
            raise DecodeError(
                f"{msg.DESCRIPTOR.name} stamp {stamp} ns is {ahead:+.3g} s from the receiver's clock", "stamp"
            )
