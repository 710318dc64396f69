"""Candidate poses of a model database's objects in a prepared scene: the making of hypotheses.

Per cluster: VFH -> the nearest views of every object -> camera-roll alignment -> coarse ICP from
every start, fine ICP from the best few -> accept on fitness, coverage and RMSE. Objects that
touch share a cluster: a confident match explaining part of it is explained away and the rest is
matched again. When objects stand on a known support (``Stance``), each is also stood on it at
pieces of what no match explained (with colour, also where its colours show there), and at
fragments a split of merged objects shed. Nothing here
decides what the frame holds: every candidate goes on to the joint resolution (``recognition.resolve``).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from recognition.align import (
    RAN_OFF,
    IcpResult,
    ImageBounds,
    Surface,
    align_to_z,
    damped_icp,
    facing_camera,
    icp_passes,
    refine_icp,
    roll_correlations,
    roll_peaks,
    rot_z,
    views_to_scene,
)
from recognition.cloud import PointIndex
from recognition.config import RecognitionConfig
from recognition.descriptor import ClusterDescription, describe
from recognition.models import ModelDatabase, ObjectModel
from recognition.segment import PointGraph, euclidean_clusters
from recognition.verify import distinct_from_grey, paled, palest
from schemas.geometry import invert_pose, make_pose, rotation_angle, rotation_between

log = logging.getLogger(__name__)
#: An upright object's +z is within 45 deg of world up.
UPRIGHT_COS = float(np.cos(np.radians(45.0)))
#: Touching objects explained away one after another in one cluster, at most.
MAX_OBJECTS_PER_CLUSTER = 3
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
#: Pieces of a cluster no match explained (``Matcher._piece_centres``): seeds per object and cluster ...
MAX_SEEDS = 4
#: ... a piece tried for an object only if the cluster's rest holds this share of its model's points
#: (a view shows about half of a surface, and verification wants 40 % of that) ...
PIECE_SHARE = 0.1
#: ... and where the rest shows an object's colour (``Matcher._colour_seeds``), at most this many more ...
COLOUR_SEEDS = 2
#: ... the yaws an object is stood on the support at ...
YAW_STEP_DEG = 30
#: ... and the fitness from which a piece's hypothesis goes on to verification, which judges it on
#: the surface the camera should see (a partly hidden object's fitness over its facing side is low).
PIECE_FITNESS = 0.2
#: A part of a split cluster with fewer points than this share of the smallest model's is no whole
#: object (a view shows about half a surface): it may be a fragment of one (``Matcher.fragments``).
SMALL_PART = 0.5
#: The sides an object may lie on besides its base (``Stance.rest``): turns of its frame that
#: bring each side's outward normal (+-x, +-y) to -z. Not its top: a box or a can upside down fits
#: a standing one as well, and its frame would be reported upside down.
RESTS = tuple(
    rotation_between(np.array(side, float), [0.0, 0.0, -1.0]) for side in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))
)
#: Two sides are alike when the object lain on one, turned about the vertical by some multiple of
#: YAW_STEP_DEG, is the object lain on the other: 99 % of its points within this many voxels of it
#: (the same surface sampled twice: up to 0.5; a box's long side against its short one: 3; a block
#: of a twentieth of its surface at another place: 2.5). Alike sides make the same candidates, so
#: only the first is tried (a can on one side of four, a box on two).
ALIKE_VOXELS = 1.0
#: rg-chromaticity cells per axis of an object's palette (``palette``): 0.01 wide.
PALETTE_CELLS = 100


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
    #: Only damped steps (``Matcher.score``) or a refit to the depth reached it: taken only with its colour
    #: agreeing where a grey surface's would not (``Verdict.distinct_agreement``).
    needs_colour: bool = False


@dataclass(frozen=True)
class Stance:
    """How objects stand in a frame: world up in the camera frame (3,) for the upright test (None:
    any way up), the level plane they rest on (a, b, c, d; unit normal towards the camera; None: no
    rest test; the pieces path needs it and ``up``: ``resting``), and the side they rest on: ``rest``
    (3, 3) turns the object's frame so that the side's outward normal is -z (identity: standing on
    its base)."""

    up: np.ndarray | None
    support: np.ndarray | None
    rest: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def resting(self) -> bool:
        """Whether objects stand or lie on the support (an up and a support): a free fit with a
        support is only rest-tested."""
        return self.up is not None and self.support is not None

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
    planes: np.ndarray = field(
        default_factory=lambda: np.zeros((0, 4))
    )  # the dominant planes removed (P, 4), ``remove_planes``
    image: ImageBounds | None = None  # the image an organised cloud was measured in
    #: Each point's rg-chromaticity (N, 2), NaN: none; None: the frame has no colour (``Matcher._palette_mask``).
    chroma: np.ndarray | None = None
    #: Each part's target, descriptor and chosen views, by its point indices' bytes: every stance a
    #: frame is tried in matches the same parts (``Matcher.target``, ``Matcher._looks``) ...
    targets: dict[bytes, Target] = field(default_factory=dict)
    looks: dict[bytes, tuple[ClusterDescription, dict, Target]] = field(default_factory=dict)
    #: ... and the pieces path's piece centres by object (``Matcher._piece_centres``).
    pieces: dict[bytes, dict[str, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class Target:
    """Scene points hypotheses are fitted to (a cluster, or what is left of one), camera frame:
    ``points`` (N, 3), the same with their normals and index for ICP. Built once per part for every
    object tried on it."""

    points: np.ndarray
    surface: Surface
    image: ImageBounds | None = None  # model points landing outside it are not looked for
    chroma: np.ndarray | None = None  # the points' rg-chromaticity (N, 2), NaN: none (``SceneCloud.chroma``)
    #: By object id: which points show one of its colours no grey surface has (``Matcher._palette_mask``)
    #: and the colour seeds among them (``Matcher._colour_seeds``), worked out once a frame.
    palette_masks: dict[str, np.ndarray] = field(default_factory=dict, compare=False)
    seeds: dict[str, list[np.ndarray]] = field(default_factory=dict, compare=False)

    @classmethod
    def of(cls, scene: SceneCloud, idx: np.ndarray) -> Target:
        chroma = None if scene.chroma is None else scene.chroma[idx]
        return cls(scene.points[idx], Surface.of(scene.points[idx], scene.normals[idx]), scene.image, chroma)

    @property
    def index(self) -> PointIndex:
        return self.surface.index


@dataclass(frozen=True)
class Candidate:
    """A hypothesis for the joint resolution: the part of the scene it was fitted to (numbered per
    frame; a part is one object at most), the cluster that part came from (None: none of its own,
    as a prior's hint or fragments), the detection, and how the object stands."""

    part: int
    cluster: int | None
    detection: Detection
    stance: Stance


class Matcher:
    """Candidate poses of a model database's objects in prepared camera-frame scenes."""

    def __init__(self, database: ModelDatabase, config: RecognitionConfig) -> None:
        self.db = database
        self.config = config
        self._views, self._owners = database.view_table()
        self._view_to_z = np.array([align_to_z(c) for c in self._views.centroid]).reshape(-1, 3, 3)
        self._smallest_model = min((len(mdl.points) for mdl in database.models.values()), default=0)
        # The fewest points a piece may hold for the pieces path to try the smallest object on it.
        self._smallest_piece = int(PIECE_SHARE * self._smallest_model)
        self._sparse = {oid: _thinned(mdl, SCREEN_POINTS) for oid, mdl in database.models.items()}
        #: Each model's points and normals the fine ICP fits (REFINE_POINTS of them); the resolution's
        #: turns about the upright axis are fitted with them too.
        self.dense = {oid: _thinned(mdl, REFINE_POINTS) for oid, mdl in database.models.items()}
        #: Each whole model's point index, built once: which scene points a pose explains is asked
        #: of every accepted hypothesis, here and in the resolution.
        self.indexes = {oid: PointIndex(mdl.points) for oid, mdl in database.models.items()}
        self._rests = {
            oid: distinct_rests(mdl.points, ALIKE_VOXELS * config.descriptor.voxel_m)
            for oid, mdl in database.models.items()
        }
        self._palettes = {
            oid: palette(mdl.chroma_range, config.colour_tolerance, config.colour_min_saturation)
            for oid, mdl in database.models.items()
            if mdl.colours is not None
        }

    def tries(self, object_id: str, stance: Stance) -> bool:
        """Whether the object is tried in this stance: lying, only on the first of sides alike."""
        return not stance.lying or any(np.array_equal(stance.rest, r) for r in self._rests[object_id])

    def explained(self, object_id: str, camera_T_object: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Mask (N,) of the scene points (N, 3), camera frame, within icp_distance_m of the posed model."""
        return explained_by(self.indexes[object_id], camera_T_object, points, self.config.icp_distance_m)

    def candidates(
        self,
        scene: SceneCloud,
        clusters: list[np.ndarray],
        first_fragment: int,
        stance: Stance,
        parts: Iterator[int],
    ) -> list[Candidate]:
        """Every candidate for the clusters (indices into the scene's points; from ``first_fragment``
        on, fragments: the pieces path only), with objects standing as ``stance`` says; parts numbered
        by ``parts``."""
        c, up, support = self.config, stance.up, stance.support
        out: list[Candidate] = []
        for k, idx in enumerate(clusters):
            rest = idx
            # Objects that touch share a cluster: a confident match that explains only part of it is
            # kept, its points are explained away, and the rest is matched again.
            for _ in range(0 if k >= first_fragment else MAX_OBJECTS_PER_CLUSTER):
                matches = self.match_cluster(scene, rest, stance)
                if not matches:
                    break
                part = next(parts)
                out.extend(Candidate(part, k, det, stance) for det, _ in matches)
                det, explained = matches[0]
                if det.needs_colour:
                    break  # weaker evidence explains nothing away: the rest is stood at pieces whole
                rest = rest[~explained]
                if det.coverage >= c.min_coverage or len(rest) < c.cluster_min_points:
                    break
            if not stance.resting:
                continue
            # What no match explained may hold objects that stand so close that they merged into one
            # cluster, hiding parts of each other: its descriptor is no object's. Each object is
            # stood on the support at pieces spread over the rest, and verification judges it.
            pieces = self._piece_centres(scene, rest)
            target = self.target(scene, rest) if pieces else None
            for oid, centres in pieces.items():
                if not self.tries(oid, stance) or (stance.lying and not self._shows_colour(target, oid)):
                    continue
                model = self.db.models[oid]
                # Where the rest shows the object's colour, a piece there is tried on its own: a small
                # object merged with larger ones lies near no ball's centroid.
                for near in [centres] + self._colour_seeds(scene, rest, oid):
                    starts = standing_starts(model.points @ stance.rest.T, near, support) @ make_pose(stance.rest)
                    match = self.score(model, target, starts, up, fitness_to_verify=PIECE_FITNESS, rest=stance.rest)
                    if match is not None:
                        # Fragments are no cluster: the rule for a match explaining part of one does not apply.
                        out.append(Candidate(next(parts), k if k < first_fragment else None, match[0], stance))
        return out

    def match_cluster(self, scene: SceneCloud, idx: np.ndarray, stance: Stance) -> list[tuple[Detection, np.ndarray]]:
        """VFH nearest views -> roll candidates -> ICP: every object's accepted hypothesis standing as
        ``stance`` says, best first (those only damped steps reached after the rest), each with the
        mask of the cluster points it explains."""
        if len(self._owners) == 0:
            return []
        desc, chosen, target = self._looks(scene, idx)
        matches = []
        for oid, (rows, rolls) in chosen.items():
            if not self.tries(oid, stance) or (stance.lying and not self._shows_colour(target, oid)):
                continue
            camera_T_view = views_to_scene(
                desc.centroid, self._views.centroid[rows], self._view_to_z[rows], np.array(rolls)
            )
            match = self.score(
                self.db.models[oid],
                target,
                camera_T_view @ self._views.view_T_object[rows],
                stance.up,
                turns=True,
                rest=stance.rest,
            )
            if match is not None:
                matches.append(match)
        # Those only damped steps reached last: the first match is what the cluster's rest is matched
        # without, and a fit on weaker evidence is not to decide that over one Open3D's steps found.
        return sorted(matches, key=lambda m: (not m[0].needs_colour, rank(m[0])), reverse=True)

    def _looks(
        self, scene: SceneCloud, idx: np.ndarray
    ) -> tuple[ClusterDescription, dict[str, tuple[list[int], list[float]]], Target]:
        """A part's (``idx`` into the scene's points) descriptor, every object's nearest views with
        their roll candidates (view rows, rolls in rad), and its target; computed once a frame."""
        key = idx.tobytes()
        if key in scene.looks:
            return scene.looks[key]
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
        scene.looks[key] = desc, chosen, self.target(scene, idx)
        return scene.looks[key]

    def score(
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
        it passes the acceptance tests, with the mask of the cluster points it explains. If none
        does, in a frame with colour and for a model with colours, the start Open3D's steps ran off
        from with the most overlap is screened again with damped ones (``Detection.needs_colour``).

        up: world up in the camera frame (None: no upright test; nor for a model from a captured cloud,
        whose frame is its camera's, not the object's). turns: with ``up``, also try the start
        that overlaps the target best turned about its upright axis (``turned_about_z``). Accepted: fitness,
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
        centre = to_rest[:3, :3] @ model.centre  # in the rest frame
        # Every start gets a cheap coarse ICP with a thinned model; the best few are refined whole.
        sparse_points, sparse_normals = self._sparse[model.object_id]
        poses = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
        if up is not None:
            poses = stand_up(poses @ from_rest, up, centre) @ to_rest
        facings = facing_camera(sparse_points, sparse_normals, poses, target.image)
        if turns and up is not None:
            shares = self._overlap(sparse_points, facings, poses, target.index)
            turned = turned_about_z(poses[np.argmax(shares)] @ from_rest, centre) @ to_rest
            turned_facings = facing_camera(sparse_points, sparse_normals, turned, target.image)
            shares = np.r_[shares, self._overlap(sparse_points, turned_facings, turned, target.index)]
            poses, facings = np.concatenate([poses, turned]), np.concatenate([facings, turned_facings])
            keep = np.argsort(-shares, kind="stable")[:ICP_STARTS]
            poses, facings, shares = poses[keep], facings[keep], shares[keep]
        elif len(poses) > ICP_STARTS:
            shares = self._overlap(sparse_points, facings, poses, target.index)
            keep = np.argsort(-shares, kind="stable")[:ICP_STARTS]
            poses, facings, shares = poses[keep], facings[keep], shares[keep]
        else:
            shares = None
        passes = icp_passes(
            sparse_points,
            facings,
            target.surface,
            poses,
            2.0 * c.icp_distance_m,
            SCREEN_ITERATIONS,
            max_shift_m=model.diameter_m,
        )
        # Not upright after the pass: a symmetric shape's mirror image.
        screened = [res for res in passes if res.fitness > 0 and _upright(res.camera_T_object @ from_rest, up)]
        shared_fitness = c.min_fitness_shared if fitness_to_verify is None else fitness_to_verify
        found = self._fine_fit(model, target, screened, up, from_rest, shared_fitness, from_prior)
        if found is not None or not self._shows_colour(target, model.object_id):
            return found
        # Nothing passed. Open3D's undamped steps run off a small curved patch: the start with the
        # most overlap they ran off from (fitness RAN_OFF under its share) is screened again with
        # damped ones (``damped_icp``). What that finds needs its colour to agree where a grey
        # surface's would not: without it such fits took the milk carton (a model without colour)
        # for a white roll at 3.2 m, and its coloured model for a pale cabinet's edge.
        shares = self._overlap(sparse_points, facings, poses, target.index) if shares is None else shares
        floor = min(c.min_fitness, shared_fitness)  # as the fine fit's: a start under it is not refined
        ran_off = [k for k, res in enumerate(passes) if res.fitness < shares[k] - RAN_OFF and shares[k] >= floor]
        if not ran_off:
            return None
        k = max(ran_off, key=lambda k: shares[k])
        damped = damped_icp(
            sparse_points[facings[k]],
            target.surface,
            poses[k],
            2.0 * c.icp_distance_m,
            SCREEN_ITERATIONS,
            max_shift_m=model.diameter_m,
        )
        if damped.fitness <= 0 or not _upright(damped.camera_T_object @ from_rest, up):
            return None
        return self._fine_fit(model, target, [damped], up, from_rest, shared_fitness, from_prior, needs_colour=True)

    def _fine_fit(
        self,
        model: ObjectModel,
        target: Target,
        screened: list[IcpResult],
        up: np.ndarray | None,
        from_rest: np.ndarray,
        shared_fitness: float,
        from_prior: bool,
        needs_colour: bool = False,
    ) -> tuple[Detection, np.ndarray] | None:
        """The best few screened poses refined with the whole model (``refine_icp``): the best result,
        with the mask of the target points it explains, if it passes ``score``'s acceptance tests
        (shared_fitness: what a match on a cluster several objects share needs)."""
        c = self.config
        screened = sorted(screened, key=lambda r: (r.fitness, -r.rmse_m), reverse=True)
        dense_points, dense_normals = self.dense[model.object_id]
        best: IcpResult | None = None
        # A start that explains under min_fitness of the model even at twice the final distance is
        # not refined: no refined start from that low has passed in the benchmark's frames.
        refined: list[np.ndarray] = []
        floor = min(c.min_fitness, shared_fitness)
        for coarse in [r for r in screened[:REFINED_STARTS] if r.fitness >= floor]:
            if any(_same_pose(coarse.camera_T_object, done) for done in refined):
                continue  # two starts that screened into one pose refine into one pose
            refined.append(coarse.camera_T_object)
            res = refine_icp(
                dense_points,
                dense_normals,
                target.surface,
                coarse.camera_T_object,
                c.icp_distance_m,
                c.icp_iterations,
                max_shift_m=model.diameter_m,
                image=target.image,
            )
            if not _upright(res.camera_T_object @ from_rest, up):
                continue
            if best is None or (res.fitness, -res.rmse_m) > (best.fitness, -best.rmse_m):
                best = res
        if best is None:
            return None
        explained = self.explained(model.object_id, best.camera_T_object, target.points)
        coverage = float(explained.mean()) if len(explained) else 0.0
        whole = best.fitness >= c.min_fitness and coverage >= c.min_coverage
        shared = best.fitness >= shared_fitness and explained.sum() >= c.cluster_min_points
        ok = (whole or shared) and best.rmse_m <= c.max_rmse_m
        log.debug(
            "%s: fitness %.2f coverage %.2f rmse %.4f -> %s",
            model.object_id,
            best.fitness,
            coverage,
            best.rmse_m,
            "accepted" if ok else "rejected",
        )
        if not ok:
            return None
        det = Detection(
            model.object_id,
            best.camera_T_object,
            best.fitness,
            coverage,
            best.rmse_m,
            int(explained.sum()),
            from_prior,
            needs_colour,
        )
        return det, explained

    def fragments(
        self, merged: list[np.ndarray], parts: list[np.ndarray], shed: list[np.ndarray], n_points: int
    ) -> list[np.ndarray]:
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

    def target(self, scene: SceneCloud, idx: np.ndarray) -> Target:
        """A part's (``idx`` into the scene's points) target; built once a frame, for the matching, the
        pieces path and a prior's check alike (a cluster no match explained is both of the first)."""
        key = idx.tobytes()
        if key not in scene.targets:
            scene.targets[key] = Target.of(scene, idx)
        return scene.targets[key]

    def _piece_centres(self, scene: SceneCloud, idx: np.ndarray) -> dict[str, np.ndarray]:
        """Per object, the centroids (K, 3) of pieces of the points ``idx`` into the scene's: the
        points within the object's radius of seeds spread over them (farthest-point sampling from
        the one nearest their centroid, at most MAX_SEEDS, half a radius apart at least). Computed
        once a frame per part."""
        key = idx.tobytes()
        if key in scene.pieces:
            return scene.pieces[key]
        out: dict[str, np.ndarray] = {}
        pts = scene.points[idx]
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
        scene.pieces[key] = out
        return out

    def _shows_colour(self, target: Target, object_id: str) -> bool:
        """Whether any of the target's points shows one of the object's colours that no grey surface
        has (``palette``; never without colour). Where none does, a hypothesis that needs its colour
        to agree there (lying, or reached by damped steps; ``Detection.needs_colour``) cannot pass
        verification: an agreeing pixel has such a colour, and the part's points sample its pixels
        at every voxel."""
        return bool(self._palette_mask(target, object_id).any())

    def _palette_mask(self, target: Target, object_id: str) -> np.ndarray:
        """Mask (N,) of the target's points whose chromaticity lies in the object's ``palette`` (all
        False without colour); once per target and object: every stance asks it again."""
        if object_id not in target.palette_masks:
            table, chroma = self._palettes.get(object_id), target.chroma
            if table is None or chroma is None:
                mask = np.zeros(len(target.points), dtype=bool)
            else:
                with np.errstate(invalid="ignore"):
                    vivid = np.all(np.isfinite(chroma), axis=1) & np.any(
                        np.abs(chroma - 1 / 3) > self.config.colour_tolerance, axis=1
                    )
                cell = np.clip((np.nan_to_num(chroma) * PALETTE_CELLS).astype(np.int64), 0, PALETTE_CELLS - 1)
                mask = vivid & table[cell[:, 0], cell[:, 1]]
            target.palette_masks[object_id] = mask
        return target.palette_masks[object_id]

    def _colour_seeds(self, scene: SceneCloud, idx: np.ndarray, object_id: str) -> list[np.ndarray]:
        """Centroids (3,) of the groups (clustered at the clustering distance, COLOUR_SEEDS largest,
        cluster_min_points or more) of the points ``idx`` whose chromaticity is one of the object's
        that no grey surface has (``_palette_mask``); none without colour. Once a frame per part and object."""
        target = self.target(scene, idx)
        if object_id not in target.seeds:
            c = self.config
            mine = idx[self._palette_mask(target, object_id)]
            seeds = []
            if len(mine) >= c.cluster_min_points:
                groups = euclidean_clusters(
                    scene.points[mine],
                    c.cluster_tolerance_m,
                    c.cluster_min_points,
                    len(mine),
                    scene.graph.subgraph(mine, c.cluster_tolerance_m),
                )
                seeds = [scene.points[mine[g]].mean(axis=0) for g in groups[:COLOUR_SEEDS]]
            target.seeds[object_id] = seeds
        return target.seeds[object_id]

    def _overlap(self, points: np.ndarray, facing: np.ndarray, poses: np.ndarray, target: PointIndex) -> np.ndarray:
        """Per start pose (S, 4, 4): the share (S,) of its facing model points (N, 3; ``facing`` (S, N))
        within the coarse ICP's distance of the target's points."""
        placed = (points @ poses[:, :3, :3].transpose(0, 2, 1) + poses[:, None, :3, 3])[
            facing
        ]  # only facing ones count
        hits = np.bincount(np.nonzero(facing)[0], target.within(placed, 2.0 * self.config.icp_distance_m), len(poses))
        return hits / np.maximum(facing.sum(axis=1), 1)


