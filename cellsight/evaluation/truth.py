"""Estimates against ground truth: the one evaluation library of reports and benchmarks.

It reads ``truth/`` keys (simulator logs) on purpose; nothing in drivers, the estimator or
recognition does. Errors are (position mm, rotation deg) from ``schemas.geometry.pose_error``.
"""

from __future__ import annotations

import bisect
import math
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimator.offline.outputs import segment_at
from estimator.offline.solve import ResolveResult, SegmentResult
from schemas import codec, keys
from schemas.codec import StampedPose
from schemas.geometry import angle_between, interpolate_pose, pose_error, position_sigma
from schemas.log import LogMessage, ReadReport, read_log

TRUTH_MIN_GAP_NS = 100_000_000  # offline evaluation keeps ground truth and online estimates at <= 10 Hz per frame
OBJECT_MATCH_GAP_NS = 50_000_000  # an object-marker pose and a truth sample further apart are not compared
STATE_NAMES = {1: "localized", 2: "unanchored", 3: "moving", 4: "stale"}
MATCH_GAP_NS = 200_000_000  # an estimate and a truth sample further apart than this are not compared


@dataclass
class CameraSummary:
    camera_id: str
    final_state: str
    first_localized_s: float | None  # scenario seconds from the first frame
    position_error_mm_final: float | None
    rotation_error_deg_final: float | None
    position_error_mm_p50_last5s: float | None
    rotation_error_deg_p50_last5s: float | None
    position_sigma_mm_final: float | None


@dataclass
class MarkerSummary:
    frame: str
    position_error_mm: float
    rotation_error_deg: float


@dataclass
class ObjectSummary:
    """One simulated object: how the recognition worker's fused world poses compare with truth.

    Errors are of the object frame's origin (base centre) and of its up axis, both unaffected by
    the turns that leave a box or a cylinder looking the same; yaw is not scored for that reason.
    """

    object_id: str
    detections: int  # objects messages that contained it
    first_detected_s: float | None  # scenario seconds from the first frame
    position_error_mm_final: float | None
    position_error_mm_p50: float | None
    tilt_error_deg_p50: float | None


@dataclass
class Timeline:
    """Per child frame: sorted stamps and poses."""

    stamps: dict[str, list[int]]
    poses: dict[str, list[StampedPose]]

    @classmethod
    def empty(cls) -> Timeline:
        return cls(defaultdict(list), defaultdict(list))

    def add(self, msg) -> None:
        for p in codec.poses_from_msg(msg).values():
            self.add_pose(p)

    def add_pose(self, p: StampedPose) -> None:
        self.stamps[p.child].append(p.stamp_ns)
        self.poses[p.child].append(p)

    def at(self, child: str, stamp_ns: int) -> StampedPose | None:
        """The pose with the nearest stamp (truth is published every frame)."""
        stamps = self.stamps.get(child)
        if not stamps:
            return None
        i = bisect.bisect_left(stamps, stamp_ns)
        best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp_ns))
        return self.poses[child][best]

    def near(self, child: str, stamp_ns: int, max_gap_ns: int = MATCH_GAP_NS) -> StampedPose | None:
        """``at``, or None when the nearest sample is ``max_gap_ns`` or more away (ns)."""
        t = self.at(child, stamp_ns)
        return t if t is not None and abs(t.stamp_ns - stamp_ns) < max_gap_ns else None

    def interpolated(self, child: str, stamp_ns: int, max_gap_ns: int = MATCH_GAP_NS) -> np.ndarray | None:
        """world_T_child (4x4) at ``stamp_ns`` between the two samples around it (position linear,
        rotation along the geodesic); None outside the samples or across a gap over ``max_gap_ns``.
        For a moving body whose samples were thinned (truth is kept at <= 10 Hz)."""
        stamps = self.stamps.get(child)
        if not stamps:
            return None
        i = bisect.bisect_left(stamps, stamp_ns)
        if i < len(stamps) and stamps[i] == stamp_ns:
            return self.poses[child][i].T
        if i == 0 or i == len(stamps) or stamps[i] - stamps[i - 1] > max_gap_ns:
            return None
        f = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        return interpolate_pose(self.poses[child][i - 1].T, self.poses[child][i].T, f)


