"""An object marker seen by two or more cameras at one instant, as a pose of its own.

DESIGN's object-marker poses per time step. A marker on an object is never fused into the map (it
does not stay put), but at one instant it is one pose that every camera seeing it observes: a link
between those cameras, like a shared static marker, and from a new view each time the object has
moved, so its views' biases differ where a static marker repeats one. Sightings are gathered per
marker on a time grid (``min_gap_s``, from the first stamp seen): per grid instant each camera
keeps its sighting nearest the instant if it lies within ``sync_ms`` / 2 of it, so any two kept
are within ``sync_ms`` of each other (a moving object must not be compared across frames taken at
different times). An instant two or more cameras kept becomes a variable (key ``o``) with one
factor per camera whose sighting agrees on where the marker is. The simulator's cameras render on
one frame clock; free-running sensors land within a few ms of each other on a few frames in a
hundred, so they get fewer links.

Memory stays bounded: past ``max_links`` instants every other one is dropped and the grid doubles.
Offline (``add_links``) every instant joins the batch solve; online (``LiveLinks``) the daemon's
graph holds the newest ``max_live`` of those that are a new view.
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.config import LinkConfig
from estimator.keyframes import consensus
from estimator.observation import ObservationRows
from estimator.symbols import object_symbol
from schemas.geometry import cov_ros_to_gtsam, covariance_in_frame, skew

FREE_ROTATION_RAD = 0.5  # a link's rotation sigma: loose enough to carry no rotation, finite for the solver
LINK_DELAY_NS = 500_000_000  # online, an instant is complete this long after its time (every camera's frame is in)
NEW_VIEW_M = 0.02  # online, an instant enters only where its marker has moved this far since the last that did


@dataclass(frozen=True)
class Sighting:
    """One camera's observation of an object marker in a static segment: camera_T_marker and the
    other IPPE branch (4, 4), covariance (6, 6; ROS order, marker frame)."""

    camera_id: str
    segment: int
    stamp_ns: int
    pose: np.ndarray
    alternative: np.ndarray
    covariance: np.ndarray


class ObjectLinks:
    """Per (marker, grid instant): each camera's sighting nearest the instant."""

    def __init__(self, config: LinkConfig) -> None:
        self.gap_ns = int(config.min_gap_s * 1e9)
        self.max_links = config.max_links
        self.sync_ns = int(config.sync_ms * 1e6)
        self.origin_ns: int | None = None  # the grid starts at the first stamp: cameras on one frame clock then hit it
        self.instants: dict[tuple[int, int], dict[str, Sighting]] = {}

    def near_instant(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Which stamps (N,) int ns lie within ``sync_ms`` / 2 of a grid instant (N,) bool: the
        cheap test that spares building sightings ``add`` would drop."""
        if self.origin_ns is None and len(stamps_ns):
            self.origin_ns = int(stamps_ns.min())
        t = stamps_ns - (self.origin_ns or 0)
        n = (t + self.gap_ns // 2) // self.gap_ns
        return 2 * np.abs(t - n * self.gap_ns) <= self.sync_ns

    def add(self, marker_id: int, s: Sighting) -> None:
        """Keep ``s`` if it is its camera's nearest to a grid instant so far (its arrays are kept:
        pass copies, not views into a larger batch)."""
        if self.origin_ns is None:
            self.origin_ns = s.stamp_ns
        t = s.stamp_ns - self.origin_ns
        n = (t + self.gap_ns // 2) // self.gap_ns
        off = abs(t - n * self.gap_ns)
        if 2 * off > self.sync_ns:
            return
        cams = self.instants.setdefault((marker_id, n), {})
        old = cams.get(s.camera_id)
        if old is None or off < abs(old.stamp_ns - self.origin_ns - n * self.gap_ns):
            cams[s.camera_id] = s
        if len(self.instants) > self.max_links:
            self.instants = {(mk, i // 2): c for (mk, i), c in self.instants.items() if i % 2 == 0}
            self.gap_ns *= 2

    def groups(self) -> list[tuple[int, list[Sighting]]]:
        """(marker, sightings) of every instant that two or more cameras saw, in (marker, time) order."""
        return [(mk, list(cams.values())) for (mk, _), cams in sorted(self.instants.items()) if len(cams) >= 2]


def block_sightings(
    camera_id: str,
    stamps: np.ndarray,
    a: ObservationRows,
    segments: list[int | None],
    object_markers: set[int],
    sink: ObjectLinks,
) -> None:
    """The object markers seen in a camera's frames (stamps (F,) ns, rows ``a``) that joined a
    static segment (``segments``, per frame; None: none), near one of ``sink``'s instants."""
    rows = np.flatnonzero(np.isin(a.ids, list(object_markers)))
    rows = rows[sink.near_instant(stamps[a.frame[rows]])]
    for j in rows.tolist():
        seg = segments[int(a.frame[j])]
        if seg is not None:  # copies: a view would keep the whole block's arrays alive
            sink.add(
                int(a.ids[j]),
                Sighting(
                    camera_id,
                    seg,
                    int(stamps[a.frame[j]]),
                    a.poses[j].copy(),
                    a.alternatives[j].copy(),
                    a.covariances[j].copy(),
                ),
            )