def palette(chroma_range: np.ndarray, tolerance: float, min_saturation: float = 1.0) -> np.ndarray:
    """The object's colours a grey surface has not, as a lookup (PALETTE_CELLS, PALETTE_CELLS) over rg-
    chromaticity: every cell within ``tolerance`` of a model point's colours ([r_min, g_min, r_max,
    g_max] (M, 4), ``verify.chroma_ranges``) where those are ``distinct_from_grey``, and of them
    paled as verification pales them (``verify.colour_agrees``: steps of 0.1 in k, each within a
    tolerance of the next)."""
    rows = chroma_range[np.all(np.isfinite(chroma_range), axis=1)]
    rows = rows[distinct_from_grey(rows[:, :2], rows[:, 2:], tolerance)]
    floor = np.clip(palest(rows[:, :2], rows[:, 2:], tolerance), min_saturation, 1.0)[:, None]
    steps = np.linspace(1.0, min_saturation, int(np.ceil(round((1.0 - min_saturation) / 0.1, 9))) + 1)
    rows = np.concatenate([paled(rows, np.maximum(k, floor)) for k in steps])
    lo = np.clip(np.floor((rows[:, :2] - tolerance) * PALETTE_CELLS), 0, PALETTE_CELLS - 1).astype(np.int64)
    hi = np.clip(np.floor((rows[:, 2:] + tolerance) * PALETTE_CELLS), 0, PALETTE_CELLS - 1).astype(np.int64)
    marks = np.zeros((PALETTE_CELLS + 1, PALETTE_CELLS + 1))  # each box as the corners of a 2-D running sum
    np.add.at(marks, (lo[:, 0], lo[:, 1]), 1)
    np.add.at(marks, (hi[:, 0] + 1, lo[:, 1]), -1)
    np.add.at(marks, (lo[:, 0], hi[:, 1] + 1), -1)
    np.add.at(marks, (hi[:, 0] + 1, hi[:, 1] + 1), 1)
    return marks.cumsum(axis=0).cumsum(axis=1)[:PALETTE_CELLS, :PALETTE_CELLS] > 0


