"""One way to open a zenoh session and to publish / subscribe typed messages, for every process.

- ``TransportConfig``: the ``--mode/--connect/--listen/--config`` flags every process takes
  (zenoh-python's ``common.py`` convention), plus pass-through settings for TLS, mTLS and access
  control. Multicast scouting is off unless asked for.
- ``Bus``: a session bound to a cell, with typed publishers, decoding subscriptions
  (``Inbox``) and liveliness tokens.

Subscriptions decode in zenoh's callback thread and keep messages in a bounded inbox: a ring
(newest wins) for frames, a FIFO for small messages. A payload that does not decode, or holds what
no sensor sends (``schemas.limits``), is counted per key and reason, logged once per key and
dropped; the subscription keeps running.
"""

from __future__ import annotations

import json
import logging
import math
import resource
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar

import zenoh
from google.protobuf.message import Message
from pydantic import BaseModel, ConfigDict, Field

from schemas import keys
from schemas.codec import check_on_key, decode
from schemas.errors import BusError, KeyError_, SchemaError
from schemas.limits import DEFAULT_LIMITS, WireLimits

log = logging.getLogger(__name__)

Msg = TypeVar("Msg", bound=Message)
DEFAULT_ROUTER = "tcp/127.0.0.1:7447"
CAP_IPC_LOCK = 14  # capability bit: lock memory beyond RLIMIT_MEMLOCK


