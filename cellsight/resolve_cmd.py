"""``cellsight resolve``: re-solve a recorded log in batch and write what people and tools read.

    DIR/resolved.mcap         solved poses and covariances on the daemon's keys (object markers over time), plus tf
    DIR/trajectories/*.tum    per-camera poses at every frame of a static segment, object markers at <= 10 Hz (for evo)
    DIR/report.html + *.png   top view, residuals, outliers per marker, online vs offline, truth
    DIR/resolve.json          the figures behind the report
    DIR/config.toml           the configuration used

Ground truth (``truth/`` keys, present in simulator logs) is read here only to evaluate; the
solve itself never sees it.
"""

from __future__ import annotations

import html
import logging
import json
import math
import tempfile
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterator, TextIO

import numpy as np

from cellsight.config import CellConfig, parse_config, save_used
from cellsight.report import MATCH_GAP_NS, Timeline, draw_ellipse, pose_error
from estimator.resolve import FrameBlock, ObjectRows, ResolveResult, SegmentResult, place_objects, resolve
from estimator.service import marker_frame
from schemas import codec, keys
from schemas import messages as m
from schemas.codec import StampedPose
from schemas.errors import DecodeError
from schemas.log import LogWriter, ReadReport, read_log

TRUTH_MIN_GAP_NS = 100_000_000  # keep ground truth and online estimates at <= 10 Hz per camera
OBJECT_GAP_NS = 100_000_000  # object markers: sightings kept per camera and poses written per marker at <= 10 Hz
log = logging.getLogger(__name__)
BLOCK_FRAMES = 30  # marker frames per camera validated and folded in together (1 s at 30 Hz)


@dataclass
class Side:
    """What the single pass over the log keeps besides the observations (bounded: <= 10 Hz)."""

    online: Timeline = field(default_factory=Timeline.empty)
    truth_cameras: Timeline = field(default_factory=Timeline.empty)
    truth_markers: dict[str, StampedPose] = field(default_factory=dict)
    object_frames: frozenset[str] = frozenset()  # marker_<id> of the object markers
    online_objects: Timeline = field(default_factory=Timeline.empty)
    truth_objects: Timeline = field(default_factory=Timeline.empty)
    cell: str | None = None

    def keep(self, tl: Timeline, msg, only: frozenset[str] | None = None) -> None:
        for child, p in codec.poses_from_msg(msg).items():
            if only is not None and child not in only:
                continue
            last = tl.stamps.get(child)
            if not last or p.stamp_ns - last[-1] >= TRUTH_MIN_GAP_NS:
                tl.stamps[child].append(p.stamp_ns)
                tl.poses[child].append(p)


def blocks_from_log(path: Path, side: Side, report: ReadReport, progress: Callable[[int, int], None] | None) -> Iterator[FrameBlock]:
    """Each camera's marker frames in blocks of ``BLOCK_FRAMES``, validated a block at a time."""
    pending: dict[str, list[m.MarkerObservations]] = {}
    for lm in read_log(path, None, report, progress, deferred=frozenset({m.MarkerObservations})):
        parsed = keys.parse(lm.key)
        side.cell = side.cell or parsed.cell
        if parsed.topic == "markers":
            msgs = pending.setdefault(lm.msg.camera_id, [])
            msgs.append(lm.msg)
            if len(msgs) == BLOCK_FRAMES:
                yield from _block(lm.msg.camera_id, pending.pop(lm.msg.camera_id), report)
        elif parsed.topic == "estimate/cameras":
            side.keep(side.online, lm.msg)
        elif parsed.topic == "estimate/markers" and side.object_frames:
            side.keep(side.online_objects, lm.msg, side.object_frames)
        elif parsed.topic == "truth/cameras":
            side.keep(side.truth_cameras, lm.msg)
        elif parsed.topic == "truth/markers":
            side.truth_markers.update(codec.poses_from_msg(lm.msg))
            if side.object_frames:
                side.keep(side.truth_objects, lm.msg, side.object_frames)
    for camera_id, msgs in pending.items():
        yield from _block(camera_id, msgs, report)


