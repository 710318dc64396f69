"""Camera resection (``estimator/resect.py``) on small synthetic scenes with known answers, checked
against gtsam's batch solve of the same star (camera, markers with priors, between factors)."""

from __future__ import annotations

import gtsam
import numpy as np

from cellsight.evaluation.synthetic import perturb
from estimator.resect import resect
from schemas.geometry import cov_gtsam_to_ros, cov_ros_to_gtsam, invert_pose, look_at_matrix, make_pose, rpy_matrix
from tests.helpers import assert_pose_close

# A marker: 1 mm / 0.1 deg map sigma; an observation: 2 mm / 0.3 deg (ROS order, marker frame).
MAP_COV = np.diag([1e-3**2] * 3 + [np.radians(0.1) ** 2] * 3)
OBS_COV = np.diag([2e-3**2] * 3 + [np.radians(0.3) ** 2] * 3)


def scene(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """world_T_camera (4, 4) 2 m from n markers (n, 4, 4) spread over a 1.5 m wall, facing it."""
    world_T_camera = make_pose(look_at_matrix(np.array([0.2, -2.0, 1.1]), np.array([0.0, 0.0, 1.0])), [0.2, -2.0, 1.1])
    markers = np.stack(
        [
            make_pose(rpy_matrix(np.pi / 2 + rng.normal() * 0.1, rng.normal() * 0.1, rng.normal() * 0.1), [x, 0.0, z])
            for x, z in rng.uniform([-0.75, 0.3], [0.75, 1.7], size=(n, 2))
        ]
    )
    return world_T_camera, markers


def test_exact_observations_give_the_camera_exactly() -> None:
    rng = np.random.default_rng(0)
    world_T_camera, markers = scene(6, rng)
    Z = np.stack([invert_pose(world_T_camera) @ M for M in markers])
    T, cov = resect(markers, np.stack([MAP_COV] * 6), Z, np.stack([OBS_COV] * 6))
    assert_pose_close(T, world_T_camera, 1e-9, 1e-7, "resected camera")
    assert np.all(np.linalg.eigvalsh(cov) > 0)


def test_resection_agrees_with_the_batch_solve_and_its_covariance_bounds_it() -> None:
    """The star's batch MAP (camera free, markers with priors at their mapped poses) is the same
    camera pose to first order: within 2 % of its sigma. Our covariance counts the map's error as
    shared by all markers, so it must contain the batch's (which counts it as independent)."""
    rng = np.random.default_rng(1)
    world_T_camera, markers = scene(8, rng)
    mapped = np.stack([perturb(M, MAP_COV, rng) for M in markers])
    Z = np.stack([perturb(invert_pose(world_T_camera) @ M, OBS_COV, rng) for M in markers])
    # Without the Huber weights (k huge): they act on a marker's whole residual here, on the
    # observation's alone in a graph, so only the Gaussian cores compare exactly.
    T, cov = resect(mapped, np.stack([MAP_COV] * 8), Z, np.stack([OBS_COV] * 8), huber_k=1e9)

    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    c = gtsam.symbol("c", 0)
    observation_noise = gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(OBS_COV))
    for i, (M, z) in enumerate(zip(mapped, Z)):
        m = gtsam.symbol("m", i)
        graph.add(
            gtsam.PriorFactorPose3(m, gtsam.Pose3(M), gtsam.noiseModel.Gaussian.Covariance(cov_ros_to_gtsam(MAP_COV)))
        )
        graph.add(gtsam.BetweenFactorPose3(c, m, gtsam.Pose3(z), observation_noise))
        values.insert(m, gtsam.Pose3(M))
    values.insert(c, gtsam.Pose3(mapped[0] @ invert_pose(Z[0])))
    batch = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    batch_cov = cov_gtsam_to_ros(gtsam.Marginals(graph, batch).marginalCovariance(c))
    xi = gtsam.Pose3.Logmap(batch.atPose3(c).between(gtsam.Pose3(T)))
    sigma = np.sqrt(np.diag(cov_ros_to_gtsam(batch_cov)))
    assert np.all(np.abs(xi) <= 0.02 * sigma), f"resection off the batch solve by {xi / sigma} sigma"
    assert np.linalg.eigvalsh(cov - batch_cov).min() > -1e-15, "the reported covariance is smaller than the batch's"


def test_one_moved_marker_barely_moves_the_camera() -> None:
    """A marker 10 cm from its mapped pose (knocked off the wall) among 8: the Huber weights cap
    its pull at ~k sigma over the rest, a fraction of a millimetre; a plain mean would move ~12 mm."""
    rng = np.random.default_rng(2)
    world_T_camera, markers = scene(8, rng)
    Z = np.stack([invert_pose(world_T_camera) @ M for M in markers])
    mapped = markers.copy()
    mapped[3] = make_pose(markers[3][:3, :3], markers[3][:3, 3] + [0.1, 0.0, 0.0])
    T, _ = resect(mapped, np.stack([MAP_COV] * 8), Z, np.stack([OBS_COV] * 8))
    assert_pose_close(T, world_T_camera, 1e-3, 0.05, "camera with one moved marker")
