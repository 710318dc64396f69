"""One frame -> detections: the paper's recognition pipeline as a pure function of a cloud.

cloud -> range limit, voxel downsample, normals -> remove dominant planes -> Euclidean clusters ->
VFH per cluster -> nearest model views -> camera-roll alignment -> ICP -> accept on fitness,
coverage and RMSE -> verify against the whole frame from the camera's viewpoint
(``recognition.verify``). A marker on an object, when seen, names it and gives ICP its starting pose.
Objects standing so close that they share a cluster (and hide parts of each other) are found a
second way when world up is known: each is stood upright on the table at pieces of what no match
explained (and of the fragments a split of merged objects shed), and only verification accepts
it. Up is known from the camera's pose, or, without one, from the level plane the objects may
stand on (``Stance``): objects are then tried free, standing and, in a frame with colour, lying on
each of four sides. Standing or lying, nothing hovers (a detection must rest on the table or on an
object found under it) and nothing is the lower part of something taller.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d

from recognition.align import (
    ImageBounds, IcpResult, align_to_z, facing_camera, icp_pass, refine_icp, roll_correlations, roll_peaks, rot_z,
    views_to_scene,
)
from recognition.cloud import PointIndex, estimate_normals, radius_neighbours, voxel_downsample
from recognition.config import RecognitionConfig
from recognition.descriptor import describe
from recognition.errors import ModelError
from recognition.models import ModelDatabase, ObjectModel
from recognition.segment import PointGraph, euclidean_clusters, remove_planes, split_oversized
from recognition.verify import MIN_COLOUR_PIXELS, DepthView, Explained, Verdict, fit_intrinsics, verdict
from schemas.geometry import invert_pose, make_pose, rotation_angle, rotation_between

log = logging.getLogger(__name__)
UPRIGHT_COS = float(np.cos(np.radians(45.0)))
#: Touching objects explained away one after another in one cluster, at most.
MAX_OBJECTS_PER_CLUSTER = 3
#: A plane past the first is removed as structure (a wall, a floor, a table seen across a room) when
#: a connected patch of it is this many times wider than the largest object: a plane that slices
#: through two objects standing side by side is not.
STRUCTURE_OBJECTS = 2.0
#: A cluster wider than this many times the largest model is split with a tighter tolerance ...
SPLIT_ABOVE = 1.2
#: ... down to this many voxels (below it a surface falls apart into its samples).
MIN_TOLERANCE_VOXELS = 1.5
#: Model points in the coarse ICP that screens every start: enough to lock on an object's shape.
SCREEN_POINTS = 100
#: ... and its iterations: it need only fall into the right basin; the refinement converges.
SCREEN_ITERATIONS = 8
#: Screened starts per object refined with a denser model ...
REFINED_STARTS = 2
#: ... of this many points (a 1 cm voxel model of a 30 cm object has ~2000; ICP's precision is
#: bounded by depth noise long before by this count).
REFINE_POINTS = 500
#: Screened starts closer than this are one start: refining both would repeat the same work.
SAME_POSE_M = 0.01
SAME_POSE_RAD = float(np.radians(10.0))
#: More starts than this are ranked by overlap (one neighbour search for all) before any ICP.
ICP_STARTS = 8
#: Pieces of a cluster no match explained (``Recognizer._piece_centres``): seeds per object and cluster ...
MAX_SEEDS = 4
#: ... a piece tried for an object only if the cluster's rest holds this share of its model's points
#: (a view shows about half of a surface, and verification wants 40 % of that) ...
PIECE_SHARE = 0.1
#: ... the yaws an object is stood on the support at ...
YAW_STEP_DEG = 30
#: ... and the fitness from which a piece's hypothesis goes on to verification, which judges it on
#: the surface the camera should see (a partly hidden object's fitness over its facing side is low).
PIECE_FITNESS = 0.2
#: A part of a split cluster with fewer points than this share of the smallest model's is no whole
#: object (a view shows about half a surface): it may be a fragment of one (``Recognizer._fragments``).
SMALL_PART = 0.5
#: Pixels another camera must be able to judge (on or in front of its measured surface) for its
#: frame to contradict a detection (``Recognizer.seen_through``): fewer say little either way.
CROSS_VIEW_PIXELS = 50
#: An upright detection with more unexplained points of its cluster above its top than this share
#: of the points it explains is part of something taller (``Recognizer._above``): true detections
#: in ``benchmarks.bop``'s frames up to 0.015, a can on a real bleach bottle's body 0.09-0.12.
TOPPED_SHARE = 0.05
#: The sides an object may lie on besides its base (``Stance.rest``): turns of its frame that
#: bring each side's outward normal (+-x, +-y) to -z. Not its top: a box or a can upside down fits
#: a standing one as well, and its frame would be reported upside down.
RESTS = tuple(rotation_between(np.array(side, float), [0.0, 0.0, -1.0]) for side in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)))
#: A removed plane is a support objects stand on if its normal is within this of world up.
SUPPORT_COS = float(np.cos(np.radians(20.0)))


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


@dataclass(frozen=True)
class Stance:
    """How objects stand in a frame: world up in the camera frame (3,) for the upright test (None:
    any way up), the level plane they rest on (a, b, c, d; unit normal towards the camera; None: no
    rest test and no pieces path), and the side they rest on: ``rest`` (3, 3) turns the object's
    frame so that the side's outward normal is -z (identity: standing on its base)."""

    up: np.ndarray | None
    support: np.ndarray | None
    rest: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def lying(self) -> bool:
        """Whether the object rests on a side other than its base."""
        return not np.array_equal(self.rest, np.eye(3))