def _block(camera_id: str, msgs: list[m.MarkerObservations], report: ReadReport) -> Iterator[FrameBlock]:
    """Validate a camera's frames together; if that fails, one by one, dropping (and counting) the bad."""
    try:
        codec.check_id(camera_id, "marker observations camera_id")
        arrays = codec.marker_batch(msgs)
    except DecodeError:
        good = []
        for msg in msgs:
            try:
                codec.check_id(msg.camera_id, "marker observations camera_id")
                codec.marker_arrays(msg)
                good.append(msg)
            except DecodeError as exc:
                report.messages -= 1
                report.undecodable += 1
                log.warning("%s frame at %d ns skipped: %s", msg.camera_id[:40], msg.stamp_ns, exc)
        if not good:
            return
        msgs, arrays = good, codec.marker_batch(good, check=False)
    yield FrameBlock(camera_id, np.array([msg.stamp_ns for msg in msgs], dtype=np.int64), arrays)


def config_of_log(report: ReadReport) -> CellConfig | None:
    """The cell config the recorder embedded in the log, if any."""
    import tomllib

    text = report.metadata.get("cellsight", {}).get("config")
    return None if text is None else parse_config(tomllib.loads(text), "config embedded in the log")


def peek_config(path: Path) -> CellConfig | None:
    """Read only up to the log's metadata record (the recorder writes it first)."""
    report = ReadReport()
    for _ in read_log(path, set(), report):
        if report.metadata:
            break
    if "cellsight" not in report.metadata:
        for _ in read_log(path, set(), report):  # metadata written later: one cheap pass (nothing decoded)
            pass
    return config_of_log(report)


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


@dataclass(frozen=True)
class ResolveFigures:
    """The figures behind the report; ``resolve.json`` is this, field for field."""

    cameras: dict[str, CameraFigures]
    marker_position_error_mm_p50: float | None
    object_markers: dict[str, ObjectFigures]
    observations: int
    frames: int
    messages_read: int
    log_complete: bool
    stopped_early: str | None
    unanchored: list[str]
    flagged_anchors: list[int]
    lm_iterations: int
    object_links: int  # instants at which an object marker linked two or more cameras

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, default=float)


@dataclass
class ResolveRun:
    result: ResolveResult
    read: ReadReport
    side: Side
    out: Path
    figures: ResolveFigures


class ObjectSpool:
    """Object-marker sightings from the log's static frames, kept on disk until the cameras are
    solved: an hour of four cameras at 10 Hz is ~10^5 rows per marker, and memory holds one chunk."""

    DTYPE = np.dtype([("stamp", "<i8"), ("segment", "<i8"), ("marker", "<i8"), ("camera", "<i8"),
                      ("pose", "<f8", (4, 4)), ("cov", "<f8", (6, 6))])  # fmt: skip

    def __init__(self, directory: Path) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".objects-")
        self.cameras: list[str] = []
        self._last: dict[tuple[str, int], int] = {}
        self.rows = 0

    def add(self, rows: ObjectRows) -> None:
        """Append the rows, at most one per camera and marker per ``OBJECT_GAP_NS``."""
        keep = []
        for i, (stamp, mk) in enumerate(zip(rows.stamps.tolist(), rows.ids.tolist())):
            last = self._last.get((rows.camera_id, mk))
            if last is None or stamp - last >= OBJECT_GAP_NS:
                self._last[(rows.camera_id, mk)] = stamp
                keep.append(i)
        if not keep:
            return
        if rows.camera_id not in self.cameras:
            self.cameras.append(rows.camera_id)
        a = np.zeros(len(keep), self.DTYPE)
        a["stamp"], a["segment"], a["marker"] = rows.stamps[keep], rows.segments[keep], rows.ids[keep]
        a["camera"], a["pose"], a["cov"] = self.cameras.index(rows.camera_id), rows.poses[keep], rows.covariances[keep]
        a.tofile(self._file)
        self.rows += len(keep)

    def chunks(self, n: int = 20_000) -> Iterator[np.ndarray]:
        """The rows in log order, ``n`` at a time (structured arrays of ``DTYPE``)."""
        self._file.flush()
        self._file.seek(0)
        while len(a := np.fromfile(self._file, dtype=self.DTYPE, count=n)):
            yield a

    def close(self) -> None:
        self._file.close()