def explained_by(index: PointIndex, camera_T_object: np.ndarray, points: np.ndarray, distance_m: float) -> np.ndarray:
    """Mask (N,) of the scene points (N, 3), camera frame, within distance_m of a model posed at
    camera_T_object (4, 4), given its points' index."""
    object_T_camera = invert_pose(camera_T_object)
    return index.within(points @ object_T_camera[:3, :3].T + object_T_camera[:3, 3], distance_m)


def distinct_rests(points: np.ndarray, tolerance_m: float) -> list[np.ndarray]:
    """Of RESTS, those an object (model points (M, 3), object frame) lain on them shows no earlier
    one's shape: the first of each kind of alike sides (``ALIKE_VOXELS``)."""
    yaws = rot_z(np.radians(np.arange(0.0, 360.0, YAW_STEP_DEG)))
    lain = [points @ R.T for R in RESTS]
    lain = [(p - p.mean(axis=0)).astype(np.float32) for p in lain]
    index = [PointIndex(p) for p in lain]
    kept: list[int] = []
    for j, p in enumerate(lain):
        alike = any(
            np.sqrt(np.percentile(index[k].nearest(p @ Y.T.astype(np.float32))[1], 99)) <= tolerance_m
            for k in kept
            for Y in yaws
        )
        if not alike:
            kept.append(j)
    return [RESTS[k] for k in kept]


