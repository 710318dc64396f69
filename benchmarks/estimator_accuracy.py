"""Estimator accuracy on the demo cell: online iSAM2 vs the batch optimum vs the paper's chain method.

Observations: ``cellsight.synthetic`` (true poses, noise drawn from the front-end's depth-refined
covariance model, 5 % planar-PnP flips), every camera at 30 Hz. The same observations feed:
- online: ``estimator.graph.Estimator`` updated at 10 Hz (the daemon's rate);
- batch: Levenberg-Marquardt over one robust factor per raw observation, same noise model;
- chain: the seed paper's method (``benchmarks.chain``) on the time-averaged pairs.
Figures: camera errors after 10 s (median over static cameras and seeds), the ratios, each of the
paper's four relation cases, and the time a bumped camera (2 deg + 30 mm) needs to get back
within 5 mm / 0.25 deg.
"""

from __future__ import annotations

import copy

import gtsam
import numpy as np

from benchmarks.chain import chain_solve
from benchmarks.common import main
from cellsight.synthetic import NoiseSettings, estimator_config, frame_observations
from drivers.sim.scenario import CameraMotion, Scenario, load_scenario
from estimator.graph import CameraState, Estimator, camera_symbol, marker_symbol
from schemas.geometry import cov_ros_to_gtsam, pose_error

RATE = 30.0
NOISE = NoiseSettings(depth=True, flip_rate=0.05)


def static_demo() -> Scenario:
    s = copy.deepcopy(load_scenario())
    for c in s.cameras:
        c.motion = []
    for o in s.objects:
        o.motion.kind = "static"
    return s


def simulate(s: Scenario, seconds: float, seed: int) -> list[list]:
    """Per frame index: the observations of every camera."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(int(seconds * RATE)):
        t = k / RATE
        stamp = int(round(t * 1e9))
        frames.append([(c.id, stamp, frame_observations(s, c.id, t, stamp, rng, NOISE)) for c in s.cameras])
    return frames


def online(s: Scenario, frames: list[list]) -> Estimator:
    est = Estimator(estimator_config(s))
    for k, frame in enumerate(frames):
        for cid, stamp, obs in frame:
            est.add_frame(cid, stamp, obs)
        if k % 3 == 0:
            est.update(stamp)
    est.update(stamp + 1)
    return est


def batch(s: Scenario, frames: list[list], est: Estimator) -> dict[str, np.ndarray]:
    """LM over every raw observation (robust, same covariances), from the online solution's values."""
    cfg = est.config
    graph = gtsam.NonlinearFactorGraph()
    for a in cfg.anchors:
        import math

        sig = [math.radians(a.sigma_rotation_deg)] * 3 + [a.sigma_position_m] * 3
        graph.add(gtsam.PriorFactorPose3(marker_symbol(a.marker_id), gtsam.Pose3(a.world_T_marker.matrix()), gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k)
    objects = set(cfg.object_markers)
    for frame in frames:
        for cid, _, obs in frame:
            ck = camera_symbol(est.camera_index[(cid, 0)])
            for o in obs:
                if o.marker_id in objects or not est.values.exists(marker_symbol(o.marker_id)):
                    continue
                noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(o.covariance)))
                graph.add(gtsam.BetweenFactorPose3(ck, marker_symbol(o.marker_id), gtsam.Pose3(o.camera_T_marker), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(200)
    result = gtsam.LevenbergMarquardtOptimizer(graph, est.values, params).optimize()
    return {cid: result.atPose3(camera_symbol(i)).matrix() for (cid, seg), i in est.camera_index.items() if seg == 0}


def accuracy(seeds: list[int], seconds: float) -> dict[str, float]:
    s = static_demo()
    cams = [c.id for c in s.cameras]
    rows = {"online": [], "batch": [], "chain": []}
    for seed in seeds:
        frames = simulate(s, seconds, seed)
        est = online(s, frames)
        e = est.estimate(frames[-1][0][1])
        b = batch(s, frames, est)
        pairs = {(cam, mk): p.mean() for ((cam, seg), mk), p in est.pairs.items() if p.n > 0 and mk not in est.object_markers}
        ch = chain_solve(est.anchors, pairs)
        for cid in cams:
            truth = s.camera(cid).world_T_camera(seconds)
            rows["online"].append(pose_error(e.cameras[cid].pose.T, truth))
            rows["batch"].append(pose_error(b[cid], truth))
            rows["chain"].append(pose_error(ch[cid], truth) if cid in ch else (np.inf, np.inf))
    med = {k: np.median(np.array(v), axis=0) for k, v in rows.items()}
    return {
        "camera_pos_mm_p50": float(med["online"][0]),
        "camera_rot_deg_p50": float(med["online"][1]),
        "batch_pos_mm_p50": float(med["batch"][0]),
        "batch_rot_deg_p50": float(med["batch"][1]),
        "chain_pos_mm_p50": float(med["chain"][0]),
        "chain_rot_deg_p50": float(med["chain"][1]),
        "online_over_batch_ratio": float(med["online"][0] / med["batch"][0]),
        "chain_over_online_ratio": float(med["chain"][0] / med["online"][0]),
        "camera_pos_mm_max": float(np.max(np.array(rows["online"])[:, 0])),
    }


def bump_recovery(seed: int) -> float:
    """Seconds from the bump until cam2 stays within 5 mm / 0.25 deg (inf if it never does)."""
    s = static_demo()
    bump_t = 4.0
    s.camera("cam2").motion = [CameraMotion(kind="bump", start_s=bump_t, rotation_deg=(2.0, 0.0, 0.0), offset=(0.03, 0.0, 0.0))]
    est = Estimator(estimator_config(s))
    rng = np.random.default_rng(seed)
    ok_since = None
    for k in range(int((bump_t + 4.0) * RATE)):
        t = k / RATE
        stamp = int(round(t * 1e9))
        for c in s.cameras:
            est.add_frame(c.id, stamp, frame_observations(s, c.id, t, stamp, rng, NOISE))
        if k % 3 == 0:
            est.update(stamp)
            if t > bump_t:
                cam = est.estimate(stamp, with_covariance=False).cameras["cam2"]
                good = cam.state is CameraState.LOCALIZED and cam.pose is not None
                if good:
                    dp, dr = pose_error(cam.pose.T, s.camera("cam2").world_T_camera(t))
                    good = dp < 5.0 and dr < 0.25
                ok_since = (ok_since or t) if good else None
    return float("inf") if ok_since is None else ok_since - bump_t


def run(quick: bool) -> dict[str, float]:
    seeds = [0, 1] if quick else [0, 1, 2, 3, 4]
    out = accuracy(seeds, 10.0)
    out["bump_recovery_s"] = float(np.median([bump_recovery(sd) for sd in seeds[:2]]))
    return out


if __name__ == "__main__":
    main("estimator_accuracy", __doc__.splitlines()[0], run)