@dataclass
class RunData:
    est_cameras: Timeline
    est_markers: Timeline
    truth_cameras: Timeline
    truth_markers: Timeline
    truth_objects: Timeline
    est_objects: Timeline  # child frames named like the truth: object_<id>
    states: dict[str, list[tuple[int, int]]]  # camera -> (stamp, state)
    read: ReadReport


def load_run(log_path: Path, cell: str) -> RunData:
    d = RunData(*(Timeline.empty() for _ in range(6)), defaultdict(list), ReadReport())
    routes = {
        keys.estimate_cameras(cell): d.est_cameras,
        keys.estimate_markers(cell): d.est_markers,
        keys.truth(cell, "cameras"): d.truth_cameras,
        keys.truth(cell, "marker_poses"): d.truth_markers,
        keys.truth(cell, "objects"): d.truth_objects,
    }
    wanted = set(routes) | {keys.estimate_status(cell), keys.objects(cell)}
    for lm in read_log(log_path, wanted, d.read):
        if lm.key in routes:
            routes[lm.key].add(lm.msg)
        elif lm.key == keys.objects(cell):
            for o in lm.msg.objects:
                T = codec.pose_from_msg(o.world_T_object, f"object {o.object_id!r}")
                stamp = o.stamp_ns or lm.msg.stamp_ns  # logs before objects had their own stamps
                d.est_objects.add_pose(StampedPose("world", keys.object_frame(o.object_id), stamp, T))
        else:
            for cam in lm.msg.cameras:
                d.states[cam.camera_id].append((lm.msg.stamp_ns, cam.state))
    for tl in (d.est_cameras, d.est_markers, d.truth_cameras, d.truth_markers, d.truth_objects, d.est_objects):
        for child in list(tl.stamps):
            order = np.argsort(tl.stamps[child], kind="stable")
            tl.stamps[child] = [tl.stamps[child][i] for i in order]
            tl.poses[child] = [tl.poses[child][i] for i in order]
    return d


def camera_errors(d: RunData, cam: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps ns, position errors mm, rotation errors deg) of every published pose of ``cam``."""
    rows = []
    for p in d.est_cameras.poses.get(cam, []):
        t = d.truth_cameras.near(cam, p.stamp_ns)
        if t is not None:
            rows.append((p.stamp_ns, *pose_error(p.T, t.T)))
    a = np.array(rows) if rows else np.zeros((0, 3))
    return a[:, 0].astype(np.int64), a[:, 1], a[:, 2]


def object_errors(d: RunData, frame: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps ns, position errors mm, tilt errors deg) of every published pose of object ``frame``."""
    rows = []
    for p in d.est_objects.poses.get(frame, []):
        t = d.truth_objects.near(frame, p.stamp_ns)
        if t is not None:
            rows.append(
                (
                    p.stamp_ns,
                    np.linalg.norm(p.T[:3, 3] - t.T[:3, 3]) * 1000,
                    math.degrees(angle_between(p.T[:3, 2], t.T[:3, 2])),
                )
            )
    a = np.array(rows) if rows else np.zeros((0, 3))
    return a[:, 0].astype(np.int64), a[:, 1], a[:, 2]


def summarize_objects(d: RunData) -> list[ObjectSummary]:
    t0 = min((s[0] for s in d.truth_cameras.stamps.values() if s), default=0)
    out = []
    for frame in sorted(d.truth_objects.stamps):
        stamps, pe, te = object_errors(d, frame)
        out.append(
            ObjectSummary(
                frame.removeprefix("object_"),
                len(d.est_objects.stamps.get(frame, [])),
                max(0.0, (int(stamps[0]) - t0) / 1e9) if len(stamps) else None,
                float(pe[-1]) if len(pe) else None,
                float(np.median(pe)) if len(pe) else None,
                float(np.median(te)) if len(te) else None,
            )
        )
    return out


