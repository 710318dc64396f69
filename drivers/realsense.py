"""Intel RealSense D4xx sensors (and their recordings) as a frame source, through librealsense.

Uses ``pyrealsense2`` (the optional extra ``cellsight[realsense]``; its wheels carry librealsense,
so no system package is needed). Opens a device by serial number (or the first one), or plays a
recording (``.bag`` from librealsense up to 2.55, ``.db3`` from 2.56 on); starts colour (rgb8) and
depth (z16) at the configured profile, aligns depth to colour (``rs.align``), converts depth
units to millimetres with the device's depth scale, and reads the intrinsics and distortion of
the colour stream (what depth is aligned to) into ``CameraInfo``.

Time stamps: librealsense stamps each frame in one of three clock domains. ``global_time`` (the
D4xx default) and ``system_time`` are the host's clock in milliseconds since the Unix epoch, used
as they are; ``hardware_clock`` (the device's own counter, and what a recording made without
global time holds) is mapped onto the host clock by the offset at the first frame, as the
OpenNI2 driver does. A colour and a depth frame make a frame only when their stamps are within
half a frame period of each other; gaps in the colour frame counter count as dropped frames.

``write_recording`` makes a recording without a camera: frames fed to a librealsense software
device shaped like a D4xx, through ``rs.recorder``; the tests and anyone without hardware play it
back through the same pipeline as a real device.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import DriverError, NoDeviceError
from drivers.frames import Frame
from schemas.codec import CameraInfo

log = logging.getLogger(__name__)
WAIT_MS = 5000  # a device that sends nothing for this long is taken as gone
POLL_MS = 100  # how often a wait looks whether a recording has ended
RECORDINGS = (".bag", ".db3")
CHECKLIST = (
    "check: the camera is on a USB 3 port (`lsusb` lists 8086:0b07 or similar), this user may access it (librealsense's "
    "udev rules, or run as root), and no other process holds it"
)


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise DriverError("the RealSense driver needs pyrealsense2: pip install 'cellsight[realsense]'") from exc
    return rs


def camera_info(intrinsics: Any) -> CameraInfo:
    """``CameraInfo`` of a librealsense ``rs.intrinsics``: K, and D in plumb_bob order (k1 k2 p1 p2 k3),
    which is librealsense's Brown-Conrady order."""
    i = intrinsics
    K = [[i.fx, 0.0, i.ppx], [0.0, i.fy, i.ppy], [0.0, 0.0, 1.0]]
    coeffs = list(i.coeffs)[:5] + [0.0] * (5 - len(list(i.coeffs)[:5]))
    model = str(i.model).rsplit(".", 1)[-1]
    if model not in ("brown_conrady", "modified_brown_conrady", "inverse_brown_conrady", "none") and any(coeffs):
        log.warning("RealSense distortion model %s is not plumb_bob; its coefficients are passed on as they are", model)
    return CameraInfo(int(i.width), int(i.height), np.array(K), np.array(coeffs))


