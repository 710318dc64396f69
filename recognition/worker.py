"""The recognition worker: depth frames and camera poses in, object poses in world coordinates out.

Owns the zenoh side: a camera's depth and colour, subscribed only while a frame of it is due (a
driver builds images only for a subscriber, and the worker uses about one of each camera's 30 a
second; a depth frame waits up to ``COLOUR_WAIT_S`` for the colour of the same stamp),
intrinsics, ``tf`` and camera states from the estimator, object-marker observations for priors;
publishes ``objects``, ``objects/scene`` and the fused cloud on ``points``. Recognition itself is
``recognition.pipeline.Recognizer``; fusion across cameras is ``fuse``, ``cross_checked`` holds
back a fused object another camera's frame saw through, and ``refined_in_cloud`` fits each fused
object to every camera's points around it. A camera is used once the estimator has
localized it (detections are only useful in world frame), and its detections are dropped while the
estimator says it is moving or unanchored.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import open3d as o3d

from recognition.align import facing_camera, icp_pass
from recognition.config import RecognitionConfig
from recognition.models import ModelDatabase
from recognition.pipeline import Detection, Prior, Recognizer
from recognition.cloud import depth_to_cloud, finite_points, voxel_downsample
from recognition.verify import DepthView, Verdict
from schemas import codec, keys
from schemas import geometry
from schemas import messages as m
from schemas.bus import Bus, Subscription
from schemas.errors import DecodeError, KeyError_
from schemas.rmw_zenoh import NodeName, Ros2Node
from schemas.ros2 import CLOUD, DETECTIONS, Ros2Config, ros2_types

log = logging.getLogger(__name__)
#: Marker observations this close in time to a depth frame (ns) count as seen with it.
PRIOR_WINDOW_NS = 100_000_000
#: Detections from cameras further apart than this are not the same object (m).
SAME_OBJECT_M = 0.05
#: Estimator camera states in which a camera's world pose is not to be trusted.
UNUSABLE_STATES = (m.CameraState.MOVING, m.CameraState.UNANCHORED)
#: A camera pose that moved this far since a detection means the camera was moved: the detection is
#: dropped rather than carried over (m, deg). Estimator refinements are millimetres.
MOVED_M, MOVED_DEG = 0.05, 3.0
#: Voxel of the cameras' points fused objects are refined in (m): recognition's own 1 cm leaves an
#: object's side near the table with fewer points than the table, which then pulls the object into it.
REFINE_VOXEL_M = 0.005
#: Neighbours (at most) a point's normal is fitted to in that refinement.
NORMAL_NEIGHBOURS = 30
#: Between refinements (``RecognitionConfig.refine_period_s``) an object keeps its last refined pose
#: while its fused pose stays within this of the one refined (m, deg).
REFINED_HOLD_M, REFINED_HOLD_DEG = 0.005, 2.0
#: A fused object's refinement in the cameras' points (``refined_in_cloud``) that moves it further than
#: this (m), or tilts it by more than this (deg: turns the world's up in the object's frame; a turn
#: about the up, as an object on a table takes, is free) slid off: the fused pose stands.
REFINE_MAX_SHIFT_M, REFINE_MAX_TILT_DEG = 0.02, 3.0
#: How long a depth frame waits for the colour frame of its stamp before it is recognised without
#: colour (s): a driver sends both within milliseconds; one without colour sends none.
COLOUR_WAIT_S = 0.2
#: Colours of the cameras' points in the fused cloud (RGBA), in camera-id order.
CLOUD_COLOURS = np.array([[31, 119, 180, 255], [255, 127, 14, 255], [44, 160, 44, 255], [214, 39, 40, 255],
                          [148, 103, 189, 255], [140, 86, 75, 255], [227, 119, 194, 255], [188, 189, 34, 255]], np.uint8)


@dataclass(frozen=True)
class WorldDetection:
    """One camera's detection in world frame. stamp_ns: the depth frame's time (ns); world_T_camera:
    the camera's estimated pose it was put in world with."""

    camera_id: str
    stamp_ns: int
    world_T_object: np.ndarray
    detection: Detection
    world_T_camera: np.ndarray

    @property
    def score(self) -> float:
        d = self.detection
        return d.fitness * d.coverage / max(d.rmse_m, 1e-4) ** 2


