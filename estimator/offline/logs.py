"""Read a recorded log as the offline solve's input: each camera's marker frames in blocks.

Reading and decoding is half of an offline solve's work and needs nothing from the solve, so
``background_frame_blocks`` does it in a child process while the caller checks and solves.
"""

from __future__ import annotations

import dataclasses
import fcntl
import logging
import pickle
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from estimator.errors import EstimatorError
from estimator.observation import validated_fields
from estimator.offline.solve import FrameBlock
from schemas import codec, keys
from schemas import messages as m
from schemas.codec import MarkerFields
from schemas.log import LogMessage, ReadReport, read_log

log = logging.getLogger(__name__)
BLOCK_FRAMES = 30  # marker frames per camera validated and folded in together (1 s at 30 Hz)
PROGRESS_EVERY_S = 0.2
Progress = Callable[[int, int], None] | None  # (bytes read, total bytes)
OnMessage = Callable[[LogMessage], None] | None  # every message that is not a marker observation
Cells = set[str] | None  # the cell names of the keys read are added here
PIPE_BYTES = 1 << 20  # Linux's ceiling for an unprivileged pipe: ~5 blocks of 30 frames


@dataclass(frozen=True)
class FrameFields:
    """Consecutive marker frames of one camera as read, not yet checked: stamps (F,) int ns and
    the markers' fields (``MarkerFields.rows[:, 1]`` indexes the frames)."""

    camera_id: str
    stamps: np.ndarray
    fields: MarkerFields
    cell: str


def frame_blocks(
    path: Path,
    report: ReadReport,
    progress: Progress = None,
    on_message: OnMessage = None,
    cells: Cells = None,
) -> Iterator[FrameBlock]:
    """Each camera's marker frames in blocks of ``BLOCK_FRAMES``, validated a block at a time; every
    other message goes to ``on_message`` as it is read (one pass over the log). The cell names of
    the keys read are added to ``cells``."""
    for raw in frame_fields(path, report, progress, on_message, cells):
        yield from checked(raw, report)


def frame_fields(
    path: Path,
    report: ReadReport,
    progress: Progress = None,
    on_message: OnMessage = None,
    cells: Cells = None,
) -> Iterator[FrameFields]:
    """``frame_blocks`` before the checks: the part of the work that reads the log."""
    pending: dict[str, list[m.MarkerObservations]] = {}
    for lm in read_log(path, None, report, progress, deferred=frozenset({m.MarkerObservations})):
        parsed = keys.parse(lm.key)
        if cells is not None and parsed.cell not in cells:
            cells.add(parsed.cell)
        if parsed.topic == "markers":
            msgs = pending.setdefault((parsed.cell, lm.msg.camera_id), [])  # read_log checked the id against the key
            msgs.append(lm.msg)
            if len(msgs) == BLOCK_FRAMES:
                yield _fields(parsed.cell, lm.msg.camera_id, pending.pop((parsed.cell, lm.msg.camera_id)))
        elif on_message is not None:
            on_message(lm)
    for (cell, camera_id), msgs in pending.items():
        yield _fields(cell, camera_id, msgs)


def _fields(cell: str, camera_id: str, msgs: list[m.MarkerObservations]) -> FrameFields:
    return FrameFields(
        camera_id, np.array([msg.stamp_ns for msg in msgs], dtype=np.int64), codec.marker_fields(msgs), cell
    )


def checked(raw: FrameFields, report: ReadReport) -> Iterator[FrameBlock]:
    """The block of a camera's frames that pass the checks the daemon makes; each dropped frame is
    counted in ``report`` as undecodable and refused (by reason), and the first of each reason logged."""
    v = validated_fields(raw.camera_id, len(raw.stamps), raw.fields)
    for i, why, reason in v.dropped:
        report.messages -= 1
        report.undecodable += 1
        where = (keys.markers(raw.cell, raw.camera_id), reason)
        report.refused[where] += 1
        if report.refused[where] == 1:
            log.warning(
                "%s frame at %d ns skipped: %s (further ones only counted)", raw.camera_id[:40], int(raw.stamps[i]), why
            )
    if v.rows is not None:
        yield FrameBlock(raw.camera_id, raw.stamps[v.kept], v.rows)


