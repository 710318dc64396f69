"""Read a recorded log as the offline solve's input: each camera's marker frames in blocks."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from estimator.observation import validated_rows
from estimator.offline.solve import FrameBlock
from schemas import keys
from schemas import messages as m
from schemas.log import LogMessage, ReadReport, read_log

log = logging.getLogger(__name__)
BLOCK_FRAMES = 30  # marker frames per camera validated and folded in together (1 s at 30 Hz)


def frame_blocks(
    path: Path,
    report: ReadReport,
    progress: Callable[[int, int], None] | None = None,
    on_message: Callable[[LogMessage], None] | None = None,
    cells: set[str] | None = None,
) -> Iterator[FrameBlock]:
    """Each camera's marker frames in blocks of ``BLOCK_FRAMES``, validated a block at a time; every
    other message goes to ``on_message`` as it is read (one pass over the log). The cell names of
    the keys read are added to ``cells``."""
    pending: dict[str, list[m.MarkerObservations]] = {}
    for lm in read_log(path, None, report, progress, deferred=frozenset({m.MarkerObservations})):
        parsed = keys.parse(lm.key)
        if cells is not None and parsed.cell not in cells:
            cells.add(parsed.cell)
        if parsed.topic == "markers":
            msgs = pending.setdefault(lm.msg.camera_id, [])
            msgs.append(lm.msg)
            if len(msgs) == BLOCK_FRAMES:
                yield from _block(lm.msg.camera_id, pending.pop(lm.msg.camera_id), report)
        elif on_message is not None:
            on_message(lm)
    for camera_id, msgs in pending.items():
        yield from _block(camera_id, msgs, report)


def _block(camera_id: str, msgs: list[m.MarkerObservations], report: ReadReport) -> Iterator[FrameBlock]:
    v = validated_rows(camera_id, msgs)
    for stamp_ns, why in v.dropped:
        report.messages -= 1
        report.undecodable += 1
        log.warning("%s frame at %d ns skipped: %s", camera_id[:40], stamp_ns, why)
    if v.rows is not None:
        yield FrameBlock(camera_id, np.array([msgs[i].stamp_ns for i in v.kept], dtype=np.int64), v.rows)
