"""ROS 2 messages for our poses, transforms and images, encoded as CDR with ``rosbags`` (message
definitions, serialisation and RIHS01 type hashes in pure Python: no ROS installation).

Frame ids follow REP-103/105: ``world`` is the cell's frame, a camera's frame is its colour
optical frame ``<camera>_color_optical_frame``, markers and objects keep our names
(``marker_<id>``, ``object_<id>``). Our protobuf keys stay the native wire; this is the view of
the same data a ROS 2 tool reads (``cellsight export ros2``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from schemas import codec
from schemas import messages as m
from schemas.errors import SchemaError
from schemas.geometry import quat_from_matrix

WORLD = "world"
DISTROS = ("jazzy", "humble")
#: .msg definitions of the packages rosbags' stores lack (vision_msgs), as ``<package>/msg/<Name>.msg``.
SHIPPED_MSGS = Path(__file__).parent / "ros2_msgs"
DETECTIONS = "vision_msgs/msg/Detection3DArray"
CLOUD = "sensor_msgs/msg/PointCloud2"


class Ros2Config(BaseModel):
    """ROS 2 on the cell's zenoh routers (rmw_zenoh's wire): what the estimator publishes for robots."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(default=False, description="publish /tf, /tf_static and camera poses as rmw_zenoh does")
    domain_id: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID of the robots that read them")
    distro: Literal["jazzy", "humble"] = Field(
        default="jazzy", description="jazzy and later: RIHS01 type hashes; humble: none"
    )
    node: str = Field(default="cellsight_estimator", description="the ROS 2 node name the estimator appears as")
    recognition_node: str = Field(
        default="cellsight_recognition", description="the node name the recognition worker appears as"
    )
    static_every_s: float = Field(
        default=1.0, gt=0, description="/tf_static (anchors) is re-sent this often for late joiners"
    )


def optical_frame(camera_id: str) -> str:
    """REP-105 frame id of a camera's colour optical frame."""
    return f"{camera_id}_color_optical_frame"


def ros_frame(child: str) -> str:
    """Our child frame name as a ROS frame id: markers (``marker_<id>``) and objects (``object_<id>``)
    keep theirs; every other child of ``world`` is a camera and becomes its optical frame."""
    return child if child.startswith(("marker_", "object_")) else optical_frame(child)