def background_frame_blocks(
    path: Path,
    report: ReadReport,
    progress: Progress = None,
    on_message: OnMessage = None,
    cells: Cells = None,
) -> Iterator[FrameBlock]:
    """``frame_blocks`` with the log read in a child process (``python -m estimator.offline.logs``):
    the same blocks, messages, report and cells, in the same order, while the caller's solve runs
    on another core. The child reads and decodes (``frame_fields``), this process checks and
    converts (``checked``): that splits the work about evenly. Items come back pickled through a
    pipe, whose buffer keeps the child at most a few blocks ahead, so memory stays flat however
    long the log is (a reader thread here to hold more was slower: it fights the solve for the
    GIL). The child is stopped if the caller stops early."""
    forward = "messages" if on_message is not None else "blocks"
    child = subprocess.Popen(
        [sys.executable, "-m", "estimator.offline.logs", str(path), forward], stdout=subprocess.PIPE
    )
    assert child.stdout is not None
    try:  # a deeper pipe lets the child run a few blocks ahead through the solve's slower moments
        fcntl.fcntl(child.stdout.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (AttributeError, OSError):
        pass
    dropped = ReadReport()  # frames this process's checks dropped, added to the child's counts
    try:
        while True:
            try:
                kind, *rest = pickle.load(child.stdout)
            except EOFError:
                raise EstimatorError(f"{path}: the log reader process ended early (exit code {child.wait()})") from None
            if kind == "fields":
                yield from checked(rest[0], dropped)
            elif kind == "message":  # sent serialised: generated protobuf classes do not pickle
                key, payload, log_time_ns, publish_time_ns = rest
                on_message(LogMessage(key, keys.message_type(key).FromString(payload), log_time_ns, publish_time_ns))  # type: ignore[misc]
            elif kind == "progress":
                if progress is not None:
                    progress(*rest)
            elif kind == "error":
                raise EstimatorError(f"{path}: reading the log failed: {rest[0]}")
            else:  # "end": the child's report and cells become the caller's
                for f in dataclasses.fields(ReadReport):
                    setattr(report, f.name, getattr(rest[0], f.name))
                report.messages += dropped.messages
                report.undecodable += dropped.undecodable
                report.refused.update(dropped.refused)
                if cells is not None:
                    cells |= rest[1]
                return
    finally:
        if child.poll() is None:
            child.terminate()
        child.stdout.close()
        child.wait()


def _read_into(path: Path, forward_messages: bool, out: BinaryIO) -> None:
    """The child's side of ``background_frame_blocks``: every item pickled to ``out``."""
    report: ReadReport = ReadReport()
    cells: set[str] = set()
    last = 0.0

    def put(*item: Any) -> None:
        pickle.dump(item, out, protocol=pickle.HIGHEST_PROTOCOL)

    def progress(done: int, total: int) -> None:
        nonlocal last
        if time.monotonic() - last >= PROGRESS_EVERY_S or done == total:
            last = time.monotonic()
            put("progress", done, total)

    try:

        def forward(lm: LogMessage) -> None:
            put("message", lm.key, lm.msg.SerializeToString(), lm.log_time_ns, lm.publish_time_ns)

        on_message = forward if forward_messages else None
        for raw in frame_fields(path, report, progress, on_message, cells):
            put("fields", raw)
        put("end", report, cells)
    except Exception as exc:  # everything the child meets goes to the parent, which decides
        put("error", f"{type(exc).__name__}: {exc}")
    out.flush()


if __name__ == "__main__":
    from estimator.offline import logs  # this module under its own name, so its classes pickle as such

    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    logs._read_into(Path(sys.argv[1]), sys.argv[2] == "messages", sys.stdout.buffer)
