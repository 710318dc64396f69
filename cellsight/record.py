"""The recorder: every key of a cell (or the ones asked for) into MCAP logs.

A payload is written if it parses as its key's message type (every message in the log parses as
its channel's schema) and its ids and stamps are what any receiver accepts (``codec.check_on_key``:
a camera's message names its key's camera, stamps within the window of the recorder's clock);
anything else is refused and counted per key and reason (``refused``), and the file stays valid
past it. Its content (finite poses, definite covariances, image sizes) is checked by whoever reads
the log, as every subscriber checks it on the bus (``schemas.log`` skips and counts what fails),
so a recording keeps what a faulty producer sent. Images can be
thinned to ``max_image_hz`` per key so a long run stays a reasonable size (recording the whole
cell, images are subscribed only when one is due: ``schemas.bus.CellTap``). A recording is never
overwritten: a restarted recorder writes ``NAME.1.mcap``, ``NAME.2.mcap``, ... beside the first
part. A failing disk ends the current part (readable up to its last complete chunk); every
``retry_s`` the recorder tries a new part, so recording resumes once there is space again.

A camera it hears nothing from for ``gap_after_s`` (its driver sends a status every second, so
this is a dead driver or a dropped link, not a quiet scene) is marked in the log when it is heard
again, or when the recording ends: an MCAP metadata record ``gap/<camera>/<from_ns>``
(``schemas.log.Gap``), so that whoever reads the log knows the silence was not the scene's.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from pathlib import Path

from cellsight.errors import RunError
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus
from schemas.errors import SchemaError
from schemas.log import Gap, LogWriter, stamp_of

log = logging.getLogger(__name__)
#: Seconds between attempts to start a new part after a write failed.
RETRY_S = 5.0
#: Seconds without a message from a camera that make a gap (its driver's status comes every second).
GAP_AFTER_S = 3.0


def free_part(path: Path) -> Path:
    """``path`` if nothing is there yet, else the first free ``path.N.mcap`` (N = 1, 2, ...)."""
    candidate, n = path, 0
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}.{n}{path.suffix}")
    return candidate


class Recorder:
    """Records bus traffic into ``parts`` (the first at ``path`` or the next free name)."""

    def __init__(
        self,
        bus: Bus,
        path: Path,
        key_exprs: list[str] | None = None,
        max_image_hz: float | None = None,
        metadata: dict[str, str] | None = None,
        retry_s: float = RETRY_S,
        gap_after_s: float = GAP_AFTER_S,
    ) -> None:
        self.path = path
        self.max_image_hz = max_image_hz
        self.retry_s = retry_s
        self.metadata = metadata
        self.parts: list[Path] = []
        self.failures: list[str] = []  # one per part a write error ended
        self.messages = 0
        self.lost = 0  # valid messages that arrived while no part could be written
        self.bad: Counter[str] = Counter()
        self.refused: Counter[tuple[str, str]] = Counter()  # (key, reason) -> messages not written
        self.thinned = 0
        self.gap_after_s = gap_after_s
        self.gaps: list[Gap] = []
        self._heard: dict[str, int] = {}  # camera -> receive time (ns) of its last message
        self._writer: LogWriter | None = None
        self._retry_at = 0.0
        self._last_image: dict[str, int] = {}
        self._lock = threading.Lock()
        self._refuse_lock = threading.Lock()  # refusals come from zenoh's threads, some while _lock is held
        self.limits = bus.limits
        if not self._new_part():
            raise RunError(f"cannot record to {path}: {self.failures[-1]}")
        tapped = bool(max_image_hz) and not key_exprs  # images subscribed only when one is due
        if tapped:
            self._subs = [bus.tap_cell(self._on_sample, max_image_hz)]
        else:
            self._subs = [bus.subscribe_raw(k, self._on_sample) for k in (key_exprs or [keys.everything(bus.cell)])]
        bus.declare_alive("recorder", "main")

    def _new_part(self) -> bool:
        path = free_part(self.path)
        try:
            self._writer = LogWriter(path, metadata=self.metadata)
        except OSError as exc:
            path.unlink(missing_ok=True)  # it holds nothing recorded
            self.failures.append(str(exc))
            self._retry_at = time.monotonic() + self.retry_s
            return False
        if self.parts:
            log.warning("recording resumed in %s", path)
        elif path != self.path:
            log.warning("%s exists (an earlier recording): recording to %s", self.path, path)
        self.parts.append(path)
        return True

    def _on_sample(self, key: str, payload: bytes, receive_ns: int) -> bool | None:
        """Record one message; False: an image refused, stamped too soon after the last kept one."""
        try:
            parsed = keys.parse(key)
            msg_type = parsed.message_type
            msg = codec.decode(payload, msg_type, semantic=False)  # content: the reader's (~0.5 ms a message)
            # Ids and stamps the log could not hold or a reader would refuse: a negative stamp made the
            # MCAP writer fail half-way through a record, and the log unreadable past it.
            codec.check_on_key(msg, parsed.camera, receive_ns, self.limits)
        except SchemaError as exc:
            self._refuse(key, exc)
            return
        stamp = stamp_of(msg, receive_ns)
        if self.max_image_hz and msg_type is m.RawImage:
            last = self._last_image.get(key)
            if last is not None and stamp - last < 1e9 / self.max_image_hz:
                self.thinned += 1
                return False
            self._last_image[key] = stamp
        with self._lock:
            if parsed.camera is not None:
                last = self._heard.get(parsed.camera)
                self._heard[parsed.camera] = receive_ns
                if last is not None and receive_ns - last > self.gap_after_s * 1e9:
                    self._mark(Gap(parsed.camera, last, receive_ns))
            if self._writer is None and (time.monotonic() < self._retry_at or not self._new_part()):
                self.lost += 1
                return
            try:
                self._writer.write_raw(key, msg_type, payload, receive_ns, stamp)
                self.messages += 1
            except SchemaError as exc:  # checked before anything was written: the part stays valid
                self._refuse(key, exc)
            except OSError as exc:  # e.g. disk full: end this part, keep what is on disk, retry later
                self._writer.abandon()
                self._writer = None
                self.failures.append(str(exc))
                self._retry_at = time.monotonic() + self.retry_s
                self.lost += 1
                log.error(
                    "recording to %s stopped: %s (readable up to its last complete chunk; a new part is tried "
                    "every %.0f s)",
                    self.parts[-1],
                    exc,
                    self.retry_s,
                )

    def _refuse(self, key: str, exc: SchemaError) -> None:
        with self._refuse_lock:
            self.bad[key] += 1
            self.refused[key, exc.reason] += 1
            first = self.bad[key] == 1
        if first:  # once per key: a flood must not flood the log
            log.warning("not recording a message on %s: %s (further ones on this key are only counted)", key, exc)

    def _mark(self, gap: Gap) -> None:
        """Note a gap (caller holds the lock); written into the current part, if there is one."""
        self.gaps.append(gap)
        log.warning("nothing from camera %s for %.1f s: marked in the log", gap.camera, gap.seconds)
        if self._writer is not None:
            try:
                self._writer.add_metadata(*gap.metadata())
            except OSError as exc:  # the next message's write ends the part; the gap stays in self.gaps
                log.error("could not mark the gap in %s: %s", self.parts[-1], exc)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            end = time.time_ns()
            for camera, last in self._heard.items():  # silent until the end
                if end - last > self.gap_after_s * 1e9:
                    self._mark(Gap(camera, last, end))
            if self._writer is not None:
                try:
                    self._writer.close()
                except OSError as exc:
                    self._writer.abandon()
                    self.failures.append(str(exc))
                    log.error("could not finish %s: %s (readable up to its last complete chunk)", self.parts[-1], exc)
                self._writer = None
