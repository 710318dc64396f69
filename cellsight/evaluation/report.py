"""The demo's summary (``summary.json``, ``summary.md``, pictures) from a run's log, through
``cellsight.evaluation.truth``."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cellsight.evaluation.truth import (
    CameraSummary,
    MarkerSummary,
    ObjectSummary,
    RunData,
    camera_errors,
    load_run,
    object_errors,
    summarize,
    summarize_objects,
)


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
        ax.plot(
            T[0, 3],
            T[1, 3],
            "s",
            ms=5,
            mfc="none",
            mec="0.5",
            label="marker (truth)" if child == next(iter(d.truth_markers.poses)) else None,
        )
    for poses in d.est_markers.poses.values():
        T, cov = poses[-1].T, poses[-1].covariance
        ax.plot(T[0, 3], T[1, 3], "s", ms=3, color="tab:blue")
        draw_ellipse(ax, T, cov, "tab:blue")
    for child, poses in d.truth_objects.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "o", ms=9, mfc="none", mec="tab:orange")
        ax.annotate(
            child.replace("object_", ""),
            (T[0, 3], T[1, 3]),
            textcoords="offset points",
            xytext=(6, -10),
            fontsize=8,
            color="tab:orange",
        )
    for poses in d.est_objects.poses.values():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "o", ms=5, color="tab:orange")
    for cam, poses in d.truth_cameras.poses.items():
        T = poses[-1].T
        ax.plot(T[0, 3], T[1, 3], "^", ms=10, mfc="none", mec="k")
        fwd = T[:3, 2] * 0.4
        ax.arrow(T[0, 3], T[1, 3], fwd[0], fwd[1], head_width=0.05, color="k", alpha=0.5)
        ax.annotate(cam, (T[0, 3], T[1, 3]), textcoords="offset points", xytext=(8, 4))
    for poses in d.est_cameras.poses.values():
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
        ys = np.concatenate([np.asarray(line.get_ydata(), float) for line in ax.get_lines()] or [np.zeros(0)])
        if np.any(np.isfinite(ys) & (ys > 0)):  # a log axis needs a positive value (a slow run may have none yet)
            ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
    axes[-1].set_xlabel("scenario time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