def summarize(d: RunData) -> tuple[list[CameraSummary], list[MarkerSummary]]:
    t0 = min((s[0] for s in d.truth_cameras.stamps.values() if s), default=0)
    cams = []
    for cam in sorted(d.truth_cameras.stamps):
        stamps, pe, re = camera_errors(d, cam)
        states = d.states.get(cam, [])
        final_state = STATE_NAMES.get(states[-1][1], "unknown") if states else "never seen"
        first = next((s for s, st in states if st == 1), None)
        last5 = stamps >= (stamps[-1] - 5_000_000_000) if len(stamps) else np.zeros(0, bool)
        final = d.est_cameras.poses[cam][-1] if d.est_cameras.poses.get(cam) else None
        sigma = None
        if final is not None and final.covariance is not None:
            sigma = position_sigma(final.covariance) * 1000
        cams.append(
            CameraSummary(
                cam,
                final_state,
                None if first is None else (first - t0) / 1e9,
                float(pe[-1]) if len(pe) else None,
                float(re[-1]) if len(re) else None,
                float(np.median(pe[last5])) if last5.any() else None,
                float(np.median(re[last5])) if last5.any() else None,
                sigma,
            )
        )
    markers = []
    for child, poses in sorted(d.est_markers.poses.items()):
        t = d.truth_markers.at(child, poses[-1].stamp_ns)
        if t is not None:
            markers.append(MarkerSummary(child, *pose_error(poses[-1].T, t.T)))
    return cams, markers


# ---------------------------------------------------------------- offline solve vs online vs truth


@dataclass
class LogEvidence:
    """What an offline solve is judged against, collected from the same single pass over the log
    (``take`` each message that is not a marker observation): the online estimates and, in
    simulator logs, ground truth; bounded at <= 10 Hz per frame."""

    online: Timeline = field(default_factory=Timeline.empty)
    truth_cameras: Timeline = field(default_factory=Timeline.empty)
    truth_markers: dict[str, StampedPose] = field(default_factory=dict)
    object_frames: frozenset[str] = frozenset()  # marker_<id> of the object markers
    online_objects: Timeline = field(default_factory=Timeline.empty)
    truth_objects: Timeline = field(default_factory=Timeline.empty)

    def take(self, lm: LogMessage) -> None:
        """Keep what evaluation needs of one logged message."""
        topic = keys.parse(lm.key).topic
        if topic == "estimate/cameras":
            self.keep(self.online, lm.msg)
        elif topic == "estimate/markers" and self.object_frames:
            self.keep(self.online_objects, lm.msg, self.object_frames)
        elif topic == "truth/cameras":
            self.keep(self.truth_cameras, lm.msg)
        elif topic == "truth/marker_poses":
            self.truth_markers.update(codec.poses_from_msg(lm.msg))
            if self.object_frames:
                self.keep(self.truth_objects, lm.msg, self.object_frames)

    def keep(self, tl: Timeline, msg, only: frozenset[str] | None = None) -> None:
        for child, p in codec.poses_from_msg(msg).items():
            if only is not None and child not in only:
                continue
            last = tl.stamps.get(child)
            if not last or p.stamp_ns - last[-1] >= TRUTH_MIN_GAP_NS:
                tl.stamps[child].append(p.stamp_ns)
                tl.poses[child].append(p)


MmDeg = tuple[float, float]  # (position error mm, rotation error deg)


@dataclass(frozen=True)
class Paired:
    """Offline and online errors against ground truth at the same instants (``stamps`` of them):
    medians and RMS, (mm, deg)."""

    stamps: int
    offline_mm_deg_p50: MmDeg
    online_mm_deg_p50: MmDeg
    offline_mm_deg_rms: MmDeg
    online_mm_deg_rms: MmDeg


@dataclass(frozen=True)
class CameraFigures:
    """One camera's median errors (mm, deg); those against truth are None in logs without it."""

    offline_vs_truth_mm_deg: MmDeg | None
    online_vs_truth_mm_deg: MmDeg | None
    online_vs_offline_mm_deg: MmDeg | None
    paired: Paired | None
    moving_frames: int  # frames of a moving camera solved as poses of their own
    moving_frames_vs_truth_mm_deg: MmDeg | None


@dataclass(frozen=True)
class ObjectFigures:
    """One object marker: poses written, median errors (mm, deg) against truth."""

    poses: int
    offline_vs_truth_mm_deg: MmDeg | None
    online_vs_truth_mm_deg: MmDeg | None


