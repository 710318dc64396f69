"""``cellsight run``: one router, one driver per camera, the estimator, recognition and the recorder, supervised.
On an edge host (``[cell] role = "edge"``): its router, peered with the cell's, and its cameras' drivers.

Every component runs as its own process (``python -m cellsight.cli ...``) with the run's saved
config, so a crash in one never takes the others down. A process that exits on its own is
restarted with exponential backoff; Ctrl-C / SIGTERM stops everything, SIGTERM first and SIGKILL
for whatever has not exited after a grace period, leaving no process behind.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from cellsight.config import CellConfig, save_used
from schemas.bus import DEFAULT_ROUTER
from schemas.errors import BusError

log = logging.getLogger(__name__)
CLI = [sys.executable, "-m", "cellsight.cli"]
GRACE_S = 5.0
#: Shutdown order (name prefixes): what derives data stops while its inputs still flow, so that its
#: last word is not "every camera stale"; the recorder then has everything, and the router goes last.
STOP_ORDER = ("estimator", "recognition", "driver/", "recorder", "router")
#: The longest a stop can take (s): every stage uses its whole grace period, then SIGKILL.
STOP_BOUND_S = GRACE_S * len(STOP_ORDER)
MAX_BACKOFF_S = 8.0
HEALTHY_AFTER_S = 30.0


@dataclass
class Child:
    name: str
    argv: list[str]
    log_path: Path
    proc: subprocess.Popen | None = None
    started: float = 0.0
    restarts: int = 0
    backoff_s: float = 0.5
    restart_at: float | None = None
    events: list[str] = field(default_factory=list)
    shm_starts: int | None = None  # frame publishers: starts with shared memory, then plain bytes

    @property
    def plain_bytes(self) -> bool:
        """Whether this start sends frames as plain bytes (its shared-memory starts are used up)."""
        return self.shm_starts is not None and self.restarts >= self.shm_starts

    def start(self) -> None:
        log_file = open(self.log_path, "ab")
        env = {**os.environ, "CELLSIGHT__TRANSPORT__SHARED_MEMORY": "false"} if self.plain_bytes else None
        self.proc = subprocess.Popen(
            self.argv, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True, env=env
        )
        log_file.close()
        self.started = time.monotonic()
        self.restart_at = None

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Supervisor:
    """Keeps a set of child processes running until ``stop``; ``manifest`` lists them as JSON."""

    def __init__(self, children: list[Child], manifest: Path | None = None) -> None:
        self.children = children
        self.stopping = False
        self.manifest = manifest

    def write_manifest(self, all_children: list[Child] | None = None) -> None:
        """``processes.json`` in the run folder: name, pid, restarts of every process (atomic)."""
        if self.manifest is None:
            return
        rows = [
            {"name": c.name, "pid": c.pid, "restarts": c.restarts, "argv": c.argv}
            for c in (all_children or self.children)
        ]
        tmp = self.manifest.with_suffix(".tmp")
        tmp.write_text(json.dumps(rows, indent=1))
        os.replace(tmp, self.manifest)

    def start(self) -> None:
        for child in self.children:
            child.start()
            log.info("started %s (pid %d)", child.name, child.pid)

    def poll(self) -> list[str]:
        """Restart children that died; return the events of this call (also logged)."""
        events = []
        now = time.monotonic()
        for child in self.children:
            if self.stopping or child.alive():
                continue
            code = child.proc.returncode if child.proc else None
            if code == 0:  # finished its job (a scenario or a replay ended): nothing to restart
                if not child.events or child.events[-1] != "finished":
                    child.events.append("finished")
                    events.append(f"{child.name} finished")
                continue
            if child.restart_at is None:
                if now - child.started > HEALTHY_AFTER_S:
                    child.backoff_s = 0.5
                child.restart_at = now + child.backoff_s
                events.append(f"{child.name} exited with code {code}; restarting in {child.backoff_s:.1f} s")
                child.backoff_s = min(child.backoff_s * 2, MAX_BACKOFF_S)
            elif now >= child.restart_at:
                child.restarts += 1
                child.start()
                plain = (
                    ", frames as plain bytes: each new shared-memory pool stays mapped in every reader"
                    if child.plain_bytes
                    else ""
                )
                events.append(f"{child.name} restarted (pid {child.pid}, restart {child.restarts}{plain})")
                self.write_manifest()
        for e in events:
            log.warning(e)
        return events

    def stop(self) -> None:
        """Stop the children in STOP_ORDER: SIGTERM each group, then SIGKILL (the whole process group)
        what is left of it after the grace period."""
        self.stopping = True
        rank = {
            c.name: next((i for i, p in enumerate(STOP_ORDER) if c.name.startswith(p)), len(STOP_ORDER))
            for c in self.children
        }
        for stage in sorted(set(rank.values())):
            self._stop_group([c for c in self.children if rank[c.name] == stage])

    @staticmethod
    def _stop_group(children: list[Child]) -> None:
        for child in children:
            if child.alive():
                child.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + GRACE_S
        for child in children:
            if child.proc is None:
                continue
            try:
                child.proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", child.name, GRACE_S)
                try:
                    os.killpg(child.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                child.proc.wait()


def router_endpoint(cfg: CellConfig) -> str | None:
    """The loopback router the launcher must start, or None when the config joins existing routers."""
    t = cfg.transport
    secure_edge = cfg.cell.role == "edge" and cfg.cell.router_config is not None
    if t.mode not in (None, "client") or (t.zenoh_config is not None and not secure_edge):
        return None
    loopback = [
        e
        for e in (t.connect if t.connect is not None else [DEFAULT_ROUTER])
        if "127.0.0.1" in e or "localhost" in e or "[::1]" in e
    ]
    return loopback[0] if loopback else None


def plan(cfg: CellConfig, run_dir: Path, record: Path | None, max_image_hz: float | None, epoch_ns: int) -> list[Child]:
    """The processes of one cell. The config they all read is saved in ``run_dir`` first."""
    cfg_path = save_used(cfg, run_dir)
    logs = run_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    common = ["--cell-config", str(cfg_path)]
    children = []
    router = router_endpoint(cfg)
    edge = cfg.cell.role == "edge"
    if router is not None:
        upstream = [arg for endpoint in cfg.cell.upstream for arg in ("--connect", endpoint)] if edge else []
        secure = ["--config", str(cfg.cell.router_config)] if edge and cfg.cell.router_config is not None else []
        children.append(Child("router", CLI + ["router", "--listen", router] + upstream + secure, logs / "router.log"))
    for cam in cfg.cameras:
        if cam.source == "sim":
            argv = CLI + ["driver", "sim", "--camera", cam.id, "--epoch-ns", str(epoch_ns)] + common
        else:  # openni2 | realsense: the driver reads the rest of its camera section from the config
            argv = CLI + ["driver", cam.source, "--camera", cam.id] + common
        children.append(
            Child(f"driver/{cam.id}", argv, logs / f"driver_{cam.id}.log", shm_starts=cfg.transport.shm_driver_starts)
        )
    if edge:  # the cameras only: their markers and status cross to the cell, images stay unless asked for
        return children
    state = cfg.estimator.state_file or run_dir / "estimator_state.json"
    children.append(
        Child("estimator", CLI + ["estimator", "--state-file", str(state)] + common, logs / "estimator.log")
    )
    if cfg.recognition.enabled:
        children.append(Child("recognition", CLI + ["recognition"] + common, logs / "recognition.log"))
    if record is not None:
        argv = CLI + ["record", "--out", str(record)] + common
        if max_image_hz:
            argv += ["--max-image-hz", str(max_image_hz)]
        children.append(Child("recorder", argv, logs / "recorder.log"))
    return children


def wait_for_router(endpoint: str, timeout_s: float = 10.0) -> None:
    """Block until the router accepts TCP connections (children then connect at once)."""
    import socket

    host_port = endpoint.split("/", 1)[1]
    host, port = host_port.rsplit(":", 1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise BusError(f"the zenoh router on {endpoint} did not come up within {timeout_s:.0f} s (see the router log)")


def with_models(cfg: CellConfig, run_dir: Path) -> CellConfig:
    """The config with a model database for recognition, or with recognition off if there is none.

    A simulated cell's objects are built into RUN_DIR/models before the cell starts: inside the
    running cell the (niced) worker would compete with the renderers for the CPU for minutes.
    """
    rec = cfg.recognition
    if not rec.enabled or rec.models is not None or cfg.cell.role == "edge":  # an edge host runs no recognition
        return cfg
    from cellsight.model_build import models_for
    from recognition.errors import ModelError

    try:
        log.info("building the recognition models of the scenario's objects into %s", run_dir / "models")
        models_for(cfg).save(run_dir / "models")
        rec = rec.model_copy(update={"models": (run_dir / "models").resolve()})
    except ModelError as exc:
        log.warning("recognition is off: %s", exc)
        rec = rec.model_copy(update={"enabled": False})
    return cfg.model_copy(update={"recognition": rec})


def run_cell(
    cfg: CellConfig,
    run_dir: Path,
    *,
    duration_s: float | None,
    record: Path | None = None,
    max_image_hz: float | None = None,
    stop: threading.Event | None = None,
    on_tick=None,
) -> Supervisor:
    """Start the cell, supervise it until ``duration_s`` or ``stop``, shut it down; returns the supervisor."""
    stop = stop or threading.Event()
    cfg = with_models(cfg, run_dir)
    epoch_ns = time.time_ns() + 3_000_000_000  # scenario time 0, once every process is up
    children = plan(cfg, run_dir, record, max_image_hz, epoch_ns)
    sup = Supervisor(children, run_dir / "processes.json")
    router = children[0] if children and children[0].name == "router" else None
    try:
        if router is not None:
            router.start()
            wait_for_router(router_endpoint(cfg))
        sup.children = [c for c in children if c is not router]
        sup.start()
        sup.children = children
        sup.write_manifest()
        end = None if duration_s is None else time.time_ns() / 1e9 + duration_s + 3.0
        while not stop.is_set() and (end is None or time.time_ns() / 1e9 < end):
            sup.poll()
            if on_tick is not None:
                on_tick(sup)
            stop.wait(0.2)
    finally:
        # Stop the producers first and the router last, so the recorder sees everything.
        order = [c for c in children if c.name.startswith("driver")] + [
            c for c in children if c.name in ("estimator", "recognition")
        ]
        order += [c for c in children if c.name == "recorder"] + [c for c in children if c.name == "router"]
        for group in ([c for c in order if c.name != "router"], [c for c in order if c.name == "router"]):
            Supervisor(group).stop()
    return sup
