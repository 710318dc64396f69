"""Round trips of every message type through ``schemas.codec``, and rejection of bad payloads."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from estimator.observation import observation_rows
from schemas import codec, geometry, keys
from schemas import messages as m
from schemas.errors import DecodeError, KeyError_
from tests.helpers import assert_pose_close

finite = st.floats(-100, 100, allow_nan=False, allow_infinity=False)
quats = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1)


def random_pose(q: np.ndarray, t: list[float]) -> np.ndarray:
    return geometry.make_pose(geometry.matrix_from_quat(q), t)


def random_covariance(seed: int) -> np.ndarray:
    A = np.random.default_rng(seed).normal(size=(6, 6))
    return A @ A.T + 1e-6 * np.eye(6)


@given(quats, st.lists(finite, min_size=3, max_size=3))
def test_pose_round_trip(q: np.ndarray, t: list[float]) -> None:
    T = random_pose(q, t)
    back = codec.pose_from_msg(m.Pose.FromString(codec.pose_to_msg(T).SerializeToString()))
    assert_pose_close(back, T, 1e-9, 1e-6)


@given(st.integers(0, 2**31))
def test_covariance_reorder_is_a_permutation(seed: int) -> None:
    cov = random_covariance(seed)
    g = geometry.cov_ros_to_gtsam(cov)
    # Translation block (ROS 0..2) becomes gtsam 3..5; rotation block (ROS 3..5) becomes gtsam 0..2.
    np.testing.assert_array_equal(g[3:, 3:], cov[:3, :3])
    np.testing.assert_array_equal(g[:3, :3], cov[3:, 3:])
    np.testing.assert_array_equal(g[:3, 3:], cov[3:, :3])
    np.testing.assert_array_equal(geometry.cov_gtsam_to_ros(g), cov)


@settings(max_examples=30)
@given(
    hnp.arrays(np.uint8, st.tuples(st.integers(1, 20), st.integers(1, 20), st.just(3))),
    st.integers(0, 2**62),
)
def test_color_image_round_trip(img: np.ndarray, stamp: int) -> None:
    msg = codec.decode(codec.image_to_msg(img, stamp, "cam1", "rgb8").SerializeToString(), m.RawImage)
    np.testing.assert_array_equal(codec.image_from_msg(msg), img)
    assert codec.timestamp_to_stamp(msg.timestamp) == stamp


@settings(max_examples=30)
@given(hnp.arrays(np.uint16, st.tuples(st.integers(1, 20), st.integers(1, 20))))
def test_depth_image_round_trip(depth: np.ndarray) -> None:
    msg = codec.decode(codec.image_to_msg(depth, 1, "cam1", "16UC1").SerializeToString(), m.RawImage)
    np.testing.assert_array_equal(codec.image_from_msg(msg), depth)


@settings(max_examples=30)
@given(
    st.integers(0, 50).flatmap(
        lambda n: st.tuples(
            hnp.arrays(np.float32, (n, 3), elements=st.floats(-10, 10, width=32)), hnp.arrays(np.uint8, (n, 4))
        )
    )
)
def test_point_cloud_round_trip_in_foxglove_layout(cloud) -> None:
    xyz, rgba = cloud
    msg = codec.decode(codec.points_to_msg(5, "world", xyz, rgba).SerializeToString(), m.PointCloud)
    got_xyz, got_rgba = codec.points_from_msg(msg)
    np.testing.assert_array_equal(got_xyz, xyz)
    np.testing.assert_array_equal(got_rgba, rgba)
    # Foxglove reads colour from fields named red/green/blue/alpha.
    assert [f.name for f in msg.fields] == ["x", "y", "z", "red", "green", "blue", "alpha"] and msg.point_stride == 16


def test_point_cloud_in_another_layout_is_rejected() -> None:
    msg = codec.points_to_msg(5, "world", np.zeros((2, 3)), np.zeros((2, 4), np.uint8))
    msg.point_stride = 12
    with pytest.raises(DecodeError, match="stride 12"):
        codec.points_from_msg(msg)
    with pytest.raises(ValueError, match="colours"):
        codec.points_to_msg(5, "world", np.zeros((2, 3)), np.zeros((3, 4), np.uint8))


def test_camera_info_round_trip_and_kinect_defaults() -> None:
    info = codec.CameraInfo.kinect_v1()
    assert (info.K[0, 0], info.K[1, 1], info.K[0, 2], info.K[1, 2]) == (525.0, 525.0, 319.5, 239.5)
    back = codec.CameraInfo.from_msg(codec.decode(info.to_msg(7, "cam1").SerializeToString(), m.CameraCalibration))
    np.testing.assert_array_equal(back.K, info.K)
    assert (back.width, back.height) == (640, 480)


@given(st.lists(st.tuples(quats, st.lists(finite, min_size=3, max_size=3)), min_size=1, max_size=5))
def test_transforms_and_pose_lists_round_trip(items) -> None:
    poses = [random_pose(q, t) for q, t in items]
    tf = codec.decode(
        codec.transforms_to_msg(5, [("world", f"c{i}", T) for i, T in enumerate(poses)]).SerializeToString(),
        m.FrameTransforms,
    )
    got = codec.transforms_from_msg(tf)
    plist = codec.poses_to_msg(
        5, [codec.StampedPose("world", f"c{i}", 5, T, random_covariance(i)) for i, T in enumerate(poses)]
    )
    back = codec.poses_from_msg(codec.decode(plist.SerializeToString(), m.PosesWithCovariance))
    for i, T in enumerate(poses):
        assert_pose_close(got[("world", f"c{i}")], T, 1e-9, 1e-6)
        assert_pose_close(back[f"c{i}"].T, T, 1e-9, 1e-6)
        np.testing.assert_allclose(back[f"c{i}"].covariance, random_covariance(i))


def test_a_bad_transform_among_good_ones_is_named() -> None:
    tf = codec.transforms_to_msg(5, [("world", f"c{i}", geometry.make_pose(t=[i, 0, 1])) for i in range(4)])
    tf.transforms[2].rotation.w = 3.0
    tf.transforms[3].translation.y = float("nan")
    with pytest.raises(DecodeError, match="transform c2: quaternion norm 3"):
        codec.transforms_from_msg(tf)
    tf.transforms[2].rotation.w = 1.0
    with pytest.raises(DecodeError, match="transform c3: contains NaN"):
        codec.transforms_from_msg(tf)
    assert codec.transforms_from_msg(m.FrameTransforms()) == {}


def test_a_bad_covariance_among_good_poses_is_named() -> None:
    msg = codec.poses_to_msg(
        5,
        [
            codec.StampedPose("world", f"c{i}", 5, geometry.make_pose(t=[i, 0, 1]), random_covariance(i))
            for i in range(4)
        ],
    )
    msg.poses.add(parent_frame_id="world", child_frame_id="no_cov", stamp_ns=5).pose.qw = 1.0
    assert codec.poses_from_msg(msg)["no_cov"].covariance is None
    for k, value, why in (
        (1, -1.0, "not positive definite"),
        (2, 7.0, "not symmetric"),
        (3, float("inf"), "contains NaN or inf"),
    ):
        bad = m.PosesWithCovariance()
        bad.CopyFrom(msg)
        bad.poses[k].covariance[1 if why == "not symmetric" else 0] = value
        with pytest.raises(DecodeError, match=f"pose of 'c{k}': {why}"):
            codec.poses_from_msg(bad)
    del msg.poses[2].covariance[30:]
    with pytest.raises(DecodeError, match="pose of 'c2': expected 36 values, got 30"):
        codec.poses_from_msg(msg)


def good_marker_observations() -> m.MarkerObservations:
    msg = m.MarkerObservations(camera_id="cam1", stamp_ns=1, image_width=640, image_height=480)
    obs = msg.markers.add(marker_id=3, dictionary="DICT_APRILTAG_36h11", side_m=0.1)
    obs.corners_px.extend([0.0] * 8)
    codec.pose_to_msg(geometry.make_pose(t=[0, 0, 1]), obs.camera_T_marker)
    obs.covariance.extend(codec.covariance_to_list(np.eye(6) * 1e-4))
    return msg


@pytest.mark.parametrize(
    "mutate, why",
    [
        (lambda o: o.covariance.__delitem__(slice(0, 6)), "36 values"),
        (lambda o: setattr(o, "side_m", -0.1), "side length"),
        (lambda o: setattr(o.camera_T_marker, "qw", float("nan")), "NaN"),
        (lambda o: setattr(o.camera_T_marker, "qw", 3.0), "quaternion norm"),
        (lambda o: o.corners_px.append(1.0), "corner values"),
    ],
)
def test_bad_marker_observations_are_rejected_with_a_reason(mutate, why: str) -> None:
    msg = good_marker_observations()
    codec.decode(msg.SerializeToString(), m.MarkerObservations)  # the unmutated one is fine
    mutate(msg.markers[0])
    with pytest.raises(DecodeError, match=why):
        codec.decode(msg.SerializeToString(), m.MarkerObservations)


@pytest.mark.parametrize("refined_from", ["a", "b"])
def test_the_alternative_is_the_other_ippe_branch_at_the_chosen_position(refined_from: str) -> None:
    """Depth refinement turns either IPPE candidate and replaces planar PnP's range. The estimator's
    alternative must be the other branch, at the refined position: a corrected flip must not bring
    back PnP's range error (tens of mm at 3 m; it once shifted a pair's mean by 70 mm)."""
    Ra, Rb = geometry.matrix_from_quat([0.0, 0.0, 0.0, 1.0]), geometry.matrix_from_quat([0.17, 0.0, 0.0, 0.985])
    tilt = geometry.matrix_from_quat([0.0, 0.02, 0.0, 0.9998])  # the plane's correction of the chosen rotation
    cand = {"a": geometry.make_pose(Ra, [0.1, 0.0, 3.04]), "b": geometry.make_pose(Rb, [0.1, 0.0, 3.06])}
    chosen = geometry.make_pose(tilt @ cand[refined_from][:3, :3], [0.1, 0.0, 3.0])
    msg = good_marker_observations()
    o = msg.markers[0]
    codec.pose_to_msg(cand["a"], o.candidate_a)
    codec.pose_to_msg(cand["b"], o.candidate_b)
    codec.pose_to_msg(chosen, o.camera_T_marker)
    a = observation_rows(codec.marker_arrays(codec.decode(msg.SerializeToString(), m.MarkerObservations)))
    other = cand["b" if refined_from == "a" else "a"]
    np.testing.assert_allclose(a.poses[0], chosen, atol=1e-9)
    np.testing.assert_allclose(a.alternatives[0][:3, :3], other[:3, :3], atol=1e-9)
    np.testing.assert_allclose(a.alternatives[0][:3, 3], chosen[:3, 3], atol=1e-12)


def test_image_with_wrong_size_is_rejected() -> None:
    msg = codec.image_to_msg(np.zeros((4, 4, 3), np.uint8), 1, "c", "rgb8")
    msg.data = msg.data[:-1]
    with pytest.raises(DecodeError, match="do not match"):
        codec.decode(msg.SerializeToString(), m.RawImage)


def test_keys_build_parse_and_reject() -> None:
    assert keys.markers("demo", "cam1") == "cellsight/demo/cam1/markers"
    assert keys.parse(keys.depth("demo", "cam1")).message_type is m.RawImage
    assert keys.parse(keys.estimate_status("demo")).camera is None
    assert keys.message_type(keys.truth("demo", "cameras")) is m.PosesWithCovariance
    for bad in ("cam/1", "*", "", "tf"):
        with pytest.raises(KeyError_):
            keys.markers("demo", bad)
    with pytest.raises(KeyError_):
        keys.parse("cellsight/demo/cam1/nonsense")


def test_only_the_public_estimate_topics_fall_under_a_per_camera_wildcard() -> None:
    """A subscriber to every camera's topic (the estimator's ``<cell>/*/markers``) matches any
    cell-wide key of the same shape, and zenoh then reports that key as wanted: drivers computed
    the simulator's truth for an estimator that drops it. ``estimate/markers`` and
    ``estimate/status`` are the wire contract robots read, so they stay (subscribers skip them by
    type); no other cell-wide topic may be matched."""
    import zenoh

    matched = {
        topic
        for topic in keys.CELL_TOPICS
        for cam_topic in keys.CAMERA_TOPICS
        if zenoh.KeyExpr(keys.all_cameras("demo", cam_topic)).intersects(zenoh.KeyExpr(f"cellsight/demo/{topic}"))
    }
    assert matched == {"estimate/markers", "estimate/status"}


def test_covariances_read_from_the_packed_bytes_equal_the_values_one_by_one() -> None:
    """Marker covariances are taken from the serialised message where the layout allows (much
    faster); a covariance whose bytes contain the field's own header, or a marker with another
    count, takes the value-by-value path. Both must give the same numbers."""
    msgs = []
    rng = np.random.default_rng(3)
    for _k in range(5):
        msg = good_marker_observations()
        for _ in range(3):
            o = msg.markers.add()
            o.CopyFrom(msg.markers[0])
            o.marker_id = int(rng.integers(1, 500))
            A = rng.normal(size=(6, 6))
            del o.covariance[:]
            o.covariance.extend(codec.covariance_to_list(A @ A.T + np.eye(6)))
        msgs.append(msg)
    # A value whose bytes hold the header 0x52 0xa0 0x02 (a false hit): the careful path then.
    tricky = np.frombuffer(bytes([0x52, 0xA0, 0x02, 0, 0, 0, 0xF0, 0x3F]), "<f8")[0]
    msgs[2].markers[1].covariance[7] = tricky
    msgs[2].markers[1].covariance[42 % 36] = tricky
    for batch in (msgs[:2], msgs):
        f = codec.marker_fields(batch)
        expected = np.array([list(o.covariance) for msg in batch for o in msg.markers])
        np.testing.assert_array_equal(f.covariances, expected)
