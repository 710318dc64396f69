"""The recorder: every key of a cell (or the ones asked for) into an MCAP log.

Payloads are validated before they are written (the log holds only what decodes), images can be
thinned to ``max_image_hz`` per key so a long run stays a reasonable size, and a failing disk
stops the recording with an error while keeping every chunk already written.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from pathlib import Path

from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus
from schemas.errors import SchemaError
from schemas.log import LogWriter, stamp_of

log = logging.getLogger(__name__)


class Recorder:
    def __init__(self, bus: Bus, path: Path, key_exprs: list[str] | None = None, max_image_hz: float | None = None, metadata: dict[str, str] | None = None) -> None:
        self.writer = LogWriter(path, metadata=metadata)
        self.path = path
        self.max_image_hz = max_image_hz
        self.bad: Counter[str] = Counter()
        self.thinned = 0
        self.failed: str | None = None
        self._last_image: dict[str, int] = {}
        self._lock = threading.Lock()
        self._subs = [bus.subscribe_raw(k, self._on_sample) for k in (key_exprs or [keys.everything(bus.cell)])]
        bus.declare_alive("recorder", "main")

    def _on_sample(self, key: str, payload: bytes, receive_ns: int) -> None:
        try:
            msg_type = keys.message_type(key)
            msg = codec.decode(payload, msg_type)
        except SchemaError as exc:
            self.bad[key] += 1
            if self.bad[key] == 1:
                log.warning("not recording malformed payload on %s: %s", key, exc)
            return
        stamp = stamp_of(msg, receive_ns)
        if self.max_image_hz and msg_type is m.RawImage:
            last = self._last_image.get(key)
            if last is not None and stamp - last < 1e9 / self.max_image_hz:
                self.thinned += 1
                return
            self._last_image[key] = stamp
        with self._lock:
            if self.failed is not None:
                return
            try:
                self.writer.write_raw(key, msg_type, payload, receive_ns, stamp)
            except OSError as exc:  # e.g. disk full: stop writing, keep what is on disk
                self.failed = str(exc)
                log.error("recording to %s stopped: %s (the file is readable up to the last complete chunk)", self.path, exc)

    @property
    def messages(self) -> int:
        return self.writer.messages

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            if self.failed is None:
                try:
                    self.writer.close()
                except OSError as exc:
                    log.error("could not finish %s: %s (readable up to the last complete chunk)", self.path, exc)
