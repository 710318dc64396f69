"""The recognition worker: depth frames and camera poses in, object poses in world coordinates out.

Owns the zenoh side: a camera's depth and colour, subscribed only while a frame of it is due (a
driver builds images only for a subscriber, and the worker uses about one of each camera's 30 a
second; a depth frame waits up to ``COLOUR_WAIT_S`` for the colour of the same stamp),
intrinsics, ``tf`` and camera states from the estimator, object-marker observations for priors;
publishes ``objects``, ``objects/scene`` and the fused cloud on ``points``. Recognition itself is
``recognition.pipeline.Recognizer``; what several cameras make of it (fused, cross-checked and
fitted in every camera's points) is ``recognition.fusion``. A camera is used once the estimator has
localized it (detections are only useful in world frame), and its detections are dropped while the
estimator says it is moving or unanchored.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import replace

import numpy as np

from recognition.cloud import depth_to_cloud, voxel_downsample
from recognition.config import RecognitionConfig
from recognition.fusion import (
    REFINE_VOXEL_M,
    CameraPoints,
    CameraView,
    FusedObject,
    WorldDetection,
    cross_checked,
    display_cloud,
    found_in_cloud,
    fuse,
    fused_cloud,
    refined_in_cloud,
)
from recognition.models import ModelDatabase
from recognition.pipeline import Prior, Recognizer
from recognition.verify import DepthView
from schemas import codec, geometry, keys
from schemas import messages as m
from schemas.bus import Bus, Subscription
from schemas.errors import DecodeError, KeyError_
from schemas.rmw_zenoh import NodeName, Ros2Node
from schemas.ros2 import CLOUD, DETECTIONS, Ros2Config, ros2_types

log = logging.getLogger(__name__)
#: Marker observations this close in time to a depth frame (ns) count as seen with it.
PRIOR_WINDOW_NS = 100_000_000
#: Estimator camera states in which a camera's world pose is not to be trusted.
UNUSABLE_STATES = (m.CameraState.MOVING, m.CameraState.UNANCHORED)
#: A camera pose that moved this far since a detection means the camera was moved: the detection is
#: dropped rather than carried over (m, deg). Estimator refinements are millimetres.
MOVED_M, MOVED_DEG = 0.05, 3.0
#: Between refinements (``RecognitionConfig.refine_period_s``) an object keeps its last refined pose
#: while its fused pose stays within this of the one refined (m, deg).
REFINED_HOLD_M, REFINED_HOLD_DEG = 0.005, 2.0
#: How long a depth frame waits for the colour frame of its stamp before it is recognised without
#: colour (s): a driver sends both within milliseconds; one without colour sends none.
COLOUR_WAIT_S = 0.2


def _still_at(then: np.ndarray, now: np.ndarray) -> bool:
    """Whether a camera's world pose ``now`` (4, 4) is within ``MOVED_M`` / ``MOVED_DEG`` of ``then``:
    refined by the estimator, not moved."""
    return _within(then, now, MOVED_M, MOVED_DEG)


def _within(a: np.ndarray, b: np.ndarray, metres: float, degrees: float) -> bool:
    """Whether poses a and b (4, 4) are within ``metres`` and ``degrees`` of each other."""
    step = geometry.invert_pose(a) @ b
    return bool(
        np.linalg.norm(step[:3, 3]) <= metres
        and np.degrees(geometry.rotation_angle(np.eye(3), step[:3, :3])) <= degrees
    )


def detections_to_msg(stamp_ns: int, objects: list[FusedObject]) -> m.ObjectDetections:
    msg = m.ObjectDetections(stamp_ns=stamp_ns)
    for o in objects:
        item = msg.objects.add(object_id=o.object_id, fitness=o.fitness, rmse_m=o.rmse_m, stamp_ns=o.stamp_ns)
        item.camera_ids.extend(o.camera_ids)
        codec.pose_to_msg(o.world_T_object, item.world_T_object)
    return msg


def scene_to_msg(
    stamp_ns: int, objects: list[FusedObject], boxes: dict[str, tuple[np.ndarray, np.ndarray]]
) -> m.SceneUpdate:
    """Foxglove 3-D scene: each object's model bounding box (``model_boxes``), posed in world, with its name."""
    msg = m.SceneUpdate()
    for o in objects:
        if o.object_id not in boxes:
            continue
        centre, size = boxes[o.object_id]
        ent = msg.entities.add(frame_id="world", id=keys.object_frame(o.object_id))
        codec.stamp_to_timestamp(stamp_ns, ent.timestamp)
        ent.lifetime.FromNanoseconds(2_000_000_000)
        cube = ent.cubes.add()
        box_T = o.world_T_object.copy()
        box_T[:3, 3] = o.world_T_object[:3, :3] @ centre + o.world_T_object[:3, 3]
        codec.foxglove_pose(box_T, cube.pose)
        cube.size.x, cube.size.y, cube.size.z = (float(v) for v in size)
        cube.color.r, cube.color.g, cube.color.b, cube.color.a = 0.2, 0.8, 0.3, 0.5
        text = ent.texts.add(text=o.object_id, billboard=True, font_size=14)
        codec.foxglove_pose(o.world_T_object, text.pose)
        text.color.r = text.color.g = text.color.b = text.color.a = 1.0
    return msg