@dataclass
class SceneCloud:
    """The prepared scene: the downsampled points off the dominant planes, with normals, (N, 3), and
    their pairs within the clustering tolerance (found with the normals' neighbours, in one search)."""

    points: np.ndarray
    normals: np.ndarray
    graph: PointGraph
    planes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # the dominant planes removed (P, 4), ``remove_planes``
    image: ImageBounds | None = None  # the image an organised cloud was measured in


@dataclass(frozen=True)
class Target:
    """Scene points hypotheses are fitted to (a cluster, or what is left of one), camera frame:
    ``points`` (N, 3), the same with normals for Open3D's ICP, and their index. Built once per part
    for every object tried on it."""

    points: np.ndarray
    cloud: o3d.geometry.PointCloud
    index: PointIndex
    image: ImageBounds | None = None  # model points landing outside it are not looked for

    @classmethod
    def of(cls, scene: SceneCloud, idx: np.ndarray) -> "Target":
        points = scene.points[idx]
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
        cloud.normals = o3d.utility.Vector3dVector(scene.normals[idx].astype(np.float64))
        return cls(points, cloud, PointIndex(points), scene.image)


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
        self._views, self._owners = database.view_table()
        self._view_to_z = np.array([align_to_z(c) for c in self._views.centroid]).reshape(-1, 3, 3)
        self._largest = max((mdl.diameter_m for mdl in database.models.values()), default=np.inf)
        self._smallest_model = min((len(mdl.points) for mdl in database.models.values()), default=0)
        # The fewest points a piece may hold for the pieces path to try the smallest object on it.
        self._smallest_piece = int(PIECE_SHARE * self._smallest_model)
        self._sparse = {oid: _thinned(mdl, SCREEN_POINTS) for oid, mdl in database.models.items()}
        self._dense = {oid: _thinned(mdl, REFINE_POINTS) for oid, mdl in database.models.items()}
        self._centre = {oid: mdl.points.mean(axis=0) for oid, mdl in database.models.items()}
        # Each whole model's point index, built once: which cluster points a pose explains is asked
        # of every accepted hypothesis.
        self._model_index = {oid: PointIndex(mdl.points) for oid, mdl in database.models.items()}

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
        empty = SceneCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                           PointGraph.empty(c.cluster_tolerance_m))
        pts = self.workspace_points(cloud, world_T_camera)
        if len(pts) == 0:
            return empty
        pts = voxel_downsample(pts, d.voxel_m)
        # Planes first, normals after: most of a scene is table, and an object's normals should not
        # lean towards the table it stands on (the model's views have no table either).
        # A workspace box has already cut the room away: only its table is left to remove (a search
        # for walls there costs ~8 ms a frame and finds none).
        cropped = world_T_camera is not None and c.workspace_min is not None
        off_planes, planes = remove_planes(pts, c.plane_distance_m, min(c.max_planes, 1) if cropped else c.max_planes,
                                           c.min_plane_fraction, c.plane_noise_per_m2, min_extent_m=STRUCTURE_OBJECTS * self._largest)
        pts = pts[off_planes]
        if len(pts) == 0:
            return empty
        neighbours = radius_neighbours(pts, max(d.normal_radius_m, c.cluster_tolerance_m))
        normals, _ = estimate_normals(pts, d.normal_radius_m, neighbours=neighbours)
        ok = np.flatnonzero(np.all(np.isfinite(normals), axis=1))
        graph = PointGraph.from_neighbours(neighbours).subgraph(ok, c.cluster_tolerance_m)
        grid = np.asarray(cloud)
        # Only which pixels a model point lands on is asked of it: a sparse fit is ample.
        image = ImageBounds(fit_intrinsics(grid, 16), grid.shape[:2]) if grid.ndim == 3 and min(grid.shape[:2]) > 1 else None
        return SceneCloud(pts[ok], normals[ok], graph, planes, image)

    def recognize(
        self, cloud: np.ndarray, priors: Sequence[Prior] = (), world_T_camera: np.ndarray | None = None,
        view: DepthView | None = None, rgb: np.ndarray | None = None,
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
        stances = self._stances(scene.planes, world_T_camera, coloured)
        merged = euclidean_clusters(scene.points, c.cluster_tolerance_m, c.cluster_min_points, c.cluster_max_points,
                                    scene.graph)
        clusters, shed = split_oversized(scene.points, merged, SPLIT_ABOVE * self._largest, c.cluster_tolerance_m,
                                         MIN_TOLERANCE_VOXELS * c.descriptor.voxel_m, c.cluster_min_points, scene.graph)
        first_fragment = len(clusters)  # clusters from here on are fragments: the pieces path only
        if any(s.support is not None for s in stances):
            clusters += self._fragments(merged, clusters, shed, len(scene.points))
        # Candidates (part, detection, how it stands): a part is a cluster, or what is left of one
        # once a touching object is explained away, or a prior's own hint.
        candidates: list[tuple[int, Detection, Stance]] = []
        used = np.zeros(len(clusters), dtype=bool)
        up = stances[0].up
        for prior in priors:
            model = self.db.models.get(prior.object_id)
            if model is None:
                continue
            k = _cluster_near(scene.points, clusters, prior.camera_T_object[:3, 3], model.diameter_m)
            if k is None:
                continue
            match = self._score(model, Target.of(scene, clusters[k]), [prior.camera_T_object], up, from_prior=True)
            if match is not None:
                used[k] = match[0].coverage >= c.min_coverage
                candidates.append((-1 - len(candidates), match[0], stances[0]))
        cluster_of: dict[int, int | None] = {}  # part -> its cluster (None: no cluster of its own)
        for stance in stances:
            candidates += self._candidates(scene, clusters, first_fragment, used, stance, cluster_of)
        # Each object is in the scene once, and each part is one object: best matches first, so that
        # a part two objects fit goes to the one not found better elsewhere. A hypothesis the frame
        # contradicts never takes a part, and a pixel explains one object.
        candidates = sorted(candidates, key=lambda pd: _rank(pd[1]), reverse=True)
        # Judged only when it could be taken: most frames hold candidates for objects already found.
        view = (view or DepthView.of(cloud, rgb)) if c.verify and candidates else None
        found: dict[str, Detection] = {}
        cluster_found: dict[str, int | None] = {}  # object -> the cluster its part came from (None: a prior's)
        stance_found: dict[str, Stance] = {}
        taken: set[int] = set()
        explained = Explained()
        # Objects rest on the support or on an object found under them (``_rests``): one that does
        # not yet waits for another pass, in case what it stands on is found after it.
        pending = candidates
        while pending:
            waiting, before = [], len(found)
            for p, det, stance in pending:
                if p in taken or det.object_id in found:
                    continue
                if stance.support is not None and c.max_float_m > 0 and not self._rests(det, found.values(), stance.support):
                    waiting.append((p, det, stance))
                    continue
                v = self._verdict(view, det, scene.planes) if view is not None else None
                if v is not None and stance.lying and v.colour_judged < MIN_COLOUR_PIXELS:
                    log.debug("%s rejected: lying on a side, it needs its colour judged (%d pixels could be)",
                              det.object_id, v.colour_judged)  # fmt: skip
                    continue
                seen = explained.support(v) if v is not None else 1.0
                if v is not None and not (v.fitness >= c.min_visible_fitness and seen >= c.min_visible_support
                                          and v.clutter <= c.max_clutter and v.outline_seen >= c.min_outline_seen
                                          and v.penetration <= c.max_penetration
                                          and v.colour_agreement >= c.min_colour_agreement and explained.admit(v)):  # fmt: skip
                    log.debug("%s rejected by verification: visible fitness %.2f, support %.2f (%d of %d visible "
                              "pixels, %d seen through), clutter %.2f, outline seen %.2f (of %d pixels), inside a "
                              "support %.3f, colour %.2f (of %d pixels)", det.object_id, v.fitness, seen, v.inliers,
                              v.visible, v.violations, v.clutter, v.outline_seen, v.outline, v.penetration,
                              v.colour_agreement, v.colour_judged)  # fmt: skip
                    continue
                taken.add(p)
                found[det.object_id] = det
                cluster_found[det.object_id] = cluster_of.get(p)
                stance_found[det.object_id] = stance
            if len(found) == before:
                for _, det, _ in waiting:
                    log.debug("%s rejected: it floats above the support with nothing found under it", det.object_id)
                break
            pending = waiting
        # A match explaining only part of its cluster was kept for touching objects: it stands only
        # if another object was found in the same cluster. Alone, it is a shape that fits a piece of
        # some larger unknown surface (a carton's faces on a person, on a cabinet).
        for oid, det in list(found.items()):
            k = cluster_found[oid]
            if k is not None and det.coverage < c.min_coverage and not any(
                    cluster_found[other] == k for other in found if other != oid):  # fmt: skip
                log.debug("%s rejected: it explains %.0f %% of its cluster and nothing else was found in the rest",
                          oid, 100 * det.coverage)  # fmt: skip
                del found[oid]
        # An upright object is no part of something taller: cluster points above its top, inside its
        # footprint, that nothing found explains say it was fitted to the lower part of a larger
        # shape (a can on a bleach bottle's body, the bottle's shoulder and neck above it).
        for oid, det in list(found.items()):
            k, up = cluster_found[oid], stance_found[oid].up
            if k is None or up is None or not self.db.models[oid].stands_on_z:
                continue
            above = self._above(det, scene.points[clusters[k]], found.values(), stance_found[oid].rest)
            if above > TOPPED_SHARE * det.points:
                log.debug("%s rejected: %d points of its cluster stand on its top and nothing found explains them",
                          oid, above)
                del found[oid]
        return sorted(found.values(), key=lambda d: d.object_id)

    def _stances(self, planes: np.ndarray, world_T_camera: np.ndarray | None, coloured: bool) -> list[Stance]:
        """How objects may stand in this frame, each tried in turn (``Stance``).

        With the camera's pose: world up, for the upright test (when ``upright``). Without it there
        is no world up; the removed plane whose normal is nearest the image's up (-y; a camera is
        mounted upright) is a table or a floor, not a wall: with ``level_support`` every object
        stands on it, with ``stand_on_level`` objects are tried both free and standing on it, and
        with ``rest_on_sides`` lying on it on each of four sides, when the frame has colour (three
        times the poses tried: on depth alone they fitted boxes and cans to PCL's real rooms).
        """
        c = self.config
        if world_T_camera is not None:
            up = world_T_camera[2, :3].copy() if c.upright else None
            return [Stance(up, _support(planes, up) if c.verify else None)]
        if not (c.upright and len(planes) and (c.level_support or c.stand_on_level)):
            return [Stance(None, None)]
        unit = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        level = unit[np.argmax(-unit[:, 1])]
        support = _support(planes, level) if c.verify else None
        if c.level_support:
            return [Stance(level, support)]
        lying = [Stance(level, support, rest) for rest in RESTS] if c.rest_on_sides and coloured else []
        return [Stance(None, None), Stance(level, support), *lying]

    def _candidates(
        self, scene: SceneCloud, clusters: list[np.ndarray], first_fragment: int, used: np.ndarray, stance: Stance,
        cluster_of: dict[int, int | None],
    ) -> list[tuple[int, Detection, Stance]]:
        """Every hypothesis (part, detection, ``stance``) for the clusters (indices into the scene's
        points; from ``first_fragment`` on, fragments: the pieces path only) that no prior has
        ``used``, with objects standing as ``stance`` says. Parts are numbered on from
        ``cluster_of`` (part -> its cluster, None for none of its own), which this extends."""
        c, up, support = self.config, stance.up, stance.support
        out: list[tuple[int, Detection, Stance]] = []
        part = len(cluster_of)
        for k, idx in enumerate(clusters):
            rest = idx
            # Objects that touch share a cluster: a confident match that explains only part of it is
            # kept, its points are explained away, and the rest is matched again.
            for _ in range(0 if used[k] or k >= first_fragment else MAX_OBJECTS_PER_CLUSTER):
                matches = self._match_cluster(scene, rest, up, stance.rest)
                if not matches:
                    break
                out.extend((part, det, stance) for det, _ in matches)
                cluster_of[part] = k
                part += 1
                det, explained = matches[0]
                rest = rest[~explained]
                if det.coverage >= c.min_coverage or len(rest) < c.cluster_min_points:
                    break
            if support is None or used[k]:
                continue
            # What no match explained may hold objects that stand so close that they merged into one
            # cluster, hiding parts of each other: its descriptor is no object's. Each object is
            # stood on the support at pieces spread over the rest, and verification judges it.
            pieces = self._piece_centres(scene.points, rest)
            target = Target.of(scene, rest) if pieces else None
            for oid, centres in pieces.items():
                model = self.db.models[oid]
                starts = standing_starts(model.points @ stance.rest.T, centres, support) @ make_pose(stance.rest)
                match = self._score(model, target, starts, up, fitness_to_verify=PIECE_FITNESS, rest=stance.rest)
                if match is not None:
                    out.append((part, match[0], stance))
                    # Fragments are no cluster: the rule for a match explaining part of one does not apply.
                    cluster_of[part] = k if k < first_fragment else None
                    part += 1
        return out

    def seen_through(self, view: DepthView, object_id: str, camera_T_object: np.ndarray) -> Verdict | None:
        """Another camera's judgement of a detection: the verdict of the object posed in that camera's
        frame (camera_T_object (4, 4)) against its depth view, if it contradicts the detection (the
        camera measured surfaces behind where the object would be: under ``min_cross_view_fitness``
        of the ``CROSS_VIEW_PIXELS`` or more it could judge), else None."""
        model, c = self.db.models[object_id], self.config
        v = verdict(view, model.points, model.normals, camera_T_object, c.icp_distance_m, c.plane_noise_per_m2,
                    spacing_m=c.descriptor.voxel_m)
        judged = v.inliers + v.violations
        return v if judged >= CROSS_VIEW_PIXELS and v.fitness < c.min_cross_view_fitness else None

    def _verdict(self, view: DepthView, det: Detection, planes: np.ndarray) -> Verdict:
        """A hypothesis judged against the frame's depth and the supports removed from it
        (``recognition.verify``)."""
        model, c = self.db.models[det.object_id], self.config
        return verdict(view, model.points, model.normals, det.camera_T_object, c.icp_distance_m, c.plane_noise_per_m2, planes,
                       model.chroma_range, c.colour_tolerance, c.descriptor.voxel_m)  # fmt: skip

    def _match_cluster(
        self, scene: SceneCloud, idx: np.ndarray, up: np.ndarray | None, rest: np.ndarray | None = None
    ) -> list[tuple[Detection, np.ndarray]]:
        """VFH nearest views -> roll candidates -> ICP: every object's accepted hypothesis, best first,
        each with the mask of the cluster points it explains."""
        if len(self._owners) == 0:
            return []
        desc = describe(scene.points[idx], scene.normals[idx], self.config.descriptor)
        dist = np.abs(self._views.vfh - desc.vfh).sum(axis=1)  # L1 between histograms
        rolls_of = roll_peaks(roll_correlations(desc.roll, self._views.roll), self.config.roll_peaks)
        # The nearest views of every object, not of the database as a whole: on noisy clusters the
        # descriptor ranks objects poorly, and ICP's fitness is the better judge between them.
        want = self.config.candidates * self.config.roll_peaks
        chosen: dict[str, tuple[list[int], list[float]]] = {}
        for row in np.argsort(dist, kind="stable"):
            rows, rolls = chosen.setdefault(self._owners[row], ([], []))
            if len(rolls) >= want:
                continue
            for roll in rolls_of[row]:
                rows.append(int(row))
                rolls.append(roll)
        matches = []
        target = Target.of(scene, idx)
        for oid, (rows, rolls) in chosen.items():
            camera_T_view = views_to_scene(desc.centroid, self._views.centroid[rows], self._view_to_z[rows],
                                           np.array(rolls))
            match = self._score(self.db.models[oid], target, camera_T_view @ self._views.view_T_object[rows], up,
                                turns=True, rest=rest)
            if match is not None:
                matches.append(match)
        return sorted(matches, key=lambda m: _rank(m[0]), reverse=True)

    def _score(
        self,
        model: ObjectModel,
        target: Target,
        starts: list[np.ndarray],
        up: np.ndarray | None,
        from_prior: bool = False,
        fitness_to_verify: float | None = None,
        turns: bool = False,
        rest: np.ndarray | None = None,
    ) -> tuple[Detection, np.ndarray] | None:
        """Coarse ICP from each start onto the cluster, fine ICP from the best few; the best result if
        it passes the acceptance tests, with the mask of the cluster points it explains.

        up: world up in the camera frame (None: no upright test; nor for a model from a captured cloud,
        whose frame is its camera's, not the object's). turns: with ``up``, also try the start
        that overlaps the target best turned about its upright axis (``_turned``). Accepted: fitness,
        coverage and RMSE within bounds; or, for a cluster several objects share, a fitness of at least
        min_fitness_shared (``fitness_to_verify``, when given) with enough explained points to be a
        cluster itself. rest (3, 3): the side the object rests on (``Stance``; None: its base), which
        the upright test and the turns then take for its base.
        """
        c = self.config
        up = up if model.stands_on_z else None
        # The upright machinery works on the object turned to rest on its base: camera_T_rest =
        # camera_T_object @ from_rest, and back @ to_rest.
        to_rest = make_pose(rest) if rest is not None else np.eye(4)  # rest_T_object
        from_rest = invert_pose(to_rest)
        centre = to_rest[:3, :3] @ self._centre[model.object_id]  # in the rest frame
        # Every start gets a cheap coarse ICP with a thinned model; the best few are refined whole.
        sparse_points, sparse_normals = self._sparse[model.object_id]
        poses = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
        if up is not None:
            poses = _stand_up(poses @ from_rest, up, centre) @ to_rest
        facings = facing_camera(sparse_points, sparse_normals, poses, target.image)
        if turns and up is not None:
            shares = self._overlap(sparse_points, facings, poses, target.index)
            turned = _turned(poses[np.argmax(shares)] @ from_rest, centre) @ to_rest
            turned_facings = facing_camera(sparse_points, sparse_normals, turned, target.image)
            shares = np.r_[shares, self._overlap(sparse_points, turned_facings, turned, target.index)]
            poses, facings = np.concatenate([poses, turned]), np.concatenate([facings, turned_facings])
            keep = np.argsort(-shares, kind="stable")[:ICP_STARTS]
            poses, facings = poses[keep], facings[keep]
        elif len(poses) > ICP_STARTS:
            keep = np.argsort(-self._overlap(sparse_points, facings, poses, target.index), kind="stable")[:ICP_STARTS]
            poses, facings = poses[keep], facings[keep]
        screened: list[IcpResult] = []
        for start, facing in zip(poses, facings):
            res = icp_pass(sparse_points[facing], target.cloud, start, 2.0 * c.icp_distance_m, SCREEN_ITERATIONS,
                           max_shift_m=model.diameter_m)
            if res.fitness > 0 and _upright(res.camera_T_object @ from_rest, up):  # else a symmetric shape's mirror image
                screened.append(res)
        screened.sort(key=lambda r: (r.fitness, -r.rmse_m), reverse=True)
        dense_points, dense_normals = self._dense[model.object_id]
        best: IcpResult | None = None
        # A start that explains under min_fitness of the model even at twice the final distance is
        # not refined: no refined start from that low has passed in the benchmark's frames.
        refined: list[np.ndarray] = []
        shared_fitness = c.min_fitness_shared if fitness_to_verify is None else fitness_to_verify
        floor = min(c.min_fitness, shared_fitness)
        for coarse in [r for r in screened[:REFINED_STARTS] if r.fitness >= floor]:
            if any(_same_pose(coarse.camera_T_object, done) for done in refined):
                continue  # two starts that screened into one pose refine into one pose
            refined.append(coarse.camera_T_object)
            res = refine_icp(dense_points, dense_normals, target.cloud, coarse.camera_T_object, c.icp_distance_m,
                             c.icp_iterations, max_shift_m=model.diameter_m, index=target.index, image=target.image)
            if not _upright(res.camera_T_object @ from_rest, up):
                continue
            if best is None or (res.fitness, -res.rmse_m) > (best.fitness, -best.rmse_m):
                best = res
        if best is None:
            return None
        explained = self._explained(model.object_id, best.camera_T_object, target.points)
        coverage = float(explained.mean()) if len(explained) else 0.0
        whole = best.fitness >= c.min_fitness and coverage >= c.min_coverage
        shared = best.fitness >= shared_fitness and explained.sum() >= c.cluster_min_points
        ok = (whole or shared) and best.rmse_m <= c.max_rmse_m
        log.debug("%s: fitness %.2f coverage %.2f rmse %.4f -> %s", model.object_id, best.fitness, coverage,
                  best.rmse_m, "accepted" if ok else "rejected")
        if not ok:
            return None
        det = Detection(model.object_id, best.camera_T_object, best.fitness, coverage, best.rmse_m,
                        int(explained.sum()), from_prior)
        return det, explained

    def _fragments(self, merged: list[np.ndarray], parts: list[np.ndarray], shed: list[np.ndarray], n_points: int) -> list[np.ndarray]:
        """Where a small object half hidden among larger ones may be, when their cluster (one of
        ``merged``) was split: its visible surface falls apart at the finer tolerance, into crumbs
        the split shed (``shed``) and parts too small to be any whole object. Per shed set, those
        crumbs with the small ``parts`` of the same merged cluster, if they hold enough points for
        the pieces path to try the smallest object; no view matches fragments."""
        if not shed:
            return []
        origin = np.full(n_points, -1)
        for k, idx in enumerate(merged):
            origin[idx] = k
        small = [idx for idx in parts if len(idx) < SMALL_PART * self._smallest_model]
        out = []
        for crumbs in shed:
            idx = np.concatenate([crumbs] + [p for p in small if origin[p[0]] == origin[crumbs[0]]])
            if len(idx) >= max(self.config.cluster_min_points, self._smallest_piece):
                out.append(idx)
        return out

    def _piece_centres(self, points: np.ndarray, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Per object, the centroids (K, 3) of pieces of the points ``idx`` into ``points`` (N, 3): the
        points within the object's radius of seeds spread over them (farthest-point sampling from
        the one nearest their centroid, at most MAX_SEEDS, half a radius apart at least)."""
        out: dict[str, np.ndarray] = {}
        pts = points[idx]
        for oid, mdl in self.db.models.items():
            if len(idx) < max(self.config.cluster_min_points, PIECE_SHARE * len(mdl.points)):
                continue
            r = 0.5 * mdl.diameter_m
            seeds = [int(np.argmin(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
            dist = np.linalg.norm(pts - pts[seeds[0]], axis=1)
            while len(seeds) < MAX_SEEDS and dist.max() > 0.5 * r:
                seeds.append(int(np.argmax(dist)))
                dist = np.minimum(dist, np.linalg.norm(pts - pts[seeds[-1]], axis=1))
            pieces = [pts[np.linalg.norm(pts - pts[seed], axis=1) <= r] for seed in seeds]
            centres = [p.mean(axis=0) for p in pieces if len(p) >= self.config.cluster_min_points]
            if centres:
                out[oid] = np.array(centres)
        return out

    def _overlap(self, points: np.ndarray, facing: np.ndarray, poses: np.ndarray, target: PointIndex) -> np.ndarray:
        """Per start pose (S, 4, 4): the share (S,) of its facing model points (N, 3; ``facing`` (S, N))
        within the coarse ICP's distance of the target's points."""
        placed = (points @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3])[facing]  # only facing ones count
        hits = np.bincount(np.nonzero(facing)[0], target.within(placed, 2.0 * self.config.icp_distance_m), len(poses))
        return hits / np.maximum(facing.sum(axis=1), 1)

    def _rests(self, det: Detection, found: Iterable[Detection], support: np.ndarray) -> bool:
        """Whether a detection's lowest point is within max_float_m of the support plane (a, b, c, d;
        unit normal up, camera frame), or of the top of a found detection whose footprint it overlaps.

        Nothing in a cell hovers: a pose that fits a surface with its base in the air has fitted the
        wrong surface (a tote fitted over a smaller crate's top).
        """
        limit = self.config.max_float_m
        base = self._heights(det, support).min()
        if base <= limit:
            return True  # the common case: one product of the model's points
        centre, radius = self._footprint(det, support)
        for other in found:
            if abs(self._heights(other, support).max() - base) <= limit:
                other_centre, other_radius = self._footprint(other, support)
                if np.linalg.norm(centre - other_centre) < radius + other_radius:
                    return True
        return False

    def _above(self, det: Detection, points: np.ndarray, found: Iterable[Detection], rest: np.ndarray) -> int:
        """How many of the points (N, 3, camera frame) lie above the posed model's top (its +z up once
        turned by ``rest``, by more than icp_distance_m) and over its footprint (its x-y box there,
        that much narrower: the side of a taller object standing beside it is not on it), that no
        found detection explains."""
        model, tol = self.db.models[det.object_id], self.config.icp_distance_m
        for other in found:
            points = points[~self._explained(other.object_id, other.camera_T_object, points)]
        object_T_camera = invert_pose(det.camera_T_object)
        local = (points @ object_T_camera[:3, :3].T + object_T_camera[:3, 3]) @ rest.T
        model_points = model.points @ rest.T
        lo, hi = model_points.min(axis=0), model_points.max(axis=0)
        over = np.all((local[:, :2] >= lo[:2] + tol) & (local[:, :2] <= hi[:2] - tol), axis=1)
        return int(np.sum(over & (local[:, 2] > hi[2] + tol)))

    def _heights(self, det: Detection, support: np.ndarray) -> np.ndarray:
        """Heights (M,) of the posed model's points above the support (a, b, c, d), m."""
        T, n = det.camera_T_object, support[:3]
        return self.db.models[det.object_id].points @ (T[:3, :3].T @ n) + (T[:3, 3] @ n + support[3])

    def _footprint(self, det: Detection, support: np.ndarray) -> tuple[np.ndarray, float]:
        """The posed model's centre projected on the support (3,), camera frame, and its radius
        along the support (m)."""
        T, n = det.camera_T_object, support[:3]
        points = self.db.models[det.object_id].points @ T[:3, :3].T + T[:3, 3]
        along = points - np.outer(points @ n, n)
        centre = along.mean(axis=0)
        return centre, float(np.linalg.norm(along - centre, axis=1).max())

    def _explained(self, object_id: str, camera_T_object: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Mask (N,) of the cluster points (N, 3), camera frame, within icp_distance_m of the posed model."""
        object_T_camera = invert_pose(camera_T_object)
        local = points @ object_T_camera[:3, :3].T + object_T_camera[:3, 3]
        return self._model_index[object_id].within(local, self.config.icp_distance_m)


def _support(planes: np.ndarray, up: np.ndarray | None) -> np.ndarray | None:
    """Of the removed planes (a, b, c, d; normal towards the camera) that are level (normal within
    20 deg of world up ``up``, camera frame), the one nearest the camera (a table over the floor),
    normalised; None without one or without ``up``."""
    if up is None:
        return None
    unit = planes / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    level = unit[unit[:, :3] @ (up / np.linalg.norm(up)) >= SUPPORT_COS]
    return level[np.argmin(level[:, 3])] if len(level) else None


def standing_starts(model_points: np.ndarray, near: np.ndarray, support: np.ndarray) -> np.ndarray:
    """Poses (K * S, 4, 4), camera frame, of an object standing upright on the support plane (a, b, c,
    d; unit normal towards the camera): its base's centre (the model's lowest points, object frame
    (M, 3)) below each of ``near`` (K, 3) or (3,) and half its smaller width further from the
    camera, at yaws YAW_STEP_DEG apart; S of them per point, the ones below it first."""
    n, d = support[:3], support[3]
    near = np.atleast_2d(near)
    foot = near - (near @ n + d)[:, None] * n  # onto the plane
    away = foot - (foot @ n)[:, None] * n  # the camera's viewing direction along the plane
    # Looking straight down: any direction along the plane.
    anywhere = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    away = np.where(np.linalg.norm(away, axis=1, keepdims=True) < 1e-6, anywhere, away)
    away /= np.linalg.norm(away, axis=1, keepdims=True)
    plane_T_yaw0 = np.stack([away, np.cross(n, away), np.broadcast_to(n, away.shape)], axis=2)  # (K, 3, 3)
    yaw_R = rot_z(np.radians(np.arange(0.0, 360.0, YAW_STEP_DEG)))  # (Y, 3, 3)
    R = plane_T_yaw0[:, None] @ yaw_R  # (K, Y, 3, 3)
    lo, hi = model_points.min(axis=0), model_points.max(axis=0)
    base = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    out = np.tile(np.eye(4), (len(near), 2, len(yaw_R), 1, 1))
    out[..., :3, :3] = R[:, None]
    for i, back in enumerate((0.0, 0.5 * min(hi[0] - lo[0], hi[1] - lo[1]))):
        out[:, i, :, :3, 3] = (foot + back * away)[:, None] - R @ base
    return out.reshape(-1, 4, 4)


def _thinned(model: ObjectModel, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n of the model's points and normals, evenly through its (voxel-ordered) list."""
    keep = np.unique(np.linspace(0, len(model.points) - 1, min(n, len(model.points))).astype(np.int64))
    return model.points[keep], model.normals[keep]


