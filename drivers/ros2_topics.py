"""ROS 2 camera topics as a frame source: any ROS 2 camera driver (realsense2_camera,
orbbec_camera, azure_kinect_ros_driver, ...) on the cell's zenoh router, read off rmw_zenoh's wire
with no ROS installed (CDR decoded by ``rosbags``).

Subscribes to ``sensor_msgs/Image`` colour (rgb8 or bgr8), depth aligned to colour (16UC1 in
millimetres, or 32FC1 in metres) and ``sensor_msgs/CameraInfo``, whatever their type hash (any
distribution). A colour and a depth image make a frame when their header stamps are within half a
frame period of each other; the newest pair wins (a slow detector skips frames, counted as dropped).
Stamps are the images' header stamps, the camera driver's clock.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np
import zenoh

from drivers.errors import DriverError, NoDeviceError
from drivers.frames import Frame
from schemas.codec import CameraInfo
from schemas.rmw_zenoh import dds_type_name
from schemas.ros2 import Ros2Types, stamp_ns

log = logging.getLogger(__name__)
IMAGE, INFO = "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo"
WAIT_S = 5.0  # no pair for this long: the camera driver is gone


def topic_pattern(domain_id: int, topic: str, typename: str) -> str:
    """The key expression of a ROS 2 topic for any type hash."""
    return f"{domain_id}/{topic.lstrip('/')}/{dds_type_name(typename)}/*"


def image_array(msg: Any) -> tuple[np.ndarray, str]:
    """(pixels, kind) of a sensor_msgs/Image: rgb8 (H, W, 3) uint8 from rgb8/bgr8, or depth (H, W)
    uint16 millimetres from 16UC1/mono16 or 32FC1 metres. Raises ``DriverError`` otherwise."""
    h, w, step, data = int(msg.height), int(msg.width), int(msg.step), np.asarray(msg.data, dtype=np.uint8)
    layouts = {
        "rgb8": (np.uint8, 3),
        "bgr8": (np.uint8, 3),
        "16UC1": ("<u2", 1),
        "mono16": ("<u2", 1),
        "32FC1": ("<f4", 1),
    }
    if msg.encoding not in layouts:
        raise DriverError(f"image encoding {msg.encoding!r} is not supported; use one of {sorted(layouts)}")
    dtype, channels = layouts[msg.encoding]
    row = w * channels * np.dtype(dtype).itemsize
    if msg.is_bigendian or step < row or len(data) < step * h:
        raise DriverError(f"image {w}x{h} {msg.encoding}: step {step} and {len(data)} bytes do not fit")
    pixels = data.reshape(h, step)[:, :row].copy().view(dtype).reshape((h, w, channels) if channels > 1 else (h, w))
    if msg.encoding == "bgr8":
        return pixels[:, :, ::-1].copy(), "color"
    if msg.encoding == "rgb8":
        return pixels, "color"
    if msg.encoding == "32FC1":  # metres, NaN where there is no depth
        mm = np.nan_to_num(pixels.astype(np.float64) * 1000.0, nan=0.0, posinf=0.0, neginf=0.0)
        return np.clip(np.rint(mm), 0, 65535).astype(np.uint16), "depth"
    return pixels.astype(np.uint16), "depth"


class Ros2TopicsSource:
    """Frames from a ROS 2 camera's colour, depth and camera-info topics on ``session``."""

    def __init__(
        self,
        camera_id: str,
        session: zenoh.Session,
        types: Ros2Types,
        *,
        color: str,
        depth: str,
        info: str,
        domain_id: int = 0,
        rate_hz: float = 30.0,
    ) -> None:
        self.camera_id = camera_id
        self.name = f"ros2:{color}"
        self.types = types
        self.dropped = 0
        self.half_period_ns = int(0.5e9 / rate_hz)
        self._cond = threading.Condition()
        self._latest: dict[str, tuple[int, np.ndarray]] = {}
        self._info: CameraInfo | None = None
        self._pair: tuple[int, np.ndarray, np.ndarray] | None = None
        self._bad = 0
        self._subs = [
            session.declare_subscriber(topic_pattern(domain_id, color, IMAGE), lambda s: self._image(s, "color")),
            session.declare_subscriber(topic_pattern(domain_id, depth, IMAGE), lambda s: self._image(s, "depth")),
            session.declare_subscriber(topic_pattern(domain_id, info, INFO), self._camera_info),
        ]

    def _decode(self, sample: zenoh.Sample, typename: str) -> Any | None:
        try:
            return self.types.deserialize(sample.payload.to_bytes(), typename)
        except Exception as exc:  # untrusted CDR: rosbags raises several kinds; count, log once, drop
            self._bad += 1
            if self._bad == 1:
                log.warning("%s: dropping an undecodable %s on %s: %s", self.camera_id, typename, sample.key_expr, exc)
            return None

    def _camera_info(self, sample: zenoh.Sample) -> None:
        msg = self._decode(sample, INFO)
        if msg is None:
            return
        try:
            info = CameraInfo(
                int(msg.width),
                int(msg.height),
                np.asarray(msg.k, dtype=np.float64),
                np.asarray(msg.d, dtype=np.float64)[:5],
            )
        except Exception as exc:
            log.warning("%s: camera info refused: %s", self.camera_id, exc)
            return
        with self._cond:
            self._info = info

    def _image(self, sample: zenoh.Sample, want: str) -> None:
        msg = self._decode(sample, IMAGE)
        if msg is None:
            return
        try:
            pixels, kind = image_array(msg)
        except DriverError as exc:
            log.warning("%s: %s", self.camera_id, exc)
            return
        if kind != want:
            return
        stamp = stamp_ns(msg.header.stamp)
        with self._cond:
            self._latest[kind] = (stamp, pixels)
            other = self._latest.get("depth" if kind == "color" else "color")
            if other is not None and abs(other[0] - stamp) <= self.half_period_ns:
                color, depth = (pixels, other[1]) if kind == "color" else (other[1], pixels)
                if self._pair is not None:
                    self.dropped += 1  # the previous pair was never read: newest wins
                self._pair = (max(stamp, other[0]), color, depth)
                self._latest.clear()
                self._cond.notify_all()

    def read(self) -> Frame | None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._pair is not None and self._info is not None, timeout=WAIT_S):
                raise NoDeviceError(
                    f"{self.name}: no colour+depth pair with camera info for {WAIT_S:.0f} s "
                    "(is the ROS 2 camera driver running, on this router, with these topics?)"
                )
            stamp, color, depth = self._pair
            self._pair = None
            info = self._info
        if depth.shape != color.shape[:2] or (info.width, info.height) != (color.shape[1], color.shape[0]):
            raise DriverError(
                f"{self.name}: colour {color.shape[1]}x{color.shape[0]}, depth {depth.shape[::-1]} and camera info "
                f"{info.width}x{info.height} differ: depth must be aligned to colour"
            )
        return Frame(self.camera_id, stamp, color, depth, info)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