def run_resolve(log_path: Path, out: Path, cfg: CellConfig, progress: Callable[[int, int], None] | None = None) -> ResolveRun:
    out.mkdir(parents=True, exist_ok=True)
    save_used(cfg, out)
    side = Side(object_frames=frozenset(marker_frame(k) for k in cfg.estimator.object_markers))
    report, spool = ReadReport(), ObjectSpool(out)
    try:
        result = resolve(blocks_from_log(log_path, side, report, progress), cfg.estimator, objects=spool.add)
        figures = write_outputs(result, side, report, out, side.cell or cfg.cell.name, spool, cfg.estimator.object_markers)
    finally:
        spool.close()
    return ResolveRun(result, report, side, out, figures)


def object_poses(spool: ObjectSpool, result: ResolveResult) -> Iterator[StampedPose]:
    """Each object marker through the solved cameras, at most every ``OBJECT_GAP_NS``: of the
    sightings of one marker in one such period the one with the smallest position covariance
    (cameras see an object at different distances and through different uncertainties)."""
    segments = {(s.camera_id, s.segment): s for s in result.segments}
    best: dict[tuple[int, int], tuple[float, StampedPose]] = {}  # (marker, period) -> best so far
    newest = -1
    for a in spool.chunks():
        for ci, cam in enumerate(spool.cameras):
            rows = a[a["camera"] == ci]
            if not len(rows):
                continue
            T, cov, solved = place_objects(ObjectRows(cam, rows["stamp"], rows["segment"], rows["marker"], rows["pose"], rows["cov"]), segments)
            for stamp, mk, Ti, Ci in zip(rows["stamp"][solved].tolist(), rows["marker"][solved].tolist(), T, cov):
                key, score = (mk, stamp // OBJECT_GAP_NS), float(np.trace(Ci[:3, :3]))
                if key not in best or score < best[key][0]:
                    best[key] = (score, StampedPose("world", marker_frame(mk), stamp, Ti, Ci))
        # Sightings arrive in log order, a few frames apart across cameras: periods two behind are final.
        newest = max([newest] + [p for _, p in best])
        for key in sorted(k for k in best if k[1] < newest - 1):
            yield best.pop(key)[1]
    for key in sorted(best):
        yield best[key][1]


def segment_at(result: ResolveResult, cam: str, stamp: int) -> SegmentResult | None:
    """The solved segment of ``cam`` that covers ``stamp`` (None if it was moving or unanchored)."""
    best = None
    for s in result.segments:
        if s.camera_id == cam and s.frames and s.first_stamp_ns <= stamp <= s.last_stamp_ns:
            best = s
    return best


def write_outputs(result: ResolveResult, side: Side, report: ReadReport, out: Path, cell: str, spool: ObjectSpool | None = None,
                  object_markers: list[int] | None = None) -> ResolveFigures:  # fmt: skip
    end = max((s.last_stamp_ns for s in result.segments), default=0)
    # resolved.mcap: each segment's pose at its first and last frame, object markers over time,
    # static markers and tf at the end.
    w = LogWriter(out / "resolved.mcap", metadata={"source": "cellsight resolve", "object_markers": " ".join(map(str, object_markers or []))})
    for s in result.segments:
        for stamp in sorted({s.first_stamp_ns, s.last_stamp_ns}):
            w.write(keys.estimate_cameras(cell), codec.poses_to_msg(stamp, [StampedPose("world", s.camera_id, stamp, s.world_T_camera, s.covariance)]), stamp)
    for k in result.keyframes:  # a moving camera's frames, each solved as a pose of its own
        w.write(keys.estimate_cameras(cell), codec.poses_to_msg(k.stamp_ns, [StampedPose("world", k.camera_id, k.stamp_ns, k.world_T_camera, k.covariance)]), k.stamp_ns)
    tdir = out / "trajectories"
    tdir.mkdir(exist_ok=True)
    objects = ObjectErrors()
    if spool is not None:
        with ExitStack() as files:  # streamed: an hour is ~36,000 poses per object marker
            tum: dict[str, TextIO] = {}
            for p in object_poses(spool, result):
                w.write(keys.estimate_markers(cell), codec.poses_to_msg(p.stamp_ns, [p]), p.stamp_ns)
                if p.child not in tum:
                    tum[p.child] = files.enter_context((tdir / f"{p.child}.tum").open("w"))
                tum[p.child].write(f"{p.stamp_ns / 1e9:.9f} {tum_pose(p.T)}\n")
                objects.add(p, side)
    markers = [StampedPose("world", marker_frame(k), end, T, C) for k, (T, C) in result.markers.items()]
    w.write(keys.estimate_markers(cell), codec.poses_to_msg(end, markers), end)
    latest = {}
    for s in result.segments:
        latest[s.camera_id] = s
    w.write(keys.tf(cell), codec.transforms_to_msg(end, [("world", c, s.world_T_camera) for c, s in latest.items()] + [("world", p.child, p.T) for p in markers]), end)
    w.close()
    # TUM trajectories: "t tx ty tz qx qy qz qw" per frame of a solved static segment, and per
    # moving frame solved on its own.
    pose_text = {(s.camera_id, s.segment): tum_pose(s.world_T_camera) for s in result.segments}  # once: 10^5 frames/h
    for cam in sorted(set(result.frame_stamps) | {k.camera_id for k in result.keyframes}):
        rows = [(stamp, pose_text[(cam, seg)]) for stamp, seg in result.frame_stamps.get(cam, []) if (cam, seg) in pose_text]
        rows += [(k.stamp_ns, tum_pose(k.world_T_camera)) for k in result.keyframes if k.camera_id == cam]
        lines = [f"{stamp / 1e9:.9f} {text}" for stamp, text in sorted(rows)]
        (tdir / f"{cam}.tum").write_text("\n".join(lines) + ("\n" if lines else ""))
    figures = ResolveFigures(
        cameras=evaluate(result, side), marker_position_error_mm_p50=marker_error_p50(result, side),
        object_markers=objects.summary(side), observations=result.observations, frames=result.frames,
        messages_read=report.messages, log_complete=report.stopped_early is None, stopped_early=report.stopped_early,
        unanchored=result.unanchored, flagged_anchors=result.flagged_anchors, lm_iterations=result.iterations,
        object_links=result.object_links,
    )  # fmt: skip
    (out / "resolve.json").write_text(figures.to_json())
    plots(result, side, out)
    (out / "report.html").write_text(html_report(result, figures))
    return figures


def tum_pose(T: np.ndarray) -> str:
    q, t = codec.quat_from_matrix(T[:3, :3]), T[:3, 3]
    return f"{t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}"


@dataclass
class ObjectErrors:
    """Per object marker: poses written and, in simulator logs, their errors against ground truth."""

    poses: dict[str, int] = field(default_factory=dict)
    offline: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)  # (s, mm, deg)

    def add(self, p: StampedPose, side: Side) -> None:
        self.poses[p.child] = self.poses.get(p.child, 0) + 1
        t = side.truth_objects.at(p.child, p.stamp_ns)
        if t is not None and abs(t.stamp_ns - p.stamp_ns) <= OBJECT_GAP_NS // 2:
            self.offline.setdefault(p.child, []).append((p.stamp_ns / 1e9, *pose_error(p.T, t.T)))

    def summary(self, side: Side) -> dict[str, ObjectFigures]:
        out = {}
        for child in sorted(self.poses):
            online = []
            for p in side.online_objects.poses.get(child, []):
                t = side.truth_objects.at(child, p.stamp_ns)
                if t is not None and abs(t.stamp_ns - p.stamp_ns) <= OBJECT_GAP_NS // 2:
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