def add_links(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    links: ObjectLinks,
    segment_keys: dict[tuple[str, int], int],
    max_fused: int,
    robust: gtsam.noiseModel.mEstimator.Base,
) -> int:
    """Add each linked instant whose sightings' solved segments (``segment_keys``, with values in
    ``values``) agree on the marker's pose to ``graph`` and ``values`` (in place): a pose ``o<i>``
    and one robust factor per agreeing sighting. Returns how many instants were added.

    A factor constrains the marker's position only: the rotation of a small marker on an object is
    its least reliable part (the demo cell's are 0.2-1.5 deg off in single frames), and at 2-3 m a
    camera's rotation pulled by 0.3 deg moves what it sees by 10-15 mm. Positions at different
    instants fix the cameras' relative rotation too, once the object has moved. While the object
    stands still its instants repeat one view with one bias, so a camera's sightings of one marker
    count at most ``max_fused`` single frames together, as a fused static pair does.
    """
    groups = links.groups()
    count: dict[tuple[str, int], int] = {}  # instants per (camera, marker)
    for mk, sightings in groups:
        for s in sightings:
            count[(s.camera_id, mk)] = count.get((s.camera_id, mk), 0) + 1
    added = 0
    for mk, sightings in groups:
        solved = [s for s in sightings if (s.camera_id, s.segment) in segment_keys]
        keys = [segment_keys[(s.camera_id, s.segment)] for s in solved]
        key = object_symbol(added)
        made = instant_factors(
            key,
            solved,
            keys,
            [values.atPose3(k).matrix() for k in keys],
            [count[(s.camera_id, mk)] / max_fused for s in solved],
            robust,
        )
        if made is None:
            continue
        values.insert(key, gtsam.Pose3(made[0]))
        for _, factor in made[1]:
            graph.add(factor)
        added += 1
    return added


def instant_factors(
    key: int,
    sightings: list[Sighting],
    camera_keys: list[int],
    world_T_cameras: list[np.ndarray],
    repeats: list[float],
    robust: gtsam.noiseModel.mEstimator.Base,
) -> tuple[np.ndarray, list[tuple[Sighting, gtsam.BetweenFactorPose3]]] | None:
    """One linked instant: where the sightings (each from the camera pose of the same index, with
    its key) agree the marker is, world_T_marker (4, 4), and one factor per agreeing sighting onto
    the instant's variable ``key``; None unless two or more agree. A sighting's position covariance
    is multiplied by its ``repeats`` where above 1 (instants of one view count at most
    ``max_fused`` frames together, see ``add_links``)."""
    if len(sightings) < 2:
        return None
    agreed = consensus(np.stack([[T @ s.pose, T @ s.alternative] for T, s in zip(world_T_cameras, sightings)]))
    if agreed is None:
        return None
    world_T_marker, chosen = agreed
    factors = []
    for i, k in chosen:
        s = sightings[i]
        given = s.covariance if k == 0 else covariance_in_frame(s.covariance, s.pose[:3, :3], s.alternative[:3, :3])
        cov = np.zeros((6, 6))
        cov[:3, :3] = given[:3, :3] * max(1.0, repeats[i])
        cov[3:, 3:] = np.eye(3) * FREE_ROTATION_RAD**2
        noise = gtsam.noiseModel.Robust.Create(robust, gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(cov)))
        factors.append(
            (s, gtsam.BetweenFactorPose3(camera_keys[i], key, gtsam.Pose3((s.pose, s.alternative)[k]), noise))
        )
    return world_T_marker, factors


def instant_gain(
    world_T_cameras: np.ndarray, sightings: list[Sighting], repeats: list[float], joint_covariance: np.ndarray
) -> float:
    """The largest share of predicted variance an instant removes: over every two of its sightings,
    1 - trace(posterior) / trace(prior) of the difference between the marker positions their
    cameras imply, the prior from the cameras' joint covariance (6K, 6K; gtsam's tangent order per
    camera, body frame, in the order of ``world_T_cameras`` (K, 4, 4)), the measurement from the
    sightings' position covariances (times ``repeats`` where above 1, as ``instant_factors``).

    0 where the graph already knows the cameras' relative position at the marker far better than
    one frame tells it, 1 where it knows nothing of it.
    """
    K = len(sightings)
    J = np.zeros((K, 3, 6))  # d(world position of the marker) / d(camera perturbation)
    M = np.zeros((K, 3, 3))  # the sighting's position covariance, world frame
    for i, (T, s) in enumerate(zip(world_T_cameras, sightings)):
        R = T[:3, :3]
        J[i, :, :3] = -R @ skew(s.pose[:3, 3])
        J[i, :, 3:] = R
        Rw = R @ s.pose[:3, :3]
        M[i] = Rw @ s.covariance[:3, :3] @ Rw.T * max(1.0, repeats[i])
    best = 0.0
    for i in range(K):
        for j in range(i + 1, K):
            D = np.zeros((3, 6 * K))
            D[:, 6 * i : 6 * i + 6], D[:, 6 * j : 6 * j + 6] = J[i], -J[j]
            prior = D @ joint_covariance @ D.T
            if np.trace(prior) <= 0.0:
                continue  # the cameras move as one: nothing to learn of their relative position
            posterior = prior - prior @ np.linalg.solve(prior + M[i] + M[j], prior)
            best = max(best, 1.0 - float(np.trace(posterior) / np.trace(prior)))
    return best


