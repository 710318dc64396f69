"""Long-run cost of the estimator core: hours of 8 cameras x 30 Hz x 8 markers, cameras moving.

A ring of 16 markers (4 anchors) seen by 8 cameras, each seeing 8 of them; noise from the
front-end's depth-refined covariance model, pre-drawn (a pool of frames per camera, cycled with
advancing stamps) so the benchmark measures the estimator, not the random number generator.
Every ``--move-every`` simulated seconds (default 20; 0: a still cell) one camera, in turn, is
bumped: 2-5 cm and 0.5-2 deg from where it was installed; its pool moves with it (each
observation left-multiplied by the bump, so its noise stays what it was in the marker's frame).
The daemon's own path: every 10 Hz tick, each camera's 3 new frames go in as one block
(``Estimator.add_frames``), then one ``update``, then the ``estimate`` the daemon publishes
(poses and covariances). Figures: update, estimate and tick (ingest + update) latency, factors in
the graph (largest seen), resident memory growth after the first simulated minute, observations
consumed per wall-clock second, how many updates did solver work, and each camera's position
error against truth just before the last move.

The last/first-hour latency ratio is measured twice. Sequentially (``_sequential``): the run's
last hour against its first, minutes or hours of wall time apart, so it also measures how the
machine's speed drifted (a third, on this machine class, within an afternoon). Paired (the
figure): after the run, the aged estimator's next hour and a fresh estimator's first hour, fed
the same frames tick by tick, alternately, in the same wall-clock minutes. Latency percentiles
exclude each estimator's first simulated minute (first placement of every camera and marker),
whose worst update is reported on its own as ``warmup_update_ms_max``. ``--hours`` sets the
simulated span; the hour windows shrink to half of it when it is shorter than two hours.

``--arm``: one camera (``cam0``) on an arm that never stops, the others bumped in turn as above;
the daemon takes a moving camera's frames (``[estimator.keyframes] online``, its default). The arm sweeps
10 cm and 5 deg about where it was installed (periods of 7, 9 and 11 s, so it never rests); its
frames enter the graph ``lag_s`` after they were seen, and the newest ``max_live`` stay there.
The ring's synthetic views carry noise and no bias, so its static pairs fit ~15 times better than
their covariances claim, and weighed by that (``keyframes.weigh_by_fit``, ``estimator.variance``)
the arm's frames would mostly be left out (3,753 of 3,899 in a quarter hour at 64 cameras, a run with the
weighing on); views that carry the
bias the pairs allow for weigh them at their own covariances (the rendered demo does), so here they
enter so, and the benchmark measures what entering them costs. What the weighing costs is one pass
over every pair at most every 30 simulated s while frames enter: ``static_fit_ms``, best of 5 at
the end of every run.
Reported: the frames that entered (``keyframes_entered``), the arm's position error at the end
(``arm_pos_mm_final``, NaN when the estimator gives it no pose) and the other figures as above,
the bumped cameras' errors without the arm's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from rich.progress import Progress

from benchmarks.common import main
from cellsight.evaluation.synthetic import perturb
from drivers.markers import PlaneFit, covariance_model
from estimator.config import AnchorConfig, EstimatorConfig
from estimator.graph import Estimator
from estimator.observation import ObservationRows
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose, look_at_matrix, normal_matrix, quat_from_matrix
from schemas.spec import PoseSpec

RATE = 30
UPDATE_EVERY = 3  # frames per camera per tick: the daemon's 10 Hz
POOL = 64  # pre-drawn ticks per camera
TICK_NS = UPDATE_EVERY * 1_000_000_000 // RATE


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def ring_cell(n_cams: int = 8, n_markers: int = 16, per_cam: int | None = None):
    """Markers on a 2.5 m ring (4 anchors evenly spread), cameras on a 1 m ring looking outward, each
    seeing its ``per_cam`` nearest markers (default: 8, or enough that every marker is seen twice)."""
    per_cam = per_cam or max(8, math.ceil(2 * n_markers / n_cams))
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
    anchors = [i * n_markers // 4 for i in range(4)]
    return markers, cams, anchors


def tick_pools(markers, cams, rng: np.random.Generator) -> dict[str, list[ObservationRows]]:
    """POOL ticks per camera, each UPDATE_EVERY frames of noisy observations as one block."""
    info = CameraInfo.kinect_v1()
    pools: dict[str, list[ObservationRows]] = {}
    for cid, (T, seen) in cams.items():
        truth = [(m, invert_pose(T) @ markers[m]) for m in seen]
        covs = [covariance_model(Tm, 0.25, info, 0.5, PlaneFit(Tm[:3, 2], 0.0, 900, 0.0, 0.2)) for _, Tm in truth]
        ids = np.array([m for _ in range(UPDATE_EVERY) for m, _ in truth])
        frame = np.repeat(np.arange(UPDATE_EVERY), len(truth))
        block_covs = np.array(covs * UPDATE_EVERY)
        # (POOL, rows, 4, 4): every block's frames drawn at once, each row about its marker's truth
        poses = perturb(
            np.broadcast_to(np.array([Tm for _, Tm in truth] * UPDATE_EVERY), (POOL, len(ids), 4, 4)), block_covs, rng
        )
        pools[cid] = [ObservationRows(ids, P, P.copy(), block_covs, np.zeros(len(ids), bool), frame) for P in poses]
    return pools


@dataclass
class Mover:
    """Bumps one camera in turn every ``every_ticks`` ticks; moves its pool with it; knows the truth."""

    cams: dict[str, tuple[np.ndarray, list[int]]]  # installed world_T_camera and markers seen (the bumped ones)
    base: dict[str, list[ObservationRows]]  # the pools at the installed poses
    pools: dict[str, list[ObservationRows]]  # what the runners read (changed in place)
    every_ticks: int
    rng: np.random.Generator
    moves: int = 0
    truth: dict[str, np.ndarray] = field(init=False)

    def __post_init__(self) -> None:
        self.truth = {cid: T for cid, (T, _) in self.cams.items()}
        # Every camera's pool gets its own copy now, rewritten in place on a move: a copy made on
        # each camera's first move was the benchmark's own RSS growth (~1.5 MB a camera).
        for cid, blocks in self.base.items():
            self.pools[cid] = [replace(b, poses=b.poses.copy(), alternatives=b.alternatives.copy()) for b in blocks]

    def due(self, tick: int) -> bool:
        return self.every_ticks > 0 and tick > 0 and tick % self.every_ticks == 0

    def move(self) -> str:
        cid = sorted(self.cams)[self.moves % len(self.cams)]
        axis = self.rng.normal(size=3)
        angle = math.radians(self.rng.uniform(0.5, 2.0))
        shift = self.rng.normal(size=3)
        bump = np.eye(4)  # installed_T_bumped, in the camera's own frame
        bump[:3, :3] = gtsam_rotation(axis / np.linalg.norm(axis) * angle)
        bump[:3, 3] = shift / np.linalg.norm(shift) * self.rng.uniform(0.02, 0.05)
        self.truth[cid] = self.cams[cid][0] @ bump
        back = invert_pose(bump)  # camera_T_marker after = bump^-1 @ camera_T_marker before
        for moved, b in zip(self.pools[cid], self.base[cid]):
            np.matmul(back, b.poses, out=moved.poses)
            np.matmul(back, b.alternatives, out=moved.alternatives)
        self.moves += 1
        return cid


@dataclass(frozen=True)
class Arm:
    """A camera that never stops: a smooth sweep about its installed pose (``--arm``)."""

    camera_id: str
    world_T_installed: np.ndarray  # (4, 4)
    sweep_m: float = 0.10
    sweep_deg: float = 5.0

    def installed_T_camera(self, t_s: float) -> np.ndarray:
        """The arm's displacement (4, 4) at t_s seconds, in the installed camera's frame: sideways and
        up at incommensurate periods, panning at a third, so position and view change all the time."""
        w = 2 * math.pi * t_s
        T = np.eye(4)
        T[:3, :3] = gtsam_rotation(np.array([0.0, math.radians(self.sweep_deg) * math.sin(w / 11.0), 0.0]))
        T[:3, 3] = [0.5 * self.sweep_m * math.sin(w / 7.0), 0.25 * self.sweep_m * math.sin(w / 9.0), 0.0]
        return T

    def world_T_camera(self, stamp_ns: int) -> np.ndarray:
        return self.world_T_installed @ self.installed_T_camera(stamp_ns * 1e-9)

    def moved(self, block: ObservationRows, stamps: np.ndarray) -> ObservationRows:
        """The installed camera's block as the arm saw it: each frame's rows left-multiplied by its
        stamp's camera_T_installed (the noise stays what it was in the marker's frame)."""
        back = np.stack([invert_pose(self.installed_T_camera(t * 1e-9)) for t in stamps])[block.frame]
        return replace(block, poses=back @ block.poses, alternatives=back @ block.alternatives)


def gtsam_rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad)."""
    import gtsam

    return gtsam.Rot3.Expmap(rotvec).matrix()