def evaluate(result: ResolveResult, side: Side) -> dict[str, CameraFigures]:
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
        cams[cam] = CameraFigures(_median_pair(off_truth), _median_pair(on_truth), _median_pair(on_off), _paired(paired),
                                  len(moving), _median_pair([e for _, e in moving_vs_truth(result, side, cam)]))  # fmt: skip
    return cams


def at_online_stamps(result: ResolveResult, side: Side, cam: str) -> Iterator[tuple[StampedPose, SegmentResult | None, StampedPose | None]]:
    """Each online estimate of ``cam`` with the solved segment covering its stamp and the ground
    truth within ``MATCH_GAP_NS`` of it (either None where there is none)."""
    for p in side.online.poses.get(cam, []):
        yield p, segment_at(result, cam, p.stamp_ns), side.truth_cameras.near(cam, p.stamp_ns)


def moving_vs_truth(result: ResolveResult, side: Side, cam: str) -> list[tuple[int, MmDeg]]:
    """(stamp ns, error) of each of ``cam``'s moving frames solved on their own, against ground
    truth interpolated to the frame's stamp (truth is kept at <= 10 Hz)."""
    out = []
    for k in result.keyframes:
        if k.camera_id == cam and (T := side.truth_cameras.interpolated(cam, k.stamp_ns)) is not None:
            out.append((k.stamp_ns, pose_error(k.world_T_camera, T)))
    return out