class TransportConfig(BaseModel):
    """How a process joins the zenoh network. Defaults: client of one router on loopback."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    mode: Literal["client", "peer", "router"] | None = Field(
        default=None, description="zenoh mode; unset: the zenoh config file's, else client"
    )
    connect: list[str] | None = Field(
        default=None, description=f"endpoints to connect to; unset: the zenoh config file's, else {DEFAULT_ROUTER}"
    )
    listen: list[str] = Field(default_factory=list, description="endpoints to listen on")
    multicast_scouting: bool = False
    shared_memory: bool = Field(
        default=True,
        description="frames through zenoh shared memory between processes on this host (needs "
        "unlimited locked memory: root, CAP_IPC_LOCK or `ulimit -l unlimited`; otherwise switched off with a warning)",
    )
    shm_pool_mb: int = Field(
        default=16,
        ge=2,
        le=4096,
        description="shared-memory pool of each frame-publishing process (a VGA RGB-D pair is 1.5 MB; decoders release "
        "a frame at once). Every reader maps it too and, zenoh 1.10, keeps a crashed publisher's pool mapped for its "
        "own lifetime (zenoh issue 2787): see shm_driver_starts",
    )
    shm_driver_starts: int = Field(
        default=1,
        ge=0,
        description="how many times `cellsight run` starts a driver with shared memory; a driver restarted after that "
        "sends plain bytes, because every pool a reader has seen stays mapped in it (zenoh issue 2787): with 1, "
        "driver crashes cost the readers nothing more, the crashed camera 1.5x the transport CPU",
    )
    zenoh_config: Path | None = Field(
        default=None, description="zenoh JSON5 config file loaded first (TLS, mTLS, access control)"
    )
    overrides: dict[str, Any] = Field(
        default_factory=dict, description="zenoh config paths set last, e.g. {'transport/link/tls/...': ...}"
    )

    def to_zenoh(self) -> zenoh.Config:
        """Build the ``zenoh.Config``; raise ``BusError`` naming the setting zenoh refused.

        The file (``zenoh_config``) is loaded first; mode, connect and listen override it only where
        they are set, so that a secure profile's TLS endpoints are not replaced by the defaults.
        """
        try:
            cfg = zenoh.Config.from_file(str(self.zenoh_config)) if self.zenoh_config else zenoh.Config()
        except (zenoh.ZError, OSError) as exc:
            raise BusError(f"cannot load zenoh config {self.zenoh_config}: {exc}") from exc
        settings: dict[str, Any] = {
            "scouting/multicast/enabled": self.multicast_scouting,
            "transport/shared_memory/enabled": self.shared_memory,
            # Off: zenoh would give every process a 16 MiB pool of its own for any message over 3 KB,
            # and each restart of any process would leave one more pool mapped in its readers.
            # Frames get their pool explicitly (Bus.publisher(frames=True)); nothing else needs one.
            "transport/shared_memory/transport_optimization/enabled": False,
        }
        if self.mode is not None or self.zenoh_config is None:
            settings["mode"] = self.mode or "client"
        if self.connect is not None:
            settings["connect/endpoints"] = self.connect
        elif self.zenoh_config is None and self.mode != "router":
            settings["connect/endpoints"] = [DEFAULT_ROUTER]
        if self.listen:
            settings["listen/endpoints"] = self.listen
        settings.update(self.overrides)
        for path, value in settings.items():
            try:
                cfg.insert_json5(path, json.dumps(value))
            except zenoh.ZError as exc:
                raise BusError(f"zenoh refused setting {path}={value!r}: {exc}") from exc
        return cfg

    @classmethod
    def router(cls, listen: list[str], connect: list[str] | None = None) -> TransportConfig:
        """A router listening on ``listen``; ``connect``: other routers it peers with."""
        return cls(mode="router", connect=list(connect or []), listen=listen)


def memory_lock_problem(status_file: Path = Path("/proc/self/status")) -> str | None:
    """Why this process cannot use zenoh shared memory, or None when it can.

    zenoh locks (mlock) its own pool and every pool it receives frames from. Without CAP_IPC_LOCK
    that is capped by RLIMIT_MEMLOCK (8 MiB on Debian), and a sample whose pool cannot be locked
    is dropped without a word (zenoh issue 2788): a reader would see a silent camera. A finite
    limit only postpones that, since pools of crashed publishers stay locked.
    """
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        caps = next(
            int(line.split()[1], 16) for line in status_file.read_text().splitlines() if line.startswith("CapEff:")
        )
    except (OSError, StopIteration, ValueError, IndexError):
        caps = 0
    if caps >> CAP_IPC_LOCK & 1:
        return None
    return f"locked memory is limited to {soft // 1024} KiB (RLIMIT_MEMLOCK) and the process lacks CAP_IPC_LOCK"


def usable_transport(transport: TransportConfig) -> TransportConfig:
    """``transport``, with shared memory switched off (and a warning) where it cannot work."""
    if not transport.shared_memory:
        return transport
    problem = memory_lock_problem()
    if problem is None:
        return transport
    log.warning(
        "zenoh shared memory off for this process: %s. Frames travel as plain bytes (more CPU). To use it, run with "
        "`ulimit -l unlimited` (systemd: LimitMEMLOCK=infinity) or set transport.shared_memory = false to silence this.",
        problem,
    )
    return transport.model_copy(update={"shared_memory": False})


def open_session(transport: TransportConfig) -> zenoh.Session:
    """Open a zenoh session; raise ``BusError`` with the endpoints tried when it fails."""
    transport = usable_transport(transport)
    try:
        return zenoh.open(transport.to_zenoh())
    except zenoh.ZError as exc:
        raise BusError(
            f"cannot open zenoh session (mode {transport.mode}, connect {transport.connect}, "
            f"listen {transport.listen}): {exc}. Is the router running (cellsight run / cellsight router)?"
        ) from exc


@dataclass(frozen=True)
class Received(Generic[Msg]):
    """A decoded message with its concrete key and local receive time (ns, ``time.time_ns``)."""

    key: str
    msg: Msg
    receive_ns: int


class Inbox(Generic[Msg]):
    """Thread-safe bounded queue of decoded messages. ``ring=True`` drops the oldest when full."""

    def __init__(self, capacity: int, ring: bool) -> None:
        self._items: deque[Received[Msg]] = deque(maxlen=capacity if ring else None)
        self._capacity = capacity
        self._ring = ring
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, item: Received[Msg]) -> None:
        with self._cond:
            if len(self._items) >= self._capacity:
                self.dropped += 1
                if not self._ring:
                    return  # FIFO full: refuse the newest, keep what we have
            self._items.append(item)
            self._cond.notify()

    def get(self, timeout_s: float | None = None) -> Received[Msg] | None:
        """The oldest message, waiting up to ``timeout_s`` seconds (None: forever)."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._items, timeout=timeout_s):
                return None
            return self._items.popleft()

    def wait(self, timeout_s: float) -> bool:
        """Block until a message is waiting (True) or ``timeout_s`` seconds passed (False); takes nothing."""
        with self._cond:
            return bool(self._cond.wait_for(lambda: self._items, timeout=timeout_s))

    def drain(self) -> list[Received[Msg]]:
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items


