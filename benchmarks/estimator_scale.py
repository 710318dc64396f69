"""Long-run cost of the estimator core: hours of 8 cameras x 30 Hz x 8 markers, as fast as possible.

A ring of 16 markers (4 anchors) seen by 8 static cameras, each seeing 8 of them; noise from the
front-end's depth-refined covariance model, pre-drawn (a pool of frames per camera, cycled with
advancing stamps) so the benchmark measures the estimator, not the random number generator.
Updates at the daemon's 10 Hz. Figures: update latency (p50, p99), the ratio of the last hour's
median update latency to the first hour's, resident memory growth after the first simulated
minute, and observations consumed per wall-clock second. Latency percentiles exclude the first
simulated minute (first placement of every camera and marker), whose worst update is reported
on its own as ``warmup_update_ms_max``. ``--hours`` sets the simulated span.
"""

from __future__ import annotations

import math
import time

import numpy as np

from benchmarks.common import main
from benchmarks.scenes import perturb
from drivers.markers import PlaneFit, covariance_model
from estimator.config import AnchorConfig, EstimatorConfig
from estimator.graph import Estimator
from estimator.observation import Observation
from schemas.codec import CameraInfo, invert_pose, quat_from_matrix
from schemas.spec import PoseSpec, look_at_matrix, normal_matrix

RATE = 30
UPDATE_EVERY = 3  # frames: 10 Hz
POOL = 64


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def ring_cell(n_cams: int = 8, n_markers: int = 16, per_cam: int = 8):
    markers = {}
    for i in range(n_markers):
        a = 2 * math.pi * i / n_markers
        p = np.array([2.5 * math.cos(a), 2.5 * math.sin(a), 1.0])
        T = np.eye(4)
        T[:3, :3] = normal_matrix(-p * np.array([1, 1, 0]))
        T[:3, 3] = p
        markers[i] = T
    cams = {}
    for j in range(n_cams):
        a = 2 * math.pi * j / n_cams + math.pi
        p = np.array([1.0 * math.cos(a), 1.0 * math.sin(a), 1.6])
        T = np.eye(4)
        T[:3, :3] = look_at_matrix(p, -p * np.array([1, 1, 0]) * 2 + np.array([0, 0, 1.0]))
        T[:3, 3] = p
        seen = sorted(markers, key=lambda m: np.linalg.norm(markers[m][:3, 3] - (-p)))[:per_cam]
        cams[f"cam{j}"] = (T, seen)
    anchors = [0, 4, 8, 12]
    return markers, cams, anchors


def run(quick: bool, args=None) -> dict[str, float]:
    hours = 0.02 if quick else (args.hours if args is not None else 24.0)
    markers, cams, anchors = ring_cell()
    cfg = EstimatorConfig(
        anchors=[AnchorConfig(marker_id=a, world_T_marker=PoseSpec(position=tuple(markers[a][:3, 3]), quaternion=tuple(quat_from_matrix(markers[a][:3, :3])))) for a in anchors]
    )
    est = Estimator(cfg)
    info = CameraInfo.kinect_v1()
    rng = np.random.default_rng(0)
    pools = {}
    for cid, (T, seen) in cams.items():
        frames = []
        for _ in range(POOL):
            obs = []
            for m in seen:
                Tm = invert_pose(T) @ markers[m]
                cov = covariance_model(Tm, 0.25, info, 0.5, PlaneFit(Tm[:3, 2], 0.0, 900, 0.0, 0.2))
                obs.append((m, perturb(Tm, cov, rng), cov))
            frames.append(obs)
        pools[cid] = frames
    n_frames = int(hours * 3600 * RATE)
    hour_frames = 3600 * RATE
    first_window = min(hour_frames, n_frames // 2)
    lat_first, lat_last, lat_all, lat_warm = [], [], [], []
    warmup = min(60 * RATE, n_frames // 10)
    rss0 = None
    n_obs = 0
    t_start = time.perf_counter()
    for k in range(n_frames):
        stamp = k * 1_000_000_000 // RATE
        for cid, frames in pools.items():
            pool = frames[k % POOL]
            est.add_frame(cid, stamp, [Observation(cid, stamp, m, T, cov) for m, T, cov in pool])
            n_obs += len(pool)
        if k % UPDATE_EVERY == 0:
            t0 = time.perf_counter()
            est.update(stamp)
            dt = (time.perf_counter() - t0) * 1e3
            (lat_warm if k < warmup else lat_all).append(dt)
            if k < warmup:
                pass
            elif k < first_window:
                lat_first.append(dt)
            elif k >= n_frames - first_window:
                lat_last.append(dt)
        if rss0 is None and k == warmup:
            rss0 = rss_mb()
    wall = time.perf_counter() - t_start
    lat = np.array(lat_all)
    return {
        "simulated_hours": hours,
        "observations": float(n_obs),
        "observations_per_s": n_obs / wall,
        "update_ms_p50": float(np.median(lat)),
        "update_ms_p99": float(np.percentile(lat, 99)),
        "warmup_update_ms_max": float(np.max(lat_warm)) if lat_warm else 0.0,
        "last_over_first_hour_latency_ratio": float(np.median(lat_last) / np.median(lat_first)),
        "rss_growth_mb": rss_mb() - (rss0 or rss_mb()),
        "factors_in_graph": float(est.factor_graph().size()),
    }


def add_args(parser) -> None:
    parser.add_argument("--hours", type=float, default=24.0, help="simulated span (default 24 h)")


if __name__ == "__main__":
    main("estimator_scale", __doc__.splitlines()[0], run, add_args)
