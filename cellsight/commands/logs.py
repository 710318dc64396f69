"""Recorded logs: ``resolve``, ``export ros2``, ``compare``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    VerboseOpt,
    fail,
    load,
    setup_logging,
    stderr,
)

export_app = typer.Typer(help="Logs in other tools' formats.", no_args_is_help=True)


def resolve_cmd(
    log_file: Annotated[Path, typer.Argument(help="MCAP log (cellsight record / demo / replay)")],
    out: Annotated[Path | None, typer.Option("--out", help="output folder (default: LOG's name + _resolved)")] = None,
    config: Annotated[
        Path | None,
        typer.Option("--config", help="cell config with the anchors (default: the one embedded in the log)"),
    ] = None,
    verbose: VerboseOpt = False,
) -> None:
    """Re-solve a log in batch: resolved.mcap, TUM trajectories, report.html with figures."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TimeRemainingColumn

    from cellsight.evaluation.resolve_report import peek_config, run_resolve

    setup_logging(verbose)
    if not log_file.is_file():
        raise fail(f"{log_file}: no such log file", 2)
    from schemas.log import ReadReport

    peeked = ReadReport()
    cfg = load(config) if config is not None else peek_config(log_file, peeked)
    if cfg is None and peeked.stopped_early:
        raise fail(
            f"{log_file} is cut or damaged {peeked.stopped_early.removeprefix('cut or damaged ')}, before its cell config: "
            "nothing to solve there; give --config with the anchors to solve what precedes the damage",
            2,
        )
    if cfg is None:
        raise fail(
            f"{log_file} has no embedded cell config (not written by cellsight record?): give --config with the anchors",
            2,
        )
    if not cfg.estimator.anchors:
        from cellsight.scenario_config import complete

        cfg = complete(cfg)
    out = out or log_file.with_name(log_file.stem + "_resolved")
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        DownloadColumn(),
        TimeRemainingColumn(),
        console=stderr(),
    ) as bar:
        task = bar.add_task("reading and solving", total=log_file.stat().st_size)
        run = run_resolve(log_file, out, cfg, lambda done, total: bar.update(task, completed=done))
    r = run.result
    typer.echo(
        f"{out}/: {r.frames} frames, {r.observations} observations, {len(r.segments)} segments, {len(r.markers)} markers"
        + (f", {r.object_links} object-marker instants linking cameras" if r.object_links else "")
    )
    if r.moving_frames_left_out:
        typer.echo(
            f"  {r.moving_frames_left_out} moving frames left out: the still views fit {r.moving_frames_scale:.3g} times better "
            "than the moving ones, each against its covariances (keyframes.max_inflation)"
        )
    for cam, c in run.figures.cameras.items():
        off, on = c.offline_vs_truth_mm_deg, c.online_vs_truth_mm_deg
        if off is not None:
            moving = f"; {c.moving_frames} moving frames solved" if c.moving_frames else ""
            paired = (
                f" (RMS at the same instants {c.paired.offline_mm_deg_rms[0]:.2f} / {c.paired.online_mm_deg_rms[0]:.2f} mm)"
                if c.paired
                else ""
            )
            typer.echo(
                f"  {cam}: offline {off[0]:.2f} mm / {off[1]:.3f} deg vs truth"
                + (f", online {on[0]:.2f} mm / {on[1]:.3f} deg" if on else "")
                + paired
                + moving
            )
    for child, o in run.figures.object_markers.items():
        off = o.offline_vs_truth_mm_deg
        typer.echo(
            f"  {child}: {o.poses} poses" + (f", offline {off[0]:.2f} mm / {off[1]:.2f} deg vs truth" if off else "")
        )
    for (key, reason), n in sorted(run.read.refused.items()):
        stderr().print(
            f"[yellow]skipped:[/] {n} messages on {key} ({reason}), as a running cell would have refused them"
        )
    if run.read.stopped_early:
        stderr().print(
            f"[yellow]warning:[/] the log is {run.read.stopped_early}; resolved from the {run.read.messages} messages before it"
        )
    if r.frames == 0:
        raise fail(f"{log_file}: no marker frames to solve (nothing written to {out} is a solution)", 1)


@export_app.command("ros2")
def export_ros2(
    log_file: Annotated[Path, typer.Argument(help="MCAP log (cellsight record / demo, or resolve's resolved.mcap)")],
    out: Annotated[Path, typer.Option("--out", help="new folder for the ROS 2 bag")],
    distro: Annotated[str, typer.Option(help="ROS 2 message definitions: jazzy or humble")] = "jazzy",
) -> None:
    """Write a log as a ROS 2 bag (MCAP storage, CDR): tf, camera poses, observations, images."""
    from rich.progress import BarColumn, DownloadColumn, Progress

    from cellsight.export_ros2 import export_bag

    if not log_file.is_file():
        raise fail(f"{log_file}: no such log file", 2)
    with Progress("[progress.description]{task.description}", BarColumn(), DownloadColumn(), console=stderr()) as bar:
        task = bar.add_task("exporting", total=log_file.stat().st_size)
        result = export_bag(log_file, out, distro, lambda done, total: bar.update(task, completed=done))
    for topic, n in sorted(result.messages.items()):
        typer.echo(f"{n:8d}  {topic}")
    typer.echo(f"wrote {result.bag}/ (ros2 bag play {result.bag})")
    if result.read.stopped_early:
        stderr().print(
            f"[yellow]warning:[/] the log ended early ({result.read.stopped_early}); exported what was readable"
        )


def compare_cmd(
    a: Annotated[Path, typer.Argument(help="first solved log (resolved.mcap, or a recording with estimates)")],
    b: Annotated[Path, typer.Argument(help="second solved log")],
    min_mm: Annotated[float, typer.Option(help="smallest position change that counts as moved")] = 1.0,
    min_deg: Annotated[float, typer.Option(help="smallest rotation change that counts as moved")] = 0.05,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
) -> None:
    """How much each camera and marker moved between two solved logs, with a verdict against its uncertainty."""
    import json as json_

    from rich.console import Console
    from rich.table import Table

    from cellsight.compare import compare, newest_poses

    for f in (a, b):
        if not f.is_file():
            raise fail(f"{f}: no such log file", 2)
    (pa, _), (pb, _) = newest_poses(a), newest_poses(b)
    if not pa or not pb:
        raise fail(f"{a if not pa else b}: holds no estimate/cameras or estimate/markers (resolve it first)", 2)
    changes = compare(pa, pb, min_mm, min_deg)
    if as_json:
        typer.echo(json_.dumps([c.__dict__ for c in changes]))
        return
    t = Table(title=f"{a} -> {b}")
    for col in ("frame", "position (mm)", "rotation (deg)", "sigmas", "verdict"):
        t.add_column(col, no_wrap=True)
    for c in changes:
        style = "bold red" if c.verdict == "moved" else ""
        t.add_row(
            c.frame,
            f"{c.position_mm:.2f}",
            f"{c.rotation_deg:.3f}",
            "-" if c.sigmas is None else f"{c.sigmas:.1f}",
            f"[{style}]{c.verdict}[/]" if style else c.verdict,
        )
    Console(width=120).print(t)