def marker_error_p50(result: ResolveResult, side: Side) -> float | None:
    """Median position error (mm) of the solved static markers that ground truth has."""
    err = [pose_error(T, t.T)[0] for k, (T, _) in result.markers.items() if (t := side.truth_markers.get(f"marker_{k}")) is not None]
    return float(np.median(err)) if err else None


def plots(result: ResolveResult, side: Side, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    for child, p in side.truth_markers.items():
        ax.plot(p.T[0, 3], p.T[1, 3], "s", ms=6, mfc="none", mec="0.6")
    for k, (T, C) in result.markers.items():
        ax.plot(T[0, 3], T[1, 3], "s", ms=3, color="tab:blue")
        draw_ellipse(ax, T, C, "tab:blue")
    for s in result.segments:
        ax.plot(s.world_T_camera[0, 3], s.world_T_camera[1, 3], "^", ms=7, color="tab:red")
        draw_ellipse(ax, s.world_T_camera, s.covariance, "tab:red")
        ax.annotate(f"{s.camera_id}.{s.segment}", s.world_T_camera[:2, 3], textcoords="offset points", xytext=(6, 4), fontsize=8)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_title("Resolved cameras (segment) and markers, 2-sigma ellipses x10")
    fig.tight_layout()
    fig.savefig(out / "top_view.png", dpi=110)
    plt.close(fig)

    cams = sorted({r.camera_id for r in result.residuals})
    fig, axes = plt.subplots(1, max(len(cams), 1), figsize=(3 * max(len(cams), 1), 3), squeeze=False)
    for ax, cam in zip(axes[0], cams):
        ax.hist([r.whitened_error for r in result.residuals if r.camera_id == cam], bins=15, color="tab:blue")
        ax.set_title(cam)
        ax.set_xlabel("whitened residual per pair")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=100)
    plt.close(fig)

    rejected: dict[int, int] = {}
    for r in result.residuals:
        rejected[r.marker_id] = rejected.get(r.marker_id, 0) + r.rejected
    fig, ax = plt.subplots(figsize=(8, 3))
    ids = sorted(rejected)
    ax.bar(range(len(ids)), [rejected[i] for i in ids], color="tab:orange")
    ax.set_xticks(range(len(ids)), [str(i) for i in ids])  # positions, not category strings (matplotlib logs those)
    ax.set_xlabel("marker id")
    ax.set_ylabel("observations rejected")
    ax.set_title("Outliers rejected per marker")
    fig.tight_layout()
    fig.savefig(out / "outliers.png", dpi=100)
    plt.close(fig)

    truth_cams = [cam for cam in sorted({s.camera_id for s in result.segments}) if side.truth_cameras.poses.get(cam)]
    t0 = min((s[0] for s in side.online.stamps.values() if s), default=0)
    if truth_cams:  # simulator logs: both solutions against ground truth, over time
        fig, axes = plt.subplots(len(truth_cams), 1, figsize=(8, 1.9 * len(truth_cams) + 0.6), sharex=True, squeeze=False)
        for ax, cam in zip(axes[:, 0], truth_cams):
            online = [((p.stamp_ns - t0) / 1e9, pose_error(p.T, t.T)[0]) for p, _, t in at_online_stamps(result, side, cam) if t is not None]
            if online:
                ax.plot(*zip(*_gaps_broken(online, MATCH_GAP_NS / 1e9)), "-", lw=0.9, color="tab:gray", label="online")
            # NaN where no segment covers the stamp: the line breaks while the camera moves
            offline = [((t.stamp_ns - t0) / 1e9, np.nan if (seg := segment_at(result, cam, t.stamp_ns)) is None else pose_error(seg.world_T_camera, t.T)[0])
                       for t in side.truth_cameras.poses[cam]]  # fmt: skip
            ax.plot(*zip(*offline), "-", lw=1.6, color="tab:blue", label="offline (segment)")
            moving = moving_vs_truth(result, side, cam)
            if moving:
                ax.plot([(s - t0) / 1e9 for s, _ in moving], [e[0] for _, e in moving], ".", ms=4, color="tab:red", label="offline (moving frame)")
            ax.set_ylabel(f"{cam} (mm)")
            ax.grid(alpha=0.3)
        axes[0, 0].set_title("Position error against ground truth")
        axes[0, 0].legend(fontsize=8, ncol=3, loc="upper right")
        axes[-1, 0].set_xlabel("log time (s)")
        fig.tight_layout()
        fig.savefig(out / "errors_vs_truth.png", dpi=100)
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 3.5))
    for cam, poses in sorted(side.online.poses.items()):
        rows = [((p.stamp_ns - t0) / 1e9, pose_error(p.T, seg.world_T_camera)[0]) for p in poses if (seg := segment_at(result, cam, p.stamp_ns)) is not None]
        if rows:
            ax.plot(*zip(*rows), ".-", ms=2, lw=0.8, label=cam)
    ax.set_yscale("log")
    ax.set_xlabel("log time (s)")
    ax.set_ylabel("online - offline position (mm)")
    ax.set_title("How far the online estimate was from the offline solution")
    ax.grid(alpha=0.3, which="both")
    if side.online.poses:
        ax.legend(fontsize=8, ncol=4)
    fig.tight_layout()
    fig.savefig(out / "online_vs_offline.png", dpi=100)
    plt.close(fig)