@dataclass
class LinkFactor:
    """A live instant's factor from one camera segment; ``slot``: its index in iSAM2 once added."""

    segment: tuple[str, int]
    slot: int | None = None


@dataclass
class LiveInstant:
    key: int
    marker_id: int
    factors: list[LinkFactor]


class LiveLinks:
    """Online links (the daemon's graph): the same instants as offline, in a fixed lag.

    An instant is complete ``LINK_DELAY_NS`` after its grid time (every camera's frame of it has
    arrived); then, if two or more of its cameras' segments are in the graph and agree, and it
    would remove at least ``min_gain`` of what the graph does not know of their relative position
    (``instant_gain``), it enters iSAM2 as offline's do, against the cameras' current estimates.
    The newest ``max_live`` stay; older ones leave (their factors removed: iSAM2 drops a variable with none), and a segment that
    ends takes its instants with it (its history keeps static pairs only). So the graph holds at
    most ``max_live`` extra variables, and what links give, a moving object's fresh views, counts
    while it is recent. Repeats of one view are weighted as offline, over the live instants.
    """

    def __init__(self, config: LinkConfig) -> None:
        self.gather = ObjectLinks(config)
        self.max_live = config.max_live
        self.min_gain = config.min_gain
        self.live: deque[LiveInstant] = deque()
        self.repeats: Counter[tuple[str, int]] = Counter()  # live instants per (camera id, marker)
        self.last_position: dict[int, np.ndarray] = {}  # marker -> where its last weighed instant had it (world, m)
        self._next_key = 0

    def complete(self, now_ns: int) -> list[tuple[int, list[Sighting]]]:
        """Take the instants at least LINK_DELAY_NS old out of the gathering: (marker, sightings)
        of those two or more cameras saw."""
        g = self.gather
        if g.origin_ns is None:
            return []
        last = (now_ns - LINK_DELAY_NS - g.origin_ns) // g.gap_ns
        done = sorted(k for k in g.instants if k[1] <= last)
        out = [(k[0], list(g.instants[k].values())) for k in done if len(g.instants[k]) >= 2]
        for k in done:
            del g.instants[k]
        return out

    def new_key(self) -> int:
        self._next_key += 1
        return object_symbol(self._next_key - 1)

    def is_new_view(self, marker_id: int, world_T_marker: np.ndarray) -> bool:
        """Has the marker moved NEW_VIEW_M since its last instant that entered or was refused? A
        still object's instants repeat one view: its noise averages over them, but a bias would not."""
        last = self.last_position.get(marker_id)
        return last is None or float(np.linalg.norm(world_T_marker[:3, 3] - last)) >= NEW_VIEW_M

    def judged(self, marker_id: int, world_T_marker: np.ndarray) -> None:
        """An instant of the marker was weighed here (entered or not): the next must be a new view of it."""
        self.last_position[marker_id] = world_T_marker[:3, 3].copy()

    def enter(self, instant: LiveInstant, world_T_marker: np.ndarray) -> None:
        self.judged(instant.marker_id, world_T_marker)
        self.live.append(instant)
        for f in instant.factors:
            self.repeats[(f.segment[0], instant.marker_id)] += 1

    def trim(self, remove: list[int]) -> list[int]:
        """Drop the oldest instants beyond ``max_live`` (those in iSAM2 already: the newest have no
        slots until their update ends); as ``drop``."""
        dropped = []
        while len(self.live) > self.max_live and all(f.slot is not None for f in self.live[0].factors):
            dropped.append(self.live.popleft())
        return self._forget(dropped, remove)

    def drop(self, keep: Callable[[LiveInstant], bool], remove: list[int]) -> list[int]:
        """Drop the live instants ``keep`` refuses: their factors' slots go into ``remove``; returns their keys."""
        dropped = [i for i in self.live if not keep(i)]
        if dropped:
            self.live = deque(i for i in self.live if keep(i))
        return self._forget(dropped, remove)

    def _forget(self, dropped: list[LiveInstant], remove: list[int]) -> list[int]:
        for instant in dropped:
            for f in instant.factors:
                self.repeats[(f.segment[0], instant.marker_id)] -= 1
                if f.slot is not None:
                    remove.append(f.slot)
        return [i.key for i in dropped]
