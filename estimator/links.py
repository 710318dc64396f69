"""Offline: an object marker seen by two or more cameras at one instant, as a pose of its own.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.config import LinkConfig
from estimator.graph import object_symbol
from estimator.keyframes import consensus
from schemas.geometry import cov_ros_to_gtsam

FREE_ROTATION_RAD = 0.5  # a link's rotation sigma: loose enough to carry no rotation, finite for the solver


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


def add_links(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, links: ObjectLinks, segment_keys: dict[tuple[str, int], int],
    max_fused: int, robust: gtsam.noiseModel.mEstimator.Base,
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
        if len(solved) < 2:
            continue
        wTc = [values.atPose3(segment_keys[(s.camera_id, s.segment)]).matrix() for s in solved]
        agreed = consensus(np.stack([[T @ s.pose, T @ s.alternative] for T, s in zip(wTc, solved)]))
        if agreed is None:
            continue
        world_T_marker, chosen = agreed
        key = object_symbol(added)
        values.insert(key, gtsam.Pose3(world_T_marker))
        for i, k in chosen:
            s = solved[i]
            cov = np.zeros((6, 6))
            cov[:3, :3] = s.covariance[:3, :3] * max(1.0, count[(s.camera_id, mk)] / max_fused)
            cov[3:, 3:] = np.eye(3) * FREE_ROTATION_RAD**2
            noise = gtsam.noiseModel.Robust.Create(robust, gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(cov)))
            graph.add(gtsam.BetweenFactorPose3(segment_keys[(s.camera_id, s.segment)], key, gtsam.Pose3((s.pose, s.alternative)[k]), noise))
        added += 1
    return added
