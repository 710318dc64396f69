"""SE(3) helpers against gtsam and closed forms, with explicit tolerances."""

from __future__ import annotations

import math

import gtsam
import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import geometry
from schemas.geometry import make_pose, rpy_matrix

quats = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1)


def random_pose(rng: np.random.Generator, angle_rad: float) -> np.ndarray:
    axis = rng.normal(size=3)
    return gtsam.Pose3(gtsam.Rot3.Expmap(axis / np.linalg.norm(axis) * angle_rad), rng.normal(size=3)).matrix()


@pytest.mark.parametrize("angle", [1e-9, 1e-5, 0.3, 3.0])
def test_rotation_angle_is_accurate_from_tiny_to_large(angle: float) -> None:
    R = gtsam.Rot3.Expmap(np.array([0.0, angle, 0.0])).matrix()
    assert geometry.rotation_angle(np.eye(3), R) == pytest.approx(angle, rel=1e-6)


def test_pose_difference_is_gtsams_local_rotation_and_body_translation() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = random_pose(rng, rng.uniform(0, 3))
        b = a @ make_pose(rpy_matrix(*rng.normal(scale=0.2, size=3)), rng.normal(scale=0.1, size=3))
        xi = geometry.pose_difference(a, b)
        rot = gtsam.Rot3.Logmap(gtsam.Rot3(a[:3, :3]).between(gtsam.Rot3(b[:3, :3])))
        np.testing.assert_allclose(xi[3:], rot, atol=1e-9)
        np.testing.assert_allclose(xi[:3], a[:3, :3].T @ (b[:3, 3] - a[:3, 3]), atol=1e-12)


def test_pose_retract_undoes_pose_difference_and_matches_gtsams_rotation_expmap() -> None:
    rng = np.random.default_rng(2)
    a = np.array([random_pose(rng, rng.uniform(0, 3)) for _ in range(20)])
    d = np.concatenate([rng.normal(scale=0.1, size=(20, 3)), rng.normal(scale=0.5, size=(20, 3))], axis=1)
    d[0, 3:] = 1e-12  # the small-angle series
    moved = geometry.pose_retract(a, d)
    np.testing.assert_allclose(geometry.pose_difference(a, moved), d, atol=1e-9)
    for T, x, m in zip(a, d, moved):
        np.testing.assert_allclose(m[:3, :3], T[:3, :3] @ gtsam.Rot3.Expmap(x[3:]).matrix(), atol=1e-12)


def test_cov_reorder_batches_and_is_its_own_inverse() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 6, 6))
    one = np.array([geometry.cov_ros_to_gtsam(c) for c in A])
    np.testing.assert_array_equal(geometry.cov_ros_to_gtsam(A), one)
    np.testing.assert_array_equal(one[2][:3, :3], A[2][3:, 3:])  # rotation block first in gtsam's order
    np.testing.assert_array_equal(geometry.cov_gtsam_to_ros(geometry.cov_ros_to_gtsam(A)), A)
    np.testing.assert_array_equal(geometry.cov_ros_to_gtsam(A[0].ravel()), one[0])


def test_mahalanobis_of_a_sigma_step_is_one_and_batches() -> None:
    cov = np.diag([4.0, 1.0, 9.0])
    d = np.array([[2.0, 0, 0], [0, 1.0, 0], [0, 0, 3.0]])
    np.testing.assert_allclose(geometry.mahalanobis_sq(d, np.broadcast_to(cov, (3, 3, 3))), [1.0, 1.0, 1.0])
    assert float(geometry.mahalanobis_sq(d[0], cov)) == pytest.approx(1.0)


def test_interpolated_pose_follows_gtsams_slerp() -> None:
    rng = np.random.default_rng(2)
    a, b = random_pose(rng, 0.4), random_pose(rng, 2.0)
    for f in (0.0, 0.25, 0.5, 1.0):
        T = geometry.interpolate_pose(a, b, f)
        R = gtsam.Rot3(a[:3, :3]).slerp(f, gtsam.Rot3(b[:3, :3])).matrix()
        assert geometry.rotation_angle(T[:3, :3], R) < 1e-9
        np.testing.assert_allclose(T[:3, 3], (1 - f) * a[:3, 3] + f * b[:3, 3], atol=1e-12)