def _upright(camera_T_object: np.ndarray, up: np.ndarray | None) -> bool:
    """Whether the object's +z is within 45 deg of world up (always, when up is unknown)."""
    return up is None or camera_T_object[:3, 2] @ up >= UPRIGHT_COS


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two poses (4, 4) are within SAME_POSE_M and SAME_POSE_RAD of each other."""
    return bool(np.linalg.norm(a[:3, 3] - b[:3, 3]) <= SAME_POSE_M and rotation_angle(a[:3, :3], b[:3, :3]) <= SAME_POSE_RAD)


def _turned(camera_T_object: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The upright pose (4, 4) turned about the object's own z axis through its centre (object
    frame, m) by every YAW_STEP_DEG but 0: (S, 4, 4).

    A view's descriptor and roll pin a box's yaw poorly: a 30 x 22 cm tote turned by 90 deg
    overhangs its own footprint by 4 cm, and ICP from there stays there."""
    R = rot_z(np.radians(np.arange(YAW_STEP_DEG, 360.0, YAW_STEP_DEG)))  # (S, 3, 3)
    out = np.tile(camera_T_object, (len(R), 1, 1))
    out[:, :3, :3] = camera_T_object[:3, :3] @ R
    out[:, :3, 3] = (centre - R @ centre) @ camera_T_object[:3, :3].T + camera_T_object[:3, 3]
    return out