def round_about_z(points: np.ndarray, tolerance_m: float) -> bool:
    """Whether an object (model points (M, 3), object frame) looks the same turned about its z axis
    through its centre by every YAW_STEP_DEG (a can; not a mug, whose handle moves): 99 % of its
    points within tolerance_m of it, as sides alike are told (``distinct_rests``)."""
    p = (points - points.mean(axis=0)).astype(np.float32)
    index = PointIndex(p)
    yaws = rot_z(np.radians(np.arange(YAW_STEP_DEG, 360.0, YAW_STEP_DEG)))
    return all(np.sqrt(np.percentile(index.nearest(p @ Y.T.astype(np.float32))[1], 99)) <= tolerance_m for Y in yaws)


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
    return bool(
        np.linalg.norm(a[:3, 3] - b[:3, 3]) <= SAME_POSE_M and rotation_angle(a[:3, :3], b[:3, :3]) <= SAME_POSE_RAD
    )


def turned_about_z(camera_T_object: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The upright pose (4, 4) turned about the object's own z axis through its centre (object
    frame, m) by every YAW_STEP_DEG but 0: (S, 4, 4).

    A view's descriptor and roll pin a box's yaw poorly: a 30 x 22 cm tote turned by 90 deg
    overhangs its own footprint by 4 cm, and ICP from there stays there."""
    R = rot_z(np.radians(np.arange(YAW_STEP_DEG, 360.0, YAW_STEP_DEG)))  # (S, 3, 3)
    out = np.tile(camera_T_object, (len(R), 1, 1))
    out[:, :3, :3] = camera_T_object[:3, :3] @ R
    out[:, :3, 3] = (centre - R @ centre) @ camera_T_object[:3, :3].T + camera_T_object[:3, 3]
    return out


def stand_up(camera_T_objects: np.ndarray, up: np.ndarray, centre: np.ndarray) -> np.ndarray:
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


def rank(d: Detection) -> tuple[float, float]:
    """Sort key of detections, better last: explained share of model times share of cluster, then RMSE."""
    return d.fitness * d.coverage, -d.rmse_m
