"""The estimator daemon: marker observations from every camera in, poses and states out.

Owns the zenoh session, the update loop (on arriving frames; ``update_hz`` when none arrive), publishing, the ``estimate/map``
queryable, the liveliness token and the persisted map. The estimation itself is
``estimator.graph.Estimator``; nothing here changes its answer.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

import numpy as np
import zenoh

from estimator.config import EstimatorConfig
from estimator.errors import StateFileError
from estimator.estimate import CameraState, Estimate
from estimator.graph import Estimator
from estimator.observation import validated_rows
from estimator.state import SavedMarker, load_state, save_state, set_aside
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, Received
from schemas.errors import DecodeError
from schemas.rmw_zenoh import QOS_LATCHED, QOS_TF, NodeName, Ros2Node, Ros2Publisher
from schemas.ros2 import WORLD, Ros2Config, optical_frame, ros2_types

log = logging.getLogger(__name__)
SAVE_PERIOD_S = 5.0
_STATE = {
    CameraState.LOCALIZED: m.CameraState.LOCALIZED,
    CameraState.UNANCHORED: m.CameraState.UNANCHORED,
    CameraState.MOVING: m.CameraState.MOVING,
    CameraState.STALE: m.CameraState.STALE,
}


class Clock:
    """The sensors' clock as seen from here: newest stamp plus wall time since it arrived (ns).

    Works for live sensors and for replayed logs whose stamps are hours old.
    """

    def __init__(self) -> None:
        self.stamp_ns = 0
        self.received_ns = 0

    def observe(self, stamp_ns: int, received_ns: int) -> None:
        if stamp_ns >= self.stamp_ns:
            self.stamp_ns, self.received_ns = stamp_ns, received_ns

    def now(self) -> int:
        return self.stamp_ns + (time.time_ns() - self.received_ns) if self.stamp_ns else 0


class ClockJumps:
    """Takes jumps of each sensor's clock out of its stamps, so the daemon's timeline stays continuous.

    Per camera, the offset = stamp - arrival time (ns) moves only with transport delay while the
    clocks keep time (and steadily during a replay at another rate, so it is compared frame to
    frame). An offset more than ``jump_ns`` ahead of the last one is a forward step of the sensor's
    clock: nothing else puts stamps ahead. One that far behind is either a late frame (a stalled
    driver publishing a frame it stamped before the stall) or a backward step; it counts as a step
    once ``confirm_frames`` frames in a row are that late. A frame more than half of ``jump_ns``
    late never becomes the reference. A step is added to the camera's correction,
    so its later stamps continue where they were. Without this, a camera stepped an hour ahead drags
    the daemon's clock with it (every other camera turns stale), and one stepped back has every
    frame refused as going backwards until its clock catches up.
    """

    def __init__(self, jump_ns: int, confirm_frames: int = 5) -> None:
        self.jump_ns = jump_ns
        self.confirm_frames = confirm_frames
        self.jumps: Counter[str] = Counter()
        self._correction_ns: dict[str, int] = {}
        self._offset_ns: dict[str, int] = {}  # camera -> offset of its last on-time frame, corrected
        self._late: Counter[str] = Counter()  # camera -> consecutive frames far behind that offset

    def correct(self, camera_id: str, stamp_ns: int, received_ns: int) -> int:
        """The frame's stamp on the camera's continuous timeline (ns)."""
        stamp_ns -= self._correction_ns.get(camera_id, 0)
        offset = stamp_ns - received_ns
        last = self._offset_ns.setdefault(camera_id, offset)
        step = offset - last
        if step < -self.jump_ns:
            self._late[camera_id] += 1
            if self._late[camera_id] < self.confirm_frames:
                return stamp_ns  # late, perhaps: the estimator refuses it if it goes backwards
        elif step < -self.jump_ns // 2:
            # Seconds late but not a step: a frame held up by a stalled driver. It is no reference:
            # a few such frames either side of the threshold would walk the reference down until the
            # on-time frame after them read as a step ahead. A slower replay drifts by milliseconds.
            return stamp_ns
        elif step <= self.jump_ns:
            self._late[camera_id] = 0
            self._offset_ns[camera_id] = offset
            return stamp_ns
        self._late[camera_id] = 0
        self._correction_ns[camera_id] = self._correction_ns.get(camera_id, 0) + step
        self.jumps[camera_id] += 1
        log.warning(
            "the clock of camera %s jumped %+.3f s; its stamps are shifted back onto the timeline it had "
            "(check the time sync of its host)",
            camera_id,
            step / 1e9,
        )
        return stamp_ns - step


class Ros2Out:
    """The estimates on ROS 2's wire (rmw_zenoh) beside our own keys: /tf (world -> each camera's
    optical frame, each mapped marker and each object the recognition worker reports), /tf_static
    (the anchors, re-sent every ``static_every_s`` for late joiners), ``/cellsight/<camera>/pose``
    with covariance. tf has one publisher, this node, so the secure profile can name who writes it."""

    def __init__(self, bus: Bus, config: Ros2Config, anchors: dict[int, np.ndarray]) -> None:
        self.config = config
        self.types = ros2_types(config.distro)
        self.node = Ros2Node(bus.session, NodeName(config.domain_id, config.node), self.types)
        self.tf = self.node.publisher("/tf", "tf2_msgs/msg/TFMessage", QOS_TF)
        self.tf_static = self.node.publisher("/tf_static", "tf2_msgs/msg/TFMessage", QOS_LATCHED)
        self.anchors = anchors
        self.poses: dict[str, Ros2Publisher] = {}
        self._objects = bus.subscribe(keys.objects(bus.cell), m.ObjectDetections, capacity=1, ring=True)
        self._last_static = 0.0

    def publish(self, cams: list[codec.StampedPose], marks: list[codec.StampedPose], stamp_ns: int) -> None:
        frames = [(p.parent, optical_frame(p.child), p.T) for p in cams] + [(p.parent, p.child, p.T) for p in marks]
        self.tf.put(self.types.tf_message(stamp_ns, frames), stamp_ns)
        for p in cams:
            if p.child not in self.poses:
                self.poses[p.child] = self.node.publisher(
                    f"/cellsight/{p.child}/pose", "geometry_msgs/msg/PoseWithCovarianceStamped"
                )
            self.poses[p.child].put(self.types.pose_with_covariance(p.stamp_ns, WORLD, p.T, p.covariance), p.stamp_ns)
        if self.anchors and time.monotonic() - self._last_static >= self.config.static_every_s:
            anchors = [(WORLD, keys.marker_frame(k), T) for k, T in sorted(self.anchors.items())]
            self.tf_static.put(self.types.tf_message(stamp_ns, anchors), stamp_ns)
            self._last_static = time.monotonic()
        for item in self._objects.drain():  # each object stamped with the depth frame it was seen in
            for o in item.msg.objects:
                frame = (WORLD, keys.object_frame(o.object_id), codec.pose_from_msg(o.world_T_object))
                self.tf.put(self.types.tf_message(o.stamp_ns, [frame]), o.stamp_ns)

    def close(self) -> None:
        self.node.close()


class EstimatorService:
    def __init__(self, bus: Bus, config: EstimatorConfig, ros2: Ros2Config | None = None) -> None:
        self.bus = bus
        self.config = config
        self.estimator = Estimator(config)
        self.clock = Clock()
        self.clock_jumps = ClockJumps(int(config.clock_jump_s * 1e9))
        self._lock = threading.Lock()  # the queryable answers from zenoh's thread
        self._map: m.Map | None = None
        self._last_save = time.monotonic()
        self._last_map = -1.0  # monotonic s of the last markers/status publish
        self.save_failures = 0  # consecutive, so a full disk is reported once, not every period
        self.restored = self._restore()
        cell = bus.cell
        # Content is validated once, a camera's frames together, in ``ingest``.
        self._sub = bus.subscribe(
            keys.all_cameras(cell, "markers"), m.MarkerObservations, capacity=8192, semantic=False
        )
        self.bad_frames: Counter[str] = Counter()  # camera -> frames dropped as malformed
        self.rejected: Counter[tuple[str, str]] = Counter()  # (key, reason) -> frames dropped here
        self._pub = {
            "tf": bus.publisher(keys.tf(cell)),
            "cameras": bus.publisher(keys.estimate_cameras(cell)),
            "markers": bus.publisher(keys.estimate_markers(cell)),
            "status": bus.publisher(keys.estimate_status(cell)),
        }
        self._queryable = bus.session.declare_queryable(keys.estimate_map(cell), self._answer_map)
        self.ros2 = Ros2Out(bus, ros2, self.estimator.anchors) if ros2 is not None and ros2.enabled else None
        bus.declare_alive("estimator", "main")

    # ------------------------------------------------------------ state

    def _restore(self) -> int:
        path = self.config.state_file
        if path is None or not path.exists():
            return 0
        try:
            saved = load_state(path, self.bus.cell)
        except StateFileError as exc:
            where = set_aside(path)
            log.error("%s; moved to %s and starting from the anchors alone", exc, where)
            return 0
        self.estimator.seed_map({k: (v.T, v.covariance) for k, v in saved.items()})
        log.info("restored %d markers from %s", len(saved), path)
        return len(saved)

    def save(self, est: Estimate) -> None:
        path = self.config.state_file
        if path is None:
            return
        markers = {k: SavedMarker(p.T, p.covariance) for k, p in est.markers.items() if p.covariance is not None}
        try:
            save_state(path, markers, self.bus.cell)
        except OSError as exc:  # a full disk must not stop the estimator; the old file stays intact
            if not self.save_failures:
                log.error(
                    "cannot save state to %s: %s (previous state kept; retrying every %.0f s)", path, exc, SAVE_PERIOD_S
                )
            self.save_failures += 1
            return
        if self.save_failures:
            log.warning("state saved to %s again after %d failed attempts", path, self.save_failures)
            self.save_failures = 0

    # ------------------------------------------------------------ loop

    def ingest(self, items: list[Received[m.MarkerObservations]]) -> None:
        """One update's frames: validated together in one numpy pass, then each camera's as one block
        (``Estimator.add_frames``: a still camera's frames fold in with numpy, the same as one by
        one). Cameras are independent between updates."""
        cams, receive, msgs, keys_ = [], [], [], []
        for item in items:
            try:  # before the id keys any per-camera state
                codec.check_id(item.msg.camera_id, "marker observations camera_id")
            except DecodeError as exc:
                self.bad_frames["(invalid camera id)"] += 1
                self.rejected[item.key, exc.reason] += 1
                continue
            cams.append(item.msg.camera_id)
            receive.append(item.receive_ns)
            msgs.append(item.msg)
            keys_.append(item.key)
        if not msgs:
            return
        v = validated_rows(msgs, self.bus.limits)
        for i, why, reason in v.dropped:
            camera_id = cams[i]
            self.bad_frames[camera_id] += 1
            self.rejected[keys_[i], reason] += 1
            if self.bad_frames[camera_id] == 1:  # once per camera: garbage must not flood the log
                log.warning(
                    "dropping malformed marker observations of %r at %d ns: %s (further ones are only counted)",
                    camera_id[:40],
                    msgs[i].stamp_ns,
                    why,
                )
        if v.rows is None:
            return
        # Only frames that passed reach the clocks: a dropped frame's stamp is as untrusted as the rest
        # of it (garbage stamped in the past read as a sensor clock stepping back, and shifted its frames).
        stamps = {}
        for i in v.kept:
            stamps[i] = self.clock_jumps.correct(cams[i], msgs[i].stamp_ns, receive[i])
            self.clock.observe(stamps[i], receive[i])
        owner = np.array([cams[i] for i in v.kept])
        for camera_id in dict.fromkeys(owner.tolist()):
            mine = np.flatnonzero(owner == camera_id)  # positions among the kept frames, in arrival order
            self.estimator.add_frames(
                camera_id, np.array([stamps[v.kept[j]] for j in mine], dtype=np.int64), v.rows.of_frames(mine)
            )

    def step(self) -> Estimate:
        """Ingest what arrived, update, publish. One call per update period."""
        self.ingest(self._sub.drain())
        now = self.clock.now()
        self.estimator.update(now)
        est = self.estimator.estimate(now)
        self.publish(est, now)
        if time.monotonic() - self._last_save > SAVE_PERIOD_S:
            self.save(est)
            self._last_save = time.monotonic()
        return est

    def publish(self, est: Estimate, stamp_ns: int) -> None:
        """Camera poses (``estimate/cameras`` and their ``tf``) after every update; the map (markers,
        their ``tf``, status, the ``estimate/map`` answer) at most ``update_hz``: it changes slowly,
        and publishing it with every frame-triggered update cost as much CPU as the update itself."""
        now = time.monotonic()
        with_map = now - self._last_map >= 1.0 / self.config.update_hz
        # Each camera's pose carries the stamp of its newest frame in the estimate: how old it is.
        cams = [
            codec.StampedPose("world", c.camera_id, c.last_stamp_ns, c.pose.T, c.pose.covariance)
            for c in est.cameras.values()
            if c.pose is not None and c.state in (CameraState.LOCALIZED, CameraState.MOVING, CameraState.STALE)
        ]
        marks = []
        if with_map:
            marks = [
                codec.StampedPose("world", keys.marker_frame(k), stamp_ns, p.T, p.covariance)
                for k, p in est.markers.items()
            ]
            marks += [
                codec.StampedPose("world", keys.marker_frame(k), stamp_ns, p.T, p.covariance)
                for k, p in est.object_markers.items()
            ]
        cams_msg = codec.poses_to_msg(stamp_ns, cams)
        self._pub["tf"].put(codec.transforms_to_msg(stamp_ns, [(p.parent, p.child, p.T) for p in cams + marks]))
        self._pub["cameras"].put(cams_msg)
        if self.ros2 is not None:
            self.ros2.publish(cams, marks, stamp_ns)
        if with_map:
            marks_msg, status = codec.poses_to_msg(stamp_ns, marks), self.status_msg(est, stamp_ns)
            self._pub["markers"].put(marks_msg)
            self._pub["status"].put(status)
            self._last_map = now
            with self._lock:
                self._map = m.Map(cameras=cams_msg, markers=marks_msg, status=status)

    def status_msg(self, est: Estimate, stamp_ns: int) -> m.EstimatorStatus:
        c = self.estimator.counters
        msg = m.EstimatorStatus(
            stamp_ns=stamp_ns,
            observations=c.observations,
            rejected=c.rejected + sum(self._sub.bad.values()) + sum(self.bad_frames.values()),
            unknown_markers=c.unknown_markers,
            update_ms=c.last_update_ms,
            factors=self.estimator.factor_count(),
            factors_rebuilt=c.factors_rebuilt,
            update_cpu_ms=c.last_update_cpu_ms,
        )
        msg.flagged_anchors.extend(est.flagged_anchors)
        for (key, reason), count in sorted((self._sub.rejected + self.rejected).items()):
            msg.rejections.add(key=key, reason=reason, count=count)
        for cam in sorted(est.cameras.values(), key=lambda x: x.camera_id):
            sigma = 0.0
            if cam.pose is not None and cam.pose.covariance is not None:
                sigma = float(np.sqrt(np.linalg.eigvalsh(cam.pose.covariance[:3, :3]).max()))
            msg.cameras.add(
                camera_id=cam.camera_id,
                state=_STATE[cam.state],
                segment=cam.segment,
                last_stamp_ns=cam.last_stamp_ns,
                markers_seen=cam.markers_seen,
                position_sigma_m=sigma,
            )
        return msg

    def _answer_map(self, query: zenoh.Query) -> None:
        with self._lock:
            snapshot = self._map
        if snapshot is not None:
            query.reply(keys.estimate_map(self.bus.cell), snapshot.SerializeToString())

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        """Update when frames arrive (at most ``max_update_hz``; frames that arrive meanwhile are
        coalesced into the next update, never queued behind it), and ``update_hz`` when none do."""
        stop = stop or threading.Event()
        idle, gap = 1.0 / self.config.update_hz, 1.0 / max(self.config.max_update_hz, self.config.update_hz)
        start = time.monotonic()
        est = None
        try:
            while not stop.is_set() and (duration_s is None or time.monotonic() - start < duration_s):
                t0 = time.monotonic()
                est = self.step()
                stop.wait(max(gap - (time.monotonic() - t0), 0.0))
                self._sub.inbox.wait(max(idle - (time.monotonic() - t0), 0.0))
        finally:
            if est is not None:
                self.save(est)
            self._queryable.undeclare()
            if self.ros2 is not None:
                self.ros2.close()