@dataclass(frozen=True)
class FusedObject:
    """An object as reported: world_T_object (4, 4), the cameras that agree on it, best fitness and RMSE."""

    object_id: str
    stamp_ns: int
    world_T_object: np.ndarray
    camera_ids: list[str]
    fitness: float
    rmse_m: float


def fuse(detections: list[WorldDetection]) -> list[FusedObject]:
    """One pose per object from the cameras' latest detections.

    The best-scored detection (fitness x coverage / RMSE^2) sets the rotation: symmetric shapes give
    equally valid rotations that must not be averaged. Positions of the detections within 5 cm of it
    are averaged with the same weights; detections further away are outvoted, not blended in.
    """
    by_object: dict[str, list[WorldDetection]] = {}
    for d in detections:
        by_object.setdefault(d.detection.object_id, []).append(d)
    out = []
    for oid, group in sorted(by_object.items()):
        best = max(group, key=lambda d: d.score)
        agree = [d for d in group if np.linalg.norm(d.world_T_object[:3, 3] - best.world_T_object[:3, 3]) <= SAME_OBJECT_M]
        w = np.array([d.score for d in agree])
        T = best.world_T_object.copy()
        T[:3, 3] = np.average([d.world_T_object[:3, 3] for d in agree], axis=0, weights=w)
        out.append(FusedObject(oid, max(d.stamp_ns for d in agree), T, sorted(d.camera_id for d in agree),
                               best.detection.fitness, best.detection.rmse_m))
    return out


@dataclass(frozen=True)
class CameraView:
    """One camera's last recognised frame, judge of the other cameras' detections: its depth view,
    the frame's stamp (ns) and the world pose (4, 4) it was taken from."""

    camera_id: str
    stamp_ns: int
    view: DepthView
    world_T_camera: np.ndarray


@dataclass(frozen=True)
class Contradiction:
    """A fused object held back: ``camera_id``'s frame saw through where ``detected_by`` put it."""

    object_id: str
    detected_by: list[str]
    camera_id: str
    verdict: Verdict


#: judge(view, object_id, camera_T_object): the verdict when that view contradicts the object there, else None.
Judge = Callable[[DepthView, str, np.ndarray], Verdict | None]


def cross_checked(detections: list[WorldDetection], views: list[CameraView], judge: Judge,
                  max_age_ns: int) -> tuple[list[FusedObject], list[Contradiction]]:  # fmt: skip
    """The fused objects (``fuse``) that no other camera's frame contradicts, and those held back.

    A fused object is judged by the view of every camera not among those that agree on it, taken
    within ``max_age_ns`` of it: one camera may fit an object to a surface that another, looking
    from elsewhere, sees lying behind where the object would be. A contradicted object's detections
    are dropped and the rest fused again, so that a camera outvoted by a wrong pose is heard.
    """
    left, held = list(detections), []
    while True:
        objects = fuse(left)
        wrong: set[tuple[str, str]] = set()
        for o in objects:
            for cv in views:
                if cv.camera_id in o.camera_ids or abs(cv.stamp_ns - o.stamp_ns) > max_age_ns:
                    continue
                v = judge(cv.view, o.object_id, geometry.invert_pose(cv.world_T_camera) @ o.world_T_object)
                if v is not None:
                    held.append(Contradiction(o.object_id, o.camera_ids, cv.camera_id, v))
                    wrong |= {(c, o.object_id) for c in o.camera_ids}
                    break
        if not wrong:
            return objects, held
        left = [d for d in left if (d.camera_id, d.detection.object_id) not in wrong]


@dataclass(frozen=True)
class CameraPoints:
    """One camera's last recognised frame: its points in the workspace, one per ``REFINE_VOXEL_M``
    voxel, (N, 3), camera frame, and the world pose (4, 4) it was taken from."""

    camera_id: str
    stamp_ns: int
    points: np.ndarray
    world_T_camera: np.ndarray


