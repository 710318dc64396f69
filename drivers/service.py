"""A driver process: one frame source -> marker detection -> every camera key on the bus.

The loop (``DriverService.run``) owns timing, status and publishing; the source and the marker
detector are pure. A frame that fails detection is counted and skipped, never fatal.
"""

from __future__ import annotations

import logging
import threading
import time

import cv2

from drivers.config import MarkerConfig
from drivers.errors import DriverError, NoDeviceError
from drivers.frames import Frame, FrameSource, observations_to_msg
from drivers.markers import MarkerDetector
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus

log = logging.getLogger(__name__)
STATUS_PERIOD_S = 1.0
TRUTH_PERIOD_S = 0.1


def use_opencv_threads(n: int) -> None:
    """OpenCV's thread pool for this process: n threads, 0 for OpenCV's default (its own 0 would mean
    none at all). Process-wide, so a driver process sets it once at start (``markers.opencv_threads``)."""
    cv2.setNumThreads(n if n > 0 else -1)


class DriverService:
    """Publishes one camera. ``truth`` (sim only) is a callable t_s -> (cameras, markers, objects)."""

    def __init__(
        self, bus: Bus, source: FrameSource, camera_id: str, markers: MarkerConfig, *, publish_images: bool = True
    ) -> None:
        self.bus = bus
        self.source = source
        self.camera_id = keys.check_name(camera_id, "camera id")
        self.detector = MarkerDetector(markers)
        self.dictionary = markers.dictionary
        self.publish_images = publish_images
        cell = bus.cell
        self._pub = {
            "color": bus.publisher(keys.color(cell, camera_id), frames=True),
            "depth": bus.publisher(keys.depth(cell, camera_id), frames=True),
            "info": bus.publisher(keys.camera_info(cell, camera_id)),
            "markers": bus.publisher(keys.markers(cell, camera_id)),
            "status": bus.publisher(keys.status(cell, camera_id)),
        }
        self._truth_pubs = None
        if hasattr(source, "truth"):
            self._truth_pubs = {w: bus.publisher(keys.truth(cell, w)) for w in ("cameras", "marker_poses", "objects")}
        self.frames = 0
        self.failed = 0
        self._window: list[float] = []
        self._last_status = 0.0
        self._last_truth = -1.0
        bus.declare_alive("driver", camera_id)

    def step(self) -> bool:
        """Read, detect and publish one frame; False when the source has ended."""
        frame = self.source.read()
        if frame is None:
            return False
        self._publish(frame)
        return True

    def _publish(self, frame: Frame) -> None:
        cid, stamp = self.camera_id, frame.stamp_ns
        try:
            detections = self.detector.detect(frame.rgb, frame.info, frame.depth_mm)
        except DriverError as exc:
            self.failed += 1
            log.warning("frame %d of %s skipped: %s", self.frames, cid, exc)
            return
        if self.publish_images:  # images only to a subscriber: 1.5 MB a frame to copy for nobody
            if self._pub["color"].wanted():
                self._pub["color"].put(codec.image_to_msg(frame.rgb, stamp, cid, "rgb8"))
            if frame.depth_mm is not None and self._pub["depth"].wanted():
                self._pub["depth"].put(codec.image_to_msg(frame.depth_mm, stamp, cid, "16UC1"))
            self._pub["info"].put(frame.info.to_msg(stamp, cid))
        self._pub["markers"].put(observations_to_msg(cid, stamp, frame.info, detections, self.dictionary))
        self.frames += 1
        now = time.monotonic()
        self._window.append(now)
        if self._truth_pubs is not None:
            self._publish_truth(stamp)
        if now - self._last_status >= STATUS_PERIOD_S:
            self.publish_status(m.DriverStatus.RUNNING)
            self._last_status = now

    def _publish_truth(self, stamp_ns: int) -> None:
        """The simulator's truth, to whoever scores against it (tests, benchmarks, a recording); none
        computed while nobody subscribes (~1 ms a frame)."""
        wanted = {w: p.wanted() for w, p in self._truth_pubs.items()}
        t_s = self.source.t_s  # scenario time of the frame just published
        with_map = (wanted["marker_poses"] or wanted["objects"]) and t_s - self._last_truth >= TRUTH_PERIOD_S
        if not (with_map or wanted["cameras"]):
            return
        cams, markers, objects = self.source.truth(t_s, with_map)
        if wanted["cameras"]:
            self._truth_pubs["cameras"].put(codec.poses_to_msg(stamp_ns, cams))
        if with_map:
            for what, poses in (("marker_poses", markers), ("objects", objects)):
                if wanted[what]:
                    self._truth_pubs[what].put(codec.poses_to_msg(stamp_ns, poses))
            self._last_truth = t_s

    def publish_status(self, state: int, message: str = "") -> None:
        now = time.monotonic()
        self._window = [t for t in self._window if now - t <= STATUS_PERIOD_S * 2]
        rate = len(self._window) / (STATUS_PERIOD_S * 2)
        self._pub["status"].put(
            m.DriverStatus(
                camera_id=self.camera_id,
                stamp_ns=time.time_ns(),
                state=state,
                source=self.source.name,
                rate_hz=rate,
                frames=self.frames,
                dropped=getattr(self.source, "dropped", 0) + self.failed,
                message=message,
            )
        )

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Publish until the source ends, ``stop`` is set or ``duration_s`` has passed."""
        stop = stop or threading.Event()
        start = time.monotonic()
        self.publish_status(m.DriverStatus.STARTING)
        final = m.DriverStatus.STOPPED, ""
        try:
            while not stop.is_set():
                if duration_s is not None and time.monotonic() - start >= duration_s:
                    break
                if not self.step():
                    log.info("source %s ended after %d frames", self.source.name, self.frames)
                    break
        except DriverError as exc:  # the device went away: say so on the bus, then let the supervisor restart us
            final = (m.DriverStatus.NO_DEVICE if isinstance(exc, NoDeviceError) else m.DriverStatus.ERROR), str(exc)
            raise
        finally:
            self.publish_status(*final)
            self.source.close()
