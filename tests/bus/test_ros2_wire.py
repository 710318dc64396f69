"""ROS 2 on our bus without ROS: the estimator's poses on rmw_zenoh's wire, read by an
implementation nobody here wrote (``zenoh-ros2-sdk``, which speaks rmw_zenoh in Python)."""

from __future__ import annotations

import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cellsight.evaluation.synthetic import NoiseSettings, estimator_config, frame_observations, observations_msg
from estimator.service import EstimatorService
from schemas import keys
from schemas.bus import Bus, TransportConfig
from schemas.rmw_zenoh import attachment, dds_type_name, mangle, topic_key
from schemas.ros2 import Ros2Config, ros2_types
from tests.bus.test_estimator_service import CELL, scene
from tests.helpers import ros2_subscriber, wait_until


def test_keys_hashes_and_attachment_as_rmw_zenoh_states_them() -> None:
    """ros2/rmw_zenoh docs/design.md: topic keys are ``<domain>/<topic>/<DDS type>/<type hash>``,
    liveliness names mangle ``/`` to ``%``; the attachment is sequence, source time, GID."""
    assert dds_type_name("std_msgs/msg/String") == "std_msgs::msg::dds_::String_"
    humble, jazzy = ros2_types("humble"), ros2_types("jazzy")
    assert (
        topic_key(0, "/chatter", "std_msgs/msg/String", humble.type_hash("std_msgs/msg/String"))
        == "0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    )
    # REP-2011's hash of tf2_msgs/msg/TFMessage, as rmw_zenoh puts it in Jazzy keys
    assert (
        jazzy.type_hash("tf2_msgs/msg/TFMessage")
        == "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    )
    # ... and of the cloud and (from the vision_msgs definitions we ship) the objects, as
    # `ros2 topic info -v` on Jazzy prints them: our definitions hash like the real packages'.
    assert (
        jazzy.type_hash("sensor_msgs/msg/PointCloud2")
        == "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
    )
    assert (
        jazzy.type_hash("vision_msgs/msg/Detection3DArray")
        == "RIHS01_793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018"
    )
    assert (
        topic_key(3, "/cellsight/cam1/pose", "geometry_msgs/msg/PoseWithCovarianceStamped", "H")
        == "3/cellsight/cam1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/H"
    )
    assert mangle("/cellsight/cam1/pose") == "%cellsight%cam1%pose" and mangle("/") == "%"
    gid = bytes(range(16))
    assert attachment(7, 123, gid) == struct.pack("<QQB", 7, 123, 16) + gid


@pytest.mark.slow
def test_a_ros2_node_reads_the_estimators_tf_and_poses(ros2_router: str, ros2_messages: Path) -> None:
    tf_sub, tf = ros2_subscriber(ros2_router, "/tf", "tf2_msgs/msg/TFMessage")
    poses_sub, poses = ros2_subscriber(ros2_router, "/cellsight/a/pose", "geometry_msgs/msg/PoseWithCovarianceStamped")
    s = scene()
    transport = TransportConfig(connect=[ros2_router])
    with Bus(transport, CELL) as svc_bus, Bus(transport, CELL) as client:
        svc = EstimatorService(svc_bus, estimator_config(s, update_hz=20.0), Ros2Config(enabled=True))
        stop = threading.Event()
        thread = threading.Thread(target=svc.run, args=(stop,))
        thread.start()
        try:
            time.sleep(0.5)
            pub, rng = client.publisher(keys.markers(CELL, "a")), np.random.default_rng(0)
            for k in range(60):
                stamp = 10**18 + int(k * 1e9 / 30)
                pub.put(observations_msg("a", stamp, frame_observations(s, "a", 0.0, stamp, rng, NoiseSettings())))
                time.sleep(1 / 60)
            wait_until(
                lambda: any(t.child_frame_id == "a_color_optical_frame" for m in tf for t in m.transforms) and poses,
                5.0,
                "the ROS 2 subscriber to get the camera's tf and pose",
            )
            tokens = [str(r.ok.key_expr) for r in client.session.liveliness().get("@ros2_lv/**", timeout=2.0) if r.ok]
        finally:
            stop.set()
            thread.join(10)
    for sub in (tf_sub, poses_sub):
        sub.close()
    assert any("/NN/%/%/cellsight_estimator" in t for t in tokens), tokens
    assert any("/MP/%/%/cellsight_estimator/%tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_" in t for t in tokens), tokens
    # The transform the robot got is the estimate we published, to the last digits the wire carries.
    ours = svc.estimator.estimate(0).cameras["a"].pose.T
    last = [t for m in tf for t in m.transforms if t.child_frame_id == "a_color_optical_frame"][-1]
    assert last.header.frame_id == "world"
    got = np.array([last.transform.translation.x, last.transform.translation.y, last.transform.translation.z])
    np.testing.assert_allclose(got, ours[:3, 3], atol=1e-9)
    assert np.reshape(poses[-1].pose.covariance, (6, 6))[0, 0] > 0
