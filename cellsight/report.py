"""The demo's summary: estimates against simulator ground truth, read back from the run's log.

This is evaluation code (it reads ``truth/`` keys on purpose); nothing in the estimator or
recognition reads them.
"""

from __future__ import annotations

import bisect
import json
import math
from collections import defaultdict
from dataclasses import asdict, dataclass
from pathlib import Path

import gtsam
import numpy as np

from schemas import codec, keys
from schemas.codec import StampedPose
from schemas.log import ReadReport, read_log

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
    def empty(cls) -> "Timeline":
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
        a, b = self.poses[child][i - 1].T, self.poses[child][i].T
        f = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        T = np.eye(4)
        T[:3, :3] = gtsam.Rot3(a[:3, :3]).slerp(f, gtsam.Rot3(b[:3, :3])).matrix()
        T[:3, 3] = (1 - f) * a[:3, 3] + f * b[:3, 3]
        return T


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(position error mm, rotation error deg)."""
    ang = math.degrees(codec.rotation_angle(T_est[:3, :3], T_true[:3, :3]))
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]) * 1000), ang


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
        keys.estimate_cameras(cell): d.est_cameras, keys.estimate_markers(cell): d.est_markers,
        keys.truth(cell, "cameras"): d.truth_cameras, keys.truth(cell, "markers"): d.truth_markers,
        keys.truth(cell, "objects"): d.truth_objects,
    }  # fmt: skip
    wanted = set(routes) | {keys.estimate_status(cell), keys.objects(cell)}
    for lm in read_log(log_path, wanted, d.read):
        if lm.key in routes:
            routes[lm.key].add(lm.msg)
        elif lm.key == keys.objects(cell):
            for o in lm.msg.objects:
                T = codec.pose_from_msg(o.world_T_object, f"object {o.object_id!r}")
                stamp = o.stamp_ns or lm.msg.stamp_ns  # logs before objects had their own stamps
                d.est_objects.add_pose(StampedPose("world", f"object_{o.object_id}", stamp, T))
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
            cos_tilt = float(np.clip(p.T[:3, 2] @ t.T[:3, 2], -1.0, 1.0))
            rows.append((p.stamp_ns, np.linalg.norm(p.T[:3, 3] - t.T[:3, 3]) * 1000, math.degrees(math.acos(cos_tilt))))
    a = np.array(rows) if rows else np.zeros((0, 3))
    return a[:, 0].astype(np.int64), a[:, 1], a[:, 2]


def summarize_objects(d: RunData) -> list[ObjectSummary]:
    t0 = min((s[0] for s in d.truth_cameras.stamps.values() if s), default=0)
    out = []
    for frame in sorted(d.truth_objects.stamps):
        stamps, pe, te = object_errors(d, frame)
        out.append(ObjectSummary(
            frame.removeprefix("object_"), len(d.est_objects.stamps.get(frame, [])),
            max(0.0, (int(stamps[0]) - t0) / 1e9) if len(stamps) else None,
            float(pe[-1]) if len(pe) else None, float(np.median(pe)) if len(pe) else None,
            float(np.median(te)) if len(te) else None,
        ))  # fmt: skip
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
            sigma = float(np.sqrt(np.linalg.eigvalsh(final.covariance[:3, :3]).max()) * 1000)
        cams.append(CameraSummary(
            cam, final_state, None if first is None else (first - t0) / 1e9,
            float(pe[-1]) if len(pe) else None, float(re[-1]) if len(re) else None,
            float(np.median(pe[last5])) if last5.any() else None, float(np.median(re[last5])) if last5.any() else None, sigma,
        ))  # fmt: skip
    markers = []
    for child, poses in sorted(d.est_markers.poses.items()):
        t = d.truth_markers.at(child, poses[-1].stamp_ns)
        if t is not None:
            markers.append(MarkerSummary(child, *pose_error(poses[-1].T, t.T)))
    return cams, markers


@dataclass(frozen=True)
class RunSummary:
    """What ``summary.json`` holds, field for field."""

    log: str
    messages_read: int
    log_complete: bool
    cameras: list[CameraSummary]
    markers: list[MarkerSummary]
    objects: list[ObjectSummary]

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)


def write_report(log_path: Path, cell: str, out_dir: Path) -> RunSummary:
    """summary.json, summary.md, top_view.png and errors.png in ``out_dir``; returns the summary."""
    d = load_run(log_path, cell)
    cams, markers = summarize(d)
    objects = summarize_objects(d)
    summary = RunSummary(str(log_path), d.read.messages, d.read.stopped_early is None, cams, markers, objects)
    (out_dir / "summary.json").write_text(summary.to_json())
    (out_dir / "summary.md").write_text(markdown(cams, markers, objects))
    plot_top_view(d, out_dir / "top_view.png")
    plot_errors(d, out_dir / "errors.png")
    return summary


def _fmt(v: float | None, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def markdown(cams: list[CameraSummary], markers: list[MarkerSummary], objects: list[ObjectSummary] = ()) -> str:
    lines = [
        "| camera | final state | localized after (s) | final pos err (mm) | final rot err (deg) | p50 last 5 s (mm / deg) | reported sigma (mm) |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cams:
        lines.append(
            f"| {c.camera_id} | {c.final_state} | {_fmt(c.first_localized_s, '.1f')} | {_fmt(c.position_error_mm_final, '.1f')} | "
            f"{_fmt(c.rotation_error_deg_final, '.2f')} | {_fmt(c.position_error_mm_p50_last5s, '.1f')} / {_fmt(c.rotation_error_deg_p50_last5s, '.2f')} | "
            f"{_fmt(c.position_sigma_mm_final, '.1f')} |"
        )
    if markers:
        pe = np.array([m.position_error_mm for m in markers])
        lines += ["", f"Markers ({len(markers)}): position error median {np.median(pe):.1f} mm, max {pe.max():.1f} mm."]
    if objects:
        lines += [
            "",
            "| object | detections | first seen (s) | final pos err (mm) | p50 pos err (mm) | p50 tilt err (deg) |",
            "|---|---|---|---|---|---|",
        ]
        for o in objects:
            lines.append(
                f"| {o.object_id} | {o.detections} | {_fmt(o.first_detected_s, '.1f')} | {_fmt(o.position_error_mm_final, '.1f')} | "
                f"{_fmt(o.position_error_mm_p50, '.1f')} | {_fmt(o.tilt_error_deg_p50, '.1f')} |"
            )
    return "\n".join(lines) + "\n"


def plot_top_view(d: RunData, path: Path) -> None:
    """Cameras, markers and objects seen from above, with 2-sigma ellipses (x 10) of the estimates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 7))
    for child, poses in d.truth_markers.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "s", ms=5, mfc="none", mec="0.5", label="marker (truth)" if child == next(iter(d.truth_markers.poses)) else None)
    for child, poses in d.est_markers.poses.items():
        T, cov = poses[-1].T, poses[-1].covariance
        ax.plot(T[0, 3], T[1, 3], "s", ms=3, color="tab:blue")
        draw_ellipse(ax, T, cov, "tab:blue")
    for child, poses in d.truth_objects.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "o", ms=9, mfc="none", mec="tab:orange")
        ax.annotate(child.replace("object_", ""), (T[0, 3], T[1, 3]), textcoords="offset points", xytext=(6, -10), fontsize=8, color="tab:orange")
    for child, poses in d.est_objects.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "o", ms=5, color="tab:orange")
    for cam, poses in d.truth_cameras.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "^", ms=10, mfc="none", mec="k")
        fwd = T[:3, 2] * 0.4
        ax.arrow(T[0, 3], T[1, 3], fwd[0], fwd[1], head_width=0.05, color="k", alpha=0.5)
        ax.annotate(cam, (T[0, 3], T[1, 3]), textcoords="offset points", xytext=(8, 4))
    for cam, poses in d.est_cameras.poses.items():
        T, cov = poses[-1].T, poses[-1].covariance
        ax.plot(T[0, 3], T[1, 3], "^", ms=6, color="tab:red")
        draw_ellipse(ax, T, cov, "tab:red")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Top view: truth (hollow) and estimates (filled), 2-sigma ellipses x10")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def draw_ellipse(ax, T: np.ndarray, cov: np.ndarray | None, color: str) -> None:
    """2-sigma x10 ellipse of a pose's x-y position uncertainty (body-frame covariance, ROS order)."""
    from matplotlib.patches import Ellipse

    if cov is None:
        return
    # Body-frame position covariance into the world frame, x-y block.
    C = (T[:3, :3] @ cov[:3, :3] @ T[:3, :3].T)[:2, :2]
    vals, vecs = np.linalg.eigh(C)
    vals = np.maximum(vals, 0)
    angle = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
    w, h = 2 * 2 * np.sqrt(vals[::-1]) * 10  # 2 sigma, x10
    ax.add_patch(Ellipse((T[0, 3], T[1, 3]), w, h, angle=angle, fill=False, color=color, lw=1))


