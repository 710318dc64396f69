"""OpenNI2 sensors (Kinect v1, Xtion, Carmine, .oni recordings) as a frame source.

Uses the ``openni`` bindings over Debian's ``libopenni2``. Opens a device by URI (a device URI,
``Dummy`` for OpenNI's test device, a ``.oni`` file, or empty for the first device), starts depth
and colour at the requested mode when the device offers it, turns on depth-to-colour registration
and frame sync when offered, and stamps frames with the device clock mapped onto Unix time.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from drivers.errors import NoDeviceError
from drivers.frames import Frame
from schemas.codec import CameraInfo

log = logging.getLogger(__name__)
DEFAULT_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib")
CHECKLIST = (
    "check: the sensor is plugged in and powered (Kinect v1 needs its mains adapter), `lsusb` lists it, "
    "udev rules give this user access (Debian's libopenni2-0 installs them; re-plug after installing), "
    "and libopenni2-dev is installed (./setup.sh does it)"
)


def _initialize(lib_dir: Path | None):
    from openni import openni2

    if openni2.is_initialized():  # initialising twice in one process crashes the library
        return openni2
    tried = (
        [str(lib_dir)]
        if lib_dir
        else [d for d in DEFAULT_LIB_DIRS if Path(d, "libOpenNI2.so").exists() or Path(d, "libOpenNI2.so.0").exists()]
    )
    errors = []
    for d in tried or list(DEFAULT_LIB_DIRS):
        try:
            openni2.initialize(d)
            return openni2
        except Exception as exc:  # the bindings raise bare Exception / OpenNIError / OSError
            errors.append(f"{d}: {exc}")
    raise NoDeviceError(f"cannot load libOpenNI2 (tried {', '.join(errors) or DEFAULT_LIB_DIRS}); {CHECKLIST}")


class OpenNI2Source:
    """Frames from one OpenNI2 device. ``read`` blocks for the next depth+colour pair."""

    def __init__(
        self,
        camera_id: str,
        uri: str = "",
        *,
        width: int = 640,
        height: int = 480,
        rate_hz: float = 30.0,
        info: CameraInfo | None = None,
        lib_dir: Path | None = None,
    ) -> None:
        self.camera_id = camera_id
        self.name = f"openni2:{uri or 'first device'}"
        self.dropped = 0
        self._openni2 = openni2 = _initialize(lib_dir)
        try:
            if uri.endswith(".oni"):
                self.device = openni2.Device.open_file(uri.encode())
            elif uri:
                self.device = openni2.Device(uri.encode())
            else:
                self.device = openni2.Device.open_any()
        except Exception as exc:
            available = [u.decode() for u in openni2.Device.enumerate_uris()]
            raise NoDeviceError(
                f"cannot open OpenNI2 device {uri or '(first device)'!r}: {exc}; devices found: {available or 'none'}; {CHECKLIST}"
            ) from exc
        self.depth = self._start(openni2.SENSOR_DEPTH, width, height, rate_hz)
        self.color = (
            self._start(openni2.SENSOR_COLOR, width, height, rate_hz)
            if self.device.has_sensor(openni2.SENSOR_COLOR)
            else None
        )
        if self.color is not None:
            if self.device.is_image_registration_mode_supported(openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR):
                self.device.set_image_registration_mode(openni2.IMAGE_REGISTRATION_DEPTH_TO_COLOR)
            else:
                log.warning("%s: no depth-to-colour registration; depth is in the IR camera's frame", self.name)
            try:
                self.device.set_depth_color_sync_enabled(True)
            except Exception:  # optional capability; many devices (and Dummy) do not offer it
                log.info("%s: frame sync not offered", self.name)
        mode = (self.color or self.depth).get_video_mode()
        self.width, self.height = mode.resolutionX, mode.resolutionY
        self.info = info if info is not None else CameraInfo.kinect_v1(self.width, self.height)
        self._offset_ns: int | None = None
        self._last_stamp = -1

    def _start(self, sensor, width: int, height: int, rate_hz: float):
        stream = (
            self.device.create_depth_stream()
            if sensor == self._openni2.SENSOR_DEPTH
            else self.device.create_color_stream()
        )
        wanted = [
            m
            for m in stream.get_sensor_info().videoModes
            if m.resolutionX == width and m.resolutionY == height and abs(m.fps - rate_hz) < 1
        ]
        if wanted:
            stream.set_video_mode(wanted[0])
        stream.start()
        return stream

    def _stamp(self, device_us: int) -> int:
        """Device microseconds mapped onto Unix nanoseconds (offset fixed at the first frame)."""
        if self._offset_ns is None:
            self._offset_ns = time.time_ns() - device_us * 1000
        return self._offset_ns + device_us * 1000

    def read(self) -> Frame | None:
        d = self.depth.read_frame()
        depth = np.frombuffer(d.get_buffer_as_uint16(), dtype=np.uint16).reshape(d.height, d.width).copy()
        rgb = None
        if self.color is not None:
            c = self.color.read_frame()
            rgb = np.frombuffer(c.get_buffer_as_uint8(), dtype=np.uint8).reshape(c.height, c.width, 3).copy()
        if rgb is None:  # depth-only device: a grey image so the frame is still well-formed
            rgb = np.repeat(np.clip(depth / 16, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)
        if depth.shape != rgb.shape[:2]:
            depth = None  # not registered to colour at this size: never publish it as if it were
        stamp = self._stamp(int(d.timestamp))
        if stamp <= self._last_stamp:
            self.dropped += 1
            return self.read()
        self._last_stamp = stamp
        return Frame(self.camera_id, stamp, rgb, depth, self.info)

    def close(self) -> None:
        # Streams only. The bindings' Device.close() leaves the process so that the next
        # zenoh.open() segfaults, and initialising again after openni2.unload() crashes too; the
        # device is released when the process exits.
        for s in (self.depth, self.color):
            if s is not None:
                s.stop()