@dataclass
class ObjectErrors:
    """Per object marker: poses written and, in simulator logs, their errors against ground truth."""

    poses: dict[str, int] = field(default_factory=dict)
    offline: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)  # (s, mm, deg)

    def add(self, p: StampedPose, side: LogEvidence) -> None:
        self.poses[p.child] = self.poses.get(p.child, 0) + 1
        t = side.truth_objects.at(p.child, p.stamp_ns)
        if t is not None and abs(t.stamp_ns - p.stamp_ns) <= OBJECT_MATCH_GAP_NS:
            self.offline.setdefault(p.child, []).append((p.stamp_ns / 1e9, *pose_error(p.T, t.T)))

    def summary(self, side: LogEvidence) -> dict[str, ObjectFigures]:
        out = {}
        for child in sorted(self.poses):
            online = []
            for p in side.online_objects.poses.get(child, []):
                t = side.truth_objects.at(child, p.stamp_ns)
                if t is not None and abs(t.stamp_ns - p.stamp_ns) <= OBJECT_MATCH_GAP_NS:
                    online.append(pose_error(p.T, t.T))
            off = [e[1:] for e in self.offline.get(child, [])]
            out[child] = ObjectFigures(self.poses[child], _median_pair(off), _median_pair(online))
        return out


def _median_pair(rows: list[MmDeg]) -> MmDeg | None:
    """Median position and rotation error of (mm, deg) rows, None without rows."""
    return (float(np.median([r[0] for r in rows])), float(np.median([r[1] for r in rows]))) if rows else None


def _paired(rows: list[tuple[float, float, float, float]]) -> Paired | None:
    """Rows of (offline mm, offline deg, online mm, online deg) at the same instants."""
    if not rows:
        return None
    a = np.array(rows)
    med, rms = np.median(a, axis=0).tolist(), np.sqrt(np.mean(a**2, axis=0)).tolist()
    return Paired(len(rows), (med[0], med[1]), (med[2], med[3]), (rms[0], rms[1]), (rms[2], rms[3]))


def evaluate_offline(result: ResolveResult, side: LogEvidence) -> dict[str, CameraFigures]:
    """Offline vs online vs truth, per camera: median position / rotation errors.

    ``paired``: at every online estimate's stamp that a solved segment covers and ground truth
    has, both errors at that instant (the like-for-like comparison): medians and RMS.
    ``moving_frames``: how many of the camera's moving frames were solved as poses of their own,
    and their median error against ground truth interpolated to their stamps.
    """
    cams: dict[str, CameraFigures] = {}
    for cam in sorted({s.camera_id for s in result.segments}):
        off_truth, on_truth, on_off, paired = [], [], [], []
        for p, seg, t in at_online_stamps(result, side, cam):
            if seg is not None:
                on_off.append(pose_error(p.T, seg.world_T_camera))
            if t is not None:
                on_truth.append(pose_error(p.T, t.T))
                if seg is not None:
                    paired.append((*pose_error(seg.world_T_camera, t.T), *pose_error(p.T, t.T)))
        for t in side.truth_cameras.poses.get(cam, []):
            seg = segment_at(result, cam, t.stamp_ns)
            if seg is not None:
                off_truth.append(pose_error(seg.world_T_camera, t.T))
        moving = [k for k in result.keyframes if k.camera_id == cam]
        cams[cam] = CameraFigures(
            _median_pair(off_truth),
            _median_pair(on_truth),
            _median_pair(on_off),
            _paired(paired),
            len(moving),
            _median_pair([e for _, e in moving_vs_truth(result, side, cam)]),
        )
    return cams


def at_online_stamps(
    result: ResolveResult, side: LogEvidence, cam: str
) -> Iterator[tuple[StampedPose, SegmentResult | None, StampedPose | None]]:
    """Each online estimate of ``cam`` with the solved segment covering its stamp and the ground
    truth within ``MATCH_GAP_NS`` of it (either None where there is none)."""
    for p in side.online.poses.get(cam, []):
        yield p, segment_at(result, cam, p.stamp_ns), side.truth_cameras.near(cam, p.stamp_ns)


def moving_vs_truth(result: ResolveResult, side: LogEvidence, cam: str) -> list[tuple[int, MmDeg]]:
    """(stamp ns, error) of each of ``cam``'s moving frames solved on their own, against ground
    truth interpolated to the frame's stamp (truth is kept at <= 10 Hz)."""
    out = []
    for k in result.keyframes:
        if k.camera_id == cam and (T := side.truth_cameras.interpolated(cam, k.stamp_ns)) is not None:
            out.append((k.stamp_ns, pose_error(k.world_T_camera, T)))
    return out


def marker_error_p50(result: ResolveResult, side: LogEvidence) -> float | None:
    """Median position error (mm) of the solved static markers that ground truth has."""
    err = [
        pose_error(T, t.T)[0]
        for k, (T, _) in result.markers.items()
        if (t := side.truth_markers.get(keys.marker_frame(k))) is not None
    ]
    return float(np.median(err)) if err else None
