"""One frame -> detections: the paper's recognition pipeline as a pure function of a cloud.

cloud -> range limit, voxel downsample -> remove dominant planes -> normals -> Euclidean clusters
(split where objects merged) -> candidates (``recognition.hypotheses``: VFH, camera-roll alignment,
ICP; objects stood on the support at pieces of what no match explained) -> joint resolution
(``recognition.resolve``: each verified against the whole frame from the camera's viewpoint,
``recognition.verify``). A marker on an object, when seen, names it and gives ICP its starting
pose. Up is known from the camera's pose, or, without one, from the level plane the objects may
stand on (``Stance``): objects are then tried free, standing and, in a frame with colour, lying on
each of four sides (sides alike once, ``hypotheses.distinct_rests``).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from recognition.align import ImageBounds
from recognition.cloud import estimate_normals, radius_neighbours, voxel_downsample
from recognition.config import RecognitionConfig
from recognition.errors import ModelError
from recognition.hypotheses import RESTS, Candidate, Detection, Matcher, SceneCloud, Stance
from recognition.models import ModelDatabase
from recognition.resolve import Resolver
from recognition.segment import PointGraph, euclidean_clusters, remove_planes, split_oversized
from recognition.verify import DepthView, Verdict, fit_intrinsics, project, verdict

log = logging.getLogger(__name__)
#: A plane past the first is removed as structure (a wall, a floor, a table seen across a room) when
#: a connected patch of it is this many times wider than the largest object: a plane that slices
#: through two objects standing side by side is not.
STRUCTURE_OBJECTS = 2.0
#: A cluster wider than this many times the largest model is split with a tighter tolerance ...
SPLIT_ABOVE = 1.2
#: ... down to this many voxels (below it a surface falls apart into its samples).
MIN_TOLERANCE_VOXELS = 1.5
#: Pixels another camera must be able to judge (on or in front of its measured surface) for its
#: frame to contradict a detection (``Recognizer.seen_through``): fewer say little either way.
CROSS_VIEW_PIXELS = 50
#: A removed plane is a support objects stand on if its normal is within this of world up.
SUPPORT_COS = float(np.cos(np.radians(20.0)))


@dataclass(frozen=True)
class Prior:
    """A pose hint for one object, e.g. from a marker fixed on it. camera_T_object (4, 4)."""

    object_id: str
    camera_T_object: np.ndarray


class Recognizer:
    """Recognise the objects of a model database in single camera-frame clouds."""

    def __init__(self, database: ModelDatabase, config: RecognitionConfig) -> None:
        if database.descriptor != config.descriptor:
            raise ModelError(
                f"the model database was built with {database.descriptor.model_dump()} but recognition is configured "
                f"with {config.descriptor.model_dump()}; rebuild the database or change [recognition.descriptor]"
            )
        self.db = database
        self.config = config
        self._largest = max((mdl.diameter_m for mdl in database.models.values()), default=np.inf)
        self.matcher = Matcher(database, config)
        self.resolver = Resolver(database, config, self.matcher.indexes, self.matcher.dense)

    def workspace_points(self, cloud: np.ndarray, world_T_camera: np.ndarray | None = None) -> np.ndarray:
        """The cloud's finite points within range, and within the workspace when the camera pose is
        known: (N, 3) float32, camera frame."""
        c = self.config
        pts = np.asarray(cloud, dtype=np.float32).reshape(-1, 3)
        # A 640x480 frame is 307k points and this runs on every frame: the workspace (which drops
        # most of them) in one OpenCV pass each for the transform and the box, then the range.
        # NaN points fail every comparison.
        if world_T_camera is not None and c.workspace_min is not None and len(pts):
            world = cv2.transform(pts.reshape(-1, 1, 3), np.asarray(world_T_camera, np.float64)[:3])
            inside = cv2.inRange(world, np.array(c.workspace_min, np.float64), np.array(c.workspace_max, np.float64))
            pts = pts[inside.reshape(-1).view(bool)]
        return pts[np.einsum("ij,ij->i", pts, pts) <= np.float32(c.max_range_m**2)]

    def prepare(self, cloud: np.ndarray, world_T_camera: np.ndarray | None = None) -> SceneCloud:
        """Finite points within range (and the workspace, when the camera pose is known), downsampled,
        off the dominant planes, with normals."""
        c, d = self.config, self.config.descriptor
        empty = SceneCloud(
            np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), PointGraph.empty(c.cluster_tolerance_m)
        )
        pts = self.workspace_points(cloud, world_T_camera)
        if len(pts) == 0:
            return empty
        pts = voxel_downsample(pts, d.voxel_m)
        # Planes first, normals after: most of a scene is table, and an object's normals should not
        # lean towards the table it stands on (the model's views have no table either).
        # A workspace box has already cut the room away: only its table is left to remove (a search
        # for walls there costs ~8 ms a frame and finds none).
        cropped = world_T_camera is not None and c.workspace_min is not None
        off_planes, planes = remove_planes(
            pts,
            c.plane_distance_m,
            min(c.max_planes, 1) if cropped else c.max_planes,
            c.min_plane_fraction,
            c.plane_noise_per_m2,
            c.plane_seed,
            STRUCTURE_OBJECTS * self._largest,
        )
        pts = pts[off_planes]
        if len(pts) == 0:
            return empty
        neighbours = radius_neighbours(pts, max(d.normal_radius_m, c.cluster_tolerance_m))
        normals, _ = estimate_normals(pts, d.normal_radius_m, neighbours=neighbours)
        ok = np.flatnonzero(np.all(np.isfinite(normals), axis=1))
        graph = PointGraph.from_neighbours(neighbours).subgraph(ok, c.cluster_tolerance_m)
        grid = np.asarray(cloud)
        # Only which pixels a model point lands on is asked of it: a sparse fit is ample.
        image = (
            ImageBounds(fit_intrinsics(grid, 16), grid.shape[:2])
            if grid.ndim == 3 and min(grid.shape[:2]) > 1
            else None
        )
        return SceneCloud(pts[ok], normals[ok], graph, planes, image)

    def recognize(
        self,
        cloud: np.ndarray,
        priors: Sequence[Prior] = (),
        world_T_camera: np.ndarray | None = None,
        view: DepthView | None = None,
        rgb: np.ndarray | None = None,
    ) -> list[Detection]:
        """Detections in one cloud ((H, W, 3) organised or (N, 3), camera frame, metres), at most one
        per object and one per cluster.

        world_T_camera (4, 4), when known, crops the scene to the configured workspace. view: the
        cloud's ``DepthView``, when the caller has it (else built when a hypothesis is judged, with
        rgb: the points' colours, uint8, the cloud's layout, if the sensor sent them).
        """
        scene = self.prepare(cloud, world_T_camera)
        if len(scene.points) == 0:
            return []
        c = self.config
        coloured = view.chroma is not None if view is not None else rgb is not None
        # The view is built now: objects are seeded where their colour shows, and fits that need it to
        # agree are made only where it does.
        if coloured:
            view = view or DepthView.of(cloud, rgb)
            u, v, ok = project(scene.points, view.K, view.z.shape)
            scene.chroma = np.where(ok[:, None], view.chroma[v, u], np.nan)
        stances = self._stances(scene.planes, world_T_camera, coloured)
        merged = euclidean_clusters(
            scene.points, c.cluster_tolerance_m, c.cluster_min_points, c.cluster_max_points, scene.graph
        )
        clusters, shed = split_oversized(
            scene.points,
            merged,
            SPLIT_ABOVE * self._largest,
            c.cluster_tolerance_m,
            MIN_TOLERANCE_VOXELS * c.descriptor.voxel_m,
            c.cluster_min_points,
            scene.graph,
        )
        first_fragment = len(clusters)  # clusters from here on are fragments: the pieces path only
        if any(s.resting for s in stances):
            clusters += self.matcher.fragments(merged, clusters, shed, len(scene.points))
        # Candidates: a part is a cluster, or what is left of one once a touching object is
        # explained away, or a prior's own hint. A prior only adds one: its cluster is matched as
        # any other (a hint may be wrong, and its cluster may hold other objects), and the joint
        # resolution chooses.
        parts = itertools.count()
        candidates: list[Candidate] = []
        for prior in priors:
            model = self.db.models.get(prior.object_id)
            if model is None:
                continue
            k = _cluster_near(scene.points, clusters, prior.camera_T_object[:3, 3], model.diameter_m)
            if k is None:
                continue
            target = self.matcher.target(scene, clusters[k])
            match = self.matcher.score(model, target, [prior.camera_T_object], stances[0].up, from_prior=True)
            if match is not None:
                candidates.append(Candidate(next(parts), None, match[0], stances[0]))
        for stance in stances:
            candidates += self.matcher.candidates(scene, clusters, first_fragment, stance, parts)
        # The frame's depth view is built only when a candidate is there to be judged against it.
        view = (view or DepthView.of(cloud, rgb)) if c.verify and candidates else None
        return self.resolver.resolve(candidates, view, scene, clusters)

    def _stances(self, planes: np.ndarray, world_T_camera: np.ndarray | None, coloured: bool) -> list[Stance]:
        """How objects may stand in this frame, each tried in turn (``Stance``).

        With the camera's pose: world up, for the upright test (when ``upright``), every object
        standing (with ``free_with_pose``: tried as below, with the pose's up). Without it there
        is no world up; the removed plane whose normal is nearest the image's up (-y; a camera is
        mounted upright) is a table or a floor, not a wall: with ``level_support`` every object
        stands on it, with ``stand_on_level`` objects are tried both free and standing on it, and
        with ``rest_on_sides`` lying on it on each of four sides, when the frame has colour (up to
        three times the poses tried: on depth alone they fitted boxes and cans to PCL's real rooms;
        an object is tried on one of sides alike, ``Matcher.tries``). Free or not, an object rests on
        the support where there is one (``Resolver.rests``).
        """
        c = self.config
        if world_T_camera is not None:
            level = world_T_camera[2, :3].copy() if c.upright else None
            support = support_plane(planes, level) if c.verify else None
            if not (c.free_with_pose and level is not None):
                return [Stance(level, support)]
        elif c.upright and len(planes) and (c.level_support or c.stand_on_level):
            unit = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
            level = unit[np.argmax(-unit[:, 1])]
            support = support_plane(planes, level) if c.verify else None
            if c.level_support:
                return [Stance(level, support)]
        else:
            return [Stance(None, None)]
        lying = [Stance(level, support, rest) for rest in RESTS] if c.rest_on_sides and coloured else []
        # A free object rests on the support too (nothing hovers): without a pose the level plane
        # stands in for it, else the piece of a leg or a chair a carton fits is taken for one.
        return [Stance(None, support), Stance(level, support), *lying]

    def seen_through(self, view: DepthView, object_id: str, camera_T_object: np.ndarray) -> Verdict | None:
        """Another camera's judgement of a detection: the verdict of the object posed in that camera's
        frame (camera_T_object (4, 4)) against its depth view, if it contradicts the detection (the
        camera measured surfaces behind where the object would be: under ``min_cross_view_fitness``
        of the ``CROSS_VIEW_PIXELS`` or more it could judge), else None."""
        model, c = self.db.models[object_id], self.config
        v = verdict(
            view,
            model.points,
            model.normals,
            camera_T_object,
            c.icp_distance_m,
            c.plane_noise_per_m2,
            spacing_m=c.descriptor.voxel_m,
        )
        judged = v.inliers + v.violations
        return v if judged >= CROSS_VIEW_PIXELS and v.fitness < c.min_cross_view_fitness else None


def support_plane(planes: np.ndarray, up: np.ndarray | None) -> np.ndarray | None:
    """Of the removed planes (a, b, c, d; normal towards the camera) that are level (normal within
    20 deg of world up ``up``, camera frame), the one nearest the camera (a table over the floor),
    normalised; None without one or without ``up``."""
    if up is None:
        return None
    unit = planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    level = unit[unit[:, :3] @ (up / np.linalg.norm(up)) >= SUPPORT_COS]
    return level[np.argmin(level[:, 3])] if len(level) else None


def _cluster_near(points: np.ndarray, clusters: list[np.ndarray], position: np.ndarray, radius: float) -> int | None:
    """The cluster with the most points within radius of position, if any."""
    counts = [int(np.sum(np.linalg.norm(points[idx] - position, axis=1) <= radius)) for idx in clusters]
    if not counts or max(counts) == 0:
        return None
    return int(np.argmax(counts))