def _gaps_broken(rows: list[tuple[float, float]], gap_s: float) -> list[tuple[float, float]]:
    """(t s, value) rows with a NaN inserted where consecutive stamps are over ``gap_s`` apart, so
    a plotted line breaks there (the online estimate is not published while a camera moves)."""
    out = rows[:1]
    for a, b in zip(rows, rows[1:]):
        if b[0] - a[0] > gap_s:
            out.append((a[0], np.nan))
        out.append(b)
    return out


def html_report(result: ResolveResult, fig: ResolveFigures) -> str:
    def fmt(v: MmDeg | None) -> str:
        return "-" if v is None else f"{v[0]:.2f} mm / {v[1]:.3f} deg"

    def rms(p: Paired | None) -> str:
        return "-" if p is None else f"{p.offline_mm_deg_rms[0]:.2f} / {p.online_mm_deg_rms[0]:.2f} mm ({p.stamps})"

    rows = "".join(
        f"<tr><td>{html.escape(c)}</td><td>{fmt(v.offline_vs_truth_mm_deg)}</td><td>{fmt(v.online_vs_truth_mm_deg)}</td><td>{rms(v.paired)}</td>"
        f"<td>{fmt(v.online_vs_offline_mm_deg)}</td><td>{v.moving_frames}</td><td>{fmt(v.moving_frames_vs_truth_mm_deg)}</td></tr>"
        for c, v in fig.cameras.items()
    )
    segs = "".join(
        f"<tr><td>{html.escape(s.camera_id)}</td><td>{s.segment}</td><td>{s.frames}</td><td>{' '.join(f'{v:+.4f}' for v in s.world_T_camera[:3, 3])}</td>"
        f"<td>{1000 * math.sqrt(max(np.linalg.eigvalsh(s.covariance[:3, :3]).max(), 0)):.2f}</td></tr>"
        for s in result.segments
    )
    objects = "".join(
        f"<tr><td>{html.escape(c)}</td><td>{v.poses}</td><td>{fmt(v.offline_vs_truth_mm_deg)}</td><td>{fmt(v.online_vs_truth_mm_deg)}</td></tr>"
        for c, v in fig.object_markers.items()
    )
    objects_html = (
        "<h2>Object markers (placed through the solved cameras, at most 10 Hz; median errors)</h2>"
        f"<table><tr><th>marker</th><th>poses</th><th>offline vs truth</th><th>online vs truth</th></tr>{objects}</table>"
    ) if objects else ""
    truth_img = '<h2>Against ground truth</h2><img src="errors_vs_truth.png">' if any(c.offline_vs_truth_mm_deg for c in fig.cameras.values()) else ""
    warn = "" if fig.log_complete else f"<p class=warn>The log was not complete ({html.escape(str(fig.stopped_early))}); this covers what was readable.</p>"
    return f"""<!doctype html><html><head><meta charset=utf-8><title>cellsight resolve</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}} table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;padding:3px 8px}} .warn{{color:#a40}}</style></head><body>
<h1>Offline re-solve</h1>{warn}
<p>{fig.frames} frames, {fig.observations} marker observations, {len(result.segments)} camera segments, {len(result.markers)} markers;
Levenberg-Marquardt {fig.lm_iterations} iterations; {sum(c.moving_frames for c in fig.cameras.values())} moving frames and
{fig.object_links} object-marker instants seen by several cameras solved as poses of their own. Unanchored cameras: {', '.join(fig.unanchored) or 'none'}.
Anchors flagged as moved: {', '.join(map(str, fig.flagged_anchors)) or 'none'}.</p>
<h2>Cameras (median errors; truth only in simulator logs)</h2>
<table><tr><th>camera</th><th>offline vs truth</th><th>online vs truth</th><th>RMS at the same instants, offline / online (instants)</th><th>online vs offline</th><th>moving frames solved</th><th>their error vs truth</th></tr>{rows}</table>
{objects_html}
<h2>Segments</h2><table><tr><th>camera</th><th>segment</th><th>frames</th><th>position (m)</th><th>sigma (mm)</th></tr>{segs}</table>
<h2>Top view</h2><img src="top_view.png">
<h2>Residuals</h2><img src="residuals.png">
<h2>Outliers</h2><img src="outliers.png">
<h2>Online vs offline</h2><img src="online_vs_offline.png">{truth_img}
</body></html>"""
