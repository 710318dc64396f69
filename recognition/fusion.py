"""Several cameras' detections and points -> the objects reported, as pure functions.

Each camera's detections are put in world frame by its pose (``WorldDetection``) and fused into one
pose per object (``fuse``); a fused object another camera's frame saw through is held back
(``cross_checked``); the rest are fitted to every camera's points around them (``refined_in_cloud``),
and what no camera found is looked for in all their points together (``found_in_cloud``).
``fused_cloud`` is the cameras' points in one world cloud for viewing. ``recognition.worker`` owns
the zenoh side and calls these.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import open3d as o3d

from recognition.align import Surface, facing_camera, icp_pass
from recognition.cloud import finite_points, voxel_downsample
from recognition.hypotheses import Detection
from recognition.models import ModelDatabase
from recognition.verify import DepthView, Verdict
from schemas import geometry

log = logging.getLogger(__name__)
#: Detections from cameras further apart than this are not the same object (m).
SAME_OBJECT_M = 0.05
#: Voxel of the cameras' points fused objects are refined in (m): recognition's own 1 cm leaves an
#: object's side near the table with fewer points than the table, which then pulls the object into it.
REFINE_VOXEL_M = 0.005
#: Neighbours (at most) a point's normal is fitted to in that refinement.
NORMAL_NEIGHBOURS = 30
#: A fused object's refinement in the cameras' points (``refined_in_cloud``) that moves it further than
#: this (m), or tilts it by more than this (deg: turns the world's up in the object's frame; a turn
#: about the up, as an object on a table takes, is free) slid off: the fused pose stands.
REFINE_MAX_SHIFT_M, REFINE_MAX_TILT_DEG = 0.02, 3.0
#: Colours of the cameras' points in the fused cloud (RGBA), in camera-id order.
CLOUD_COLOURS = np.array(
    [
        [31, 119, 180, 255],
        [255, 127, 14, 255],
        [44, 160, 44, 255],
        [214, 39, 40, 255],
        [148, 103, 189, 255],
        [140, 86, 75, 255],
        [227, 119, 194, 255],
        [188, 189, 34, 255],
    ],
    np.uint8,
)


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
        agree = [
            d for d in group if np.linalg.norm(d.world_T_object[:3, 3] - best.world_T_object[:3, 3]) <= SAME_OBJECT_M
        ]
        w = np.array([d.score for d in agree])
        T = best.world_T_object.copy()
        T[:3, 3] = np.average([d.world_T_object[:3, 3] for d in agree], axis=0, weights=w)
        out.append(
            FusedObject(
                oid,
                max(d.stamp_ns for d in agree),
                T,
                sorted(d.camera_id for d in agree),
                best.detection.fitness,
                best.detection.rmse_m,
            )
        )
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


def cross_checked(
    detections: list[WorldDetection], views: list[CameraView], judge: Judge, max_age_ns: int
) -> tuple[list[FusedObject], list[Contradiction]]:
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


def refined_in_cloud(
    objects: list[FusedObject],
    cameras: list[CameraPoints],
    models: ModelDatabase,
    distance_m: float,
    normal_radius_m: float,
    min_fitness: float,
) -> list[FusedObject]:
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
        centre = o.world_T_object[:3, :3] @ model.centre + o.world_T_object[:3, 3]
        near = pts[np.linalg.norm(pts - centre, axis=1) <= model.diameter_m / 2 + 2 * distance_m]
        if len(near) < 3:
            log.debug("%s: kept its fused pose, no camera's points around it", o.object_id)
            out.append(o)
            continue
        facing = np.zeros(len(model.points), bool)
        for c in cameras:
            facing |= facing_camera(
                model.points, model.normals, geometry.invert_pose(c.world_T_camera) @ o.world_T_object
            )[0]
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(near.astype(np.float64)))
        target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=NORMAL_NEIGHBOURS))
        fit = icp_pass(
            model.points[facing],
            Surface.of(near, np.asarray(target.normals)),
            o.world_T_object,
            distance_m,
            max_shift_m=REFINE_MAX_SHIFT_M,
        )
        # world up in the object's frame, before and after
        tilt = np.degrees(geometry.angle_between(o.world_T_object[2, :3], fit.camera_T_object[2, :3]))
        if fit.fitness < min_fitness or tilt > REFINE_MAX_TILT_DEG:
            log.debug(
                "%s: kept its fused pose, the fit in the cameras' points scored %.2f and tilted it %.1f deg",
                o.object_id,
                fit.fitness,
                tilt,
            )
            out.append(o)
            continue
        out.append(replace(o, world_T_object=fit.camera_T_object))
    return out


def points_in_frame(cameras: list[CameraPoints], world_T_camera: np.ndarray) -> np.ndarray:
    """Every camera's points together, (N, 3) float32, in the frame of a camera at world_T_camera (4, 4)."""
    if not cameras:
        return np.zeros((0, 3), np.float32)
    camera_T_world = geometry.invert_pose(world_T_camera)
    out = []
    for c in cameras:
        T = camera_T_world @ c.world_T_camera
        out.append(c.points @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(out).astype(np.float32)


#: recognise(cloud (N, 3) camera frame, world_T_camera (4, 4), that camera's view): its detections.
Recognise = Callable[[np.ndarray, np.ndarray, DepthView], list[Detection]]


def found_in_cloud(
    missing: set[str], judge: CameraView, cameras: list[CameraPoints], recognise: Recognise
) -> list[WorldDetection]:
    """Objects no camera found (``missing``) recognised in every camera's points together, put in
    the frame of ``judge``'s camera and verified against its frame: what one camera sees of an
    object only partly, another completes. Detections of that camera (the caller cross-checks them
    with the other cameras' frames, as any camera's)."""
    if not missing:
        return []
    found = recognise(points_in_frame(cameras, judge.world_T_camera), judge.world_T_camera, judge.view)
    return [
        WorldDetection(
            judge.camera_id, judge.stamp_ns, judge.world_T_camera @ d.camera_T_object, d, judge.world_T_camera
        )
        for d in found
        if d.object_id in missing
    ]


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