class RealSenseSource:
    """Frames from one RealSense device or recording. ``read`` blocks for the next colour+depth pair;
    None when a recording has ended. ``real_time=False`` plays a recording frame by frame as fast as
    it is read (nothing skipped), for tests and offline work."""

    def __init__(
        self,
        camera_id: str,
        *,
        serial: str | None = None,
        recording: Path | None = None,
        width: int = 640,
        height: int = 480,
        rate_hz: float = 30.0,
        record_to: Path | None = None,
        real_time: bool = True,
    ) -> None:
        rs = self._rs = _rs()
        self.camera_id = camera_id
        self.dropped = 0
        self.recording = recording
        self.name = f"realsense:{recording or serial or 'first device'}"
        config = rs.config()
        if recording is not None:
            if Path(recording).suffix not in RECORDINGS or not Path(recording).is_file():
                raise DriverError(f"{recording}: not a RealSense recording ({' or '.join(RECORDINGS)} file)")
            config.enable_device_from_file(str(recording), repeat_playback=False)
        else:
            if serial:
                config.enable_device(serial)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, int(round(rate_hz)))
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, int(round(rate_hz)))
            if record_to is not None:
                config.enable_record_to_file(str(record_to))
        if recording is None:  # say at once what is there, rather than after the pipeline's own time-out
            found = [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()]
            if not found or (serial and serial not in found):
                raise NoDeviceError(
                    f"no RealSense {serial or 'device'} on this host; devices found: {found or 'none'}; {CHECKLIST}"
                )
        self.pipeline = rs.pipeline()
        try:
            profile = self.pipeline.start(config)
        except RuntimeError as exc:
            raise NoDeviceError(
                f"cannot open RealSense {recording or serial or '(first device)'}: {exc}; {CHECKLIST}"
            ) from exc
        device = profile.get_device()
        self._playback = device.as_playback() if recording is not None else None
        if self._playback is not None:  # real time: paced like the camera; else every frame, as fast as it is read
            self._playback.set_real_time(real_time)
        color = profile.get_stream(rs.stream.color).as_video_stream_profile()
        self.info = camera_info(color.get_intrinsics())
        self.depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
        self.serial = (
            device.get_info(rs.camera_info.serial_number) if device.supports(rs.camera_info.serial_number) else ""
        )
        self.period_ms = 1000.0 / max(color.fps(), 1)
        self._align = rs.align(rs.stream.color)
        self._offset_ns: int | None = None
        self._last_number: int | None = None
        self._last_stamp = -1

    def _stamp(self, frame: Any) -> int:
        """The frame's capture time on the host clock (ns): see the module docstring."""
        ms = frame.get_timestamp()
        if frame.get_frame_timestamp_domain() != self._rs.timestamp_domain.hardware_clock:
            return int(round(ms * 1e6))
        if self._offset_ns is None:
            self._offset_ns = time.time_ns() - int(round(ms * 1e6))
        return self._offset_ns + int(round(ms * 1e6))

    def read(self) -> Frame | None:
        waited_ms = 0
        while True:
            ok, frames = self.pipeline.try_wait_for_frames(POLL_MS)
            if not ok:
                if self._playback is not None and self._playback.current_status() == self._rs.playback_status.stopped:
                    return None  # the recording has ended
                waited_ms += POLL_MS
                if waited_ms >= WAIT_MS:
                    raise NoDeviceError(f"{self.name}: no frames for {WAIT_MS / 1000:.0f} s (unplugged?); {CHECKLIST}")
                continue
            waited_ms = 0
            aligned = self._align.process(frames)
            depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
            if not depth or not color or abs(depth.get_timestamp() - color.get_timestamp()) > self.period_ms / 2:
                continue  # not a pair: the syncer offers a frame with each neighbour; gaps are counted below
            number = color.get_frame_number()
            if self._last_number is not None and number > self._last_number + 1:
                self.dropped += number - self._last_number - 1  # frames the SDK dropped before we saw them
            self._last_number = number
            stamp = self._stamp(color)
            if stamp <= self._last_stamp:
                continue  # a repeated frame (playback pairs a frame with its neighbours too)
            self._last_stamp = stamp
            rgb = np.asanyarray(color.get_data()).copy()
            raw = np.asanyarray(depth.get_data())
            if abs(self.depth_scale_m - 0.001) < 1e-9:
                depth_mm = raw.copy()
            else:  # e.g. 0.0001 m units (D405): millimetres as the wire carries them
                depth_mm = np.clip(np.rint(raw * (self.depth_scale_m * 1000.0)), 0, 65535).astype(np.uint16)
            return Frame(self.camera_id, stamp, rgb, depth_mm, self.info)

    def close(self) -> None:
        try:
            self.pipeline.stop()
        except RuntimeError:  # never started, or already stopped
            pass


def write_recording(path: Path, frames: list[Frame], *, serial: str = "0000000000", rate_hz: float = 30.0) -> Path:
    """Record ``frames`` (rgb8 colour, depth in millimetres registered to it, one ``CameraInfo``)
    to ``path`` (``.db3``; ``.bag`` for librealsense <= 2.55) through a software device: depth and
    colour sensors with the frames' intrinsics, identity extrinsics, 1 mm depth units, stamps in
    the device's hardware clock (milliseconds from the first frame's stamp)."""
    rs = _rs()
    info = frames[0].info
    intr = rs.intrinsics()
    intr.width, intr.height = info.width, info.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = info.K[0, 0], info.K[1, 1], info.K[0, 2], info.K[1, 2]
    intr.model, intr.coeffs = rs.distortion.brown_conrady, [float(v) for v in info.D[:5]]
    device = rs.software_device()
    device.register_info(rs.camera_info.serial_number, serial)
    device.register_info(rs.camera_info.name, "cellsight software D4xx")
    sensors, profiles = {}, {}
    for uid, (kind, fmt, bpp, name) in enumerate(
        ((rs.stream.depth, rs.format.z16, 2, "Depth"), (rs.stream.color, rs.format.rgb8, 3, "Color"))
    ):
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid, stream.fmt, stream.bpp = kind, 0, uid, fmt, bpp
        stream.width, stream.height, stream.fps, stream.intrinsics = info.width, info.height, int(round(rate_hz)), intr
        sensors[name] = device.add_sensor(name)
        profiles[name] = sensors[name].add_video_stream(stream, True)
    sensors["Depth"].add_read_only_option(rs.option.depth_units, 0.001)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    profiles["Depth"].register_extrinsics_to(profiles["Color"], identity)
    device.create_matcher(rs.matchers.dlr_c)
    recorder = rs.recorder(str(path), device)
    sink = rs.frame_queue(len(frames) * 2 + 4)
    for name in sensors:
        sensors[name].open(profiles[name])
        sensors[name].start(sink)
    t0 = frames[0].stamp_ns
    for k, frame in enumerate([frames[0], *frames]):  # the first frame twice: the recorder misses the very first
        for name, pixels, bpp in (("Depth", frame.depth_mm, 2), ("Color", frame.rgb, 3)):
            f = rs.software_video_frame()
            f.pixels, f.stride, f.bpp = np.ascontiguousarray(pixels), info.width * bpp, bpp
            f.timestamp, f.domain, f.frame_number = (
                (frame.stamp_ns - t0) / 1e6,
                rs.timestamp_domain.hardware_clock,
                max(k - 1, 0),
            )
            f.profile = profiles[name].as_video_stream_profile()
            if name == "Depth":
                f.depth_units = 0.001
            sensors[name].on_video_frame(f)
    for name in sensors:
        sensors[name].stop()
        sensors[name].close()
    del recorder  # closes the file
    return Path(path)
