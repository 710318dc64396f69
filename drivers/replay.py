"""Replay an MCAP log onto the bus with its original timing (scaled by ``rate``).

By default only what sensors publish goes out again (camera keys and simulator truth), so a
running estimator and recognition worker are driven by the recording instead of competing with
the estimates that were recorded; ``all_keys`` republishes everything.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from schemas import keys
from schemas.bus import Bus, Publisher
from schemas.errors import SchemaError
from schemas.log import ReadReport, read_log

log = logging.getLogger(__name__)


@dataclass
class ReplayResult:
    published: int
    skipped: int
    read: ReadReport


def is_sensor_key(key: str) -> bool:
    """Camera topics and ground truth: what drivers publish."""
    try:
        parsed = keys.parse(key)
    except SchemaError:
        return False
    return parsed.camera is not None or parsed.topic.startswith("truth/")


def replay(
    bus: Bus, path: Path, rate: float = 1.0, all_keys: bool = False, stop: threading.Event | None = None
) -> ReplayResult:
    """Publish the log's messages at ``rate`` times their recorded pace (log_time); returns counts."""
    if not rate > 0:
        raise ValueError(f"replay rate must be positive, got {rate}")
    stop = stop or threading.Event()
    report = ReadReport()
    pubs: dict[str, Publisher] = {}
    published = skipped = 0
    t0_log = t0_wall = None
    for lm in read_log(path, None, report):
        if stop.is_set():
            break
        if not all_keys and not is_sensor_key(lm.key):
            skipped += 1
            continue
        if t0_log is None:
            t0_log, t0_wall = lm.log_time_ns, time.monotonic()
        wait = t0_wall + (lm.log_time_ns - t0_log) / 1e9 / rate - time.monotonic()
        if wait > 0 and stop.wait(wait):
            break
        if lm.key not in pubs:
            frames = keys.parse(lm.key).topic.endswith("image_raw")
            pubs[lm.key] = bus.publisher(lm.key, frames=frames)
        pubs[lm.key].put(lm.msg)
        published += 1
    if report.stopped_early:
        log.warning("%s: replay stopped early (%s): %d messages published", path, report.stopped_early, published)
    return ReplayResult(published, skipped, report)