def model_boxes(db: ModelDatabase) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Object id -> (bounding box centre in the object frame (3,), size (3,)) of each model, metres."""
    boxes = {}
    for object_id, model in db.models.items():
        lo, hi = model.points.min(axis=0), model.points.max(axis=0)
        boxes[object_id] = ((lo + hi) / 2, hi - lo)
    return boxes


class Ros2Objects:
    """The objects and the fused cloud on ROS 2's wire (rmw_zenoh), as the node ``recognition_node``:
    ``/cellsight/objects`` (vision_msgs/Detection3DArray) and ``/cellsight/points`` (PointCloud2)."""

    def __init__(self, bus: Bus, config: Ros2Config, boxes: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        self.types = ros2_types(config.distro)
        self.node = Ros2Node(bus.session, NodeName(config.domain_id, config.recognition_node), self.types)
        self.objects = self.node.publisher("/cellsight/objects", DETECTIONS)
        self.points = self.node.publisher("/cellsight/points", CLOUD)
        self.boxes = boxes

    def publish(self, objects: m.ObjectDetections, cloud: tuple[np.ndarray, np.ndarray] | None) -> None:
        """The fused objects, and the world cloud (xyz, rgba; ``fused_cloud``) if there is one."""
        self.objects.put(self.types.detections(objects, self.boxes), objects.stamp_ns)
        if cloud is not None:
            self.points.put(self.types.point_cloud(objects.stamp_ns, "world", *cloud), objects.stamp_ns)

    def close(self) -> None:
        self.node.close()


class RecognitionWorker:
    """Runs the recogniser on each localized camera in turn, at most ``rate_hz`` per camera."""

    def __init__(
        self, bus: Bus, config: RecognitionConfig, database: ModelDatabase, ros2: Ros2Config | None = None
    ) -> None:
        self.bus = bus
        self.config = config
        self.db = database
        self.recognizer = Recognizer(database, config)
        self.boxes = model_boxes(database)
        cell = bus.cell
        self._depth: dict[str, Subscription[m.RawImage]] = {}  # camera -> its depth, while a frame of it is due
        self._colour: dict[str, Subscription[m.RawImage]] = {}  # ... and its colour, when verification judges colour
        self._info = bus.subscribe(keys.all_cameras(cell, "camera_info"), m.CameraCalibration, capacity=64, ring=True)
        self._tf = bus.subscribe(keys.tf(cell), m.FrameTransforms, capacity=16, ring=True)
        self._markers = bus.subscribe(keys.all_cameras(cell, "markers"), m.MarkerObservations, capacity=256, ring=True)
        self._status = bus.subscribe(keys.estimate_status(cell), m.EstimatorStatus, capacity=4, ring=True)
        self._pub = bus.publisher(keys.objects(cell))
        self._pub_scene = bus.publisher(keys.objects_scene(cell))
        self._pub_points = bus.publisher(keys.points(cell))
        bus.declare_alive("recognition", "main")
        self.ros2 = Ros2Objects(bus, ros2, self.boxes) if ros2 is not None and ros2.enabled else None
        self._object_T_marker = {
            mk.marker_id: (mk.object_id, mk.object_T_marker.matrix()) for mk in config.object_markers
        }
        self.intrinsics: dict[str, codec.CameraInfo] = {}
        self.world_T_camera: dict[str, np.ndarray] = {}
        self.camera_state: dict[str, int] = {}  # the estimator's latest CameraState.State per camera
        self.frames: dict[str, m.RawImage] = {}
        self.colours: dict[str, m.RawImage] = {}  # camera -> its newest colour frame, while one is due
        self._frame_since: dict[str, float] = {}  # camera -> when its first due depth frame arrived (monotonic s)
        self.marker_msgs: dict[str, m.MarkerObservations] = {}
        self.latest: dict[tuple[str, str], WorldDetection] = {}  # (camera, object) -> newest detection
        self.views: dict[str, CameraView] = {}  # camera -> its last recognised frame, judge of the others'
        self._last_cloud: dict[
            str, tuple[int, np.ndarray, np.ndarray]
        ] = {}  # camera -> (stamp, cloud, pose) last recognised
        self.scenes: dict[
            str, CameraPoints
        ] = {}  # camera -> that frame's workspace points, made when a fit or search needs them
        self.refined: dict[
            str, tuple[np.ndarray, np.ndarray]
        ] = {}  # object -> (fused pose, its refinement), last refined
        self._refined_at = -np.inf  # monotonic s of the last refinement
        self._searched_at = -np.inf  # monotonic s of the last search of the cameras' points together
        self._search_turn = 0  # whose frame the next search is seen from
        self.from_cloud: list[FusedObject] = []  # what the last search found (held until the next)
        self.held_back = 0  # fused objects another camera's frame contradicted
        self.clouds: dict[str, np.ndarray] = {}  # camera -> its newest frame's points, voxel-thinned, camera frame
        self.last_run: dict[str, float] = {}
        self.errors = 0
        self._warned: set[str] = set()

    def _absorb(self) -> None:
        for item in self._info.drain():
            try:
                self.intrinsics[keys.parse(item.key).camera] = codec.CameraInfo.from_msg(item.msg)
            except (DecodeError, KeyError_) as exc:
                self._warn_once(item.key, f"unusable camera_info on {item.key}: {exc}")
        for item in self._tf.drain():
            for (parent, child), T in codec.transforms_from_msg(item.msg).items():
                if parent == "world":
                    self.world_T_camera[child] = T
        for item in self._status.drain():
            for cam in item.msg.cameras:
                self.camera_state[cam.camera_id] = cam.state
        for camera_id, sub in self._depth.items():
            for item in sub.drain():
                self.frames[camera_id] = item.msg
                self._frame_since.setdefault(camera_id, time.monotonic())
        for camera_id, sub in self._colour.items():
            for item in sub.drain():
                self.colours[camera_id] = item.msg
        for item in self._markers.drain():
            self.marker_msgs[item.msg.camera_id] = item.msg

    def _warn_once(self, what: str, message: str) -> None:
        if what not in self._warned:
            self._warned.add(what)
            log.warning(message)

    def placed(self, camera_id: str) -> bool:
        """The camera has a world pose and the estimator does not say it is moving or unanchored."""
        return camera_id in self.world_T_camera and self.camera_state.get(camera_id) not in UNUSABLE_STATES

    def _request_frames(self) -> None:
        """Subscribe to the depth of each placed camera whose next run is due, until that run takes
        a frame (``process``); drop the subscription of a camera no longer placed."""
        now = time.monotonic()
        for c in self.intrinsics:
            if not self.placed(c):
                if c not in self.world_T_camera:
                    self._warn_once(f"unlocalized/{c}", f"{c}: waiting for the estimator to localize it")
                if c in self._depth:
                    self._close_frames(c)
                    self.frames.pop(c, None)
            elif c not in self._depth and now - self.last_run.get(c, -np.inf) >= 1.0 / self.config.rate_hz:
                self._depth[c] = self.bus.subscribe(keys.depth(self.bus.cell, c), m.RawImage, capacity=1, ring=True)
                if self.config.verify and self.config.min_colour_agreement > 0:
                    self._colour[c] = self.bus.subscribe(
                        keys.color(self.bus.cell, c), m.RawImage, capacity=1, ring=True
                    )

    def _close_frames(self, camera_id: str) -> None:
        self._depth.pop(camera_id).close()
        self._frame_since.pop(camera_id, None)
        if camera_id in self._colour:
            self._colour.pop(camera_id).close()
        self.colours.pop(camera_id, None)

    def _next_camera(self) -> str | None:
        """The camera with a due frame (and its colour, or waited ``COLOUR_WAIT_S`` for it) whose last
        run is oldest."""
        now = time.monotonic()
        ready = [
            c
            for c in self.frames
            if self.placed(c)
            and (
                c not in self._colour
                or self._colour_of(c) is not None
                or now - self._frame_since.get(c, now) >= COLOUR_WAIT_S
            )
        ]
        return min(ready, key=lambda c: self.last_run.get(c, -np.inf)) if ready else None

    def _colour_of(self, camera_id: str) -> m.RawImage | None:
        """The colour frame of the waiting depth frame's stamp, if it came."""
        colour, depth = self.colours.get(camera_id), self.frames.get(camera_id)
        if (
            colour is None
            or depth is None
            or codec.timestamp_to_stamp(colour.timestamp) != codec.timestamp_to_stamp(depth.timestamp)
        ):
            return None
        return colour

    def _rgb(self, camera_id: str, msg: m.RawImage | None, shape: tuple[int, int]) -> np.ndarray | None:
        """A colour frame as (H, W, 3) rgb8 of the depth's size (H, W), or None (none came, or it is
        unusable: said once, and the frame is recognised on depth alone)."""
        if msg is None:
            return None
        try:
            rgb = codec.rgb_from_msg(msg)
            if rgb.shape[:2] != shape:
                raise DecodeError(
                    f"colour is {rgb.shape[1]}x{rgb.shape[0]}, depth {shape[1]}x{shape[0]} (not registered to it)"
                )
        except DecodeError as exc:
            self._warn_once(f"colour/{camera_id}", f"{camera_id}: recognising on depth alone: {exc}")
            return None
        return rgb

    def priors(self, camera_id: str, stamp_ns: int) -> list[Prior]:
        msg = self.marker_msgs.get(camera_id)
        if msg is None or abs(msg.stamp_ns - stamp_ns) > PRIOR_WINDOW_NS or not self._object_T_marker:
            return []
        a = codec.marker_arrays(msg, check=False)
        out = []
        for marker_id, camera_T_marker in zip(a.ids, a.poses):
            if int(marker_id) in self._object_T_marker:
                oid, object_T_marker = self._object_T_marker[int(marker_id)]
                out.append(Prior(oid, camera_T_marker @ geometry.invert_pose(object_T_marker)))
        return out

    def process(self, camera_id: str) -> list[WorldDetection]:
        """Recognise the newest frame of one camera; remember and return its world-frame detections."""
        colour = self._colour_of(camera_id)
        frame = self.frames.pop(camera_id)
        if camera_id in self._depth:  # the next frame is due a period from now
            self._close_frames(camera_id)
        self.last_run[camera_id] = time.monotonic()
        stamp_ns = codec.timestamp_to_stamp(frame.timestamp)
        if frame.encoding != "16UC1":
            raise DecodeError(f"{camera_id}: depth encoding {frame.encoding!r}, expected 16UC1 millimetres")
        depth = codec.image_from_msg(frame)
        info = self.intrinsics[camera_id]
        if depth.shape != (info.height, info.width):
            raise DecodeError(
                f"{camera_id}: depth is {depth.shape[1]}x{depth.shape[0]} but camera_info says "
                f"{info.width}x{info.height}"
            )
        rgb = self._rgb(camera_id, colour, depth.shape)
        world_T_camera = self.world_T_camera[camera_id]
        cloud = depth_to_cloud(depth, info.K, depth_scale=0.001)
        if self.config.cloud_voxel_m > 0:
            self.clouds[camera_id] = display_cloud(
                cloud, info.K[0, 0], self.config.cloud_voxel_m, self.config.max_range_m
            )
        # Kept to judge the other cameras' detections; without that check, the recogniser builds
        # one only for a frame with a hypothesis to verify.
        view = DepthView.of(cloud, rgb) if self.config.min_cross_view_fitness > 0 else None
        if view is not None:
            self.views[camera_id] = CameraView(camera_id, stamp_ns, view, world_T_camera)
        if self.config.refine_in_cloud or self.config.search_fused_cloud:
            self._last_cloud[camera_id] = (stamp_ns, cloud, world_T_camera)  # its points only when needed (~6 ms)
        found = self.recognizer.recognize(cloud, self.priors(camera_id, stamp_ns), world_T_camera, view, rgb)
        for key in [k for k in self.latest if k[0] == camera_id]:
            del self.latest[key]  # what this camera no longer sees is no longer reported by it
        out = [
            WorldDetection(camera_id, stamp_ns, world_T_camera @ d.camera_T_object, d, world_T_camera) for d in found
        ]
        for d in out:
            self.latest[(camera_id, d.detection.object_id)] = d
        return out

    def step(self) -> list[FusedObject] | None:
        """Absorb what arrived, recognise one camera if one is due, publish the fused objects."""
        self._absorb()
        self._request_frames()
        cam = self._next_camera()
        if cam is None:
            return None
        try:
            self.process(cam)
        except (DecodeError, ValueError) as exc:  # one bad frame never stops the worker
            self.errors += 1
            log.warning("%s: frame skipped: %s", cam, exc)
            return None
        objects = self.fused()
        stamp = max((o.stamp_ns for o in objects), default=0)
        detections = detections_to_msg(stamp, objects)
        cloud = fused_cloud(self.clouds, self.world_T_camera) if self.config.cloud_voxel_m > 0 else None
        self._pub.put(detections)
        self._pub_scene.put(scene_to_msg(stamp, objects, self.boxes))
        if cloud is not None:
            self._pub_points.put(codec.points_to_msg(stamp, "world", *cloud))
        if self.ros2 is not None:
            self.ros2.publish(detections, cloud)
        return objects

    def fused(self) -> list[FusedObject]:
        """The cameras' current detections fused, less what another camera's frame contradicts, with
        what no camera found looked for in all their points (``searched``), each fitted to the
        cameras' points around it (``refined_in_cloud``)."""
        c = self.config
        views = [
            v
            for v in self.views.values()
            if self.placed(v.camera_id) and _still_at(v.world_T_camera, self.world_T_camera[v.camera_id])
        ]
        if c.min_cross_view_fitness <= 0:
            objects = fuse(self.current_detections())
        else:
            objects, held = cross_checked(
                self.current_detections(), views, self.recognizer.seen_through, int(c.cross_view_max_age_s * 1e9)
            )
            for h in held:  # what a robot is not told, and why
                log.debug(
                    "%s from %s held back: %s saw through it (%d of %d judged pixels on its surface)",
                    h.object_id,
                    ", ".join(h.detected_by),
                    h.camera_id,
                    h.verdict.inliers,
                    h.verdict.inliers + h.verdict.violations,
                )
            self.held_back += len(held)
        if c.search_fused_cloud:
            objects = objects + self.searched(objects, views)
        if not c.refine_in_cloud or not objects:
            return objects
        now = time.monotonic()
        if now - self._refined_at < c.refine_period_s:  # hold the last refinement of what stayed put
            return [
                replace(o, world_T_object=self.refined[o.object_id][1])
                if o.object_id in self.refined
                and _within(self.refined[o.object_id][0], o.world_T_object, REFINED_HOLD_M, REFINED_HOLD_DEG)
                else o
                for o in objects
            ]
        self._refined_at = now
        cameras = self._cameras(max(o.stamp_ns for o in objects))
        refined = refined_in_cloud(
            objects, cameras, self.db, c.icp_distance_m, c.descriptor.normal_radius_m, c.min_fitness
        )
        self.refined = {o.object_id: (o.world_T_object, r.world_T_object) for o, r in zip(objects, refined)}
        return refined

    def _cameras(self, newest_ns: int) -> list[CameraPoints]:
        """The localized cameras' last recognised points, each with its newest pose, from frames within
        cross_view_max_age_s of newest_ns (ns) and taken where the camera still is."""
        for camera_id, (stamp_ns, cloud, world_T_camera) in self._last_cloud.items():
            if camera_id not in self.scenes or self.scenes[camera_id].stamp_ns != stamp_ns:
                near = voxel_downsample(self.recognizer.workspace_points(cloud, world_T_camera), REFINE_VOXEL_M)
                self.scenes[camera_id] = CameraPoints(camera_id, stamp_ns, near, world_T_camera)
        return [
            replace(p, world_T_camera=self.world_T_camera[p.camera_id])
            for p in self.scenes.values()
            if self.placed(p.camera_id)
            and _still_at(p.world_T_camera, self.world_T_camera[p.camera_id])
            and newest_ns - p.stamp_ns <= self.config.cross_view_max_age_s * 1e9
        ]

    def searched(self, objects: list[FusedObject], views: list[CameraView]) -> list[FusedObject]:
        """The objects no camera found (not in ``objects``), looked for in every camera's points
        together (``found_in_cloud``), seen from one camera a ``search_period_s`` in turn and
        cross-checked by the others; between searches, what the last one found and is still missing."""
        c = self.config
        missing = set(self.db.models) - {o.object_id for o in objects}
        if not missing or not views:
            return []
        now = time.monotonic()
        if now - self._searched_at < c.search_period_s:
            return [o for o in self.from_cloud if o.object_id in missing]
        self._searched_at = now
        judge = sorted(views, key=lambda v: v.camera_id)[self._search_turn % len(views)]
        self._search_turn += 1
        cameras = self._cameras(max(v.stamp_ns for v in views))
        found = found_in_cloud(
            missing,
            judge,
            cameras,
            lambda cloud, W, view: self.recognizer.recognize(cloud, world_T_camera=W, view=view),
        )
        self.from_cloud = cross_checked(found, views, self.recognizer.seen_through, int(c.cross_view_max_age_s * 1e9))[
            0
        ]
        for o in self.from_cloud:
            log.info(
                "%s found in %d cameras' points together, seen from %s", o.object_id, len(cameras), judge.camera_id
            )
        return self.from_cloud

    def current_detections(self) -> list[WorldDetection]:
        """The cameras' latest detections, put in world frame with each camera's newest pose.

        A camera's pose keeps improving after the frame was recognised (early on by centimetres);
        the object relative to the camera does not change, so it is carried over to the newest pose.
        A camera the estimator reports moving, or whose pose jumped, has its detections voided until
        its next frame.
        """
        out = []
        for d in self.latest.values():
            if not self.placed(d.camera_id):
                continue
            T = self.world_T_camera[d.camera_id]
            if _still_at(d.world_T_camera, T):
                out.append(replace(d, world_T_object=T @ d.detection.camera_T_object, world_T_camera=T))
        return out

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> None:
        stop = stop or threading.Event()
        start = time.monotonic()
        try:
            while not stop.is_set() and (duration_s is None or time.monotonic() - start < duration_s):
                if self.step() is None:
                    stop.wait(0.02)
        finally:
            if self.ros2 is not None:
                self.ros2.close()
