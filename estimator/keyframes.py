"""Offline: a moving camera's frames as camera poses of their own in the batch problem.

While a camera moves, the daemon leaves it out of the graph: one pose per frame would grow the
graph without bound. Offline the log is finite, so each such frame that sees at least two markers
of the solved map becomes a pose (key ``k``) with one factor per marker. Every one is a view from
somewhere new, with a bias of its own, where a static view repeats one bias in every frame and
its fused factor counts at most ``max_fused`` of them. A frame that is the same view as one of
its camera's segments (a camera settling after a move) would count that view's bias again and is
left out. At the sensors' 30 Hz a move leaves tens of such frames, which tighten the cameras
that share markers with the moving one (``benchmarks.offline_vs_online``).

A move that leaves fewer than ``min_frames`` such frames adds none: a handful of single frames
brings its noise and biases more than it informs (a camera caught at ~5 frames/s during a 2 s
tilt leaves 3-4). The frames that join are weighed against the static pairs by how each fits
(``estimator.variance``): where the pairs fit far better than their covariances claim, the
frames' covariances are scaled up by as much (``weigh_by_fit``), and past ``max_inflation`` the
move's frames are left out: they would add next to nothing for a pose and factors each.

Memory stays bounded: at most one frame per camera every ``min_gap_s``; past ``max_frames`` every
other frame is dropped and the gap doubles, so the kept frames still cover the whole log.

Online (``LiveKeyframes``) the daemon holds a moving camera's frames (the same gap), each placed
against the map as it is held, until the camera is still again and its new segment has entered
the graph, or until they are ``lag_s`` old for a camera that keeps moving; then they join by the
same rules, and the newest ``max_live`` stay in the graph. Placed as they come, a move's first
``min_frames``, which enter in one update, are not all placed in it.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass

import gtsam
import numpy as np

from estimator.config import KeyframeConfig
from estimator.observation import Observation
from estimator.resect import implied_d2, resect
from estimator.symbols import keyframe_symbol, marker_symbol
from estimator.variance import Fit, inflation
from schemas.geometry import cov_ros_to_gtsam, covariance_in_frame, invert_poses, rotation_angles, rotations_within

AGREE_RAD = np.radians(5.0)  # two markers' implied camera poses agree within this rotation
AGREE_M = 0.05  # and this distance
GATE_CHI2 = 22.46  # chi-square, 6 dof, 1 in 1,000: a marker of a placed frame outside its own covariance of the pose


@dataclass(frozen=True)
class Placement:
    """A moving frame placed on the map: its ``world_T_camera`` (4, 4), the ``rows`` of the markers
    that agree with it and their ``branches`` (0: the pose the front-end chose, 1: its alternative),
    and how those markers fit it (``fit``: their squared Mahalanobis distances, 6 dof each less the
    pose's 6)."""

    world_T_camera: np.ndarray
    rows: list[int]
    branches: list[int]
    fit: Fit


@dataclass(frozen=True)
class MovingFrame:
    """One frame of a camera that was not in a static segment: marker ids (K,), camera_T_marker
    and the other IPPE branch (K, 4, 4), covariances (K, 6, 6; ROS order, marker frame)."""

    camera_id: str
    stamp_ns: int
    ids: np.ndarray
    poses: np.ndarray
    alternatives: np.ndarray
    covariances: np.ndarray
    move: int = 0  # the segment the camera left: frames of one move share it
    placed: Placement | None = None  # online: ``place_frame`` when held (see ``LiveKeyframes``)


class MovingFrames:
    """The kept moving frames, bounded as the module docstring says."""

    def __init__(self, config: KeyframeConfig) -> None:
        self.gap_ns = int(config.min_gap_s * 1e9)
        self.max_frames = config.max_frames
        self.frames: list[MovingFrame] = []
        self._last: dict[str, int] = {}

    def add(self, frame: MovingFrame) -> None:
        if len(frame.ids) < 2:
            return
        last = self._last.get(frame.camera_id)
        if last is not None and frame.stamp_ns - last < self.gap_ns:
            return
        self._last[frame.camera_id] = frame.stamp_ns
        self.frames.append(frame)
        if len(self.frames) > self.max_frames:
            self.frames = self.frames[::2]
            self.gap_ns *= 2


def place_frame(
    frame: MovingFrame, world_T_marker: dict[int, np.ndarray], rotation_floor_rad: float = 0.0
) -> Placement | None:
    """A frame's pose from the solved markers it sees, with the markers that agree with it (see
    ``Placement``); None unless two markers agree.

    Each observation's two IPPE branches each imply a camera pose through its marker. Branches are
    judged by rotation: a flip's implied rotation is off by its flip angle, while one frame's
    implied positions scatter by the lever arm (a marker's 1 deg is 5 cm at a camera 3 m away) and
    cannot judge it. Each marker whose branch agrees in rotation with the most takes it; the pose is
    resected over them (``resect``), the markers outside their own covariance of it (chi-square,
    6 dof, ``GATE_CHI2``; the view's rotation floor added, as in their factors) are left out, and
    it is resected over the rest.
    """
    rows = [j for j, mk in enumerate(frame.ids.tolist()) if mk in world_T_marker]
    if len(rows) < 2:
        return None
    world = np.stack([world_T_marker[int(frame.ids[j])] for j in rows])
    implied = world[:, None] @ invert_poses(
        np.stack([frame.poses[rows], frame.alternatives[rows]], axis=1)
    )  # (K, 2, 4, 4)
    agreed = consensus(implied, agree_m=math.inf)
    if agreed is None:
        return None
    idx, branches = [i for i, _ in agreed[1]], [k for _, k in agreed[1]]
    poses, covs = chosen_branches(frame, [rows[i] for i in idx], branches, rotation_floor_rad)
    T = resect(world[idx], np.zeros_like(covs), poses, covs)[0]
    d2 = implied_d2(T, world[idx], poses, covs)
    inside = d2 < GATE_CHI2
    if inside.sum() < 2:
        return None
    if not inside.all():
        idx, branches = [i for i, ok in zip(idx, inside) if ok], [k for k, ok in zip(branches, inside) if ok]
        poses, covs = poses[inside], covs[inside]
        T = resect(world[idx], np.zeros_like(covs), poses, covs)[0]
        d2 = implied_d2(T, world[idx], poses, covs)
    return Placement(T, [rows[i] for i in idx], branches, Fit(float(d2.sum()), 6 * (len(idx) - 1)))


def chosen_branches(
    frame: MovingFrame, rows: list[int], branches: list[int], rotation_floor_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """camera_T_marker (K, 4, 4) and covariance (K, 6, 6; ROS order, marker frame, the rotation
    floor added) of ``rows`` on their ``branches``: the other branch's covariance turned into its
    frame (the front-end gave it in the chosen pose's)."""
    poses, covs = frame.poses[rows].copy(), frame.covariances[rows].copy()
    other = np.array(branches, dtype=bool)
    covs[other] = covariance_in_frame(covs[other], poses[other, :3, :3], frame.alternatives[rows][other, :3, :3])
    poses[other] = frame.alternatives[rows][other]
    covs[:, 3:, 3:] += np.eye(3) * rotation_floor_rad**2
    return poses, covs


def consensus(implied: np.ndarray, agree_m: float = AGREE_M) -> tuple[np.ndarray, list[tuple[int, int]]] | None:
    """The pose most witnesses agree on, from each witness's two IPPE branches (K, 2, 4, 4), and
    (witness, branch) of those that agree with it (within ``AGREE_RAD`` and ``agree_m``); None
    unless two witnesses agree."""
    flat = implied.reshape(-1, 4, 4)
    # (2K, 2K): does candidate pose c lie near witness branch j? All pairs at once: a camera on an arm
    # places a frame almost every tick, with K up to 32.
    R = flat[:, :3, :3]
    close = rotations_within(R[:, None], R[None, :], AGREE_RAD) & (
        np.linalg.norm(flat[:, None, :3, 3] - flat[None, :, :3, 3], axis=-1) < agree_m
    )
    votes = close.reshape(len(flat), -1, 2).any(axis=2).sum(axis=1)  # witnesses with a branch near each candidate
    b = int(np.argmax(votes))  # the first of the most agreed
    if votes[b] < 2:
        return None
    best = flat[b]
    gap = rotation_angles(implied[:, :, :3, :3], best[:3, :3])  # (K, 2)
    k = np.argmin(gap, axis=1)
    rows = np.arange(len(implied))
    ok = (gap[rows, k] < AGREE_RAD) & (np.linalg.norm(implied[rows, k, :3, 3] - best[:3, 3], axis=1) < agree_m)
    chosen = [(int(i), int(k[i])) for i in np.flatnonzero(ok)]
    return best, chosen


def _is_new_view(T: np.ndarray, seen: list[np.ndarray], config: KeyframeConfig) -> bool:
    """Has the camera turned or moved by a new view's worth from every pose in ``seen``?"""
    if not seen:
        return True
    S = np.stack(seen)
    same = (rotation_angles(S[:, :3, :3], T[:3, :3]) < np.radians(config.new_view_deg)) & (
        np.linalg.norm(S[:, :3, 3] - T[:3, 3], axis=1) < config.new_view_m
    )
    return not bool(same.any())


@dataclass(frozen=True)
class Selected:
    """A frame ``select_keyframes`` kept: its index in the frames it was given, and its placement."""

    index: int
    frame: MovingFrame
    placement: Placement


def select_keyframes(
    frames: list[MovingFrame],
    world_T_marker: dict[int, np.ndarray],
    segment_poses: dict[str, list[np.ndarray]],
    rotation_floor_rad: float,
    config: KeyframeConfig,
) -> list[Selected]:
    """The frames that ``place_frame`` can place and that are new views (not their camera's
    segments' ``segment_poses`` nor the frame kept before), of moves with at least
    ``config.min_frames`` of them, in order."""
    placed = []
    last: dict[str, np.ndarray] = {}
    for i, frame in enumerate(frames):
        p = frame.placed or place_frame(frame, world_T_marker, rotation_floor_rad)
        if p is None:
            continue
        seen = segment_poses.get(frame.camera_id, []) + ([last[frame.camera_id]] if frame.camera_id in last else [])
        if not _is_new_view(p.world_T_camera, seen, config):
            continue
        last[frame.camera_id] = p.world_T_camera
        placed.append(Selected(i, frame, p))
    per_move = Counter((s.frame.camera_id, s.frame.move) for s in placed)
    return [s for s in placed if per_move[(s.frame.camera_id, s.frame.move)] >= config.min_frames]


def fit_of(selected: list[Selected]) -> Fit:
    """How the selected frames' markers fit their placements, together."""
    return sum((s.placement.fit for s in selected), Fit())


def weighed(static: Fit, frames: Fit, config: KeyframeConfig) -> tuple[float, bool]:
    """The factor on moving frames' covariances against the static pairs (``inflation``; 1 without
    ``weigh_by_fit``), and whether it leaves them out (past ``max_inflation``)."""
    factor = inflation(static, frames) if config.weigh_by_fit else 1.0
    return factor, factor > config.max_inflation


def add_keyframes(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    selected: list[Selected],
    rotation_floor_rad: float,
    robust: gtsam.noiseModel.mEstimator.Base,
    first_index: int = 0,
    max_markers: int = 0,
    covariance_scale: float = 1.0,
) -> list[tuple[int, MovingFrame, int]]:
    """Add each selected frame to ``graph`` and ``values`` (in place): a pose ``k<first_index +
    index>`` and one robust factor per agreeing marker, its single-frame covariance plus the view's
    rotation floor, times ``covariance_scale`` (``estimator.variance.inflation``). Returns (key, frame,
    markers used) of the frames added, whose factors are the graph's last, in that order."""
    added = []
    for s in selected:
        frame, p = s.frame, s.placement
        key = keyframe_symbol(first_index + s.index)
        values.insert(key, gtsam.Pose3(p.world_T_camera))
        kept = p.rows
        poses, covs = chosen_branches(frame, kept, p.branches, rotation_floor_rad)
        if 0 < max_markers < len(kept):
            best = np.sort(np.argsort(np.trace(covs[:, :3, :3], axis1=1, axis2=2))[:max_markers])
            kept, poses, covs = [kept[b] for b in best], poses[best], covs[best]
        for j, T, cov in zip(kept, poses, covs * covariance_scale):
            noise = gtsam.noiseModel.Robust.Create(robust, gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(cov)))
            graph.add(gtsam.BetweenFactorPose3(key, marker_symbol(int(frame.ids[j])), gtsam.Pose3(T), noise))
        added.append((key, frame, len(kept)))
    return added


@dataclass
class KeyframeFactor:
    """A live moving frame's factor; ``slot``: its index in iSAM2 once added."""

    slot: int | None = None


@dataclass
class LiveKeyframe:
    key: int
    camera_id: str
    stamp_ns: int
    factors: list[KeyframeFactor]


class LiveKeyframes:
    """Online moving frames (the daemon's graph), in a fixed lag: see the module docstring."""

    def __init__(self, config: KeyframeConfig) -> None:
        self.config = config
        self.gap_ns = int(config.min_gap_s * 1e9)
        self.pending: dict[str, deque[MovingFrame]] = {}  # camera -> its newest frames while moving
        self.live: deque[LiveKeyframe] = deque()
        self.next_index = 0  # keys are never reused
        self._move_entered: dict[
            str, tuple[int, int, Fit]
        ] = {}  # camera -> (its latest move, frames of it entered, their fit)
        self.inflation = 1.0  # the covariance factor of the frames weighed last (``estimator.variance.inflation``)
        self.refused = 0  # frames left out for it (``max_inflation``)

    def due(self, camera_id: str, stamp_ns: int) -> bool:
        """Would a frame of this camera at ``stamp_ns`` be held (``min_gap_s`` since the last)?
        Asked first, so the frames in between are never built."""
        frames = self.pending.get(camera_id)
        return not frames or stamp_ns - frames[-1].stamp_ns >= self.gap_ns

    def hold(self, frame: MovingFrame) -> None:
        """Keep a moving camera's frame (two markers or more, one per ``min_gap_s``, the newest
        ``max_live`` a camera) until its move ends."""
        if len(frame.ids) >= 2 and self.due(frame.camera_id, frame.stamp_ns):
            self.pending.setdefault(frame.camera_id, deque(maxlen=self.config.max_live)).append(frame)

    def enter(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        frames: list[MovingFrame],
        world_T_marker: dict[int, np.ndarray],
        segment_poses: dict[str, list[np.ndarray]],
        rotation_floor_rad: float,
        robust: gtsam.noiseModel.mEstimator.Base,
        static: Fit,
    ) -> tuple[list[tuple[int, KeyframeFactor]], list[int]]:
        """``add_keyframes`` of one camera's ``frames`` (a finished move's, or the older ones of a
        move still going on), move by move, weighed against the static pairs' fit ``static`` by
        the fit of all the move's frames so far (``weigh_by_fit``); returns (position in
        ``graph``, owner) of each new factor, for its slot, and the new frames' keys. A move that
        already gave ``min_frames`` has shown it is one: its later frames join however few (a
        camera on an arm passes turning points where few frames are new views)."""
        slotted, keys = [], []
        for move in dict.fromkeys(f.move for f in frames):  # in order
            group = [f for f in frames if f.move == move]
            cid = group[0].camera_id
            entered_move, entered, fit = self._move_entered.get(cid, (-1, 0, Fit()))
            if entered_move != move:
                entered, fit = 0, Fit()
            config = (
                self.config.model_copy(update={"min_frames": 1}) if entered >= self.config.min_frames else self.config
            )
            selected = select_keyframes(group, world_T_marker, segment_poses, rotation_floor_rad, config)
            first_index, self.next_index = self.next_index, self.next_index + len(group)
            if not selected:
                continue
            fit = fit + fit_of(selected)
            self.inflation, left_out = weighed(static, fit, self.config)
            self._move_entered[cid] = (move, entered, fit)
            if left_out:
                self.refused += len(selected)
                continue
            start = graph.size()
            added = add_keyframes(
                graph,
                values,
                selected,
                rotation_floor_rad,
                robust,
                first_index=first_index,
                max_markers=self.config.max_markers_online,
                covariance_scale=self.inflation,
            )
            self._move_entered[cid] = (move, entered + len(added), fit)
            position = start
            for key, frame, n in added:
                owners = [KeyframeFactor() for _ in range(n)]
                slotted += [(position + j, f) for j, f in enumerate(owners)]
                position += n
                self.live.append(LiveKeyframe(key, frame.camera_id, frame.stamp_ns, owners))
                keys.append(key)
        return slotted, keys

    def trim(self, remove: list[int]) -> list[int]:
        """Drop the oldest frames beyond ``max_live`` that are in iSAM2 (their factors' slots go
        into ``remove``: iSAM2 drops a variable with none); returns their keys."""
        dropped = []
        while len(self.live) > self.config.max_live and all(f.slot is not None for f in self.live[0].factors):
            frame = self.live.popleft()
            remove.extend(f.slot for f in frame.factors)
            dropped.append(frame.key)
        return dropped


def moving_frame(camera_id: str, stamp_ns: int, static: list[Observation], move: int) -> MovingFrame:
    """A moving camera's frame of static-marker observations, as ``LiveKeyframes`` holds it."""
    return MovingFrame(
        camera_id,
        stamp_ns,
        np.array([o.marker_id for o in static], dtype=np.int64),
        np.array([o.camera_T_marker for o in static]).reshape(-1, 4, 4),
        np.array([o.alternative if o.alternative is not None else o.camera_T_marker for o in static]).reshape(-1, 4, 4),
        np.array([o.covariance for o in static]).reshape(-1, 6, 6),
        move,
    )
