"""Offline re-solve throughput: a synthetic log of 4 cameras at 30 Hz, end to end incl. MCAP decoding.

The log (default one hour, about 2.5 million marker observations; ``--quick``: one minute) is
written first from the demo cell's geometry with noise pre-drawn from the front-end's model and
cycled; only ``run_resolve`` (read, decode, validate, fuse, batch solve, write outputs) is timed:
as ``cellsight resolve`` runs it (the log read in a child process while this one solves), and,
as the reference in the same run, with the log read in this process.
Peak resident memory shows whether the log is streamed (it must not grow with the log's length).
"""

from __future__ import annotations

import resource
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks.common import main
from benchmarks.estimator_scale import rss_mb
from cellsight.config import CellConfig
from cellsight.evaluation.resolve_report import run_resolve
from cellsight.evaluation.synthetic import NoiseSettings, frame_observations, observations_msg
from cellsight.scenario_config import cell_config_of
from drivers.sim.scenario import load_scenario
from estimator.offline.solve import ResolveResult
from schemas import keys
from schemas import messages as m
from schemas.log import LogWriter

POOL = 32


def write_log(path: Path, seconds: float) -> tuple[CellConfig, int]:
    s = load_scenario()
    for c in s.cameras:
        c.motion = []
    cfg = cell_config_of(s)
    rng = np.random.default_rng(0)
    # Messages are built once per pool entry; per frame only the stamp changes (building each of
    # hundreds of thousands of messages through the codec made writing the log the slow part).
    pools = {
        c.id: [
            observations_msg(c.id, 0, frame_observations(s, c.id, 0.0, 0, rng, NoiseSettings(flip_rate=0.02)))
            for _ in range(POOL)
        ]
        for c in s.cameras
    }
    w = LogWriter(path, metadata={"config": cfg.to_toml()})
    n = 0
    msg = m.MarkerObservations()
    for k in range(int(seconds * 30)):
        stamp = 1_700_000_000_000_000_000 + k * 1_000_000_000 // 30
        for cam, pool in pools.items():
            msg.CopyFrom(pool[k % POOL])
            msg.stamp_ns = stamp
            w.write_raw(keys.markers(cfg.cell.name, cam), m.MarkerObservations, msg.SerializeToString(), stamp, stamp)
            n += len(msg.markers)
    w.close()
    return cfg, n


def timed_resolve(log: Path, out: Path, cfg: CellConfig, background: bool) -> tuple[ResolveResult, float, float, float]:
    """(result, wall s, cores used: this process's and its children's CPU over the wall time,
    peak resident MB of this process while resolving)."""
    peak = [rss_mb()]
    done = threading.Event()

    def sample() -> None:  # resident memory while resolving (ru_maxrss would include writing the log)
        while not done.wait(0.2):
            peak[0] = max(peak[0], rss_mb())

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    cpu0 = _cpu_s()
    t0 = time.perf_counter()
    result = run_resolve(log, out, cfg, background=background).result
    wall = time.perf_counter() - t0
    cores = (_cpu_s() - cpu0) / wall
    done.set()
    sampler.join()
    return result, wall, cores, peak[0]


def _cpu_s() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def run(quick: bool) -> dict[str, float]:
    seconds = 60.0 if quick else 3600.0
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "hour.mcap"
        cfg, n = write_log(log, seconds)
        size_mb = log.stat().st_size / 1e6
        rss_before = rss_mb()
        result, wall, cores, peak = timed_resolve(log, Path(tmp) / "out", cfg, background=True)
        # Reference in the same run: the same solve reading the log in this process.
        ref, ref_wall, _, _ = timed_resolve(log, Path(tmp) / "out_inline", cfg, background=False)
    return {
        "log_seconds": seconds,
        "log_mb": size_mb,
        "observations": float(result.observations),
        "observations_per_s": result.observations / wall,
        "observations_per_s_one_process": ref.observations / ref_wall,
        "resolve_s": wall,
        "cores_measured": cores,
        "rss_peak_mb": peak,
        "rss_before_resolve_mb": rss_before,
    }


if __name__ == "__main__":
    main("resolve", __doc__.splitlines()[0], run)
