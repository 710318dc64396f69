"""Offline re-solve against the online estimate on the rendered demo cell at the sensors' own 30 Hz.

``cellsight demo`` renders in real time on this machine's two cores, so each camera gets ~5
frames/s and cam1's 2 s tilt leaves the offline solve 1-3 moving frames. Here every frame is
rendered (not in real time): the demo cell's 4 cameras at 30 Hz for 20 s (cam1 tilts at 8-10 s,
cam2 is bumped at 14 s), each through the marker front-end, into an MCAP log with ground truth.
The online estimate is the daemon's core (its online options off) fed the same frames in capture
order, updated and published at 10 Hz; ``cellsight resolve``'s pipeline then solves the log.
Figures: per camera, the median and RMS position / rotation error of both at the same instants
(``paired``), averaged over ``--seeds`` noise seeds (``--quick``: one seed, 12 s at 15 Hz), in how
many runs offline was not worse, by how much it was behind in its worst run and on average (with a
one-sided 95 % upper bound over the runs: a non-inferiority margin is met when the bound is under
it), and how far each side moves between seeds. For a camera with two segments the median over both
can favour the side whose errors are spread: offline has one value per segment.

Online options (``VARIANTS``: links, moving frames, both) are judged against that estimator on
the same frames, ``{camera}_online_{variant}_over_without``, on two update schedules: after every
camera's frame of an instant (as the log's estimator) and ``_staggered``, after the first
camera's. An online answer short of convergence depends on when iSAM2 updates, by as much as the
options move it (markers relinearised at 0.005 did that); the two schedules check that the
verdict does not.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import Row, main
from cellsight.config import CellConfig
from cellsight.evaluation.resolve_report import ResolveRun, peek_config, run_resolve
from cellsight.scenario_config import cell_config_of
from drivers.config import MarkerConfig
from drivers.frames import observations_to_msg
from drivers.markers import MarkerDetector
from drivers.sim.render import SimCell
from drivers.sim.scenario import load_scenario
from estimator.config import EstimatorConfig
from estimator.estimate import CameraEstimate, CameraState
from estimator.graph import Estimator
from estimator.observation import observation_rows, observations_of
from schemas import codec, keys
from schemas.geometry import pose_error
from schemas.log import LogWriter

CELL = "bench"
EPOCH_NS = 1_800_000_000_000_000_000
UPDATE_NS = 100_000_000  # the daemon's 10 Hz


#: Online estimators fed the same frames beside the daemon's default one: object-marker links
#: (``[estimator.links] online``), moving frames (``[estimator.keyframes] online``), both.
VARIANTS = {"links": ("links",), "keyframes": ("keyframes",), "links_keyframes": ("links", "keyframes")}
#: When the 10 Hz update runs against the frames of one instant: after every camera's (the log's
#: estimator) or after the first camera's, the others' waiting for the next update ("staggered",
#: as the daemon's updates triggered by arriving frames meet the cameras' frames). Each variant is
#: compared with a default estimator on its own schedule.
STAGGERED = "_staggered"


def write_log(
    path: Path, seed: int, seconds: float, rate_hz: float
) -> tuple[dict[str, dict[str, list[tuple[float, float]]]], dict[str, int]]:
    """Render, detect and estimate online, frame by frame in capture order, into one log. Beside
    it, an online estimator per ``VARIANTS`` is fed the same frames, and the default and every
    variant again on the staggered schedule (``STAGGERED``): per variant (and ``name + STAGGERED``)
    and camera, (default, variant) position errors (mm) at each update; and what entered the
    variants' graphs (object-marker instants and moving frames), so a ratio of 1 is not mistaken
    for no effect."""
    scenario = load_scenario().model_copy(update={"seed": seed})
    cfg = cell_config_of(scenario, base=CellConfig.model_validate({"cell": {"name": CELL}}))
    cell = SimCell(scenario)
    detector = MarkerDetector(
        MarkerConfig(
            dictionary=scenario.dictionary,
            side_m=scenario.marker_side_m,
            sides_m={mk.id: scenario.side_of(mk) for mk in scenario.markers},
        )
    )
    e = with_options(cfg.estimator, ())
    online = Estimator(e)
    variants = {name: Estimator(with_options(e, parts)) for name, parts in VARIANTS.items()}
    staggered = {name + STAGGERED: Estimator(v.config) for name, v in variants.items()}
    staggered_default = Estimator(e)
    paired: dict[str, dict[str, list[tuple[float, float]]]] = {name: {} for name in [*variants, *staggered]}
    truth_now: dict[str, np.ndarray] = {}
    w = LogWriter(path, metadata={"config": cfg.to_toml()})
    next_update, next_staggered = EPOCH_NS, EPOCH_NS
    for k in range(int(seconds * rate_hz)):
        t = k / rate_hz
        stamp = EPOCH_NS + round(t * 1e9)
        for i, cam in enumerate(scenario.cameras):
            f = cell.render(cam.id, t, k)
            msg = observations_to_msg(
                cam.id, stamp, f.info, detector.detect(f.rgb, f.info, f.depth_mm), scenario.dictionary
            )
            w.write(keys.markers(CELL, cam.id), msg, stamp)
            obs = observations_of(cam.id, stamp, observation_rows(codec.marker_arrays(msg)))
            for est in (online, *variants.values(), staggered_default, *staggered.values()):
                est.add_frame(cam.id, stamp, obs)
            truth_now[cam.id] = f.world_T_camera
            w.write(
                keys.truth(CELL, "cameras"),
                codec.poses_to_msg(stamp, [codec.StampedPose("world", cam.id, stamp, f.world_T_camera)]),
                stamp,
            )
            if i == 0 and stamp >= next_staggered:
                staggered_default.update(stamp)
                ours = staggered_default.estimate(stamp, with_covariance=False).cameras
                compare(ours, staggered, stamp, truth_now, paired)
                next_staggered += UPDATE_NS
        if k == 0:
            truth = [
                codec.StampedPose("world", keys.marker_frame(mk.id), stamp, scenario.world_T_marker(mk, 0.0))
                for mk in scenario.markers
                if mk.object is None
            ]
            w.write(keys.truth(CELL, "marker_poses"), codec.poses_to_msg(stamp, truth), stamp)
        if stamp >= next_update:
            online.update(stamp)
            est = online.estimate(stamp)
            cams = [
                codec.StampedPose("world", c.camera_id, stamp, c.pose.T, c.pose.covariance)
                for c in est.cameras.values()
                if c.pose is not None and c.state is CameraState.LOCALIZED
            ]
            w.write(keys.estimate_cameras(CELL), codec.poses_to_msg(stamp, cams), stamp)
            compare(est.cameras, variants, stamp, truth_now, paired)
            next_update += UPDATE_NS
    w.close()
    every = variants | staggered
    entered = {f"{name}_links_entered": v.counters.links for name, v in every.items()}
    entered |= {f"{name}_keyframes_entered": v.counters.keyframes for name, v in every.items()}
    return paired, entered


def with_options(e: EstimatorConfig, parts: tuple[str, ...]) -> EstimatorConfig:
    """``e`` with the online options named in ``parts`` on and the others off."""
    return e.model_copy(
        update={part: getattr(e, part).model_copy(update={"online": part in parts}) for part in ("links", "keyframes")}
    )


def compare(
    ours: dict[str, CameraEstimate],
    variants: dict[str, Estimator],
    stamp: int,
    truth: dict[str, np.ndarray],
    paired: dict[str, dict[str, list[tuple[float, float]]]],
) -> None:
    """Update each variant at ``stamp`` (ns) and add, per camera localized in both it and the default
    estimate ``ours``, (default, variant) position errors (mm) against ``truth`` (world_T_camera)."""
    for name, v in variants.items():
        v.update(stamp)
        theirs = v.estimate(stamp, with_covariance=False).cameras
        for cid, c in ours.items():
            other = theirs.get(cid)
            if (
                c.pose is not None
                and c.state is CameraState.LOCALIZED
                and other is not None
                and other.pose is not None
                and other.state is CameraState.LOCALIZED
            ):
                paired[name].setdefault(cid, []).append(
                    (pose_error(c.pose.T, truth[cid])[0], pose_error(other.pose.T, truth[cid])[0])
                )


def run(quick: bool, args: argparse.Namespace) -> dict[str, float]:
    seeds = args.seeds
    out: dict[str, float] = {}
    per_cam: dict[str, list[list[float]]] = {}
    moving: list[int] = []
    per_segment: dict[str, list[tuple[float, float]]] = {}
    markers: list[float] = []
    variants: dict[str, dict[str, list[tuple[float, float]]]] = {  # camera -> per run (default, variant) median mm
        name: {} for name in [*VARIANTS, *(n + STAGGERED for n in VARIANTS)]
    }
    for seed in range(1 if quick else seeds):
        with tempfile.TemporaryDirectory(prefix="offline-vs-online-") as d:
            log = Path(d) / "log.mcap"
            errors, entered = write_log(log, seed, 12.0 if quick else 20.0, 15.0 if quick else 30.0)
            for key, n in entered.items():
                out[f"online_{key}"] = out.get(f"online_{key}", 0.0) + n
            for name, cams in errors.items():
                for cam, rows in cams.items():
                    a = np.array(rows)
                    variants[name].setdefault(cam, []).append((float(np.median(a[:, 0])), float(np.median(a[:, 1]))))
            resolved = run_resolve(log, Path(d) / "res", peek_config(log))
        figures = resolved.figures
        for seg, (off, on) in segment_errors(resolved).items():
            per_segment.setdefault(seg, []).append((off, on))
        markers.append(figures.marker_position_error_mm_p50)
        for cam, c in figures.cameras.items():
            p = c.paired
            per_cam.setdefault(cam, []).append(
                [*p.offline_mm_deg_p50, *p.online_mm_deg_p50, *p.offline_mm_deg_rms, *p.online_mm_deg_rms]
            )
            moving.append(c.moving_frames)
    for cam, rows in sorted(per_cam.items()):
        a = np.array(rows)
        out[f"{cam}_offline_mm_p50"], out[f"{cam}_online_mm_p50"] = float(a[:, 0].mean()), float(a[:, 2].mean())
        out[f"{cam}_offline_deg_p50"], out[f"{cam}_online_deg_p50"] = float(a[:, 1].mean()), float(a[:, 3].mean())
        out[f"{cam}_offline_mm_rms"], out[f"{cam}_online_mm_rms"] = float(a[:, 4].mean()), float(a[:, 6].mean())
        out[f"{cam}_runs_offline_not_worse_mm_p50"] = float((a[:, 0] <= a[:, 2]).sum())
        out[f"{cam}_runs_offline_not_worse_mm_rms"] = float((a[:, 4] <= a[:, 6]).sum())
        diff = a[:, 4] - a[:, 6]  # offline minus online RMS, per run: negative is offline ahead
        out[f"{cam}_offline_minus_online_mm_rms_max"] = float(diff.max())  # the worst run
        out[f"{cam}_offline_minus_online_mm_rms_mean"] = float(diff.mean())
        if len(diff) >= 5:
            out[f"{cam}_offline_minus_online_mm_rms_ci95_hi"] = upper_bound_95(diff)
        for seed, d in enumerate(diff.tolist()):
            out[f"{cam}_offline_minus_online_mm_rms_seed{seed}"] = d
        # how much each side changes with the noise seed alone
        out[f"{cam}_offline_mm_rms_spread"], out[f"{cam}_online_mm_rms_spread"] = (
            float(np.ptp(a[:, 4])),
            float(np.ptp(a[:, 6])),
        )
    for seg, rows in sorted(per_segment.items()):
        a = np.array(rows)
        out[f"{seg}_offline_mm"], out[f"{seg}_online_mm_p50"] = float(a[:, 0].mean()), float(a[:, 1].mean())
    out["segments_offline_not_worse"] = float(sum(off <= on for rows in per_segment.values() for off, on in rows))
    out["segments"] = float(sum(len(rows) for rows in per_segment.values()))
    out["runs"] = float(len(markers))
    out["moving_frames_solved"] = float(sum(moving))
    out["markers_offline_mm_p50"] = float(np.mean(markers))
    for name, cams in variants.items():
        for cam, rows in sorted(cams.items()):
            a = np.array(rows)
            out[f"{cam}_online_{name}_mm_p50"] = float(a[:, 1].mean())
            out[f"{cam}_online_{name}_over_without"] = float(a[:, 1].mean() / a[:, 0].mean())
        out[f"online_{name}_over_without_max"] = max(out[f"{cam}_online_{name}_over_without"] for cam in cams)
    return out


def upper_bound_95(x: np.ndarray) -> float:
    """One-sided 95 % upper confidence bound on the mean of ``x`` (n >= 5): mean + t * s / sqrt(n).

    Paired over seeds, the runs' differences are independent draws of the sensor noise. The
    t quantile is the Cornish-Fisher expansion of the normal one, within 1 % of the table from
    4 degrees of freedom (too small below that, hence n >= 5); it keeps scipy out of the
    dependencies.
    """
    n = len(x)
    z, nu = 1.6448536, n - 1
    t = z + (z**3 + z) / (4 * nu) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * nu**2)
    return float(x.mean() + t * x.std(ddof=1) / np.sqrt(n))


def segment_errors(resolved: ResolveRun) -> dict[str, tuple[float, float]]:
    """Per solved segment ("cam1_s0"): the offline pose's position error (mm) and the median of the
    online estimate's over that segment's stamps, both against the truth at those stamps."""
    out = {}
    side = resolved.evidence
    for seg in resolved.result.segments:
        rows = []
        for p in side.online.poses.get(seg.camera_id, []):
            t = side.truth_cameras.near(seg.camera_id, p.stamp_ns)
            if seg.first_stamp_ns <= p.stamp_ns <= seg.last_stamp_ns and t is not None:
                rows.append((pose_error(seg.world_T_camera, t.T)[0], pose_error(p.T, t.T)[0]))
        if rows:
            a = np.array(rows)
            out[f"{seg.camera_id}_s{seg.segment}"] = (float(np.median(a[:, 0])), float(np.median(a[:, 1])))
    return out


#: The rows of ``docs/performance.md`` this benchmark's recorded runs give; an option that entered
#: nothing in the run (no instant linked, no moving frame) is not exercised, whatever its ratio reads.
ROWS = tuple(
    Row(
        f"online_{name}{sched}_over_without_max",
        f"{label}: online with it over without, on the same rendered frames of the demo cell (4 cameras x 30 Hz, "
        f"20 s, the real marker front-end), median position error, the worst camera; updates {when}; entered over "
        f"the runs: {{online_{name}{sched}_links_entered}} linking instants, {{online_{name}{sched}_keyframes_entered}} "
        "moving frames",
        "<= 1.0",
        lambda v: v <= 1.0,
        exercised=(f"online_{name}{sched}_links_entered", f"online_{name}{sched}_keyframes_entered"),
    )
    for sched, when in (("", "after every camera's frame of an instant"), (STAGGERED, "after the first camera's"))
    for name, label in (
        ("links", "object-marker links"),
        ("keyframes", "a moving camera's frames"),
        ("links_keyframes", "links and moving frames"),
    )
)


def _args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=3, help="noise seeds (logs) to average over")


if __name__ == "__main__":
    main("offline_vs_online", __doc__.splitlines()[0], run, _args)
