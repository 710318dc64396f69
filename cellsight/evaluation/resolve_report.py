"""``cellsight resolve``: the offline solve of a log (``estimator.offline``), judged and reported.

    DIR/resolved.mcap         solved poses and covariances on the daemon's keys (object markers over time), plus tf
    DIR/trajectories/*.tum    per-camera poses at every frame of a static segment, object markers at <= 10 Hz (for evo)
    DIR/report.html + *.png   top view, residuals, outliers per marker, online vs offline, truth
    DIR/resolve.json          the figures behind the report
    DIR/config.toml           the configuration used

Ground truth (``truth/`` keys, present in simulator logs) is read only by ``cellsight.evaluation.truth``,
from the same single pass; the solve never sees it.
"""

from __future__ import annotations

import html
import json
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cellsight.config import CellConfig, parse_config, save_used
from cellsight.evaluation.report import draw_ellipse
from cellsight.evaluation.truth import (
    MATCH_GAP_NS,
    CameraFigures,
    LogEvidence,
    MmDeg,
    ObjectErrors,
    ObjectFigures,
    Paired,
    at_online_stamps,
    evaluate_offline,
    marker_error_p50,
    moving_vs_truth,
)
from estimator.offline.outputs import segment_at
from estimator.offline.pipeline import resolve_log
from estimator.offline.solve import ResolveResult
from schemas import keys
from schemas.geometry import pose_error, position_sigma
from schemas.log import ReadReport, read_log


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
    moving_frames_covariance_scale: (
        float  # how the moving frames were weighed against the still views (``estimator.variance``)
    )
    moving_frames_left_out: int  # moving frames left out for it (``keyframes.max_inflation``)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, default=float)


@dataclass(frozen=True)
class ResolveRun:
    """A resolve with its evaluation: the solution, what was read, the evidence it was judged
    against and the figures written."""

    result: ResolveResult
    read: ReadReport
    evidence: LogEvidence
    out: Path
    figures: ResolveFigures