@dataclass(frozen=True)
class Ros2Types:
    """The message types of one ROS 2 distribution (``rosbags`` typestore)."""

    distro: str
    store: Any

    def serialize(self, msg: object, typename: str) -> bytes:
        """CDR bytes (little endian, with the encapsulation header) of a message."""
        return bytes(self.store.serialize_cdr(msg, typename))

    def deserialize(self, data: bytes, typename: str) -> Any:
        return self.store.deserialize_cdr(data, typename)

    def type_hash(self, typename: str) -> str:
        """RIHS01 hash (Jazzy and later), or ``TypeHashNotSupported`` (Humble), as rmw_zenoh names it."""
        return self.store.hash_rihs01(typename) if self.distro != "humble" else "TypeHashNotSupported"

    def _t(self, name: str) -> Any:
        return self.store.types[name]

    def time(self, stamp_ns: int) -> Any:
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        return self._t("builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> Any:
        return self._t("std_msgs/msg/Header")(stamp=self.time(stamp_ns), frame_id=frame_id)

    def _xyz_quat(self, T: np.ndarray, xyz_type: str) -> tuple[Any, Any]:
        """The translation of a 4x4 pose as ``xyz_type`` (Point or Vector3) and its rotation as a Quaternion."""
        q = quat_from_matrix(T[:3, :3])
        return (
            self._t(xyz_type)(x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
            self._t("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])),
        )

    def pose(self, T: np.ndarray) -> Any:
        point, quat = self._xyz_quat(T, "geometry_msgs/msg/Point")
        return self._t("geometry_msgs/msg/Pose")(position=point, orientation=quat)

    def tf_message(self, stamp_ns: int, transforms: Iterable[tuple[str, str, np.ndarray]]) -> Any:
        """tf2_msgs/TFMessage of (parent frame id, child frame id, parent_T_child 4x4)."""
        out = []
        for parent, child, T in transforms:
            vector, quat = self._xyz_quat(T, "geometry_msgs/msg/Vector3")
            tr = self._t("geometry_msgs/msg/Transform")(translation=vector, rotation=quat)
            out.append(
                self._t("geometry_msgs/msg/TransformStamped")(
                    header=self.header(stamp_ns, parent), child_frame_id=child, transform=tr
                )
            )
        return self._t("tf2_msgs/msg/TFMessage")(transforms=out)

    def pose_with_covariance(self, stamp_ns: int, frame_id: str, T: np.ndarray, covariance: np.ndarray | None) -> Any:
        """geometry_msgs/PoseWithCovarianceStamped; the 6x6 covariance in ROS order (x y z rx ry rz),
        as ours is; unknown covariance: zeros but -1 first (the ROS convention for "unknown")."""
        cov = (
            np.asarray(covariance, dtype=np.float64).reshape(36)
            if covariance is not None
            else np.r_[-1.0, np.zeros(35)]
        )
        inner = self._t("geometry_msgs/msg/PoseWithCovariance")(pose=self.pose(T), covariance=cov)
        return self._t("geometry_msgs/msg/PoseWithCovarianceStamped")(
            header=self.header(stamp_ns, frame_id), pose=inner
        )

    def pose_array(self, stamp_ns: int, frame_id: str, poses: Iterable[np.ndarray]) -> Any:
        return self._t("geometry_msgs/msg/PoseArray")(
            header=self.header(stamp_ns, frame_id), poses=[self.pose(T) for T in poses]
        )

    def image(self, stamp_ns: int, frame_id: str, pixels: np.ndarray, encoding: str) -> Any:
        """sensor_msgs/Image of an (H, W, 3) rgb8 or (H, W) 16UC1 array."""
        pixels = np.ascontiguousarray(pixels)
        h, w = pixels.shape[:2]
        step = w * (pixels.shape[2] if pixels.ndim == 3 else 1) * pixels.dtype.itemsize
        return self._t("sensor_msgs/msg/Image")(
            header=self.header(stamp_ns, frame_id),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=step,
            data=pixels.view(np.uint8).reshape(-1),
        )

    def detections(
        self, msg: m.ObjectDetections, boxes: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None
    ) -> Any:
        """vision_msgs/Detection3DArray (world frame) of our fused objects: class id and ``id`` are
        the object id, score its fitness, pose covariance unknown. ``boxes``: object id -> (box
        centre in the object frame (3,), size (3,)) in metres; without one the box is the pose, size 0."""
        t, boxes = self._t, boxes or {}
        out = []
        for o in msg.objects:
            T = codec.pose_from_msg(o.world_T_object)
            centre, size = boxes.get(o.object_id, (np.zeros(3), np.zeros(3)))
            box_T = T.copy()
            box_T[:3, 3] = T[:3, :3] @ centre + T[:3, 3]
            pose = t("geometry_msgs/msg/PoseWithCovariance")(pose=self.pose(T), covariance=np.r_[-1.0, np.zeros(35)])
            hyp = t("vision_msgs/msg/ObjectHypothesisWithPose")(
                hypothesis=t("vision_msgs/msg/ObjectHypothesis")(class_id=o.object_id, score=float(o.fitness)),
                pose=pose,
            )
            size_v = t("geometry_msgs/msg/Vector3")(x=float(size[0]), y=float(size[1]), z=float(size[2]))
            out.append(
                t("vision_msgs/msg/Detection3D")(
                    header=self.header(o.stamp_ns, WORLD),
                    results=[hyp],
                    bbox=t("vision_msgs/msg/BoundingBox3D")(center=self.pose(box_T), size=size_v),
                    id=o.object_id,
                )
            )
        return t(DETECTIONS)(header=self.header(msg.stamp_ns, WORLD), detections=out)

    def point_cloud(self, stamp_ns: int, frame_id: str, xyz: np.ndarray, rgba: np.ndarray) -> Any:
        """sensor_msgs/PointCloud2 of xyz (N, 3) metres coloured rgba (N, 4) uint8: float32 x y z and
        the colour as PCL packs it (``rgb``, 0x00RRGGBB in a float32's bytes), 16 bytes a point."""
        packed = np.zeros((len(xyz), 4), np.float32)
        packed[:, :3] = xyz
        rgb = (rgba[:, 0].astype(np.uint32) << 16) | (rgba[:, 1].astype(np.uint32) << 8) | rgba[:, 2].astype(np.uint32)
        packed[:, 3] = rgb.view(np.float32)
        field = self._t("sensor_msgs/msg/PointField")
        fields = [
            field(name=n, offset=4 * i, datatype=field.FLOAT32, count=1) for i, n in enumerate(("x", "y", "z", "rgb"))
        ]
        return self._t(CLOUD)(
            header=self.header(stamp_ns, frame_id),
            height=1,
            width=len(xyz),
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * len(xyz),
            data=packed.view(np.uint8).reshape(-1),
            is_dense=True,
        )

    def camera_info(self, stamp_ns: int, frame_id: str, width: int, height: int, K: np.ndarray, D: np.ndarray) -> Any:
        P = np.hstack([np.asarray(K, np.float64), np.zeros((3, 1))])
        roi = self._t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self._t("sensor_msgs/msg/CameraInfo")(
            header=self.header(stamp_ns, frame_id),
            height=height,
            width=width,
            distortion_model="plumb_bob",
            d=np.asarray(D, np.float64),
            k=np.asarray(K, np.float64).reshape(9),
            r=np.eye(3).reshape(9),
            p=P.reshape(12),
            binning_x=0,
            binning_y=0,
            roi=roi,
        )


@cache
def ros2_types(distro: str = "jazzy") -> Ros2Types:
    """The message types of ``distro`` (``jazzy``: RIHS01 type hashes; ``humble``: none), with the
    packages we ship definitions of (``SHIPPED_MSGS``) registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if distro not in DISTROS:
        raise SchemaError(f"ROS 2 distribution {distro!r} is not supported; use one of {DISTROS}")
    store = get_typestore(Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_HUMBLE)
    for f in sorted(SHIPPED_MSGS.glob("*/msg/*.msg")):
        store.register(get_types_from_msg(f.read_text(), f"{f.parent.parent.name}/msg/{f.stem}"))
    return Ros2Types(distro, store)


def stamp_ns(t: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time."""
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)