class Subscription(Generic[Msg]):
    """A zenoh subscriber that decodes into an ``Inbox`` (or a callback) and counts bad input."""

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        msg_type: type[Msg] | None = None,
        *,
        capacity: int = 1024,
        ring: bool = False,
        callback: Callable[[Received[Msg]], None] | None = None,
        semantic: bool = True,
        limits: WireLimits = DEFAULT_LIMITS,
    ) -> None:
        self.key_expr = key_expr
        self._semantic = semantic
        self._limits = limits
        self._msg_type = msg_type
        self.inbox: Inbox[Msg] = Inbox(capacity, ring)
        self._callback = callback
        self.received = 0
        self.bad: Counter[str] = Counter()
        self.rejected: Counter[tuple[str, str]] = Counter()  # (key, reason) -> messages dropped
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            parsed = keys.parse(key)
            if self._msg_type is not None and parsed.message_type is not self._msg_type:
                # "cellsight/c/*/status" also matches "cellsight/c/estimate/status": not ours, not bad.
                return
            now_ns = time.time_ns()
            msg = decode(sample.payload.to_bytes(), parsed.message_type, self._semantic, self._limits)
            check_on_key(msg, parsed.camera, now_ns, self._limits)
            item = Received(key, msg, now_ns)
        except SchemaError as exc:
            self._count_bad(key, str(exc), exc.reason)
            return
        with self._lock:
            self.received += 1
        if self._callback is None:
            self.inbox.put(item)
            return
        try:
            self._callback(item)
        except Exception:  # zenoh's thread boundary: a handler bug must not kill the subscription
            self._count_bad(key, "handler raised", "handler")
            log.exception("handler for %s raised on a message", key)

    def _count_bad(self, key: str, why: str, reason: str) -> None:
        with self._lock:
            self.bad[key] += 1
            self.rejected[key, reason] += 1
            first = self.bad[key] == 1
        if first:  # once per key: a flood of garbage must not flood the log
            log.warning("dropping malformed payload on %s: %s (further ones on this key are only counted)", key, why)

    def get(self, timeout_s: float | None = None) -> Received[Msg] | None:
        return self.inbox.get(timeout_s)

    def drain(self) -> list[Received[Msg]]:
        return self.inbox.drain()

    def close(self) -> None:
        self._sub.undeclare()


class Publisher(Generic[Msg]):
    """Publishes one message type on one concrete key; checks the type against the contract."""

    def __init__(
        self, session: zenoh.Session, key: str, *, frames: bool = False, shm: zenoh.shm.ShmProvider | None = None
    ) -> None:
        self.key = key
        self.msg_type = keys.message_type(key)
        self._shm = shm
        self.shm_puts = 0
        # Frames: drop under congestion (newest wins downstream); small messages: block, never lose.
        cc = zenoh.CongestionControl.DROP if frames else zenoh.CongestionControl.BLOCK
        prio = zenoh.Priority.DATA_LOW if frames else zenoh.Priority.DATA
        self._pub = session.declare_publisher(key, congestion_control=cc, priority=prio)
        self.published = 0

    def put(self, msg: Msg) -> None:
        if not isinstance(msg, self.msg_type):
            raise SchemaError(f"{self.key} carries {self.msg_type.__name__}, not {type(msg).__name__}")
        data = msg.SerializeToString()
        if self._shm is not None:
            try:  # frames travel through shared memory between processes on this host
                buf = self._shm.alloc(len(data), zenoh.shm.GarbageCollect())
                buf[:] = data
                self._pub.put(buf)
                self.published += 1
                self.shm_puts += 1
                return
            except zenoh.ZError:
                pass  # the segment is full (slow subscribers): send this one as plain bytes
        self._pub.put(data)
        self.published += 1

    def wanted(self) -> bool:
        """Whether any subscriber matches this key now (zenoh's matching status, through routers):
        a frame nobody receives need not be built."""
        return self._pub.matching_status.matching

    def close(self) -> None:
        self._pub.undeclare()


