"""``resolve_log``: the offline solve of one recorded log, from MCAP to the files it writes."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from estimator.config import EstimatorConfig
from estimator.offline.logs import background_frame_blocks, frame_blocks
from estimator.offline.outputs import ObjectSpool, write_solution
from estimator.offline.solve import ResolveResult, resolve
from schemas.codec import StampedPose
from schemas.log import LogMessage, ReadReport


@dataclass(frozen=True)
class OfflineRun:
    """One resolve: the solution, what was read, the cell the log was recorded in."""

    result: ResolveResult
    read: ReadReport
    cell: str
    out: Path


def resolve_log(
    log_path: Path,
    out: Path,
    config: EstimatorConfig,
    cell: str,
    progress: Callable[[int, int], None] | None = None,
    on_message: Callable[[LogMessage], None] | None = None,
    on_object: Callable[[StampedPose], None] | None = None,
    background: bool = True,
) -> OfflineRun:
    """Solve the log in one pass and write ``out/resolved.mcap`` and ``out/trajectories/``.

    ``cell`` names the output keys unless the log's own keys name another cell; ``progress``
    gets (bytes read, total); ``on_message`` every message that is not a marker observation, as
    it is read; ``on_object`` every object-marker pose written. ``background``: read and validate
    the log in a child process while this one solves (the same answer; about half the time on two
    cores).
    """
    out.mkdir(parents=True, exist_ok=True)
    report, spool, cells = ReadReport(), ObjectSpool(out), set()
    try:
        blocks = (background_frame_blocks if background else frame_blocks)(
            log_path, report, progress, on_message, cells
        )
        result = resolve(blocks, config, objects=spool.add)
        cell = next(iter(sorted(cells)), cell)
        write_solution(result, out, cell, spool, config.object_markers, on_object)
    finally:
        spool.close()
    return OfflineRun(result, report, cell, out)
