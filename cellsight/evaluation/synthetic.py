"""Synthetic marker observations with known answers, for estimator tests and benchmarks (no renderer).

Poses come from a scenario's ground truth; noise is drawn from the marker front-end's own
covariance model (depth-refined or PnP-only), so accuracy claims are about the estimator, not the
renderer. Visibility: in the field of view, facing the camera, in range (no occlusion test).
Flips: with probability ``flip_rate`` the chosen pose is the mirrored IPPE solution (the tilt
reflected about the line of sight), reported with its own covariance as the front-end does, and
the true one is offered as the alternative.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from drivers.markers import PlaneFit, covariance_model
from drivers.sim.scenario import Scenario, load_scenario
from estimator.config import EstimatorConfig
from estimator.observation import Observation
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose, pose_retract, rotation_angle


@dataclass(frozen=True)
class NoiseSettings:
    depth: bool = True  # depth-refined covariance (else PnP-only)
    flip_rate: float = 0.0
    pixel_sigma: float = 0.5
    max_range_m: float = 4.5


def visible(cam_T_marker: np.ndarray, info: CameraInfo, side: float, max_range: float) -> bool:
    p = cam_T_marker[:3, 3]
    if not 0.4 < p[2] < max_range:
        return False
    u = info.K[0, 0] * p[0] / p[2] + info.K[0, 2]
    v = info.K[1, 1] * p[1] / p[2] + info.K[1, 2]
    margin = 20
    if not (margin < u < info.width - margin and margin < v < info.height - margin):
        return False
    facing = -cam_T_marker[:3, 2] @ (p / np.linalg.norm(p))
    return facing > 0.25 and info.K[0, 0] * side / p[2] > 18  # at least 18 px across


def flip(cam_T_marker: np.ndarray) -> np.ndarray:
    """The mirrored planar-PnP solution: marker normal reflected about the line of sight."""
    p = cam_T_marker[:3, 3]
    ray = p / np.linalg.norm(p)
    n = cam_T_marker[:3, 2]
    axis = np.cross(n, -ray)
    s = np.linalg.norm(axis)
    if s < 1e-6:
        return cam_T_marker.copy()
    angle = np.arcsin(min(s, 1.0))
    R = gtsam.Rot3.AxisAngle(axis / s, float(-2 * angle)).matrix()
    T = cam_T_marker.copy()
    T[:3, :3] = R @ cam_T_marker[:3, :3]
    return T


def perturb(T: np.ndarray, cov_ros: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poses ``T`` (..., 4, 4) moved by draws of ``cov_ros`` (..., 6, 6, ROS order, in T's own frame).

    Drawn as L z with L the Cholesky factor and z standard normal: unlike ``multivariate_normal``
    (an SVD, whose basis for equal variances depends on the CPU's BLAS kernels), one seed gives the
    same noise on every machine. A variance of zero (a rotation-only bias) gets a 3e-8 sigma.
    """
    cov = np.asarray(cov_ros, dtype=np.float64)
    L = np.linalg.cholesky(cov + 1e-15 * np.eye(6))
    T = np.asarray(T, dtype=np.float64)
    z = rng.standard_normal(np.broadcast_shapes(T.shape[:-2], cov.shape[:-2]) + (6, 1))
    return pose_retract(T, (L @ z)[..., 0])


