"""``cellsight export ros2``: a log written as a ROS 2 bag, read back with ``rosbags`` (its own
reader and CDR decoder): the same messages per topic, and tf / poses that round-trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from cellsight.export_ros2 import MARKER_POSES, OBJECTS, POINTS, TF, export_bag
from estimator.offline.outputs import RESOLVE_SOURCE
from recognition.fusion import FusedObject
from recognition.worker import detections_to_msg
from schemas import codec, keys
from schemas.codec import CameraInfo, StampedPose
from schemas.errors import SchemaError
from schemas.geometry import make_pose, rpy_matrix
from schemas.log import LogWriter, read_log
from schemas.ros2 import ros2_types, stamp_ns
from tests.helpers import ros_matrix

CELL = "ex"
T0 = 1_700_000_000_000_000_000


def pose(k: int) -> np.ndarray:
    return make_pose(rpy_matrix(0.1 * k, -0.2, 0.3 + 0.01 * k), [0.5 + k, -0.25, 1.125])


def write_log(path: Path, frames: int) -> None:
    w = LogWriter(path)
    info = CameraInfo.kinect_v1(64, 48)
    rng = np.random.default_rng(0)
    for k in range(frames):
        stamp = T0 + k * 33_333_333
        w.write(
            keys.tf(CELL),
            codec.transforms_to_msg(stamp, [("world", "cam1", pose(k)), ("world", "marker_3", pose(k + 1))]),
            stamp,
        )
        cov = np.diag(np.arange(1, 7) * 1e-6)
        w.write(
            keys.estimate_cameras(CELL),
            codec.poses_to_msg(stamp, [StampedPose("world", "cam1", stamp, pose(k), cov)]),
            stamp,
        )
        w.write(
            keys.estimate_markers(CELL),
            codec.poses_to_msg(stamp, [StampedPose("world", "marker_3", stamp, pose(k + 1))]),
            stamp,
        )
        w.write(
            keys.color(CELL, "cam1"),
            codec.image_to_msg(rng.integers(0, 255, (48, 64, 3), np.uint8), stamp, "cam1", "rgb8"),
            stamp,
        )
        w.write(
            keys.depth(CELL, "cam1"),
            codec.image_to_msg(rng.integers(0, 4000, (48, 64), np.uint16), stamp, "cam1", "16UC1"),
            stamp,
        )
        w.write(keys.camera_info(CELL, "cam1"), info.to_msg(stamp, "cam1"), stamp)
        w.write(
            keys.truth(CELL, "cameras"),
            codec.poses_to_msg(stamp, [StampedPose("world", "cam1", stamp, pose(k))]),
            stamp,
        )
        w.write(
            keys.objects(CELL),
            detections_to_msg(stamp, [FusedObject("box", stamp - 10, pose(k + 2), ["cam1"], 0.75, 0.002)]),
            stamp,
        )
        xyz = rng.normal(size=(7, 3)).astype(np.float32)
        rgba = rng.integers(0, 255, (7, 4), np.uint8)
        w.write(keys.points(CELL), codec.points_to_msg(stamp, "world", xyz, rgba), stamp)
    w.close()


def test_the_bag_holds_every_message_and_tf_round_trips(tmp_path: Path) -> None:
    write_log(tmp_path / "log.mcap", 5)
    result = export_bag(tmp_path / "log.mcap", tmp_path / "bag")
    expected = {
        TF: 15,
        "/cellsight/cam1/pose": 5,
        MARKER_POSES: 5,
        "/cam1/color/image_raw": 5,
        "/cam1/depth/image_raw": 5,
        "/cam1/color/camera_info": 5,
        OBJECTS: 5,
        POINTS: 5,
    }
    assert result.messages == expected  # and nothing from truth/
    types = ros2_types("jazzy")
    points_by_stamp = {
        lm.msg.timestamp.ToNanoseconds(): lm.msg for lm in read_log(tmp_path / "log.mcap", {keys.points(CELL)})
    }
    seen: dict[str, int] = {}
    with AnyReader([tmp_path / "bag"]) as reader:  # rosbags' own reader and decoder
        for conn, _t, raw in reader.messages():
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == TF:
                tr = msg.transforms[0]
                k = round((stamp_ns(tr.header.stamp) - T0) / 33_333_333)
                offset = {"cam1_color_optical_frame": 0, "marker_3": 1, "object_box": 2}[tr.child_frame_id]
                assert tr.header.frame_id == "world"
                np.testing.assert_allclose(
                    ros_matrix(tr.transform.translation, tr.transform.rotation), pose(k + offset), atol=1e-9
                )
            elif conn.topic == OBJECTS:
                (d,) = msg.detections
                k = round((stamp_ns(d.header.stamp) - T0) / 33_333_333)
                assert d.id == d.results[0].hypothesis.class_id == "box" and d.results[0].hypothesis.score == 0.75
                np.testing.assert_allclose(
                    ros_matrix(d.results[0].pose.pose.position, d.results[0].pose.pose.orientation),
                    pose(k + 2),
                    atol=1e-9,
                )
            elif conn.topic == POINTS:
                assert (
                    [f.name for f in msg.fields] == ["x", "y", "z", "rgb"] and msg.width == 7 and msg.point_step == 16
                )
                cloud = np.frombuffer(bytes(msg.data), np.float32).reshape(7, 4)
                xyz, rgba = codec.points_from_msg(points_by_stamp[stamp_ns(msg.header.stamp)])
                np.testing.assert_array_equal(cloud[:, :3], xyz)
                rgb = cloud[:, 3].view(np.uint32)
                np.testing.assert_array_equal(np.c_[rgb >> 16 & 255, rgb >> 8 & 255, rgb & 255], rgba[:, :3])
            elif conn.topic == "/cellsight/cam1/pose":
                np.testing.assert_allclose(np.reshape(msg.pose.covariance, (6, 6)), np.diag(np.arange(1, 7) * 1e-6))
            elif conn.topic == "/cam1/depth/image_raw":
                assert msg.encoding == "16UC1" and msg.step == 128 and len(msg.data) == 48 * 128
    assert seen == expected
    assert types.type_hash("tf2_msgs/msg/TFMessage").startswith("RIHS01_")


def test_an_existing_folder_and_an_unknown_distribution_are_refused(tmp_path: Path) -> None:
    write_log(tmp_path / "log.mcap", 1)
    (tmp_path / "bag").mkdir()
    with pytest.raises(SchemaError, match="exists"):
        export_bag(tmp_path / "log.mcap", tmp_path / "bag")
    with pytest.raises(SchemaError, match="not supported"):
        ros2_types("kinetic")


def test_a_resolved_solution_becomes_tf_over_the_logs_time(tmp_path: Path) -> None:
    """resolve's output holds each camera segment at its first and last frame and object markers at
    every instant; in the bag each of those is a tf at its own stamp (not just the final state)."""
    w = LogWriter(tmp_path / "resolved.mcap", metadata={"source": RESOLVE_SOURCE})
    stamps = [T0 + k * 1_000_000_000 for k in range(4)]
    for k, stamp in enumerate(stamps):
        w.write(
            keys.estimate_cameras(CELL),
            codec.poses_to_msg(stamp, [StampedPose("world", "cam1", stamp, pose(k))]),
            stamp,
        )
        w.write(
            keys.estimate_markers(CELL),
            codec.poses_to_msg(stamp, [StampedPose("world", "marker_9", stamp, pose(k + 5))]),
            stamp,
        )
    w.write(keys.tf(CELL), codec.transforms_to_msg(stamps[-1], [("world", "cam1", pose(3))]), stamps[-1])
    w.close()
    result = export_bag(tmp_path / "resolved.mcap", tmp_path / "bag")
    assert result.messages[TF] == 8  # 4 camera + 4 marker instants; the closing tf repeats the last
    with AnyReader([tmp_path / "bag"]) as reader:
        tfs = [reader.deserialize(raw, c.msgtype).transforms[0] for c, _, raw in reader.messages() if c.topic == TF]
    for tr in tfs:
        k = stamps.index(stamp_ns(tr.header.stamp))
        want = pose(k) if tr.child_frame_id == "cam1_color_optical_frame" else pose(k + 5)
        np.testing.assert_allclose(ros_matrix(tr.transform.translation, tr.transform.rotation), want, atol=1e-9)
