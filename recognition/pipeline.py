"""One frame -> detections: the paper's recognition pipeline as a pure function of a cloud.

cloud -> range limit, voxel downsample, normals -> remove dominant planes -> Euclidean clusters ->
VFH per cluster -> nearest model views -> camera-roll alignment -> ICP -> accept on fitness,
coverage and RMSE. A marker on an object, when seen, names it and gives ICP its starting pose.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from recognition.align import IcpResult, refine_icp, roll_candidates, rotation_between, view_to_scene
from recognition.cloud import estimate_normals, finite_points, voxel_downsample
from recognition.config import RecognitionConfig
from recognition.descriptor import describe
from recognition.errors import ModelError
from recognition.models import ModelDatabase, ObjectModel
from recognition.segment import euclidean_clusters, remove_planes, split_oversized

log = logging.getLogger(__name__)
UPRIGHT_COS = float(np.cos(np.radians(45.0)))
#: Touching objects explained away one after another in one cluster, at most.
MAX_OBJECTS_PER_CLUSTER = 3
#: A cluster wider than this many times the largest model is split with a tighter tolerance ...
SPLIT_ABOVE = 1.2
#: ... down to this many voxels (below it a surface falls apart into its samples).
MIN_TOLERANCE_VOXELS = 1.5


@dataclass(frozen=True)
class Prior:
    """A pose hint for one object, e.g. from a marker fixed on it. camera_T_object (4, 4)."""

    object_id: str
    camera_T_object: np.ndarray


@dataclass(frozen=True)
class Detection:
    """A recognised object in the camera frame. camera_T_object (4, 4); fitness and coverage 0..1."""

    object_id: str
    camera_T_object: np.ndarray
    fitness: float
    coverage: float
    rmse_m: float
    points: int  # scene points the model explains
    from_prior: bool = False


@dataclass
class SceneCloud:
    """The prepared scene: downsampled points and normals (N, 3), and which survive plane removal."""

    points: np.ndarray
    normals: np.ndarray
    foreground: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))


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
        self._table, self._rows = database.view_table()
        self._largest = max((mdl.diameter_m for mdl in database.models.values()), default=np.inf)

    def prepare(self, cloud: np.ndarray, world_T_camera: np.ndarray | None = None) -> SceneCloud:
        """Finite points within range (and the workspace, when the camera pose is known), downsampled,
        with normals, and the non-plane mask."""
        c, d = self.config, self.config.descriptor
        pts = finite_points(cloud)
        pts = pts[np.linalg.norm(pts, axis=1) <= c.max_range_m]
        if world_T_camera is not None and c.workspace_min is not None:
            world = pts @ world_T_camera[:3, :3].T.astype(np.float32) + world_T_camera[:3, 3].astype(np.float32)
            pts = pts[np.all((world >= c.workspace_min) & (world <= c.workspace_max), axis=1)]
        if len(pts) == 0:
            return SceneCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
        pts = voxel_downsample(pts, d.voxel_m)
        normals, _ = estimate_normals(pts, d.normal_radius_m)
        ok = np.all(np.isfinite(normals), axis=1)
        pts, normals = pts[ok], normals[ok]
        fg = remove_planes(pts, c.plane_distance_m, c.max_planes, c.min_plane_fraction, c.plane_noise_per_m2)
        return SceneCloud(pts, normals, fg)

    def recognize(
        self, cloud: np.ndarray, priors: Sequence[Prior] = (), world_T_camera: np.ndarray | None = None
    ) -> list[Detection]:
        """Detections in one cloud ((H, W, 3) organised or (N, 3), camera frame, metres), best per object.

        world_T_camera (4, 4), when known, crops the scene to the configured workspace.
        """
        scene = self.prepare(cloud, world_T_camera)
        if len(scene.points) == 0:
            return []
        # World up in the camera frame, when known: the upright test needs it.
        up = world_T_camera[2, :3].copy() if world_T_camera is not None and self.config.upright else None
        c = self.config
        fg_idx = np.flatnonzero(scene.foreground)
        clusters = [fg_idx[k] for k in euclidean_clusters(
            scene.points[fg_idx], c.cluster_tolerance_m, c.cluster_min_points, c.cluster_max_points)]
        clusters = split_oversized(scene.points, clusters, SPLIT_ABOVE * self._largest, c.cluster_tolerance_m,
                                   MIN_TOLERANCE_VOXELS * c.descriptor.voxel_m, c.cluster_min_points)
        found: dict[str, Detection] = {}
        used = np.zeros(len(clusters), dtype=bool)
        for prior in priors:
            model = self.db.models.get(prior.object_id)
            if model is None:
                continue
            k = _cluster_near(scene.points, clusters, prior.camera_T_object[:3, 3], model.diameter_m)
            if k is None:
                continue
            match = self._score(model, scene, clusters[k], [prior.camera_T_object], up, from_prior=True)
            if match is not None:
                used[k] = match[0].coverage >= c.min_coverage
                found[prior.object_id] = match[0]
        for k, idx in enumerate(clusters):
            rest = idx
            # Objects that touch share a cluster: a confident match that explains only part of it is
            # kept, its points are explained away, and the rest is matched again.
            for _ in range(0 if used[k] else MAX_OBJECTS_PER_CLUSTER):
                match = self._match_cluster(scene, rest, up)
                if match is None:
                    break
                det, explained = match
                if det.object_id not in found or _better(det, found[det.object_id]):
                    found[det.object_id] = det
                rest = rest[~explained]
                if det.coverage >= c.min_coverage or len(rest) < c.cluster_min_points:
                    break
        return sorted(found.values(), key=lambda d: d.object_id)

    def _match_cluster(
        self, scene: SceneCloud, idx: np.ndarray, up: np.ndarray | None
    ) -> tuple[Detection, np.ndarray] | None:
        """VFH nearest views -> roll candidates -> ICP; the best accepted hypothesis, if any."""
        if len(self._rows) == 0:
            return None
        desc = describe(scene.points[idx], scene.normals[idx], self.config.descriptor)
        dist = np.abs(self._table - desc.vfh).sum(axis=1)  # L1 between histograms
        best: tuple[Detection, np.ndarray] | None = None
        by_object: dict[str, list[np.ndarray]] = {}
        # The nearest views of every object, not of the database as a whole: on noisy clusters the
        # descriptor ranks objects poorly, and ICP's fitness is the better judge between them.
        for row in np.argsort(dist, kind="stable"):
            oid, v = self._rows[row]
            starts = by_object.setdefault(oid, [])
            if len(starts) >= self.config.candidates * self.config.roll_peaks:
                continue
            views = self.db.models[oid].views
            for roll in roll_candidates(desc.roll, views.roll[v], self.config.roll_peaks):
                camera_T_view = view_to_scene(desc.centroid, views.centroid[v], roll)
                starts.append(camera_T_view @ views.view_T_object[v])
        for oid, starts in by_object.items():
            match = self._score(self.db.models[oid], scene, idx, starts, up)
            if match is not None and (best is None or _better(match[0], best[0])):
                best = match
        return best

    def _score(
        self,
        model: ObjectModel,
        scene: SceneCloud,
        idx: np.ndarray,
        starts: list[np.ndarray],
        up: np.ndarray | None,
        from_prior: bool = False,
    ) -> tuple[Detection, np.ndarray] | None:
        """ICP from each start onto the cluster; the best result if it passes the acceptance tests,
        with the mask of the cluster points it explains.

        up: world up in the camera frame (None: no upright test). Accepted: fitness, coverage and RMSE within bounds; or, for a cluster several objects share,
        a fitness of at least min_fitness_shared with enough explained points to be a cluster itself.
        """
        c = self.config
        target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.points[idx].astype(np.float64)))
        target.normals = o3d.utility.Vector3dVector(scene.normals[idx].astype(np.float64))
        best: IcpResult | None = None
        for start in starts:
            if up is not None:
                start = _stand_up(start, up, model.points.mean(axis=0))
            res = refine_icp(model.points, model.normals, target, start, c.icp_distance_m, c.icp_iterations,
                             max_shift_m=model.diameter_m)
            if up is not None and res.camera_T_object[:3, 2] @ up < UPRIGHT_COS:
                continue  # lying on its side or upside down: the mirror image of a symmetric shape
            if best is None or (res.fitness, -res.rmse_m) > (best.fitness, -best.rmse_m):
                best = res
        if best is None:
            return None
        explained = _explained(model, best.camera_T_object, target, c.icp_distance_m)
        coverage = float(explained.mean()) if len(explained) else 0.0
        whole = best.fitness >= c.min_fitness and coverage >= c.min_coverage
        shared = best.fitness >= c.min_fitness_shared and explained.sum() >= c.cluster_min_points
        ok = (whole or shared) and best.rmse_m <= c.max_rmse_m
        log.debug("%s: fitness %.2f coverage %.2f rmse %.4f -> %s", model.object_id, best.fitness, coverage,
                  best.rmse_m, "accepted" if ok else "rejected")
        if not ok:
            return None
        det = Detection(model.object_id, best.camera_T_object, best.fitness, coverage, best.rmse_m,
                        int(explained.sum()), from_prior)
        return det, explained


def _stand_up(camera_T_object: np.ndarray, up: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The pose turned, about the object's centre (object frame, m), so that its +z is world up.

    A symmetric shape matched from the VFH of a single view is as likely upside down as not; for
    objects that stand on their base the upright twin is the physical one.
    """
    if camera_T_object[:3, 2] @ up >= UPRIGHT_COS:
        return camera_T_object
    # Exactly upside down: turn about the object's own x axis.
    R = rotation_between(camera_T_object[:3, 2], up, half_turn_axis=camera_T_object[:3, 0])
    pivot = camera_T_object[:3, :3] @ centre + camera_T_object[:3, 3]
    out = camera_T_object.copy()
    out[:3, :3] = R @ camera_T_object[:3, :3]
    out[:3, 3] = R @ (camera_T_object[:3, 3] - pivot) + pivot
    return out


def _explained(model: ObjectModel, camera_T_object: np.ndarray, target: o3d.geometry.PointCloud, dist: float) -> np.ndarray:
    """Mask of the cluster's points within dist of the posed model."""
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.points.astype(np.float64)))
    src.transform(camera_T_object)
    return np.asarray(target.compute_point_cloud_distance(src)) <= dist


def _cluster_near(points: np.ndarray, clusters: list[np.ndarray], position: np.ndarray, radius: float) -> int | None:
    """The cluster with the most points within radius of position, if any."""
    counts = [int(np.sum(np.linalg.norm(points[idx] - position, axis=1) <= radius)) for idx in clusters]
    if not counts or max(counts) == 0:
        return None
    return int(np.argmax(counts))


def _better(a: Detection, b: Detection) -> bool:
    return (a.fitness * a.coverage, -a.rmse_m) > (b.fitness * b.coverage, -b.rmse_m)
