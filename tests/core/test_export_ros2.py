"""``cellsight export ros2``: a log written as a ROS 2 bag, read back with ``rosbags`` (its own
reader and CDR decoder): the same messages per topic, and tf / poses that round-trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from cellsight.export_ros2 import MARKER_POSES, TF, export_bag
from schemas import codec, keys
from schemas.codec import CameraInfo, StampedPose
from schemas.errors import SchemaError
from schemas.geometry import make_pose, rpy_matrix
from schemas.log import LogWriter
from schemas.ros2 import ros2_types, stamp_ns

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
        w.write(keys.tf(CELL), codec.transforms_to_msg(stamp, [("world", "cam1", pose(k)), ("world", "marker_3", pose(k + 1))]), stamp)
        cov = np.diag(np.arange(1, 7) * 1e-6)
        w.write(keys.estimate_cameras(CELL), codec.poses_to_msg(stamp, [StampedPose("world", "cam1", stamp, pose(k), cov)]), stamp)
        w.write(keys.estimate_markers(CELL), codec.poses_to_msg(stamp, [StampedPose("world", "marker_3", stamp, pose(k + 1))]), stamp)
        w.write(keys.color(CELL, "cam1"), codec.image_to_msg(rng.integers(0, 255, (48, 64, 3), np.uint8), stamp, "cam1", "rgb8"), stamp)
        w.write(keys.depth(CELL, "cam1"), codec.image_to_msg(rng.integers(0, 4000, (48, 64), np.uint16), stamp, "cam1", "16UC1"), stamp)
        w.write(keys.camera_info(CELL, "cam1"), info.to_msg(stamp, "cam1"), stamp)
        w.write(keys.truth(CELL, "cameras"), codec.poses_to_msg(stamp, [StampedPose("world", "cam1", stamp, pose(k))]), stamp)
    w.close()


def test_the_bag_holds_every_message_and_tf_round_trips(tmp_path: Path) -> None:
    write_log(tmp_path / "log.mcap", 5)
    result = export_bag(tmp_path / "log.mcap", tmp_path / "bag")
    expected = {TF: 10, "/cellsight/cam1/pose": 5, MARKER_POSES: 5, "/cam1/color/image_raw": 5, "/cam1/depth/image_raw": 5,
                "/cam1/color/camera_info": 5}  # fmt: skip
    assert result.messages == expected  # and nothing from truth/
    types = ros2_types("jazzy")
    seen: dict[str, int] = {}
    with AnyReader([tmp_path / "bag"]) as reader:  # rosbags' own reader and decoder
        for conn, t, raw in reader.messages():
            seen[conn.topic] = seen.get(conn.topic, 0) + 1
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == TF:
                tr = msg.transforms[0]
                k = round((stamp_ns(tr.header.stamp) - T0) / 33_333_333)
                want = pose(k) if tr.child_frame_id == "cam1_color_optical_frame" else pose(k + 1)
                assert tr.header.frame_id == "world" and tr.child_frame_id in ("cam1_color_optical_frame", "marker_3")
                q = [tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z, tr.transform.rotation.w]
                T = codec.pose_from_msg(codec.m.Pose(x=tr.transform.translation.x, y=tr.transform.translation.y,
                                                     z=tr.transform.translation.z, qx=q[0], qy=q[1], qz=q[2], qw=q[3]))  # fmt: skip
                np.testing.assert_allclose(T, want, atol=1e-9)
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