def _stand_up(camera_T_objects: np.ndarray, up: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The poses (S, 4, 4) that are not upright turned, about the object's centre (object frame, m),
    so that their +z is world up (the smallest turn; a half turn about the object's x axis when
    exactly upside down).

    A symmetric shape matched from the VFH of a single view is as likely upside down as not; for
    objects that stand on their base the upright twin is the physical one.
    """
    out = np.array(camera_T_objects, dtype=np.float64)
    down = out[:, :3, 2] @ up < UPRIGHT_COS
    if not down.any():
        return out
    T = out[down]
    R = rotation_between(T[:, :3, 2], up, half_turn_axis=T[:, :3, 0])
    pivot = T[:, :3, :3] @ centre + T[:, :3, 3]
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = np.einsum("sij,sj->si", R, T[:, :3, 3] - pivot) + pivot
    out[down] = T
    return out


def _cluster_near(points: np.ndarray, clusters: list[np.ndarray], position: np.ndarray, radius: float) -> int | None:
    """The cluster with the most points within radius of position, if any."""
    counts = [int(np.sum(np.linalg.norm(points[idx] - position, axis=1) <= radius)) for idx in clusters]
    if not counts or max(counts) == 0:
        return None
    return int(np.argmax(counts))


def _rank(d: Detection) -> tuple[float, float]:
    """Sort key of detections, better last: explained share of model times share of cluster, then RMSE."""
    return d.fitness * d.coverage, -d.rmse_m