def plot_errors(d: RunData, path: Path) -> None:
    """Position and rotation error of each camera's published pose over time; objects' position
    error below when the run recognised any."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = min((s[0] for s in d.truth_cameras.stamps.values() if s), default=0)
    has_objects = any(d.est_objects.stamps.values())
    fig, axes = plt.subplots(3 if has_objects else 2, 1, figsize=(8, 8.5 if has_objects else 6), sharex=True)
    a1, a2 = axes[0], axes[1]
    for cam in sorted(d.truth_cameras.stamps):
        stamps, pe, re = camera_errors(d, cam)
        t = (stamps - t0) / 1e9
        a1.plot(t, pe, ".-", ms=2, lw=0.8, label=cam)
        a2.plot(t, re, ".-", ms=2, lw=0.8, label=cam)
    a1.set_ylabel("camera position error (mm)")
    a2.set_ylabel("camera rotation error (deg)")
    a1.legend(ncol=4, fontsize=8)
    a1.set_title("Pose error against ground truth")
    if has_objects:
        a3 = axes[2]
        for frame in sorted(d.truth_objects.stamps):
            stamps, pe, _ = object_errors(d, frame)
            a3.plot((stamps - t0) / 1e9, pe, "o-", ms=3, lw=0.8, label=frame.removeprefix("object_"))
        a3.set_ylabel("object position error (mm)")
        a3.legend(ncol=4, fontsize=8)
    for ax in axes:
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[-1].set_xlabel("scenario time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
