"""The estimator's pure core: cameras, markers and anchors in one gtsam iSAM2 graph.

    est = Estimator(config)
    est.add_frame("cam1", stamp_ns, observations)   # every frame of every camera
    est.update()                                    # a few times per second
    result = est.estimate(now_ns)                   # poses, covariances, per-camera state

Variables: ``c`` one pose per static segment of a camera (world_T_camera), ``m`` one pose per
static marker (world_T_marker). Factors: a prior per anchor (its surveyed sigma) and, per
(camera segment, marker) pair, ONE robust ``BetweenFactorPose3`` holding the running mean of all
its observations. That factor is replaced about once a second (``removeFactorIndices``, slots
reused), so a static cell's graph stops growing: cost per update and memory stay flat over days.
A camera whose marker positions jump (bumped, tilted) leaves the graph while it moves and comes
back as a new segment once it is still again. Markers on objects are posed per frame through the
cameras' current poses and never enter the map.

Young segments: a camera that moved comes back as a new segment, held out of the graph while
its pair means still move (``_young_segments``): its pose is resected against the mapped markers
(``estimator/resect.py``) and it enters once its pairs have settled, in one update.

Bounded history: once that new segment is in the graph, the segment the camera left is folded
(``_fold``): its pose variable stays as the camera's history, its pair factors stay fixed at their
final means, and the camera's previous history factors move onto it through the estimated
relative pose (fused per marker where both saw it); the previous history's variable goes. Per
camera the graph holds its live segment and one history star, however often it moved: sparse, so
iSAM2's Bayes tree stays shallow (a marginal on the star's markers would be one dense clique of
all of them). ``keep_history=True`` (the offline solve, which reports every segment) keeps them.

Two concerns of the class live beside it, mixed in: when each pair's factor is rebuilt
(``estimator/schedule.py``) and how the answer is read out (``estimator/readout.py``).
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np

from estimator.config import EstimatorConfig
from estimator.history import History, HistoryFactor, carried
from estimator.init import CameraKey, place
from estimator.keyframes import LiveKeyframes, moving_frame, place_frame
from estimator.links import LinkFactor, LiveInstant, LiveLinks, Sighting, block_sightings, instant_factors, instant_gain
from estimator.motion import MOVE_CHI2, RigidScreen, any_frame_moved, frame_moved
from estimator.observation import Observation, ObservationRows, observations_of
from estimator.pairs import YOUNG_PAIR, Pair, fold_rows, pair_means
from estimator.readout import ANCHOR_CHECK_NS, Readout
from estimator.resect import resect
from estimator.schedule import PairSchedule
from estimator.symbols import camera_symbol, marker_symbol
from estimator.variance import Fit, pose_fit
from schemas.geometry import cov_ros_to_gtsam, invert_pose, invert_poses, mahalanobis_sq

log = logging.getLogger(__name__)

MIN_RESECT_MARKERS = 3  # mapped markers a held segment needs for its pose (see Estimator._young_segments)
HOLD_MAX_NS = 2_000_000_000  # a segment whose pairs do not settle (markers seen now and then) enters anyway
STATIC_FIT_NS = 30_000_000_000  # how often the static pairs' fit is recomputed while moving frames enter (ns)
UNKNOWN_IDS_LOGGED = 10  # unknown marker ids named in the log; the rest are counted
#: iSAM2 checks for relinearisation every this many updates (1: a large cell's p99 doubled; accuracy the same).
RELINEARIZE_SKIP = 10


@dataclass
class CameraTrack:
    """Per-camera bookkeeping: current segment, motion detection, freshness."""

    camera_id: str
    segment: int = 0
    last_stamp_ns: int = 0
    moving: bool = False
    suspect: int = 0  # consecutive frames whose markers moved
    still: int = 0  # consecutive still frames while moving
    last_positions: dict[int, Observation] = field(default_factory=dict)
    latest: dict[int, Observation] = field(default_factory=dict)  # newest frame's observations
    markers_seen: int = 0
    segment_start_ns: int = 0  # stamp of the current segment's first frame
    backwards: int = 0  # frames refused for a stamp before the newest one
    screen: RigidScreen | None = None  # the batched path's rigid-motion screen for the current view


@dataclass
class Counters:
    observations: int = 0
    rejected: int = 0
    unknown_markers: int = 0
    updates: int = 0
    factors_rebuilt: int = 0  # pair factors (re)built in the graph
    last_update_ms: float = 0.0  # wall time of the last update() call, whether or not it had work
    last_update_cpu_ms: float = 0.0  # CPU time this thread spent in it: wall minus this is waiting (CPU, GIL)
    last_update_rebuilt: int = 0  # pair factors that call rebuilt
    links: int = 0  # object-marker instants that entered the graph (``LiveLinks``)
    links_refused: int = 0  # those left out: they would add too little (``LinkConfig.min_gain``)
    keyframes: int = 0  # moving frames that entered the graph (``LiveKeyframes``)
    keyframe_inflation: float = 1.0  # the factor on the covariances of those weighed last (``estimator.variance``)
    keyframes_refused: int = 0  # moving frames left out for it (``KeyframeConfig.max_inflation``)
    reorders: int = 0  # updates in which iSAM2 re-ordered every variable (``reorder_fill``)


class Estimator(Readout, PairSchedule):
    """Incremental joint estimate of camera and marker poses. Pure: no I/O, no clocks but stamps."""

    def __init__(self, config: EstimatorConfig, keep_history: bool = False) -> None:
        self.config = config
        self.keep_history = keep_history
        params = gtsam.ISAM2Params()
        thresholds = gtsam.ISAM2ThresholdMap()  # per key type; gtsam expects every type in the graph
        for chr_ in "cko":
            thresholds.insert((chr_, np.full(6, config.relinearize_threshold)))
        thresholds.insert(("m", np.full(6, config.relinearize_threshold_markers)))
        params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = RELINEARIZE_SKIP
        params.findUnusedFactorSlots = True  # refreshed pair factors reuse their slots
        if config.reorder_fill > 0:
            params.enableAdaptiveReorder = True
            params.adaptiveReorderThreshold = config.reorder_fill
        self.isam = gtsam.ISAM2(params)
        self.anchors = {a.marker_id: a.world_T_marker.matrix() for a in config.anchors}
        self._anchor_cov = {
            a.marker_id: np.diag([a.sigma_position_m**2] * 3 + [math.radians(a.sigma_rotation_deg) ** 2] * 3)
            for a in config.anchors
        }  # ROS order
        self.object_markers = set(config.object_markers)
        known = config.known_markers
        self.known = None if known is None else set(known) | set(self.anchors) | self.object_markers
        self.tracks: dict[str, CameraTrack] = {}
        self.pairs: dict[tuple[CameraKey, int], Pair] = {}
        # The refresh schedule (``_due_pairs``) without a pass over every pair: pairs without a
        # factor or with fewer than YOUNG_PAIR observations, and the settled rest, least recently
        # looked at first (looks set refreshed_ns to the update's stamp, so this is its order too).
        self._young: dict[tuple[CameraKey, int], Pair] = {}
        self._settled: OrderedDict[tuple[CameraKey, int], Pair] = OrderedDict()
        self._unplaced: set[tuple[CameraKey, int]] = set()  # pairs whose camera or marker may not be in the graph yet
        self._segment_pairs: dict[CameraKey, dict[int, Pair]] = {}  # the pairs of each segment, by marker id
        self._held: set[CameraKey] = set()  # young segments kept out of the graph (``_young_segments``)
        self._resected: dict[CameraKey, np.ndarray] = {}  # their poses as the last estimate reported them
        self.camera_index: dict[CameraKey, int] = {}
        self._next_camera = 0  # camera_index values are never reused: folded segments leave it
        self.history: dict[str, History] = {}  # camera id -> its folded segments (bounded history)
        self.in_graph: set[int] = set()  # gtsam keys with values in iSAM2
        self._values: gtsam.Values | None = gtsam.Values()  # None: changed since, see ``values``
        self.counters = Counters()
        self.unknown_ids: set[int] = set()
        self._robust = gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k)
        self.rotation_floor_rad = math.radians(config.view_rotation_sigma_deg)
        self._pending_priors = self._anchor_priors()
        self.seeded: set[int] = set()
        self._cov: dict[int, np.ndarray] = {}  # gtsam key -> covariance (ROS order), see _covariances
        self._cov_next = 0  # where the round of covariance refreshes goes on
        self._flagged: tuple[int, list[int]] = (-ANCHOR_CHECK_NS, [])  # (stamp ns, anchors flagged then)
        self._static_fit: tuple[int, Fit | None] = (0, None)  # (stamp ns, ``static_fit`` then)
        online_links = config.links.enabled and config.links.online and not keep_history and self.object_markers
        self.live_links = LiveLinks(config.links) if online_links else None
        self.live_keyframes = LiveKeyframes(config.keyframes) if config.keyframes.online and not keep_history else None

    def seed_map(self, markers: dict[int, tuple[np.ndarray, np.ndarray]], inflate: float = 4.0) -> None:
        """Start from a saved map: each static marker gets a prior (its saved covariance x ``inflate``).

        Cameras then localise on their first frames instead of converging from nothing. Anchors
        keep their surveyed priors; markers on objects are never part of the map.
        """
        graph, values = self._pending_priors
        for mk, (T, cov) in markers.items():
            if mk in self.anchors or mk in self.object_markers:
                continue
            key = marker_symbol(mk)
            noise = gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(cov) * inflate)
            graph.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(T), noise))
            values.insert(key, gtsam.Pose3(T))
            self.seeded.add(mk)

    # ------------------------------------------------------------ input

    def _anchor_priors(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for a in self.config.anchors:
            sig = [math.radians(a.sigma_rotation_deg)] * 3 + [a.sigma_position_m] * 3
            key = marker_symbol(a.marker_id)
            graph.add(
                gtsam.PriorFactorPose3(
                    key, gtsam.Pose3(self.anchors[a.marker_id]), gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))
                )
            )
            values.insert(key, gtsam.Pose3(self.anchors[a.marker_id]))
        return graph, values

    def add_frame(self, camera_id: str, stamp_ns: int, observations: list[Observation]) -> bool:
        """All observations of one camera frame (possibly none: the camera is alive).

        Returns True if the frame joined the camera's current segment (False: ignored, or held
        back because the camera moves or may have moved).
        """
        joined = self._add_frame(camera_id, stamp_ns, observations)
        if joined and self.live_links is not None and self.live_links.gather.near_instant(np.array([stamp_ns]))[0]:
            segment = self.tracks[camera_id].segment
            for o in observations:
                if o.marker_id in self.object_markers:
                    alt = o.alternative if o.alternative is not None else o.camera_T_marker
                    sighting = Sighting(
                        camera_id, segment, stamp_ns, o.camera_T_marker.copy(), alt.copy(), o.covariance.copy()
                    )
                    self.live_links.gather.add(o.marker_id, sighting)
        return joined

    def _add_frame(self, camera_id: str, stamp_ns: int, observations: list[Observation]) -> bool:
        track = self.tracks.setdefault(camera_id, CameraTrack(camera_id))
        if stamp_ns < track.last_stamp_ns:
            self.counters.rejected += len(observations)
            track.backwards += 1
            if track.backwards == 1:  # once per camera: a flood of stale frames must not flood the log
                log.warning(
                    "%s: frame stamp went backwards (%d < %d); frame ignored (further ones only counted)",
                    camera_id,
                    stamp_ns,
                    track.last_stamp_ns,
                )
            return False
        track.last_stamp_ns = stamp_ns
        static: list[Observation] = []
        track.latest = {}
        for obs in observations:
            if self.known is not None and obs.marker_id not in self.known:
                self.counters.unknown_markers += 1
                if obs.marker_id not in self.unknown_ids:
                    self.unknown_ids.add(obs.marker_id)
                    # A few ids by name; past that a stray pattern or a fuzzing peer would fill the log.
                    if len(self.unknown_ids) <= UNKNOWN_IDS_LOGGED:
                        log.warning(
                            "marker %d seen by %s is not in the configuration; ignored%s",
                            obs.marker_id,
                            camera_id,
                            " (further unknown ids only counted: status unknown_markers)"
                            if len(self.unknown_ids) == UNKNOWN_IDS_LOGGED
                            else "",
                        )
                continue
            track.latest[obs.marker_id] = obs
            if obs.marker_id not in self.object_markers:
                static.append(obs)
        track.markers_seen = len(track.latest)
        if not self._camera_is_still(track, static):
            if self.live_keyframes is not None and track.moving and self.live_keyframes.due(camera_id, stamp_ns):
                frame = moving_frame(camera_id, stamp_ns, static, track.segment)
                self.live_keyframes.hold(
                    replace(frame, placed=place_frame(frame, self._mapped(frame.ids), self.rotation_floor_rad))
                )
            return False
        seg = (camera_id, track.segment)
        for obs in static:
            pair = self.pairs.get((seg, obs.marker_id))
            if pair is None:
                pair = self.pairs[(seg, obs.marker_id)] = self._segment_pairs.setdefault(seg, {})[obs.marker_id] = (
                    Pair()
                )
                self._unplaced.add((seg, obs.marker_id))
            if pair.add(obs):
                self.counters.observations += 1
            else:
                self.counters.rejected += 1
            if pair.n < YOUNG_PAIR:  # new, or restarted by the majority rule
                self._young_again((seg, obs.marker_id), pair)
        return True

    def add_frames(self, camera_id: str, stamps: np.ndarray, a: ObservationRows) -> list[int | None]:
        """Consecutive frames of one camera at once (offline): stamps (F,) ns, ``a.frame`` indexes them.

        The same as ``add_frame`` per frame, vectorised for the common case of a still camera whose
        pairs have settled: the motion test and the pair means run over the whole batch against the
        means before it. Anything else (a new or young pair, a suspect or moving camera, an unknown
        marker, stamps out of order) goes frame by frame. Returns each frame's segment, None where
        the frame did not join one.
        """
        track = self.tracks.get(camera_id)
        seg_key = (camera_id, track.segment) if track else None
        ids = a.ids.tolist()  # set lookups: np.isin on a frame's few dozen ids costs ~40 us a call
        om = self.object_markers
        sa = a.rows(np.fromiter((i not in om for i in ids), bool, len(ids))) if om else a  # the static markers' rows
        marker_ids, row_pair = np.unique(sa.ids, return_inverse=True)
        pairs = [self.pairs.get((seg_key, int(mk))) for mk in marker_ids]
        fast = (
            track is not None
            and not track.moving
            and track.suspect == 0
            and len(stamps) > 0
            and stamps[0] >= track.last_stamp_ns
            and bool(np.all(np.diff(stamps) >= 0))
            and (self.known is None or self.known.issuperset(ids))
            and all(p is not None and p.n >= YOUNG_PAIR for p in pairs)
        )
        expected = np.stack([p.mean() for p in pairs])[row_pair] if fast and pairs else None
        if expected is not None:
            moved, track.screen = any_frame_moved(sa, expected, len(stamps), track.screen, self.config.bump_position_m)
            fast = not moved
        if not fast:
            out = []
            for f, stamp in enumerate(stamps):
                joined = self._add_frame(
                    camera_id, int(stamp), observations_of(camera_id, int(stamp), a.rows(a.frame == f))
                )
                out.append(self.tracks[camera_id].segment if joined else None)
            self._sight(camera_id, stamps, a, out)
            return out
        folded = (
            fold_rows(expected, row_pair, len(pairs), sa) if pairs else None
        )  # past the fast test, expected exists iff pairs do
        for j, pair in enumerate(pairs):
            if pair.rejected + folded.rejected[j] > pair.n:  # would trip the restart rule: exact, one by one
                rows = row_pair == j
                k = sum(
                    pair.add_pose(T, A, C)
                    for T, A, C in zip(sa.poses[rows], sa.alternatives[rows], sa.covariances[rows])
                )
                self.counters.observations += k
                self.counters.rejected += int(rows.sum()) - k
                if pair.n < YOUNG_PAIR:
                    self._young_again((seg_key, int(marker_ids[j])), pair)
                continue
            pair.fold(folded, j)
            self.counters.observations += int(folded.accepted[j])
            self.counters.rejected += int(folded.rejected[j])
        last = len(stamps) - 1
        track.last_stamp_ns = int(stamps[last])
        latest = observations_of(camera_id, track.last_stamp_ns, a.rows(a.frame == last))
        track.latest = {o.marker_id: o for o in latest}
        track.markers_seen = len(track.latest)
        track.last_positions = {o.marker_id: o for o in latest if o.marker_id not in self.object_markers}
        out = [track.segment] * len(stamps)
        self._sight(camera_id, stamps, a, out)
        return out

    def _sight(self, camera_id: str, stamps: np.ndarray, a: ObservationRows, segments: list[int | None]) -> None:
        """Object markers in frames that joined a segment (``segments``, per frame) near a link instant."""
        if self.live_links is not None:
            block_sightings(camera_id, stamps, a, segments, self.object_markers, self.live_links.gather)

    def _camera_is_still(self, track: CameraTrack, static: list[Observation]) -> bool:
        """Residual test on marker positions in the camera frame (rotation flips cannot fool it).

        Returns True if this frame's observations may join the camera's current segment.
        """
        positions = {o.marker_id: o for o in static}
        if track.moving:
            # Still = consecutive frames agree within their noise (chi2) or within half the move threshold.
            common = [k for k in positions if k in track.last_positions]
            still = bool(common)
            for k in common:
                a, b = positions[k], track.last_positions[k]
                d = a.camera_T_marker[:3, 3] - b.camera_T_marker[:3, 3]
                R = a.camera_T_marker[:3, :3]
                cov = R @ (a.covariance[:3, :3] + b.covariance[:3, :3]) @ R.T
                if np.linalg.norm(d) > self.config.bump_position_m / 2 and mahalanobis_sq(d, cov) > MOVE_CHI2:
                    still = False
            track.still = track.still + 1 if still else 0
            track.last_positions = positions
            if track.still < self.config.settle_frames:
                return False
            track.moving, track.suspect = False, 0
            track.segment += 1  # a new static segment: a fresh variable, placed from scratch
            track.screen = None
            track.segment_start_ns = track.last_stamp_ns
            log.info("%s is still again: segment %d", track.camera_id, track.segment)
            return True
        track.last_positions = positions
        deltas, before, rotations, obs_covs, scales, margins = [], [], [], [], [], []
        cam_key = self._camera_key((track.camera_id, track.segment))
        for obs in static:
            pair = self.pairs.get(((track.camera_id, track.segment), obs.marker_id))
            map_margin, young = 0.0, 1.0
            if pair is not None and pair.n > 0:
                # Its mean of n observations is itself uncertain by their covariance over n: from
                # its first frame on, a pair can witness a move (a slow camera has few frames).
                expected, young = pair.mean(), 1.0 + 1.0 / pair.n
            elif pair is None and cam_key in self.in_graph and marker_symbol(obs.marker_id) in self.in_graph:
                # A marker this segment never paired with, but the map knows: it must appear where
                # the map predicts (within the map's own uncertainty), or the camera has moved.
                expected = invert_pose(self._pose(cam_key)) @ self._pose(marker_symbol(obs.marker_id))
                map_margin = (2.0 * self.config.bump_position_m) ** 2
            else:
                continue
            deltas.append(obs.camera_T_marker[:3, 3] - expected[:3, 3])
            before.append(expected[:3, 3])
            rotations.append((obs.camera_T_marker[:3, :3], expected[:3, :3]))
            obs_covs.append(obs.covariance[:3, :3])
            scales.append(young)
            margins.append(map_margin)
        moved, shift_m = frame_moved(deltas, before, rotations, obs_covs, scales, margins, self.config.bump_position_m)
        track.suspect = track.suspect + 1 if moved else 0
        if track.suspect >= self.config.bump_frames:
            track.moving, track.still = True, 0
            log.info(
                "%s moved (marker shift %.1f mm): leaving the graph until it is still", track.camera_id, 1000 * shift_m
            )
            return False
        return track.suspect == 0  # hold back suspicious frames

    # ------------------------------------------------------------ solving

    def _camera_key(self, cam: CameraKey) -> int:
        if cam not in self.camera_index:
            self.camera_index[cam] = self._next_camera
            self._next_camera += 1
        return camera_symbol(self.camera_index[cam])

    def _pair_factors(self, items: list[tuple[int, int, Pair]]) -> list[gtsam.BetweenFactorPose3]:
        """The robust factors of pairs' current means, for many (camera key, marker key, pair) at once
        (each pair remembers what its factor holds: ``Pair.holds``): the means' rotation
        projections and the covariances in one batch (per pair they were most of an update's cost
        in a large cell); only the gtsam objects are made one by one."""
        if not items:
            return []
        sums = np.stack([p.sums for _, _, p in items])
        n = np.array([p.n for _, _, p in items], float)
        means = pair_means(sums, n)
        covs = sums[:, 21:].reshape(-1, 6, 6) / (n * np.minimum(n, self.config.max_fused))[:, None, None]
        covs[:, [3, 4, 5], [3, 4, 5]] += self.rotation_floor_rad**2
        factors = []
        for (ck, mk, pair), T, cov in zip(items, means, covs):
            pair.holds(T, cov, self.config.max_fused)
            factors.append(self._fixed_factor(ck, mk, T, cov))
        return factors

    def ended_segments(self, now_ns: int) -> list[CameraKey]:
        """Segments a camera left (it moved and settled again) whose camera's new segment is in the
        graph, or began at least ``fold_after_s`` ago. A fold needs no converged estimate (its
        factors stay nonlinear); waiting for the new segment's entry puts the two in different
        updates, so neither carries both costs."""
        after = int(self.config.fold_after_s * 1e9)
        out = []
        for cam in self.camera_index:
            track = self.tracks[cam[0]]
            if cam[1] < track.segment:
                current = self.camera_index.get((cam[0], track.segment))
                if now_ns - track.segment_start_ns >= after or (
                    current is not None and camera_symbol(current) in self.in_graph
                ):
                    out.append(cam)
        return out

    def _fold(self, cam: CameraKey, remove: list[int]) -> None:
        """Fold an ended segment into its camera's history (see the module docstring).

        The segment's pose stays as the history's variable and its pair factors become fixed
        factors at their final means (rebuilt where a pair had observations since its last
        refresh; the others stay in their slots). The camera's previous history factors move onto
        it through the current estimate of the relative pose, fused where both saw a marker; the
        previous history's variable leaves with its last factor. Replaced slots go into ``remove``;
        the new factors wait in the history (no slot) for ``_enter_histories``: a camera that
        settled only for moments can have two segments fold in one update, and the second moves
        the first one's new factors on before they ever reach iSAM2.
        """
        ck = self._camera_key(cam)
        if self.live_links is not None:  # the ended segment's links go (its history keeps static pairs)
            for key in self.live_links.drop(lambda i: all(f.segment != cam for f in i.factors), remove):
                self.in_graph.discard(key)
        pairs = list(self._segment_pairs.pop(cam, {}).items())
        for mk, _ in pairs:
            del self.pairs[(cam, mk)]
            self._young.pop((cam, mk), None)
            self._settled.pop((cam, mk), None)
            self._unplaced.discard((cam, mk))
        del self.camera_index[cam]
        if ck not in self.in_graph:
            return  # never reached the graph (no path to an anchor): nothing to keep
        # Pairs with observations since their factor was built get their final mean (one batched
        # build); the other factors stay in their slots.
        final = [
            (mk, p) for mk, p in pairs if p.n > 0 and marker_symbol(mk) in self.in_graph and (p.dirty or p.slot is None)
        ]
        self._pair_factors([(ck, marker_symbol(mk), p) for mk, p in final])  # each pair now holds its final mean
        built = {mk for mk, _ in final}
        factors: dict[int, HistoryFactor] = {}
        for mk, pair in pairs:
            if mk in built:
                factors[mk] = HistoryFactor(pair.factor_mean, pair.factor_cov)
            elif pair.slot is not None and pair.factor_mean is not None:
                factors[mk] = HistoryFactor(pair.factor_mean, pair.factor_cov, pair.slot)
            if pair.slot is not None and (mk not in factors or mk in built):
                remove.append(pair.slot)  # replaced, or restarted since built with nothing new: stale
        old = self.history.get(cam[0])
        if old is not None and old.key in self.in_graph:
            factors, stale = carried(old, factors, invert_pose(self._pose(ck)) @ self._pose(old.key))
            remove.extend(stale)
            self.in_graph.discard(old.key)  # iSAM2 drops a variable whose factors are all removed
        if not factors:
            self.in_graph.discard(ck)
            self.history.pop(cam[0], None)
            return
        self.history[cam[0]] = History(ck, factors, (old.segments if old else 0) + 1)

    def _enter_histories(self, camera_ids: set[str], graph: gtsam.NonlinearFactorGraph, slotted: list) -> None:
        """These cameras' history factors without a slot (this update's folds) into ``graph``."""
        for h in (self.history[c] for c in camera_ids if c in self.history):
            for mk, f in h.factors.items():
                if f.slot is None:
                    slotted.append((graph.size(), f))
                    graph.add(self._fixed_factor(h.key, marker_symbol(mk), f.mean, f.covariance))

    def _fixed_factor(self, ck: int, mk: int, mean: np.ndarray, covariance: np.ndarray) -> gtsam.BetweenFactorPose3:
        """A robust between factor camera -> marker holding ``mean`` (4x4) with ``covariance`` (ROS order)."""
        noise = gtsam.noiseModel.Robust.Create(
            self._robust, gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(covariance))
        )
        return gtsam.BetweenFactorPose3(ck, mk, gtsam.Pose3(mean), noise)

    def update(self, now_ns: int, refresh_all: bool = False) -> None:
        """Place new variables and refresh due pair factors in one iSAM2 update.

        ``refresh_all`` rebuilds every pair whose mean changed at all (the offline solve's last
        update, so the batch problem holds every final mean)."""
        t0, c0 = time.perf_counter(), time.thread_time()
        graph, values = self._pending_priors
        self._pending_priors = (gtsam.NonlinearFactorGraph(), gtsam.Values())
        remove: list[int] = []
        slotted: list[tuple[int, Pair | HistoryFactor]] = []  # position in ``graph`` -> what gets that slot
        self._held, entering = self._young_segments(now_ns)
        if not self.keep_history:
            ended = self.ended_segments(now_ns)
            for cam in ended:
                self._fold(cam, remove)
            self._enter_histories({cid for cid, _ in ended}, graph, slotted)
        new_values = gtsam.Values(values)
        placed_keys = self._link(now_ns, graph, new_values, remove, slotted) if self.live_links is not None else set()
        if self.live_keyframes is not None:
            placed_keys |= self._keyframes(now_ns, graph, new_values, remove, slotted)
        entering_keys = {self._camera_key(cam) for cam in entering}
        for cam, T in entering.items():
            new_values.insert(self._camera_key(cam), gtsam.Pose3(T))
        self._place_new(new_values, self._held, entering)
        due = [(k, p) for k, p in self.pairs.items() if p.dirty] if refresh_all else self._due_pairs(now_ns)
        rebuild, rebuilt_keys = [], []  # (camera key, marker key, pair) for _pair_factors; each pair's own key
        for key, pair in due:
            ck, mk = self._camera_key(key[0]), marker_symbol(key[1])
            if self._has(ck, new_values) and self._has(mk, new_values):
                rebuild.append((ck, mk, pair))
                rebuilt_keys.append(key)
        for key, (_, _, pair), factor in zip(rebuilt_keys, rebuild, self._pair_factors(rebuild)):
            slotted.append((graph.size(), pair))
            graph.add(factor)
            if pair.slot is not None:
                remove.append(pair.slot)
            pair.refreshed_ns, pair.dirty = now_ns, False
            if key in self._settled:
                self._settled.move_to_end(key)
        refreshed = len(rebuild)
        self.counters.last_update_rebuilt = refreshed
        if graph.size() == 0 and not remove:
            # A tick with nothing due still reports its own (tiny) cost: a stale figure here made
            # the status repeat the last real update's time at 10 Hz.
            self._timed(t0, c0)
            return
        params = gtsam.ISAM2UpdateParams()
        params.removeFactorIndices = remove
        # Relinearisation is checked every RELINEARIZE_SKIP updates, and at once while anything is
        # young (new variables, factors of fewer than YOUNG_PAIR observations): a young estimate
        # still moves far from where it was linearised.
        # A segment entering from its resected pose with settled pairs is not young: its pose is
        # already where the solve will put it.
        fresh = [k for k in new_values.keys() if k not in entering_keys and k not in placed_keys]
        params.force_relinearize = bool(fresh) or any(
            p.n < YOUNG_PAIR for ck, _, p in rebuild if ck not in entering_keys
        )
        result = self.isam.update(graph, new_values, params)
        self.counters.reorders += int(result.getBatchReorderTriggered())
        if len(fresh) > 1:
            # New variables start from BFS guesses: let them settle like a batch solve. One alone (a
            # camera's new segment after a move) is placed from its own markers and converges with
            # its young factors' refreshes over the next updates.
            self.relax(2)
        slots = list(result.getNewFactorsIndices())  # one per factor of ``graph``, in its order
        for position, owner in slotted:
            owner.slot = slots[position]
        for key in new_values.keys():
            self.in_graph.add(key)
        self._values = None
        self.counters.updates += 1
        self.counters.factors_rebuilt += refreshed
        self._timed(t0, c0)

    def _link(
        self, now_ns: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, remove: list[int], slotted: list
    ) -> set[int]:
        """Complete object-marker instants into the graph against the cameras' current estimates,
        the oldest beyond ``max_live`` out (``LiveLinks``); returns the new instants' keys."""
        links, added = self.live_links, set()
        for mk, sightings in links.complete(now_ns):
            current = [s for s in sightings if s.segment == self.tracks[s.camera_id].segment]
            solved = [
                s
                for s in current
                if (s.camera_id, s.segment) in self.camera_index
                and self._camera_key((s.camera_id, s.segment)) in self.in_graph
            ]
            keys = [self._camera_key((s.camera_id, s.segment)) for s in solved]
            repeats = [(links.repeats[(s.camera_id, mk)] + 1) / self.config.max_fused for s in solved]
            key = links.new_key()
            made = instant_factors(key, solved, keys, [self._pose(k) for k in keys], repeats, self._robust)
            if made is None or not links.is_new_view(mk, made[0]):
                continue
            if links.min_gain > 0:
                index = {id(s): i for i, s in enumerate(solved)}
                chosen = [index[id(s)] for s, _ in made[1]]
                gain = self._instant_gain(
                    [solved[i] for i in chosen], [keys[i] for i in chosen], [repeats[i] for i in chosen]
                )
                if gain < links.min_gain:
                    log.debug(
                        "marker %d: an instant left out, it would remove %.2f of what the graph does not know", mk, gain
                    )
                    self.counters.links_refused += 1
                    links.judged(mk, made[0])
                    continue
            values.insert(key, gtsam.Pose3(made[0]))
            owners = []
            for s, factor in made[1]:
                owners.append(LinkFactor((s.camera_id, s.segment)))
                slotted.append((graph.size(), owners[-1]))
                graph.add(factor)
            links.enter(LiveInstant(key, mk, owners), made[0])
            added.add(key)
            self.counters.links += 1
        for key in links.trim(remove):
            self.in_graph.discard(key)
        return added

    def _instant_gain(self, sightings: list[Sighting], keys: list[int], repeats: list[float]) -> float:
        """``instant_gain`` of a linked instant against the cameras' joint covariance now."""
        joint = self.isam.jointMarginalCovariance(gtsam.KeyVector(keys))
        full = np.block([[joint.at(a, b) for b in keys] for a in keys])
        return instant_gain(np.stack([self._pose(k) for k in keys]), sightings, repeats, full)

    def _keyframes(
        self, now_ns: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, remove: list[int], slotted: list
    ) -> set[int]:
        """A move's frames into the graph (``LiveKeyframes``): a finished move's once its camera's
        new segment is in it, a camera still moving those ``lag_s`` old (``min_frames`` at least);
        placed against the current markers, new views against the camera's current and folded
        poses; the oldest beyond ``max_live`` out. Returns the new frames' keys."""
        live, added = self.live_keyframes, set()
        lag_ns = int(live.config.lag_s * 1e9)
        static: Fit | None = None  # the static pairs' fit, once a camera's frames are due
        for cid, frames in list(live.pending.items()):
            track = self.tracks[cid]
            current = self.camera_index.get((cid, track.segment))
            placed = current is not None and camera_symbol(current) in self.in_graph
            if track.moving or track.suspect:
                ripe = sum(1 for f in frames if now_ns - f.stamp_ns >= lag_ns)
                if lag_ns == 0 or ripe < live.config.min_frames:
                    continue
                frames = [frames.popleft() for _ in range(ripe)]  # the oldest; the rest wait for their turn
            elif placed:
                del live.pending[cid]
            else:
                continue
            world_T_marker = self._mapped(np.unique(np.concatenate([f.ids for f in frames])))
            own = ([camera_symbol(current)] if placed else []) + (
                [self.history[cid].key] if cid in self.history and self.history[cid].key in self.in_graph else []
            )
            if static is None:
                static = self._recent_static_fit(now_ns) if live.config.weigh_by_fit else Fit()
            refused = live.refused
            owners, entered = live.enter(
                graph,
                values,
                list(frames),
                world_T_marker,
                {cid: [self._pose(k) for k in own]},
                self.rotation_floor_rad,
                self._robust,
                static,
            )
            slotted += owners
            if live.refused > refused:
                log.info(
                    "%s: %d of its move's held frames left out: the static pairs fit %.3g times better than the frames "
                    "against what each claims (keyframes.max_inflation)",
                    cid,
                    live.refused - refused,
                    live.inflation,
                )
            else:
                log.info(
                    "%s: %d of its move's %d held frames entered the graph, covariances x %.3g",
                    cid,
                    len(entered),
                    len(frames),
                    live.inflation,
                )
            added.update(entered)
        self.counters.keyframes += len(added)
        self.counters.keyframe_inflation, self.counters.keyframes_refused = live.inflation, live.refused
        for key in live.trim(remove):
            self.in_graph.discard(key)
        return added

    def _recent_static_fit(self, now_ns: int) -> Fit:
        """``static_fit``, recomputed at most every ``STATIC_FIT_NS``: it is the cell's (how much bias
        its views carry), and a camera on an arm enters frames in most updates (a pass over every
        pair: 0.3 ms at 8 cameras, ~5 ms at 64 and 1,000 markers)."""
        stamp, fit = self._static_fit
        if fit is None or now_ns - stamp >= STATIC_FIT_NS:
            self._static_fit = (now_ns, fit := self.static_fit())
        return fit

    def static_fit(self, values: gtsam.Values | None = None) -> Fit:
        """How the static pair factors in the graph and the anchors' priors fit the current
        estimate, or ``values`` (``estimator.variance``): their redundancy is their rows less the
        cameras' and markers' they tie."""
        pose = self._pose if values is None else (lambda key: values.atPose3(key).matrix())
        pairs = [
            (self.camera_index[cam], mk, p)
            for (cam, mk), p in self.pairs.items()
            if p.slot is not None and p.factor_mean is not None and mk not in self.object_markers
        ]
        if not pairs:
            return Fit()
        cameras = sorted({c for c, _, _ in pairs})
        anchors = [mk for mk in self.anchors if marker_symbol(mk) in self.in_graph]
        markers = sorted({mk for _, mk, _ in pairs} | set(anchors))
        row = {mk: i for i, mk in enumerate(markers)}
        world = np.array([pose(marker_symbol(mk)) for mk in markers])  # np.array: twice np.stack's speed on 1,000s
        camera_T_world = invert_poses(np.array([pose(camera_symbol(c)) for c in cameras]))
        c_row = {c: i for i, c in enumerate(cameras)}
        ci = np.array([c_row[c] for c, _, _ in pairs])
        mi = np.array([row[mk] for _, mk, _ in pairs] + [row[mk] for mk in anchors])
        measured = np.array([p.factor_mean for _, _, p in pairs] + [self.anchors[mk] for mk in anchors])
        predicted = world[mi]
        predicted[: len(pairs)] = camera_T_world[ci] @ predicted[: len(pairs)]
        covs = np.array([p.factor_cov for _, _, p in pairs] + [self._anchor_cov[mk] for mk in anchors])
        return pose_fit(measured, predicted, covs, len(cameras) + len(markers))

    def _timed(self, t0: float, c0: float) -> None:
        """Record an update's wall and thread CPU time from perf_counter / thread_time starts (s)."""
        self.counters.last_update_ms = (time.perf_counter() - t0) * 1e3
        self.counters.last_update_cpu_ms = (time.thread_time() - c0) * 1e3

    def _young_segments(self, now_ns: int) -> tuple[set[CameraKey], dict[CameraKey, np.ndarray]]:
        """Current segments held out of iSAM2 while young, and those entering it now with their
        resected poses (world_T_camera).

        A camera that moved comes back as a new segment whose pair means still move with every
        frame. In the graph, each of their refreshes re-eliminated the path to the root with a
        forced relinearisation (15-27 ms an update for ~8 updates after every move at 64 cameras).
        Held out instead, its pose is resected against the mapped markers (``estimate`` reports
        that), and it enters once, when 3/4 of its pairs have YOUNG_PAIR observations (or after
        HOLD_MAX_NS), from that pose. Online only: the offline solve has no latency to keep. A
        segment that sees fewer than MIN_RESECT_MARKERS mapped markers takes the old path.
        """
        held: set[CameraKey] = set()
        entering: dict[CameraKey, np.ndarray] = {}
        if self.keep_history:
            return held, entering
        for cid, track in self.tracks.items():
            cam = (cid, track.segment)
            if track.moving or cam not in self._segment_pairs or self._camera_key(cam) in self.in_graph:
                continue
            mapped = self._mapped_pairs(cam)
            if len(mapped) < MIN_RESECT_MARKERS:
                continue
            settled = sum(p.n >= YOUNG_PAIR for _, p in mapped)
            if 4 * settled < 3 * len(mapped) and now_ns - track.segment_start_ns < HOLD_MAX_NS:
                held.add(cam)
            else:  # from the pose the last estimate reported, if any: an initial value needs no more
                last = self._resected.get(cam)
                entering[cam] = last if last is not None else self._resect(mapped)[0]
        self._resected = {cam: T for cam, T in self._resected.items() if cam in held}
        return held, entering

    def _mapped_pairs(self, cam: CameraKey) -> list[tuple[int, Pair]]:
        """The segment's pairs with observations whose marker is in the graph."""
        return [
            (mk, p)
            for mk, p in self._segment_pairs.get(cam, {}).items()
            if p.n > 0 and marker_symbol(mk) in self.in_graph
        ]

    def _resect(self, mapped: list[tuple[int, Pair]]) -> tuple[np.ndarray, np.ndarray]:
        """world_T_camera and its covariance (ROS order) from a segment's pairs with mapped markers."""
        keys = [marker_symbol(mk) for mk, _ in mapped]
        for key in keys:
            if key not in self._cov:
                self._cov[key] = self._covariance(key)
        return resect(
            np.stack([self._pose(k) for k in keys]),
            np.stack([self._cov[k] for k in keys]),
            np.stack([p.mean() for _, p in mapped]),
            np.stack([p.factor_covariance(self.config.max_fused, self.rotation_floor_rad) for _, p in mapped]),
            self.config.huber_k,
        )

    def relax(self, iterations: int) -> None:
        """Extra iSAM2 iterations without new factors (relinearise and re-solve)."""
        for _ in range(iterations):
            self.isam.update()
        self._values = None

    @property
    def values(self) -> gtsam.Values:
        """The current estimate of every variable, computed on first use after an update (an
        update that needs none of it, most of them, skips the ~2 ms of a 1,000-marker cell)."""
        if self._values is None:
            self._values = self.isam.calculateEstimate()
        return self._values

    def _has(self, key: int, new_values: gtsam.Values) -> bool:
        return key in self.in_graph or new_values.exists(key)

    def _place_new(self, new_values: gtsam.Values, held: set[CameraKey], entering: dict[CameraKey, np.ndarray]) -> None:
        """Initial values for cameras and markers that just got a path to an anchor; ``held``
        segments wait, ``entering`` ones come with their poses (``_young_segments``)."""
        # Only pairs that appeared since everything they touch was placed are looked at (a pass
        # over every pair cost a large cell ~10 ms after each move).
        unplaced = [
            (cam, mk)
            for (cam, mk) in self._unplaced
            if self._camera_key(cam) not in self.in_graph or marker_symbol(mk) not in self.in_graph
        ]
        self._unplaced = set(unplaced)  # kept until placed: a camera may reach an anchor only later
        unplaced = [(cam, mk) for cam, mk in unplaced if cam not in held]
        if not unplaced:
            return
        # Only what touches an unplaced camera or marker can place it: the rest is not looked up.
        cams_needed = {cam for cam, _ in unplaced}
        means = {k: p.mean() for k, p in self.pairs.items() if k[0] in cams_needed and p.n > 0}
        placed_cams = {
            cam: self._pose(self._camera_key(cam)) for cam in cams_needed if self._camera_key(cam) in self.in_graph
        }
        placed_cams |= {cam: T for cam, T in entering.items() if cam in cams_needed}
        placed_marks = {mk: self._pose(marker_symbol(mk)) for _, mk in means if marker_symbol(mk) in self.in_graph}
        cams, marks = place(self.anchors, means, placed_cams, placed_marks | self._pending_seed_poses(new_values))
        for cam, T in cams.items():
            key = self._camera_key(cam)
            if key not in self.in_graph and not new_values.exists(key):
                new_values.insert(key, gtsam.Pose3(T))
        for mk, T in marks.items():
            key = marker_symbol(mk)
            if key not in self.in_graph and not new_values.exists(key):
                new_values.insert(key, gtsam.Pose3(T))

    def _pending_seed_poses(self, new_values: gtsam.Values) -> dict[int, np.ndarray]:
        """Seeded markers entering the graph in this update (their priors are in ``new_values``)."""
        return {
            mk: new_values.atPose3(marker_symbol(mk)).matrix()
            for mk in self.seeded
            if new_values.exists(marker_symbol(mk))
        }

    # ------------------------------------------------------------ for tests and the offline solver

    def factor_count(self) -> int:
        """Factors in the graph now (removed slots not counted)."""
        return int(self.isam.getFactorsUnsafe().nrFactors())

    def factor_graph(self) -> gtsam.NonlinearFactorGraph:
        """The current factors (removed slots skipped), e.g. for a batch solve of the same graph."""
        g = gtsam.NonlinearFactorGraph()
        factors = self.isam.getFactorsUnsafe()
        for i in range(factors.size()):
            f = factors.at(i)
            if f is not None:
                g.add(f)
        return g