def refined_in_cloud(objects: list[FusedObject], cameras: list[CameraPoints], models: ModelDatabase, distance_m: float,
                     normal_radius_m: float, min_fitness: float) -> list[FusedObject]:  # fmt: skip
    """Each fused object fitted (point-to-plane ICP at distance_m, m) to every camera's points around
    it, in world frame: what one camera sees of it, the others complete, so the pose is held on all
    its sides at once instead of averaged from views that each see one or two, and on the support
    it stands on (its side alone would leave it free to slide along itself). The model points facing
    at least one of the cameras take part; the points' normals are estimated within
    normal_radius_m (m). A fit under min_fitness, or one that slid or tilted more than
    ``REFINE_MAX_SHIFT_M`` / ``REFINE_MAX_TILT_DEG``, leaves the fused pose as it was. World z is up."""
    if not cameras or not objects:
        return objects
    pts = np.concatenate([c.points @ c.world_T_camera[:3, :3].T + c.world_T_camera[:3, 3] for c in cameras])
    out = []
    for o in objects:
        model = models.models[o.object_id]
        # Only the points around it (the fit builds its own search tree of the whole target): within
        # its half diameter of its centre (an object frame's origin may be at its base).
        centre = o.world_T_object[:3, :3] @ model.points.mean(axis=0) + o.world_T_object[:3, 3]
        near = pts[np.linalg.norm(pts - centre, axis=1) <= model.diameter_m / 2 + 2 * distance_m]
        if len(near) < 3:
            log.debug("%s: kept its fused pose, no camera's points around it", o.object_id)
            out.append(o)
            continue
        facing = np.zeros(len(model.points), bool)
        for c in cameras:
            facing |= facing_camera(model.points, model.normals, geometry.invert_pose(c.world_T_camera) @ o.world_T_object)[0]
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(near.astype(np.float64)))
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=NORMAL_NEIGHBOURS))
        fit = icp_pass(model.points[facing], target, o.world_T_object, distance_m, max_shift_m=REFINE_MAX_SHIFT_M)
        up_before, up_after = o.world_T_object[2, :3], fit.camera_T_object[2, :3]  # world up in the object's frame
        tilt = np.degrees(np.arccos(np.clip(up_before @ up_after, -1.0, 1.0)))
        if fit.fitness < min_fitness or tilt > REFINE_MAX_TILT_DEG:
            log.debug("%s: kept its fused pose, the fit in the cameras' points scored %.2f and tilted it %.1f deg",
                      o.object_id, fit.fitness, tilt)  # fmt: skip
            out.append(o)
            continue
        out.append(replace(o, world_T_object=fit.camera_T_object))
    return out