@dataclass
class _DueImage:
    """An image key's subscription while an image of it is due: ``waiting``, ``offered`` (the
    callback has one and may refuse it) or ``taken``."""

    sub: zenoh.Subscriber | None = None
    state: Literal["waiting", "offered", "taken"] = "waiting"


class CellTap:
    """Every key of a cell, each camera's images at most ``max_image_hz`` per key (recorder, live view).

    An image key is subscribed only while an image of it is due, from the tap's thread: a driver
    builds images only while someone subscribes, and a link between hosts carries only what a
    subscriber on its far side asked for, so a recorder keeping one image in 15 costs the drivers
    and the link about one in 15 too instead of all 30 a second. Cameras are learned from their
    other keys (status comes every second). A callback that returns False for an image refuses it
    (the recorder thins by stamp, which a driver running late moves against arrival): the
    subscription then waits for the next one.
    """

    def __init__(self, bus: Bus, callback: Callable[[str, bytes, int], bool | None], max_image_hz: float) -> None:
        if max_image_hz <= 0:
            raise BusError(f"max_image_hz must be positive, not {max_image_hz}")
        self._bus = bus
        self._callback = callback
        self._period_s = 1.0 / max_image_hz
        self._lock = threading.Lock()
        self._cameras: set[str] = set()
        self._image_keys: list[str] = []  # of every camera heard
        self._due: dict[str, _DueImage] = {}  # image key -> its subscription while an image is due
        self._taken: dict[str, float] = {}  # image key -> monotonic s its last image arrived
        self._subs = [bus.subscribe_raw(k, self._on_sample) for k in keys.everything_but_images(bus.cell)]
        self._stop = threading.Event()
        self._wake = threading.Event()  # an image arrived: its subscription goes before the camera's next frame
        self._thread = threading.Thread(target=self._pull, name="cell-tap", daemon=True)
        self._thread.start()

    def _on_sample(self, key: str, payload: bytes, receive_ns: int) -> None:
        try:
            camera = keys.parse(key).camera
        except KeyError_:
            camera = None
        if camera is not None and camera not in self._cameras:
            with self._lock:
                if camera not in self._cameras:
                    self._cameras.add(camera)
                    self._image_keys += keys.images(self._bus.cell, camera)
        self._callback(key, payload, receive_ns)

    def _on_image(self, key: str, payload: bytes, receive_ns: int) -> None:
        with self._lock:
            due = self._due.get(key)
            if due is None or due.state != "waiting":
                return  # one image per due time; the woken thread ends the subscription
            due.state = "offered"
        if self._callback(key, payload, receive_ns) is False:  # refused (stamped too soon after the last, say)
            with self._lock:
                due.state = "waiting"
            return
        with self._lock:
            due.state, self._taken[key] = "taken", time.monotonic()
        self._wake.set()

    def _pull(self) -> None:
        tick = min(0.05, self._period_s / 4)
        while not self._stop.is_set():
            self._wake.wait(tick)
            self._wake.clear()
            now = time.monotonic()
            with self._lock:
                done = [
                    self._due.pop(k).sub for k in self._image_keys if k in self._due and self._due[k].state == "taken"
                ]
                due = {
                    k: _DueImage()
                    for k in self._image_keys
                    if k not in self._due and now - self._taken.get(k, -math.inf) >= self._period_s
                }
                self._due.update(due)
            for sub in done:  # outside the lock: undeclaring waits for the subscriber's running callback
                sub.undeclare()
            for k, d in due.items():
                d.sub = self._bus.subscribe_raw(k, self._on_image)

    def undeclare(self) -> None:
        """Stop, as a zenoh subscriber's ``undeclare``."""
        self._stop.set()
        self._wake.set()
        self._thread.join()
        for sub in self._subs + [d.sub for d in self._due.values()]:
            sub.undeclare()
        self._due.clear()


