"""Soak: the demo cell under ``cellsight run --record`` for 30 minutes, with faults on a schedule.

The first and last windows are fault-free; they give memory (private resident memory of every
process of the cell, from /proc, and apart from it the shared memory each maps), the estimator's
update time (``EstimatorStatus.update_ms``, and the CPU time in it) and the pair factors it
rebuilt, at the start and at the end. In between, one fault every period, cycling through: a
driver SIGKILLed, the estimator SIGKILLed, the router SIGKILLed, the recorder SIGKILLed, the
recognition worker SIGKILLed, a driver paused (SIGSTOP, so its camera stops sending) for 5 s. A
fault is recovered when the killed process runs again under a new pid and every camera is
``localized`` again (for the recognition worker: objects published again). Afterwards the
recording (every part) is checked for gaps: each camera's marker observations must be continuous
apart from windows when a fault had the driver, the router or the recorder down.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import signal
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.common import launch_demo_cell, main
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.log import ReadReport, read_log

log = logging.getLogger("benchmarks.soak")
CELL = "soak"
CAMERAS = ("cam1", "cam2", "cam3", "cam4")
#: (name, process to fault, how): the schedule cycles through these.
FAULTS = (
    ("driver killed", "driver/cam3", "kill"),
    ("estimator killed", "estimator", "kill"),
    ("router killed", "router", "kill"),
    ("recorder killed", "recorder", "kill"),
    ("recognition killed", "recognition", "kill"),
    ("camera stops sending", "driver/cam4", "pause"),
)
PAUSE_S = 5.0
RECOVER_TIMEOUT_S = 60.0
#: A hole in a camera's recorded observations longer than this is a gap (frames come at several Hz).
GAP_S = 2.0


@dataclass
class Schedule:
    """Seconds since the cell started: warm-up, fault-free windows at both ends, fault period."""

    duration_s: float
    warmup_s: float
    window_s: float
    period_s: float
    settle_s: float  # after the last fault, before the last window

    def fault_times(self) -> list[float]:
        first = self.warmup_s + self.window_s
        last = self.duration_s - self.window_s - self.settle_s
        return list(np.arange(first, max(last, first) + 1e-9, self.period_s))


@dataclass
class Fault:
    name: str
    process: str
    how: str  # "kill" (SIGKILL) or "pause" (SIGSTOP for PAUSE_S, then SIGCONT)
    at: float  # monotonic s
    parts_before: int  # recording parts when it struck
    recovered_at: float | None = None


@dataclass
class Watch:
    """What the benchmark sees on the bus, stamped with time.monotonic() (s)."""

    states: list[tuple[float, dict[str, int]]] = field(default_factory=list)
    update_ms: list[tuple[float, float]] = field(default_factory=list)
    update_cpu_ms: list[tuple[float, float]] = field(default_factory=list)
    rebuilt: list[tuple[float, float]] = field(default_factory=list)  # EstimatorStatus.factors_rebuilt, cumulative
    objects: list[float] = field(default_factory=list)

    def on_status(self, r) -> None:
        now = time.monotonic()
        self.states.append((now, {c.camera_id: c.state for c in r.msg.cameras}))
        self.update_ms.append((now, r.msg.update_ms))
        self.update_cpu_ms.append((now, r.msg.update_cpu_ms))
        self.rebuilt.append((now, float(r.msg.factors_rebuilt)))

    def all_localized_after(self, t: float) -> bool:
        return any(at > t and all(s.get(c) == m.CameraState.LOCALIZED for c in CAMERAS) for at, s in self.states[-50:])


def processes(run_dir: Path) -> dict[str, int]:
    try:
        return {p["name"]: p["pid"] for p in json.loads((run_dir / "processes.json").read_text())}
    except (OSError, ValueError):  # being replaced this instant
        return {}


def memory_mb(pid: int) -> tuple[float, float]:
    """(private, shared-memory) resident MiB of a process, from /proc/PID/status (NaN once gone).

    Apart because they mean different things: private memory (RssAnon) is where a leak shows;
    shared memory (RssShmem) is zenoh's frame pools, which the machine holds once however many
    processes map them, and which every reader's VmRSS counts again.
    """
    found = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(("RssAnon:", "RssShmem:")):
                found[line.split(":")[0]] = int(line.split()[1]) / 1024
    except OSError:
        pass
    return found.get("RssAnon", float("nan")), found.get("RssShmem", float("nan"))


def inject(fault: Fault, pid: int) -> None:
    if fault.how == "pause":
        os.kill(pid, signal.SIGSTOP)
        time.sleep(PAUSE_S)
        os.kill(pid, signal.SIGCONT)
    else:
        os.kill(pid, signal.SIGKILL)


def recovered(fault: Fault, old_pid: int, run_dir: Path, watch: Watch) -> bool:
    if fault.how == "kill" and processes(run_dir).get(fault.process, old_pid) == old_pid:
        return False
    if fault.process == "recognition":
        return any(t > fault.at + 1.0 for t in watch.objects[-5:])
    if fault.process == "recorder":  # the restarted recorder writes a new part beside the old
        return len(list(run_dir.glob("log*.mcap"))) > fault.parts_before
    return watch.all_localized_after(fault.at + (PAUSE_S if fault.how == "pause" else 1.0))


def log_gaps(run_dir: Path, faults: list[Fault], t0_mono: float, t0_ns: int) -> tuple[int, int, int]:
    """(parts, gaps, gaps not explained by a fault) in the recorded marker observations."""
    parts = sorted(run_dir.glob("log*.mcap"))
    seen: dict[str, list[int]] = {c: [] for c in CAMERAS}
    wanted = {keys.markers(CELL, c): c for c in CAMERAS}
    for part in parts:
        for msg in read_log(part, set(wanted), ReadReport()):
            seen[wanted[msg.key]].append(msg.log_time_ns)
    down = [
        ((f.at - t0_mono) * 1e9 + t0_ns, ((f.recovered_at or f.at + RECOVER_TIMEOUT_S) - t0_mono) * 1e9 + t0_ns)
        for f in faults
        if f.process.split("/")[0] in ("driver", "router", "recorder")
    ]
    gaps = unexplained = 0
    for stamps in seen.values():
        t = np.sort(np.array(stamps, dtype=np.int64))
        for k in np.flatnonzero(np.diff(t) > GAP_S * 1e9):
            gaps += 1
            a, b = t[k], t[k + 1]
            unexplained += not any(a < hi + GAP_S * 1e9 and b > lo - GAP_S * 1e9 for lo, hi in down)
    return len(parts), gaps, unexplained


def keep(run_dir: Path, dest: Path, memory: dict) -> None:
    """The run's logs, config, state and memory series in ``dest``; not the recording (30 minutes
    of it is ~16 GB, and copying it once filled the disk and lost the figures)."""
    try:
        dest.mkdir(parents=True, exist_ok=True)
        (dest / "memory.json").write_text(json.dumps(memory))
        shutil.copytree(run_dir, dest, dirs_exist_ok=True, ignore=shutil.ignore_patterns("*.mcap"))
    except OSError as exc:  # the figures matter more than the copy
        log.warning("could not keep the run in %s: %s", dest, exc)


def window(samples: list[tuple[float, float]], lo: float, hi: float) -> np.ndarray:
    return np.array([v for t, v in samples if lo <= t < hi] or [np.nan])


def run(quick: bool, args: argparse.Namespace | None = None) -> dict[str, float]:
    minutes = 0.75 if quick else (args.minutes if args is not None else 30.0)
    sched = Schedule(minutes * 60, 10.0, 5.0, 5.0, 5.0) if quick else Schedule(minutes * 60, 60.0, 300.0, 90.0, 60.0)
    watch, faults = Watch(), []
    rss: dict[str, list[tuple[float, float]]] = {}  # process name -> (s since start, private MiB)
    shm: dict[str, list[tuple[float, float]]] = {}  # process name -> (s since start, shared-memory MiB)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        proc, run_dir, port = launch_demo_cell(
            tmp, CELL, sched.duration_s + 120
        )  # its camera motions happen in the warm-up
        bus = None
        try:
            t0, t0_ns = time.monotonic(), time.time_ns()
            bus = Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), CELL)
            bus.subscribe(keys.estimate_status(CELL), m.EstimatorStatus, callback=watch.on_status)
            bus.subscribe_raw(keys.objects(CELL), lambda k, p, t: watch.objects.append(time.monotonic()))
            schedule = [t0 + s for s in sched.fault_times()]
            pending: list[tuple[Fault, int]] = []
            next_rss = t0
            while time.monotonic() < t0 + sched.duration_s:
                now = time.monotonic()
                if now >= next_rss:
                    for name, pid in processes(run_dir).items():
                        private, shared = memory_mb(pid)
                        rss.setdefault(name, []).append((now - t0, private))
                        shm.setdefault(name, []).append((now - t0, shared))
                    next_rss = now + 5.0
                if schedule and now >= schedule[0]:
                    schedule.pop(0)
                    name, target, how = FAULTS[len(faults) % len(FAULTS)]
                    pid = processes(run_dir)[target]
                    fault = Fault(name, target, how, now, len(list(run_dir.glob("log*.mcap"))))
                    faults.append(fault)
                    inject(fault, pid)
                    pending.append((fault, pid))
                for fault, pid in list(pending):
                    if recovered(fault, pid, run_dir, watch):
                        fault.recovered_at = time.monotonic()
                        pending.remove((fault, pid))
                    elif time.monotonic() > fault.at + RECOVER_TIMEOUT_S:
                        pending.remove((fault, pid))
                        last = watch.states[-1][1] if watch.states else {}
                        log.warning(
                            "%s at %.0f s: not recovered in %.0f s (camera states %s, processes %s)",
                            fault.name,
                            fault.at - t0,
                            RECOVER_TIMEOUT_S,
                            last,
                            processes(run_dir),
                        )
                time.sleep(0.2)
            proc.send_signal(signal.SIGTERM)
            proc.wait(120)
            if args is not None and args.keep is not None:
                keep(
                    run_dir,
                    args.keep,
                    {"private_mb": rss, "shared_mb": shm, "faults": [(f.name, f.at - t0) for f in faults]},
                )
        finally:
            if bus is not None:
                bus.close()
            if proc.poll() is None:
                proc.kill()
        parts, gaps, unexplained = log_gaps(run_dir, faults, t0, t0_ns)
    end = sched.duration_s
    first = (sched.warmup_s, sched.warmup_s + sched.window_s)
    last = (end - sched.window_s, end)
    upd = [(t - t0, v) for t, v in watch.update_ms]
    upd_cpu = [(t - t0, v) for t, v in watch.update_cpu_ms]
    rebuilt = [(t - t0, v) for t, v in watch.rebuilt]
    rec_s = [f.recovered_at - f.at for f in faults if f.recovered_at is not None]
    # Median per process in each window; a process restarted in between counts with its new self.
    mb_first = {name: float(np.nanmedian(window(v, *first))) for name, v in rss.items()}
    mb_last = {name: float(np.nanmedian(window(v, *last))) for name, v in rss.items()}
    shm_first = {name: float(np.nanmedian(window(v, *first))) for name, v in shm.items()}
    shm_last = {name: float(np.nanmedian(window(v, *last))) for name, v in shm.items()}
    driver_restarts = sum(f.name == "driver killed" for f in faults)
    shm_growth_max = max(shm_last[name] - shm_first[name] for name in shm)
    return {
        "minutes": minutes,
        "faults_injected": len(faults),
        "faults_recovered": len(rec_s),
        "recovery_s_max": float(max(rec_s)) if rec_s else float("nan"),
        "rss_mb_first": sum(mb_first.values()),
        "rss_mb_last": sum(mb_last.values()),
        "rss_growth_mb": sum(mb_last.values()) - sum(mb_first.values()),
        **{f"rss_growth_mb_{name.replace('/', '_')}": mb_last[name] - mb_first[name] for name in sorted(rss)},
        "shm_mapped_mb_first_max": max(shm_first.values()),  # the most any one process maps
        "shm_mapped_mb_last_max": max(shm_last.values()),
        **{f"shm_mapped_growth_mb_{name.replace('/', '_')}": shm_last[name] - shm_first[name] for name in sorted(shm)},
        # zenoh keeps a dead publisher's pool mapped in its readers (zenoh issue 2787): the bound is one pool each
        "driver_restarts": driver_restarts,
        "shm_pool_mb": TransportConfig().shm_pool_mb,
        "shm_growth_mb_per_driver_restart_max": shm_growth_max / driver_restarts if driver_restarts else float("nan"),
        "update_ms_p99_first": float(np.nanpercentile(window(upd, *first), 99)),
        "update_ms_p99_last": float(np.nanpercentile(window(upd, *last), 99)),
        "update_ms_p50_first": float(np.nanmedian(window(upd, *first))),
        "update_ms_p50_last": float(np.nanmedian(window(upd, *last))),
        "update_cpu_ms_p99_first": float(np.nanpercentile(window(upd_cpu, *first), 99)),
        "update_cpu_ms_p99_last": float(np.nanpercentile(window(upd_cpu, *last), 99)),
        # the windows are fault-free, so the estimator's counter runs on through each
        "factors_rebuilt_first": float(np.ptp(window(rebuilt, *first))),
        "factors_rebuilt_last": float(np.ptp(window(rebuilt, *last))),
        "log_parts": parts,
        "log_gaps": gaps,
        "log_gaps_unexplained": unexplained,
        **{
            f"recovery_s_max_{name.replace(' ', '_')}": max(
                (f.recovered_at - f.at if f.recovered_at else float("inf")) for f in faults if f.name == name
            )
            for name in dict.fromkeys(f.name for f in faults)
        },
    }


def _args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--minutes", type=float, default=30.0, help="length of the full run (default 30)")
    parser.add_argument(
        "--keep",
        type=Path,
        help="copy the run folder here at the end (logs, config, state, memory series; not the recording)",
    )


if __name__ == "__main__":
    main("soak", __doc__.splitlines()[0], run, _args)
