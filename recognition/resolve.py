"""Which of a frame's candidates it holds: the joint resolution of hypotheses.

Best candidates first (``rank``; a free candidate right after a twin resting on the support that
fits about as well: both fitted the same surface, and the resting reading is the physical one),
each object is in the frame once and each part of the scene is one object: a candidate is taken
if verification accepts it, judged against the whole frame from the camera's viewpoint
(``recognition.verify``; one lying on a side, or only damped steps reached, with its colour
agreeing where a grey surface's would not; one refused for where it is alone is judged once more
refitted to the frame's depth, so too, and one refused for what the sensor saw through it turned
about its upright axis, a hidden part brought out of view), and no pixel it explains is already
another object's; of
two objects accepted on the same pixels, one is taken only if it explains RIVAL_SHARE times as many, else neither; a free
candidate found upside down is judged turned upright first, the same reading of a symmetric shape.
Standing or lying, nothing hovers: a candidate must rest on the support or on an object taken
under it, so one that does not yet waits for another pass. Then two rules on what was taken, for
objects their colour does not vouch for (``COLOUR_VOUCHES``): a match explaining only part of its
cluster stands only beside another object found in that cluster, and an upright object is no lower
part of something taller.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from recognition.align import projective_icp
from recognition.cloud import PointIndex
from recognition.config import RecognitionConfig
from recognition.hypotheses import (
    ALIKE_VOXELS,
    UPRIGHT_COS,
    Candidate,
    Detection,
    SceneCloud,
    Stance,
    explained_by,
    rank,
    round_about_z,
    stand_up,
    turned_about_z,
)
from recognition.models import ModelDatabase
from recognition.verify import (
    MIN_COLOUR_PIXELS,
    DepthView,
    Explained,
    Verdict,
    cluster_labels,
    hidden_apart,
    inliers_and_violations,
    verdict,
)
from schemas.geometry import invert_pose

log = logging.getLogger(__name__)
#: An upright detection with more unexplained points of its cluster above its top than this share
#: of the points it explains is part of something taller (``Resolver._above``): true detections
#: in ``benchmarks.bop``'s frames up to 0.015, a can on a real bleach bottle's body 0.09-0.12.
TOPPED_SHARE = 0.05

#: A free candidate (no stance) goes right after a twin of it resting on the support (same object,
#: centre within TWIN_M) that ranks at least this share of its rank: a symmetric shape fits upside
#: down as well as upright, and a robot reads the object's frame.
TWIN_SHARE = 0.97
TWIN_M = 0.02

#: Of two objects' candidates that verification accepts on the same pixels, one is taken only if it
#: explains at least this many times as many of them as the other (``Resolver._contest``).
RIVAL_SHARE = 1.5

#: An object taken whose colour agrees on at least this share of its judged pixels where a grey or
#: white surface would disagree (``Verdict.distinct_agreement``) is the object by colour as well as
#: by shape: the rules that judge a match by the rest of its cluster's shape (``Resolver._alone``,
#: ``_topped``) do not refuse it. Those two rules refused, among the demo objects packed with
#: unknown ones (``benchmarks.recognition``'s clutter on 24 other layouts, ad hoc), 10 right poses
#: with agreement 0.81-0.98 but one 0.50, and 2 wrong ones at 0.32 and 0.43.
COLOUR_VOUCHES = 0.7

#: A candidate verification rejects is refitted to the frame's depth and judged again when at least
#: this share of what the sensor could judge agreed (``Resolver._refitted``; those it brought back
#: in ``benchmarks.recognition``'s clutter: 0.67-0.88).
REFIT_FITNESS = 0.6


@dataclass
class Evidence:
    """What a frame's hypotheses are judged against: its depth view, the planes removed from it
    (rows a, b, c, d, camera frame), the level one objects stand on (None: not known), each view
    pixel's cluster (``cluster_labels``) and the pixels the objects taken so far explain."""

    view: DepthView
    planes: np.ndarray
    support: np.ndarray | None
    labels: np.ndarray
    pixels: Explained = field(default_factory=Explained)
    vouched: set[str] = field(default_factory=set)  # objects taken whose colour vouches for them (``COLOUR_VOUCHES``)
    turned: set[tuple[str, int]] = field(
        default_factory=set
    )  # (object, part) judged turned about up (``Resolver._turned``)