def fused_cloud(clouds: dict[str, np.ndarray], world_T_camera: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The cameras' points (camera frame, (N, 3) each) in world frame as one cloud: xyz (M, 3)
    float32 and a colour per camera, rgba (M, 4) uint8.

    Where the cameras' clouds of the same surface separate, their poses disagree: the view shows
    the calibration's quality at a glance.
    """
    xyz, rgba = [], []
    for i, cam in enumerate(sorted(c for c in clouds if c in world_T_camera)):
        T = world_T_camera[cam]
        xyz.append(clouds[cam] @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32))
        rgba.append(np.broadcast_to(CLOUD_COLOURS[i % len(CLOUD_COLOURS)], (len(clouds[cam]), 4)))
    if not xyz:
        return np.zeros((0, 3), np.float32), np.zeros((0, 4), np.uint8)
    return np.concatenate(xyz), np.concatenate(rgba)


def display_cloud(cloud: np.ndarray, f_px: float, voxel_m: float, max_range_m: float) -> np.ndarray:
    """One camera's share of the fused world cloud: the finite points of its organised cloud (H, W, 3),
    camera frame, within max_range_m, one per voxel_m voxel, (N, 3) float32.

    Pixels are taken on a grid with at most half a voxel between samples at max_range_m (a pixel
    spans max_range_m / f_px there; f_px the focal length, px). What the grid loses are voxels only
    a few noisy returns reach: every voxel point of the full cloud but ~2 % lies within a voxel of
    one it keeps, at a third of the time (a 640x480 demo frame: 42 -> 13 ms)."""
    step = max(1, int(0.5 * voxel_m * f_px / max_range_m))
    pts = finite_points(cloud[::step, ::step])
    pts = pts[pts[:, 2] <= max_range_m]
    return voxel_downsample(pts, voxel_m) if len(pts) else pts


def _still_at(then: np.ndarray, now: np.ndarray) -> bool:
    """Whether a camera's world pose ``now`` (4, 4) is within ``MOVED_M`` / ``MOVED_DEG`` of ``then``:
    refined by the estimator, not moved."""
    return _within(then, now, MOVED_M, MOVED_DEG)


def _within(a: np.ndarray, b: np.ndarray, metres: float, degrees: float) -> bool:
    """Whether poses a and b (4, 4) are within ``metres`` and ``degrees`` of each other."""
    step = geometry.invert_pose(a) @ b
    return bool(np.linalg.norm(step[:3, 3]) <= metres and np.degrees(geometry.rotation_angle(np.eye(3), step[:3, :3])) <= degrees)


def detections_to_msg(stamp_ns: int, objects: list[FusedObject]) -> m.ObjectDetections:
    msg = m.ObjectDetections(stamp_ns=stamp_ns)
    for o in objects:
        item = msg.objects.add(object_id=o.object_id, fitness=o.fitness, rmse_m=o.rmse_m, stamp_ns=o.stamp_ns)
        item.camera_ids.extend(o.camera_ids)
        codec.pose_to_msg(o.world_T_object, item.world_T_object)
    return msg


def scene_to_msg(stamp_ns: int, objects: list[FusedObject], boxes: dict[str, tuple[np.ndarray, np.ndarray]]) -> m.SceneUpdate:
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

    def __init__(self, bus: Bus, config: RecognitionConfig, database: ModelDatabase, ros2: Ros2Config | None = None) -> None:
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
        self._object_T_marker = {mk.marker_id: (mk.object_id, mk.object_T_marker.matrix()) for mk in config.object_markers}
        self.intrinsics: dict[str, codec.CameraInfo] = {}
        self.world_T_camera: dict[str, np.ndarray] = {}
        self.camera_state: dict[str, int] = {}  # the estimator's latest CameraState.State per camera
        self.frames: dict[str, m.RawImage] = {}
        self.colours: dict[str, m.RawImage] = {}  # camera -> its newest colour frame, while one is due
        self._frame_since: dict[str, float] = {}  # camera -> when its first due depth frame arrived (monotonic s)
        self.marker_msgs: dict[str, m.MarkerObservations] = {}
        self.latest: dict[tuple[str, str], WorldDetection] = {}  # (camera, object) -> newest detection
        self.views: dict[str, CameraView] = {}  # camera -> its last recognised frame, judge of the others'
        self.scenes: dict[str, CameraPoints] = {}  # camera -> its last recognised frame's points, to refine in
        self.refined: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # object -> (fused pose, its refinement), last refined
        self._refined_at = -np.inf  # monotonic s of the last refinement
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
                    self._colour[c] = self.bus.subscribe(keys.color(self.bus.cell, c), m.RawImage, capacity=1, ring=True)

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
        ready = [c for c in self.frames if self.placed(c) and (
            c not in self._colour or self._colour_of(c) is not None or now - self._frame_since.get(c, now) >= COLOUR_WAIT_S)]  # fmt: skip
        return min(ready, key=lambda c: self.last_run.get(c, -np.inf)) if ready else None

    def _colour_of(self, camera_id: str) -> m.RawImage | None:
        """The colour frame of the waiting depth frame's stamp, if it came."""
        colour, depth = self.colours.get(camera_id), self.frames.get(camera_id)
        if colour is None or depth is None or codec.timestamp_to_stamp(colour.timestamp) != codec.timestamp_to_stamp(depth.timestamp):
            return None
        return colour

    def _rgb(self, camera_id: str, msg: m.RawImage | None, shape: tuple[int, int]) -> np.ndarray | None:
        """A colour frame as (H, W, 3) rgb8 of the depth's size (H, W), or None (none came, or it is
        unusable: said once, and the frame is recognised on depth alone)."""
        if msg is None:
            return None
        try:
            if msg.encoding not in ("rgb8", "bgr8"):
                raise DecodeError(f"colour encoding {msg.encoding!r}, expected rgb8 or bgr8")
            rgb = codec.image_from_msg(msg)
            if rgb.shape[:2] != shape:
                raise DecodeError(f"colour is {rgb.shape[1]}x{rgb.shape[0]}, depth {shape[1]}x{shape[0]} (not registered to it)")
        except DecodeError as exc:
            self._warn_once(f"colour/{camera_id}", f"{camera_id}: recognising on depth alone: {exc}")
            return None
        return rgb[..., ::-1] if msg.encoding == "bgr8" else rgb

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
            raise DecodeError(f"{camera_id}: depth is {depth.shape[1]}x{depth.shape[0]} but camera_info says "
                              f"{info.width}x{info.height}")
        rgb = self._rgb(camera_id, colour, depth.shape)
        world_T_camera = self.world_T_camera[camera_id]
        cloud = depth_to_cloud(depth, info.K, depth_scale=0.001)
        if self.config.cloud_voxel_m > 0:
            self.clouds[camera_id] = display_cloud(cloud, info.K[0, 0], self.config.cloud_voxel_m, self.config.max_range_m)
        # Kept to judge the other cameras' detections; without that check, the recogniser builds
        # one only for a frame with a hypothesis to verify.
        view = DepthView.of(cloud, rgb) if self.config.min_cross_view_fitness > 0 else None
        if view is not None:
            self.views[camera_id] = CameraView(camera_id, stamp_ns, view, world_T_camera)
        if self.config.refine_in_cloud:
            near = voxel_downsample(self.recognizer.workspace_points(cloud, world_T_camera), REFINE_VOXEL_M)
            self.scenes[camera_id] = CameraPoints(camera_id, stamp_ns, near, world_T_camera)
        found = self.recognizer.recognize(cloud, self.priors(camera_id, stamp_ns), world_T_camera, view, rgb)
        for key in [k for k in self.latest if k[0] == camera_id]:
            del self.latest[key]  # what this camera no longer sees is no longer reported by it
        out = [WorldDetection(camera_id, stamp_ns, world_T_camera @ d.camera_T_object, d, world_T_camera) for d in found]
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
        """The cameras' current detections fused, less what another camera's frame contradicts,
        each fitted to the cameras' points around it (``refined_in_cloud``)."""
        c = self.config
        if c.min_cross_view_fitness <= 0:
            objects = fuse(self.current_detections())
        else:
            views = [v for v in self.views.values() if self.placed(v.camera_id) and _still_at(v.world_T_camera, self.world_T_camera[v.camera_id])]
            objects, held = cross_checked(self.current_detections(), views, self.recognizer.seen_through, int(c.cross_view_max_age_s * 1e9))
            for h in held:  # what a robot is not told, and why
                log.debug("%s from %s held back: %s saw through it (%d of %d judged pixels on its surface)", h.object_id,
                          ", ".join(h.detected_by), h.camera_id, h.verdict.inliers, h.verdict.inliers + h.verdict.violations)  # fmt: skip
            self.held_back += len(held)
        if not c.refine_in_cloud or not objects:
            return objects
        now = time.monotonic()
        if now - self._refined_at < c.refine_period_s:  # hold the last refinement of what stayed put
            return [replace(o, world_T_object=self.refined[o.object_id][1]) if o.object_id in self.refined
                    and _within(self.refined[o.object_id][0], o.world_T_object, REFINED_HOLD_M, REFINED_HOLD_DEG) else o
                    for o in objects]  # fmt: skip
        self._refined_at = now
        newest = max(o.stamp_ns for o in objects)
        cameras = [replace(p, world_T_camera=self.world_T_camera[p.camera_id]) for p in self.scenes.values()
                   if self.placed(p.camera_id) and _still_at(p.world_T_camera, self.world_T_camera[p.camera_id])
                   and newest - p.stamp_ns <= c.cross_view_max_age_s * 1e9]  # fmt: skip
        refined = refined_in_cloud(objects, cameras, self.db, c.icp_distance_m, c.descriptor.normal_radius_m, c.min_fitness)
        self.refined = {o.object_id: (o.world_T_object, r.world_T_object) for o, r in zip(objects, refined)}
        return refined

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