def run_resolve(
    log_path: Path,
    out: Path,
    cfg: CellConfig,
    progress: Callable[[int, int], None] | None = None,
    background: bool = True,
) -> ResolveRun:
    """Solve the log (``estimator.offline.resolve_log``; ``background``: read it in a child process),
    then write the config used, the figures and the report beside the solution in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    save_used(cfg, out)
    evidence = LogEvidence(object_frames=frozenset(keys.marker_frame(k) for k in cfg.estimator.object_markers))
    objects = ObjectErrors()
    run = resolve_log(
        log_path,
        out,
        cfg.estimator,
        cfg.cell.name,
        progress,
        evidence.take,
        lambda p: objects.add(p, evidence),
        background,
    )
    result, report = run.result, run.read
    figures = ResolveFigures(
        cameras=evaluate_offline(result, evidence),
        marker_position_error_mm_p50=marker_error_p50(result, evidence),
        object_markers=objects.summary(evidence),
        observations=result.observations,
        frames=result.frames,
        messages_read=report.messages,
        log_complete=report.stopped_early is None,
        stopped_early=report.stopped_early,
        unanchored=result.unanchored,
        flagged_anchors=result.flagged_anchors,
        lm_iterations=result.iterations,
        object_links=result.object_links,
        moving_frames_covariance_scale=result.moving_frames_scale,
        moving_frames_left_out=result.moving_frames_left_out,
    )
    (out / "resolve.json").write_text(figures.to_json())
    plots(result, evidence, out)
    (out / "report.html").write_text(html_report(result, figures))
    return ResolveRun(result, report, evidence, out, figures)


def config_of_log(report: ReadReport) -> CellConfig | None:
    """The cell config the recorder embedded in the log, if any."""
    import tomllib

    text = report.metadata.get("cellsight", {}).get("config")
    return None if text is None else parse_config(tomllib.loads(text), "config embedded in the log")


def peek_config(path: Path, report: ReadReport | None = None) -> CellConfig | None:
    """The cell config embedded in a log, reading only up to the log's metadata record (the recorder
    writes it first); ``report`` says whether the log ended early when there is none."""
    report = report if report is not None else ReadReport()
    for _ in read_log(path, set(), report):
        if report.metadata:
            break
    if "cellsight" not in report.metadata:
        for _ in read_log(path, set(), report):  # metadata written later: one cheap pass (nothing decoded)
            pass
    return config_of_log(report)


def plots(result: ResolveResult, side: LogEvidence, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    for _child, p in side.truth_markers.items():
        ax.plot(p.T[0, 3], p.T[1, 3], "s", ms=6, mfc="none", mec="0.6")
    for _k, (T, C) in result.markers.items():
        ax.plot(T[0, 3], T[1, 3], "s", ms=3, color="tab:blue")
        draw_ellipse(ax, T, C, "tab:blue")
    for s in result.segments:
        ax.plot(s.world_T_camera[0, 3], s.world_T_camera[1, 3], "^", ms=7, color="tab:red")
        draw_ellipse(ax, s.world_T_camera, s.covariance, "tab:red")
        ax.annotate(
            f"{s.camera_id}.{s.segment}", s.world_T_camera[:2, 3], textcoords="offset points", xytext=(6, 4), fontsize=8
        )
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
        fig, axes = plt.subplots(
            len(truth_cams), 1, figsize=(8, 1.9 * len(truth_cams) + 0.6), sharex=True, squeeze=False
        )
        for ax, cam in zip(axes[:, 0], truth_cams):
            online = [
                ((p.stamp_ns - t0) / 1e9, pose_error(p.T, t.T)[0])
                for p, _, t in at_online_stamps(result, side, cam)
                if t is not None
            ]
            if online:
                ax.plot(*zip(*_gaps_broken(online, MATCH_GAP_NS / 1e9)), "-", lw=0.9, color="tab:gray", label="online")
            # NaN where no segment covers the stamp: the line breaks while the camera moves
            offline = [
                (
                    (t.stamp_ns - t0) / 1e9,
                    np.nan
                    if (seg := segment_at(result, cam, t.stamp_ns)) is None
                    else pose_error(seg.world_T_camera, t.T)[0],
                )
                for t in side.truth_cameras.poses[cam]
            ]
            ax.plot(*zip(*offline), "-", lw=1.6, color="tab:blue", label="offline (segment)")
            moving = moving_vs_truth(result, side, cam)
            if moving:
                ax.plot(
                    [(s - t0) / 1e9 for s, _ in moving],
                    [e[0] for _, e in moving],
                    ".",
                    ms=4,
                    color="tab:red",
                    label="offline (moving frame)",
                )
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
        rows = [
            ((p.stamp_ns - t0) / 1e9, pose_error(p.T, seg.world_T_camera)[0])
            for p in poses
            if (seg := segment_at(result, cam, p.stamp_ns)) is not None
        ]
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
        f"<td>{1000 * position_sigma(s.covariance):.2f}</td></tr>"
        for s in result.segments
    )
    objects = "".join(
        f"<tr><td>{html.escape(c)}</td><td>{v.poses}</td><td>{fmt(v.offline_vs_truth_mm_deg)}</td><td>{fmt(v.online_vs_truth_mm_deg)}</td></tr>"
        for c, v in fig.object_markers.items()
    )
    objects_html = (
        (
            "<h2>Object markers (placed through the solved cameras, at most 10 Hz; median errors)</h2>"
            f"<table><tr><th>marker</th><th>poses</th><th>offline vs truth</th><th>online vs truth</th></tr>{objects}</table>"
        )
        if objects
        else ""
    )
    truth_img = (
        '<h2>Against ground truth</h2><img src="errors_vs_truth.png">'
        if any(c.offline_vs_truth_mm_deg for c in fig.cameras.values())
        else ""
    )
    warn = (
        ""
        if fig.log_complete
        else f"<p class=warn>The log was not complete ({html.escape(str(fig.stopped_early))}); this covers what was readable.</p>"
    )
    scale = fig.moving_frames_covariance_scale
    weighed = (
        ""
        if scale == 1.0
        else (
            f" ({fig.moving_frames_left_out} moving frames left out"
            if fig.moving_frames_left_out
            else " (the moving frames weighed down"
        )
        + f": the still views fit {scale:.3g} times better than the moving ones, each against its covariances)"
    )
    return f"""<!doctype html><html><head><meta charset=utf-8><title>cellsight resolve</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}} table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;padding:3px 8px}} .warn{{color:#a40}}</style></head><body>
<h1>Offline re-solve</h1>{warn}
<p>{fig.frames} frames, {fig.observations} marker observations, {len(result.segments)} camera segments, {len(result.markers)} markers;
Levenberg-Marquardt {fig.lm_iterations} iterations; {sum(c.moving_frames for c in fig.cameras.values())} moving frames and
{fig.object_links} object-marker instants seen by several cameras solved as poses of their own{weighed}. Unanchored cameras: {", ".join(fig.unanchored) or "none"}.
Anchors flagged as moved: {", ".join(map(str, fig.flagged_anchors)) or "none"}.</p>
<h2>Cameras (median errors; truth only in simulator logs)</h2>
<table><tr><th>camera</th><th>offline vs truth</th><th>online vs truth</th><th>RMS at the same instants, offline / online (instants)</th><th>online vs offline</th><th>moving frames solved</th><th>their error vs truth</th></tr>{rows}</table>
{objects_html}
<h2>Segments</h2><table><tr><th>camera</th><th>segment</th><th>frames</th><th>position (m)</th><th>sigma (mm)</th></tr>{segs}</table>
<h2>Top view</h2><img src="top_view.png">
<h2>Residuals</h2><img src="residuals.png">
<h2>Outliers</h2><img src="outliers.png">
<h2>Online vs offline</h2><img src="online_vs_offline.png">{truth_img}
</body></html>"""