def frame_observations(
    scenario: Scenario,
    camera_id: str,
    t_s: float,
    stamp_ns: int,
    rng: np.random.Generator,
    noise: NoiseSettings,
    world_T_camera: np.ndarray | None = None,
) -> list[Observation]:
    """Noisy observations of every visible marker by one camera at scenario time ``t_s``."""
    cam = scenario.camera(camera_id)
    info = cam.camera_info()
    wTc = cam.world_T_camera(t_s) if world_T_camera is None else world_T_camera
    cTw = invert_pose(wTc)
    out = []
    for mk in scenario.markers:
        side = scenario.side_of(mk)
        T = cTw @ scenario.world_T_marker(mk, t_s)
        if not visible(T, info, side, noise.max_range_m):
            continue
        z = float(np.linalg.norm(T[:3, 3]))
        n_px = (info.K[0, 0] * side / z) ** 2 * 0.6
        plane = PlaneFit(T[:3, 2], 0.0, int(n_px), 0.0, side * 0.8) if noise.depth else None
        cov = covariance_model(T, side, info, noise.pixel_sigma, plane)
        meas = perturb(T, cov, rng)
        alt = flip(meas)
        if rng.random() < noise.flip_rate:
            meas, alt = alt, meas
            # as the front-end gives it: the covariance of the pose it reports, in that pose's frame
            cov = covariance_model(meas, side, info, noise.pixel_sigma, plane)
        out.append(Observation(camera_id, stamp_ns, mk.id, meas, cov, alt, False))
    return out


class ViewBiases:
    """A bias per view, as the estimator's factor model allows for: each (camera, marker) view's
    observations are moved by one draw of the fused covariance (mean single-frame covariance /
    ``max_fused``, plus ``floor_rad`` on each rotation axis), drawn again once the true
    camera_T_marker moved ``new_view_m`` or turned ``new_view_deg`` since (a camera or an object
    that moved: one view, one bias). Without it the synthetic frames carry noise alone, and the
    static pairs, which average it away, fit far better than their covariances claim."""

    def __init__(self, max_fused: int, floor_rad: float, new_view_m: float = 0.005, new_view_deg: float = 0.2) -> None:
        self.max_fused, self.floor_rad = max_fused, floor_rad
        self.new_view_m, self.new_view_rad = new_view_m, np.radians(new_view_deg)
        self._drawn: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}  # -> (true view it was drawn at, bias)

    def apply(self, o: Observation, view: np.ndarray, rng: np.random.Generator) -> Observation:
        """``o`` with its view's bias, ``view`` the true camera_T_marker (4, 4)."""
        drawn = self._drawn.get((o.camera_id, o.marker_id))
        if (
            drawn is None
            or np.linalg.norm(drawn[0][:3, 3] - view[:3, 3]) > self.new_view_m
            or rotation_angle(drawn[0][:3, :3], view[:3, :3]) > self.new_view_rad
        ):
            cov = o.covariance / self.max_fused
            cov[3:, 3:] += np.eye(3) * self.floor_rad**2
            drawn = self._drawn[(o.camera_id, o.marker_id)] = (view, perturb(np.eye(4), cov, rng))
        B = drawn[1]
        alt = None if o.alternative is None else o.alternative @ B
        return Observation(o.camera_id, o.stamp_ns, o.marker_id, o.camera_T_marker @ B, o.covariance, alt, o.ambiguous)


def estimator_config(scenario: Scenario, **overrides) -> EstimatorConfig:
    """Anchors and object markers of a scenario as the estimator's configuration."""
    from cellsight.scenario_config import estimator_config_of

    return estimator_config_of(scenario, **overrides)


def demo() -> Scenario:
    return load_scenario()


def observations_msg(camera_id: str, stamp_ns: int, obs: list[Observation], side_m: float = 0.25):
    """Synthetic observations as the wire message a driver would publish (depth-refined)."""
    from schemas import codec
    from schemas import messages as m

    msg = m.MarkerObservations(camera_id=camera_id, stamp_ns=stamp_ns, image_width=640, image_height=480)
    items = []
    for o in obs:
        item = msg.markers.add(
            marker_id=o.marker_id, dictionary="DICT_APRILTAG_36h11", side_m=side_m, depth_refined=True
        )
        item.corners_px.extend([0.0] * 8)
        item.covariance.extend(codec.covariance_to_list(o.covariance))
        items.append(item)
    if obs:
        codec.poses_to_msgs(np.stack([o.camera_T_marker for o in obs]), [i.camera_T_marker for i in items])
        codec.poses_to_msgs(np.stack([o.alternative for o in obs]), [i.candidate_b for i in items])
    return msg