class Bus:
    """A zenoh session bound to one cell. Close it (or use ``with``) to leave the network."""

    def __init__(self, transport: TransportConfig, cell: str, limits: WireLimits = DEFAULT_LIMITS) -> None:
        self.cell = keys.check_name(cell, "cell name")
        self.limits = limits  # what every subscription of this bus accepts
        self.transport = usable_transport(transport)
        self.session = open_session(self.transport)
        self._tokens: list[zenoh.LivelinessToken] = []
        self._shm: zenoh.shm.ShmProvider | None = None

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def publisher(self, key: str, *, frames: bool = False) -> Publisher:
        """Typed publisher; ``frames=True``: lower priority, dropped under congestion, shared memory."""
        shm = self._frame_pool() if frames and self.transport.shared_memory else None
        return Publisher(self.session, key, frames=frames, shm=shm)

    def _frame_pool(self) -> zenoh.shm.ShmProvider | None:
        """This process's shared-memory pool for frames, made on first use; None if the OS refuses."""
        if self._shm is None:
            try:
                self._shm = zenoh.shm.ShmProvider.default_backend(self.transport.shm_pool_mb * 1024 * 1024)
            except zenoh.ZError as exc:  # /dev/shm full, or locked memory refused: plain bytes still work
                log.warning(
                    "no %d MiB shared-memory pool for frames (%s): sending them as plain bytes",
                    self.transport.shm_pool_mb,
                    exc,
                )
                self.transport = self.transport.model_copy(update={"shared_memory": False})
        return self._shm

    def subscribe(
        self,
        key_expr: str,
        msg_type: type[Msg] | None = None,
        *,
        capacity: int = 1024,
        ring: bool = False,
        callback: Callable[[Received[Msg]], None] | None = None,
        semantic: bool = True,
    ) -> Subscription[Msg]:
        """Decode messages on ``key_expr``; the type comes from the key when ``msg_type`` is None.

        ``semantic=False`` checks wire format and schema only, for a consumer that validates the
        content itself, many messages at once (the estimator's marker observations)."""
        return Subscription(
            self.session,
            key_expr,
            msg_type,
            capacity=capacity,
            ring=ring,
            callback=callback,
            semantic=semantic,
            limits=self.limits,
        )

    def subscribe_raw(self, key_expr: str, callback: Callable[[str, bytes, int], None]) -> zenoh.Subscriber:
        """Undecoded payloads: ``callback(key, payload, receive_ns)`` in zenoh's thread (recorder)."""

        def on_sample(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                callback(key, sample.payload.to_bytes(), time.time_ns())
            except Exception:  # zenoh's thread boundary: one bad sample must not end the subscription
                log.exception("raw handler for %s raised", key)

        return self.session.declare_subscriber(key_expr, on_sample)

    def tap_cell(self, callback: Callable[[str, bytes, int], bool | None], max_image_hz: float) -> CellTap:
        """Every key of the cell, undecoded, into ``callback(key, payload, receive_ns)``, each
        camera's images at most ``max_image_hz`` (``CellTap``)."""
        return CellTap(self, callback, max_image_hz)

    def declare_alive(self, component: str, ident: str) -> str:
        """Hold a liveliness token ``cellsight/<cell>/alive/<component>/<id>`` until close."""
        key = keys.alive(self.cell, component, ident)
        self._tokens.append(self.session.liveliness().declare_token(key))
        return key

    def alive(self, timeout_s: float = 1.0) -> list[str]:
        """Keys of every liveliness token currently held in this cell, sorted, without duplicates."""
        replies = self.session.liveliness().get(keys.alive_all(self.cell), timeout=timeout_s)
        return sorted({str(r.ok.key_expr) for r in replies if r.ok is not None})

    def query(self, key: str, timeout_s: float = 2.0) -> list[Received]:
        """Query a queryable (e.g. ``estimate/map``) and decode its replies; bad replies are skipped."""
        msg_type = keys.message_type(key)
        out = []
        for reply in self.session.get(key, timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                msg = decode(reply.ok.payload.to_bytes(), msg_type, limits=self.limits)
                check_on_key(msg, None, time.time_ns(), self.limits)
                out.append(Received(str(reply.ok.key_expr), msg, time.time_ns()))
            except SchemaError as exc:
                log.warning("dropping malformed reply on %s: %s", key, exc)
        return out

    def close(self) -> None:
        for tok in self._tokens:
            tok.undeclare()
        self._tokens.clear()
        self.session.close()