class Resolver:
    """The joint resolution of candidates for a model database's objects."""

    def __init__(
        self,
        database: ModelDatabase,
        config: RecognitionConfig,
        indexes: dict[str, PointIndex],
        dense: dict[str, tuple[np.ndarray, np.ndarray]],
    ) -> None:
        self.db = database
        self.config = config
        self._indexes = indexes  # each model's point index (``Matcher.indexes``)
        self._dense = dense  # each model's points and normals the fine ICP fits (``Matcher.dense``)
        # Objects standing on their base that turning about their upright axis changes (``_turned``).
        self._turnable = {
            oid
            for oid, mdl in database.models.items()
            if mdl.stands_on_z and not round_about_z(mdl.points, ALIKE_VOXELS * config.descriptor.voxel_m)
        }

    def resolve(
        self, candidates: Sequence[Candidate], view: DepthView | None, scene: SceneCloud, clusters: Sequence[np.ndarray]
    ) -> list[Detection]:
        """The detections the frame holds, by object id: of ``candidates`` fitted in ``scene`` (its
        ``clusters`` as indices into its points), those verified against ``view`` (None: not verified)."""
        support = next((cand.stance.support for cand in candidates if cand.stance.support is not None), None)
        evidence = (
            None
            if view is None
            else Evidence(view, scene.planes, support, cluster_labels(view, scene.points, clusters))
        )
        found = self._take(candidates, evidence)
        # Two rules judge a match by the rest of its cluster's shape; an object its colour vouches
        # for is past them: in clutter that rest is what stands beside it or on it.
        vouched = set() if evidence is None else evidence.vouched
        # A match explaining only part of its cluster was kept for touching objects: it stands only
        # if another object was found in the same cluster. Alone, it is a shape that fits a piece of
        # some larger unknown surface (a carton's faces on a person, on a cabinet).
        for oid in list(found):
            if oid not in vouched and self._alone(found[oid], found.values()):
                del found[oid]
        # An upright object is no part of something taller: cluster points above its top, inside its
        # footprint, that nothing found explains say it was fitted to the lower part of a larger
        # shape (a can on a bleach bottle's body, the bottle's shoulder and neck above it).
        for oid in list(found):
            if oid not in vouched and self._topped(found[oid], found.values(), scene.points, clusters):
                del found[oid]
        return sorted((cand.detection for cand in found.values()), key=lambda d: d.object_id)

    def _take(self, candidates: Sequence[Candidate], evidence: Evidence | None) -> dict[str, Candidate]:
        """The candidates taken, by object id: best first, so that a part two objects fit goes to the
        one not found better elsewhere. A hypothesis the frame contradicts never takes a part, and a
        pixel explains one object (None: nothing is verified)."""
        found: dict[str, Candidate] = {}
        taken: set[int] = set()
        # Objects rest on the support or on an object found under them (``rests``): one that does
        # not yet waits for another pass, in case what it stands on is found after it.
        pending = self._ordered(candidates)
        up = next((cand.stance.up for cand in candidates if cand.stance.up is not None), None)
        while pending:
            waiting, before = [], len(found)
            for cand in pending:
                if cand.part in taken or cand.detection.object_id in found:
                    continue
                below = [f.detection for f in found.values()]
                if self._floats(cand, below):
                    waiting.append(cand)
                    continue
                # Judged only once it could be taken: most frames hold candidates for objects already found.
                if evidence is not None:
                    if (judged := self._judged(cand, up, evidence)) is None:
                        continue
                    if (won := self._contest(judged, pending, found, below, up, evidence)) is None:
                        taken.add(cand.part)  # which object it is cannot be told: nothing is reported from it
                        continue
                    cand, v = won
                    if log.isEnabledFor(logging.DEBUG):  # the figures are formatted only for a reader
                        log.debug("%s taken: %s", cand.detection.object_id, described(v, self._support(v, evidence)))
                    evidence.pixels.admit(v)
                    if self._coloured(v, COLOUR_VOUCHES):
                        evidence.vouched.add(cand.detection.object_id)
                taken.add(cand.part)
                found[cand.detection.object_id] = cand
            if len(found) == before:
                for cand in waiting:
                    log.debug(
                        "%s rejected: it floats above the support with nothing found under it", cand.detection.object_id
                    )
                break
            pending = waiting
        return found

    def _ordered(self, candidates: Sequence[Candidate]) -> list[Candidate]:
        """Candidates best first (``rank``), a free one right after its resting twin (``TWIN_SHARE``)."""
        resting = [cand for cand in candidates if cand.stance.resting]

        def key(cand: Candidate) -> tuple[tuple[float, float], int]:
            twin = self._twin(cand, resting) if cand.stance.up is None else None
            return (rank(cand.detection), 1) if twin is None else (rank(twin.detection), 0)

        return sorted(candidates, key=key, reverse=True)

    def _upright_twin(self, free: Candidate, up: np.ndarray | None) -> Candidate | None:
        """A free candidate of an object standing on its base, found upside down (world up, camera
        frame, known from the frame's other stances), turned upright about its centre: a symmetric
        shape fits both ways, and the frame tells them apart only if the object is not symmetric, so
        this reading is verified first (the upside-down one only if it fails). None otherwise."""
        det = free.detection
        if up is None or free.stance.up is not None or not self.db.models[det.object_id].stands_on_z:
            return None
        if det.camera_T_object[:3, 2] @ up >= -UPRIGHT_COS:
            return None
        turned = stand_up(det.camera_T_object[None], up, self.db.models[det.object_id].centre)[0]
        return replace(free, detection=replace(det, camera_T_object=turned))

    def _twin(self, free: Candidate, resting: Sequence[Candidate]) -> Candidate | None:
        """The best resting candidate of the same object (one whose frame has an up: not a captured
        cloud's), centred within TWIN_M of the free one and ranking at least TWIN_SHARE of it, if any."""
        det = free.detection
        if not self.db.models[det.object_id].stands_on_z:
            return None
        at = self._centre_at(det)
        twins = [
            cand
            for cand in resting
            if cand.detection.object_id == det.object_id
            and rank(cand.detection)[0] >= TWIN_SHARE * rank(det)[0]
            and np.linalg.norm(self._centre_at(cand.detection) - at) <= TWIN_M
        ]
        return max(twins, key=lambda cand: rank(cand.detection), default=None)

    def _centre_at(self, det: Detection) -> np.ndarray:
        """The posed model's centre (its points' mean), camera frame (3,)."""
        T = det.camera_T_object
        return T[:3, :3] @ self.db.models[det.object_id].centre + T[:3, 3]

    def _judged(self, cand: Candidate, up: np.ndarray | None, evidence: Evidence) -> tuple[Candidate, Verdict] | None:
        """The candidate and its verdict if verification accepts it (a free one found upside down
        turned upright first, ``_upright_twin``), else None; its pixels are not yet explained."""
        if (upright := self._upright_twin(cand, up)) is not None:
            if (v := self._verified(upright.detection, cand.stance, evidence)) is not None:
                log.debug(
                    "%s found upside down: reported upright, which the frame holds as well", cand.detection.object_id
                )
                return upright, v
        v = self._verdict(cand.detection, evidence)
        if self._accepts(cand.detection, cand.stance, v, evidence):
            return cand, v
        if (again := self._refitted(cand, v, evidence)) is not None:
            if (v_again := self._verified(again.detection, cand.stance, evidence)) is not None:
                log.debug("%s accepted refitted to the frame's depth", cand.detection.object_id)
                return again, v_again
        return self._turned(cand, v, evidence)

    def _turned(self, cand: Candidate, v: Verdict, evidence: Evidence) -> tuple[Candidate, Verdict] | None:
        """A candidate standing or free (not lying on a side) turned down for what the sensor saw
        through (its visible fitness at least REFIT_FITNESS, under ``min_visible_fitness``), judged
        turned about its own upright axis (the model's z) by every YAW_STEP_DEG, each turn fitted
        to the frame's depth (``projective_icp``): a part the frame does not show, a mug's handle
        behind its body, was put where the sensor sees past it, and the shape it does show says
        nothing of the turn. The turn the sensor sees through least, if verification accepts it;
        once per object and part, and not for a shape every turn leaves alike (a can). As a refit
        (``_refitted``), a search on the measure verification judges: only for a colour a grey
        surface would disagree with, and taken with its colour agreeing there."""
        det, stance = cand.detection, cand.stance
        if (
            stance.lying
            or det.object_id not in self._turnable
            or v.violations == 0
            or v.colour_distinct < MIN_COLOUR_PIXELS
            or not REFIT_FITNESS <= v.fitness < self.config.min_visible_fitness
            or (det.object_id, cand.part) in evidence.turned
        ):
            return None
        evidence.turned.add((det.object_id, cand.part))
        (points, normals), c, view = self._dense[det.object_id], self.config, evidence.view
        fits = []  # (visible fitness, inliers, pose) of each turn, judged on the fine ICP's points
        for T in turned_about_z(det.camera_T_object, self.db.models[det.object_id].centre):
            # The fit to the cluster that put the part there moved the rest off too: each turn is
            # fitted to the frame's depth first (None: it lost the surface).
            if (
                T := projective_icp(points, normals, view.z, view.K, T, c.icp_distance_m, c.plane_noise_per_m2)
            ) is not None:
                inliers, violations = inliers_and_violations(
                    view, points, normals, T, c.icp_distance_m, c.plane_noise_per_m2
                )
                fits.append((inliers / max(inliers + violations, 1), inliers, T))
        if not fits:
            return None
        best = max(fits, key=lambda fit: fit[:2])[2]
        turned = replace(cand, detection=replace(det, camera_T_object=best, needs_colour=True))
        best_v = self._verdict(turned.detection, evidence)
        if not self._accepts(turned.detection, stance, best_v, evidence):
            return None
        log.debug(
            "%s accepted turned about its upright axis: it was seen through on %d pixels, turned on %d",
            det.object_id,
            v.violations,
            best_v.violations,
        )
        return turned, best_v

    def _refitted(self, cand: Candidate, v: Verdict, evidence: Evidence) -> Candidate | None:
        """A candidate rejected for where it is alone (its visible fitness, at least REFIT_FITNESS,
        or support; ``_plausible`` holds) refitted to the frame's depth (``projective_icp``), if its
        colour is one a grey or white surface would disagree with (``Verdict.colour_distinct``); the
        refitted one needs its colour to agree there (``Detection.needs_colour``): a fit to the very
        measure verification judges is no second opinion on depth. None otherwise.

        In clutter a cluster merges an object with what stands beside it, and its fit to the cluster
        can end a few cm off (ADD-S 0.04-0.07 d, fitness 0.67-0.88 where a pose within 2 cm reads
        0.94 or more): fitted to the pixels it lands on, it comes back."""
        det, c = cand.detection, self.config
        if v.colour_distinct < MIN_COLOUR_PIXELS or v.fitness < REFIT_FITNESS or not self._plausible(v):
            return None
        if self._placed(v, self._support(v, evidence)):
            return None  # rejected for another reason (its pixels another object's)
        model = self.db.models[det.object_id]
        T = projective_icp(
            model.points,
            model.normals,
            evidence.view.z,
            evidence.view.K,
            det.camera_T_object,
            c.icp_distance_m,
            c.plane_noise_per_m2,
        )
        return None if T is None else replace(cand, detection=replace(det, camera_T_object=T, needs_colour=True))

    def _contest(
        self,
        judged: tuple[Candidate, Verdict],
        pending: Sequence[Candidate],
        found: dict[str, Candidate],
        below: list[Detection],
        up: np.ndarray | None,
        evidence: Evidence,
    ) -> tuple[Candidate, Verdict] | None:
        """Of ``judged`` and its rivals (each other object's best-ranked candidate on the same part
        that verification accepts, competing for the same pixels: ``Explained.competing``), the one
        explaining at least RIVAL_SHARE times as many of the scene's pixels as each other; None if
        none does: two shapes fit what the sensor saw about as well, and which it is cannot be told."""
        cand = judged[0]
        contenders, tried = [judged], {cand.detection.object_id}
        for other in pending:
            det = other.detection
            if other.part != cand.part or det.object_id in tried or det.object_id in found:
                continue
            if self._floats(other, below):
                continue
            if (rival := self._judged(other, up, evidence)) is None:
                continue
            tried.add(det.object_id)
            if evidence.pixels.competing(judged[1], rival[1]):
                contenders.append(rival)
        if len(contenders) == 1:
            return judged
        best, second = sorted(contenders, key=lambda c: len(c[1].pixels), reverse=True)[:2]
        if len(best[1].pixels) >= RIVAL_SHARE * len(second[1].pixels):
            if best is not judged:
                log.debug(
                    "%s taken for %s: it explains %d pixels of the part, against %d",
                    best[0].detection.object_id,
                    cand.detection.object_id,
                    len(best[1].pixels),
                    len(judged[1].pixels),
                )
            return best
        log.debug(
            "%s and %s fit the same pixels about as well (%d and %d): neither is reported",
            best[0].detection.object_id,
            second[0].detection.object_id,
            len(best[1].pixels),
            len(second[1].pixels),
        )
        return None

    def _verified(self, det: Detection, stance: Stance, evidence: Evidence) -> Verdict | None:
        """The hypothesis's verdict if verification accepts it, else None."""
        v = self._verdict(det, evidence)
        return v if self._accepts(det, stance, v, evidence) else None

    def _accepts(self, det: Detection, stance: Stance, v: Verdict, evidence: Evidence) -> bool:
        """Whether verification accepts the hypothesis on its verdict ``v``."""
        c, pixels = self.config, evidence.pixels
        # Colour is the second opinion these need, and only where a grey or white surface would
        # disagree is it one: a white carton's colour agrees with a pale cabinet.
        if (det.needs_colour or stance.lying) and not self._coloured(v, c.min_colour_agreement):
            why = "lying on a side" if stance.lying else "only damped steps or a refit to the depth reached it"
            log.debug(
                "%s rejected: %s, and its colour where grey would differ is not the model's or not judged "
                "(%d of %d pixels agree)",
                det.object_id,
                why,
                v.colour_distinct_agreeing,
                v.colour_distinct,
            )
            return False
        seen = self._support(v, evidence)
        if not (self._placed(v, seen) and self._plausible(v) and pixels.admits(v)):
            if log.isEnabledFor(logging.DEBUG):
                log.debug("%s rejected by verification: %s", det.object_id, described(v, seen))
            return False
        return True

    def _support(self, v: Verdict, evidence: Evidence) -> float:
        """The share of the visible model found on the measured surface, what the objects taken so
        far hide left out (``Explained.support``)."""
        # With its colour agreeing where grey would differ, what another cluster hides in front of
        # it is no evidence against it either: in clutter objects stand behind things no database holds.
        apart = hidden_apart(v, evidence.labels) if self._coloured(v, self.config.min_colour_agreement) else None
        return evidence.pixels.support(v, apart)

    def _placed(self, v: Verdict, support: float) -> bool:
        """Whether the verdict passes verification's tests of where the object is: its visible
        fitness, and its support (``_support``)."""
        return v.fitness >= self.config.min_visible_fitness and support >= self.config.min_visible_support

    @staticmethod
    def _coloured(v: Verdict, share: float) -> bool:
        """Whether the hypothesis's colour agrees on at least ``share`` of its judged pixels where a
        grey or white surface's would not, MIN_COLOUR_PIXELS of them or more (with colour off,
        ``min_colour_agreement`` 0, still they must be judged)."""
        return v.colour_distinct >= MIN_COLOUR_PIXELS and v.distinct_agreement >= share

    def _plausible(self, v: Verdict) -> bool:
        """Whether the verdict passes verification's tests of what the object is, all but where it
        is (``_placed``): the side it shows facing the camera, its outline, not
        inside a support, its colour and its surface's shape."""
        c = self.config
        return (
            v.facing_share >= c.min_facing_share
            and v.clutter <= c.max_clutter
            and v.outline_seen >= c.min_outline_seen
            and v.flush <= c.max_flush
            and v.penetration <= c.max_penetration
            and v.colour_agreement >= c.min_colour_agreement
            and v.shape_error <= c.max_shape_error
        )

    def _alone(self, cand: Candidate, found: Iterable[Candidate]) -> bool:
        """Whether a candidate explains under min_coverage of its cluster with no other object found there."""
        det, k = cand.detection, cand.cluster
        if k is None or det.coverage >= self.config.min_coverage:
            return False
        if any(other.cluster == k for other in found if other.detection.object_id != det.object_id):
            return False
        log.debug(
            "%s rejected: it explains %.0f %% of its cluster and nothing else was found in the rest",
            det.object_id,
            100 * det.coverage,
        )
        return True

    def _topped(
        self, cand: Candidate, found: Iterable[Candidate], points: np.ndarray, clusters: Sequence[np.ndarray]
    ) -> bool:
        """Whether an upright candidate has more than TOPPED_SHARE of its points' worth of its
        cluster's unexplained points (``points`` (N, 3), the scene's) standing on its top."""
        det, k, stance = cand.detection, cand.cluster, cand.stance
        if k is None or stance.up is None or not self.db.models[det.object_id].stands_on_z:
            return False
        above = self._above(det, points[clusters[k]], [f.detection for f in found], stance.rest)
        if above <= TOPPED_SHARE * det.points:
            return False
        log.debug(
            "%s rejected: %d points of its cluster stand on its top and nothing found explains them",
            det.object_id,
            above,
        )
        return True

    def _verdict(self, det: Detection, evidence: Evidence) -> Verdict:
        """A hypothesis judged against the frame's depth, the planes removed from it and the support
        objects stand on (``recognition.verify``)."""
        model, c = self.db.models[det.object_id], self.config
        return verdict(
            evidence.view,
            model.points,
            model.normals,
            det.camera_T_object,
            c.icp_distance_m,
            c.plane_noise_per_m2,
            evidence.planes,
            model.chroma_range,
            c.colour_tolerance,
            c.descriptor.voxel_m,
            evidence.support,
            c.colour_min_saturation,
        )

    def _floats(self, cand: Candidate, below: Iterable[Detection]) -> bool:
        """Whether a candidate with a support to rest on rests neither on it nor on a detection in
        ``below`` (``rests``; never with the rest test off, ``max_float_m`` 0)."""
        support = cand.stance.support
        return support is not None and self.config.max_float_m > 0 and not self.rests(cand.detection, below, support)

    def rests(self, det: Detection, found: Iterable[Detection], support: np.ndarray) -> bool:
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
            points = points[~explained_by(self._indexes[other.object_id], other.camera_T_object, points, tol)]
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


def described(v: Verdict, support: float) -> str:
    """A verdict's figures, as verification's log lines give them (support: ``Resolver._support``)."""
    return (
        f"visible fitness {v.fitness:.2f}, support {support:.2f} ({v.inliers} of {v.visible} visible pixels, "
        f"{v.violations} seen through), facing {v.facing_share:.2f} ({v.backfacing} pixels seen from behind), clutter "
        f"{v.clutter:.2f}, outline seen {v.outline_seen:.2f} (of {v.outline} pixels), flush {v.flush:.2f}, inside a support "
        f"{v.penetration:.3f}, colour {v.colour_agreement:.2f} (of {v.colour_judged} pixels; {v.colour_distinct_agreeing} "
        f"of {v.colour_distinct} where grey would differ), shape error {v.shape_error:.1f} sigma"
    )