def camera_errors_mm(est: Estimator, truth: dict[str, np.ndarray], now_ns: int) -> dict[str, float]:
    """Each camera's position error (mm); NaN for one without a pose."""
    cams = est.estimate(now_ns, with_covariance=False).cameras
    return {
        cid: float(np.linalg.norm(cams[cid].pose.T[:3, 3] - T[:3, 3]) * 1e3)
        if cid in cams and cams[cid].pose is not None
        else float("nan")
        for cid, T in truth.items()
    }


@dataclass
class Runner:
    """One estimator fed the pools tick by tick, with its own simulated clock. Per-tick figures
    go into arrays allocated up front, so the benchmark's own bookkeeping is no memory growth."""

    est: Estimator
    pools: dict[str, list[ObservationRows]]
    ticks: int
    arm: Arm | None = None
    tick: int = 0
    ingest_ms: np.ndarray = field(init=False)
    update_ms: np.ndarray = field(init=False)
    solved: np.ndarray = field(init=False)  # per tick: did the update run iSAM2 (not return early)
    estimate_ms: np.ndarray = field(init=False)  # the daemon's next step: poses and covariances to publish

    def __post_init__(self) -> None:
        # np.full writes every page now (np.zeros would commit them as ticks fill them in)
        self.ingest_ms, self.update_ms = np.full(self.ticks, np.nan), np.full(self.ticks, np.nan)
        self.solved = np.full(self.ticks, False)
        self.estimate_ms = np.full(self.ticks, np.nan)

    def step(self) -> int:
        """One 10 Hz tick; returns the observations it fed."""
        k = self.tick
        stamps = k * TICK_NS + np.arange(UPDATE_EVERY, dtype=np.int64) * (TICK_NS // UPDATE_EVERY)
        n = 0
        t0 = time.perf_counter()
        for cid, blocks in self.pools.items():
            block = blocks[k % POOL]
            if self.arm is not None and cid == self.arm.camera_id:
                block = self.arm.moved(block, stamps)
            self.est.add_frames(cid, stamps, block)
            n += len(block.ids)
        t1 = time.perf_counter()
        before = self.est.counters.updates
        self.est.update(int(stamps[-1]))
        t2 = time.perf_counter()
        self.est.estimate(int(stamps[-1]), with_covariance=True)
        t3 = time.perf_counter()
        self.solved[k] = self.est.counters.updates > before
        self.ingest_ms[k] = (t1 - t0) * 1e3
        self.update_ms[k] = (t2 - t1) * 1e3
        self.estimate_ms[k] = (t3 - t2) * 1e3
        self.tick += 1
        return n


def median_ms(samples: np.ndarray, lo: int, hi: int) -> float:
    return float(np.median(samples[lo:hi]))


def timed_ms(call: Callable[[], object]) -> float:
    """Wall time of one call (ms)."""
    t0 = time.perf_counter()
    call()
    return (time.perf_counter() - t0) * 1e3


def median_tick_ms(r: Runner, lo: int, hi: int) -> float:
    """Median ingest + update time of ticks [lo, hi)."""
    return median_ms(r.update_ms + r.ingest_ms, lo, hi)


def run(quick: bool, args=None) -> dict[str, float]:
    if args is not None and args.scan:
        return scan(0.02 if quick else args.hours if args.hours != 24.0 else 0.05, args.move_every)
    hours = 0.15 if quick else (args.hours if args is not None else 24.0)
    move_every_s = args.move_every if args is not None else 20.0
    if args is None:
        return measure(hours, move_every_s)
    return measure(hours, move_every_s, args.cameras, args.markers, arm=args.arm)


#: (cameras, markers) of ``--scan``: cameras doubling with two markers each, then markers at 64 cameras.
SCAN = [(8, 16), (16, 32), (32, 64), (64, 128), (64, 250), (64, 500), (64, 1000)]


def scan(hours: float, move_every_s: float) -> dict[str, float]:
    """``measure`` over ``SCAN``; the growth exponents of update p99 and p50 with cameras (log-log
    fits over the two-markers-per-camera rows)."""
    out: dict[str, float] = {"simulated_hours_each": hours, "move_every_s": move_every_s}
    p99, p50 = {}, {}
    for n, mk in SCAN:
        r = measure(hours, move_every_s, n, mk)
        p99[(n, mk)], p50[(n, mk)] = r["update_ms_p99"], r["update_ms_p50"]
        for key in (
            "update_ms_p50",
            "update_ms_p99",
            "estimate_ms_p99",
            "observations_per_s",
            "rss_growth_mb",
            "factors_max",
            "solver_updates_last_hour",
        ):
            out[f"{key}_{n}cams_{mk}markers"] = r[key]
    cams = [(n, mk) for n, mk in SCAN if mk == 2 * n]
    out["growth_exponent_cameras"] = growth_exponent([n for n, _ in cams], [p99[c] for c in cams])
    out["growth_exponent_cameras_p50"] = growth_exponent([n for n, _ in cams], [p50[c] for c in cams])
    out["update_ms_p99_64cams"] = p99[(64, 1000)]
    return out


def growth_exponent(sizes: list[int], values: list[float]) -> float:
    """Slope of log(value) against log(size): value grows as size to this power."""
    return float(np.polyfit(np.log(sizes), np.log(values), 1)[0])


def measure(
    hours: float, move_every_s: float, n_cams: int = 8, n_markers: int = 16, arm: bool = False
) -> dict[str, float]:
    """One cell of ``n_cams`` cameras and ``n_markers`` markers for ``hours`` simulated hours, the
    daemon's default estimator config; with ``arm``, ``cam0`` on an arm (``Arm``)."""
    markers, cams, anchors = ring_cell(n_cams, n_markers)
    cfg = EstimatorConfig(
        anchors=[
            AnchorConfig(
                marker_id=a,
                world_T_marker=PoseSpec(
                    position=tuple(markers[a][:3, 3]), quaternion=tuple(quat_from_matrix(markers[a][:3, :3]))
                ),
            )
            for a in anchors
        ]
    )
    if arm:  # see the module docstring: the arm's frames enter at their own covariances
        cfg = cfg.model_copy(update={"keyframes": cfg.keyframes.model_copy(update={"weigh_by_fit": False})})
    base = tick_pools(markers, cams, np.random.default_rng(0))
    pools = dict(base)
    the_arm = Arm("cam0", cams["cam0"][0]) if arm else None
    bumped = {cid: c for cid, c in cams.items() if the_arm is None or cid != the_arm.camera_id}
    mover = Mover(
        bumped,
        {cid: base[cid] for cid in bumped},
        pools,
        int(move_every_s * RATE / UPDATE_EVERY),
        np.random.default_rng(1),
    )
    ticks_per_hour = 3600 * RATE // UPDATE_EVERY
    n_ticks = int(hours * ticks_per_hour)
    window = min(ticks_per_hour, n_ticks // 2)  # "an hour"
    warmup = min(60 * RATE // UPDATE_EVERY, n_ticks // 10)  # the first simulated minute
    aged = Runner(Estimator(cfg), pools, n_ticks + window, the_arm)
    n_obs, rss0, factors_max, errors = 0, float("nan"), 0, {}
    t_start = time.perf_counter()
    with Progress(transient=True) as progress:
        task = progress.add_task(f"{hours:g} simulated hours", total=n_ticks + 2 * window)
        for k in range(n_ticks):
            if mover.due(k):
                errors = camera_errors_mm(
                    aged.est, mover.truth, k * TICK_NS
                )  # the newest moved camera had a full period
                mover.move()
            n_obs += aged.step()
            if k == warmup:
                rss0 = rss_mb()
            if k % 50 == 0:
                factors_max = max(factors_max, aged.est.factor_count())
            if k % 2000 == 0:
                progress.update(task, completed=k)
            if (
                k and k % max(n_ticks // 20, 1) == 0 and not progress.console.is_terminal
            ):  # a log file sees progress too
                progress.console.log(
                    f"{k / ticks_per_hour:.3g} of {hours:g} simulated hours, {time.perf_counter() - t_start:.0f} s"
                )
        if not errors:
            errors = camera_errors_mm(aged.est, mover.truth, n_ticks * TICK_NS)
        arm_mm = float("nan")
        if the_arm is not None:  # the arm's error at the last tick's newest frame
            last_ns = (n_ticks - 1) * TICK_NS + (UPDATE_EVERY - 1) * (TICK_NS // UPDATE_EVERY)
            arm_mm = camera_errors_mm(aged.est, {the_arm.camera_id: the_arm.world_T_camera(last_ns)}, last_ns)[
                the_arm.camera_id
            ]
        keyframes = aged.est.counters.keyframes
        fit_ms = min(timed_ms(aged.est.static_fit) for _ in range(5))
        wall = time.perf_counter() - t_start
        rss_end = rss_mb()
        reorders = aged.est.counters.reorders
        # Paired: the aged estimator's next hour against a fresh one's first, alternating ticks.
        young = Runner(Estimator(cfg), pools, window, the_arm)
        paired_aged_from = n_ticks
        for k in range(window):
            if mover.due(n_ticks + k):  # both see the same moves
                mover.move()
            first, second = (aged, young) if k % 2 == 0 else (young, aged)
            first.step()
            second.step()
            if k % 2000 == 0:
                progress.update(task, completed=n_ticks + 2 * k)
    upd = aged.update_ms[warmup:n_ticks]
    tick = aged.update_ms[warmup:n_ticks] + aged.ingest_ms[warmup:n_ticks]
    seq_first = median_ms(aged.update_ms, warmup, window)
    seq_last = median_ms(aged.update_ms, n_ticks - window, n_ticks)
    paired_aged = median_ms(aged.update_ms, paired_aged_from, paired_aged_from + window)
    paired_young = median_ms(young.update_ms, warmup, window)
    return {
        "simulated_hours": hours,
        "move_every_s": move_every_s,
        "moves": float(mover.moves),
        "observations": float(n_obs),
        "observations_per_s": n_obs / wall,
        "update_ms_p50": float(np.median(upd)),
        "update_ms_p99": float(np.percentile(upd, 99)),
        "update_ms_max": float(np.max(upd)),
        "estimate_ms_p50": float(np.median(aged.estimate_ms[warmup:n_ticks])),
        "estimate_ms_p99": float(np.percentile(aged.estimate_ms[warmup:n_ticks], 99)),
        "tick_ms_p50": float(np.median(tick)),
        "tick_ms_p99": float(np.percentile(tick, 99)),
        "warmup_update_ms_max": float(np.max(aged.update_ms[:warmup])) if warmup else 0.0,
        "last_over_first_hour_latency_ratio": paired_aged / paired_young,
        "last_over_first_hour_tick_ratio": median_tick_ms(aged, paired_aged_from, paired_aged_from + window)
        / median_tick_ms(young, warmup, window),
        "last_over_first_hour_latency_ratio_sequential": seq_last / seq_first,
        "solver_updates_first_hour": float(sum(aged.solved[warmup:window])),
        "solver_updates_last_hour": float(sum(aged.solved[n_ticks - window : n_ticks])),
        "reorders": float(
            reorders
        ),  # updates in which iSAM2 re-ordered the whole tree (reorder_fill, or >65 % touched)
        "rss_growth_mb": rss_end - rss0,
        "factors_max": float(factors_max),
        "factors_in_graph": float(aged.est.factor_count()),
        "camera_pos_mm_max_final": max(errors.values()),
        "arm": float(arm),
        "keyframes_entered": float(keyframes),
        "static_fit_ms": fit_ms,
        "arm_pos_mm_final": arm_mm,
    }


def add_args(parser) -> None:
    parser.add_argument("--hours", type=float, default=24.0, help="simulated span (default 24 h)")
    parser.add_argument(
        "--move-every",
        type=float,
        default=20.0,
        help="bump one camera, in turn, this often (simulated s; 0: a still cell)",
    )
    parser.add_argument("--cameras", type=int, default=8, help="cameras on the ring (default 8)")
    parser.add_argument("--markers", type=int, default=16, help="markers on the ring (default 16; 4 are anchors)")
    parser.add_argument(
        "--arm", action="store_true", help="cam0 on an arm that never stops (its frames join the graph)"
    )
    parser.add_argument(
        "--scan",
        action="store_true",
        help="a table over cameras 8..64 and markers up to 1,000 (--hours each, default 0.05)",
    )


if __name__ == "__main__":
    main("estimator_scale", __doc__.splitlines()[0], run, add_args)