def test_pose_error_and_position_sigma_in_their_units() -> None:
    T = make_pose(rpy_matrix(0.0, 0.0, math.radians(2.0)), [0.003, 0.004, 0.0])
    mm, deg = geometry.pose_error(T, np.eye(4))
    assert mm == pytest.approx(5.0) and deg == pytest.approx(2.0)
    cov = np.zeros((6, 6))
    cov[:3, :3] = np.diag([1e-6, 4e-6, 9e-6])
    assert geometry.position_sigma(cov) == pytest.approx(3e-3)
    assert geometry.angle_between(np.array([1.0, 0, 0]), np.array([0, 1.0, 0])) == pytest.approx(math.pi / 2)


@given(quats)
def test_quaternion_is_unit_with_nonnegative_w(q: np.ndarray) -> None:
    out = geometry.quat_from_matrix(geometry.matrix_from_quat(q))
    assert np.isclose(np.linalg.norm(out), 1.0) and out[3] >= 0
    # Same rotation up to sign.
    qn = q / np.linalg.norm(q)
    assert min(np.linalg.norm(out - qn), np.linalg.norm(out + qn)) < 1e-9


vec3 = hnp.arrays(np.float64, 3, elements=st.floats(-1, 1)).filter(lambda v: np.linalg.norm(v) > 1e-3)


@settings(max_examples=200, deadline=None)
@given(vec3, vec3)
def test_rotation_between_turns_a_onto_b_by_the_smallest_angle(a: np.ndarray, b: np.ndarray) -> None:
    R = geometry.rotation_between(a, b)
    ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
    # Turning onto the exact opposite is ill-conditioned: ~1e-8 is the best double precision allows.
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-7)
    assert np.linalg.det(R) > 0
    np.testing.assert_allclose(R @ ua, ub, atol=1e-7)
    # The smallest such rotation turns by the angle between them, no more.
    assert geometry.rotation_angle(np.eye(3), R) == pytest.approx(geometry.angle_between(ua, ub), abs=1e-6)


def test_rotation_between_batches_and_turns_opposites_about_the_given_axis() -> None:
    rng = np.random.default_rng(5)
    a = rng.normal(size=(20, 3))
    a[7] = (0.0, 0.0, -2.0)  # exactly opposite to b
    axes = np.tile([0.0, 1.0, 0.0], (20, 1))
    R = geometry.rotation_between(a, np.array([0.0, 0.0, 1.0]), half_turn_axis=axes)
    assert R.shape == (20, 3, 3)
    for k in range(20):
        np.testing.assert_allclose(
            R[k], geometry.rotation_between(a[k], [0.0, 0.0, 1.0], half_turn_axis=axes[k]), atol=1e-12
        )
    np.testing.assert_allclose(R[7], np.diag([-1.0, 1.0, -1.0]), atol=1e-12)  # half turn about y


def test_rotation_angles_match_the_single_rotation_angle_over_a_stack() -> None:
    rng = np.random.default_rng(4)
    R = np.stack([geometry.matrix_from_quat(q / np.linalg.norm(q)) for q in rng.normal(size=(20, 4))])
    angles = geometry.rotation_angles(R, R[0])
    for Ri, a in zip(R, angles):
        assert abs(a - geometry.rotation_angle(Ri, R[0])) < 1e-9
    assert angles[0] < 1e-6 and geometry.rotation_angles(R, R).max() < 1e-6


def test_invert_poses_inverts_every_pose_of_a_stack() -> None:
    """A (2, 3) stack of random rigid poses: each times its inverse is the identity, and each inverse
    is what ``invert_pose`` gives alone."""
    rng = np.random.default_rng(3)
    T = np.stack(
        [
            [make_pose(rpy_matrix(*rng.uniform(-np.pi, np.pi, 3)), rng.normal(size=3)) for _ in range(3)]
            for _ in range(2)
        ]
    )
    Ti = geometry.invert_poses(T)
    assert Ti.shape == T.shape
    np.testing.assert_allclose(T @ Ti, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)
    np.testing.assert_allclose(Ti[1, 2], geometry.invert_pose(T[1, 2]), atol=1e-15)


def test_rotations_within_agrees_with_the_angle_over_a_stack() -> None:
    """Random rotations against one: within a threshold exactly where ``rotation_angles`` says so
    (away from the threshold itself, where the two differ only by rounding)."""
    rng = np.random.default_rng(5)
    R = np.stack([rpy_matrix(*rng.normal(scale=0.1, size=3)) for _ in range(200)])
    angles = geometry.rotation_angles(R, R[0])
    limit = np.radians(5.0)
    clear = np.abs(angles - limit) > 1e-9
    assert 20 < clear.sum() and 0 < (angles < limit).sum() < len(R)
    np.testing.assert_array_equal(geometry.rotations_within(R, R[0], limit)[clear], (angles < limit)[clear])
