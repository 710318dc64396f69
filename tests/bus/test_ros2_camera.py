"""A ROS 2 camera driver's topics as a cellsight camera: ``zenoh-ros2-sdk`` (an independent
rmw_zenoh implementation) publishes rendered demo frames as sensor_msgs/Image (bgr8 colour,
16UC1 depth) and CameraInfo; the ``ros2`` source reads them off the bus and its marker
observations equal the sim driver's on the same frames."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cellsight.scenario_config import cell_config_of
from drivers.markers import MarkerDetector
from drivers.ros2_topics import Ros2TopicsSource
from drivers.sim.scenario import load_scenario
from drivers.sim.source import SimSource
from schemas.bus import TransportConfig, open_session
from schemas.geometry import pose_error
from schemas.ros2 import ros2_types
from tests.helpers import wait_until


@pytest.mark.slow
def test_markers_from_ros2_camera_topics_equal_the_sim_drivers(ros2_router: str, ros2_messages: Path) -> None:
    from zenoh_ros2_sdk import ROS2Publisher

    port = int(ros2_router.rsplit(":", 1)[1])
    topics = {
        "color": "/cam/color/image_raw",
        "depth": "/cam/aligned_depth_to_color/image_raw",
        "info": "/cam/color/camera_info",
    }
    pubs = {
        k: ROS2Publisher(
            topic=t,
            msg_type="sensor_msgs/msg/CameraInfo" if k == "info" else "sensor_msgs/msg/Image",
            router_ip="127.0.0.1",
            router_port=port,
        )
        for k, t in topics.items()
    }
    store = pubs["color"].session_mgr.store.types
    frames = [f for f in (SimSource(load_scenario(), "cam1", epoch_ns=10**18, realtime=False).read() for _ in range(4))]
    session = open_session(TransportConfig(connect=[ros2_router]))
    source = Ros2TopicsSource("cam1", session, ros2_types("jazzy"), **topics)
    got = []
    reader = threading.Thread(target=lambda: got.extend(source.read() for _ in range(len(frames))))
    time.sleep(0.5)  # routes
    reader.start()

    def header(stamp: int):
        t = store["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return store["std_msgs/msg/Header"](stamp=t, frame_id="cam_color_optical_frame")

    for f in frames:
        before = len(got)
        info = f.info
        pubs["info"].publish(
            header=header(f.stamp_ns),
            height=info.height,
            width=info.width,
            distortion_model="plumb_bob",
            d=info.D.astype(np.float64),
            k=info.K.reshape(9),
            r=np.eye(3).reshape(9),
            p=np.hstack([info.K, np.zeros((3, 1))]).reshape(12),
            binning_x=0,
            binning_y=0,
            roi=store["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        bgr = np.ascontiguousarray(f.rgb[:, :, ::-1])
        pubs["color"].publish(
            header=header(f.stamp_ns),
            height=info.height,
            width=info.width,
            encoding="bgr8",
            is_bigendian=0,
            step=info.width * 3,
            data=bgr.reshape(-1),
        )
        pubs["depth"].publish(
            header=header(f.stamp_ns),
            height=info.height,
            width=info.width,
            encoding="16UC1",
            is_bigendian=0,
            step=info.width * 2,
            data=f.depth_mm.view(np.uint8).reshape(-1),
        )
        # One frame at a time (the source keeps the newest pair only): the next goes once this one is read.
        wait_until(lambda: len(got) > before or not reader.is_alive(), 20.0, "the ROS 2 source to read the frame")
    reader.join(20)
    source.close()
    session.close()
    for p in pubs.values():
        p.close()
    assert len(got) == len(frames)
    detector = MarkerDetector(cell_config_of(load_scenario()).markers)
    for f, ours in zip(frames, got):
        assert ours.stamp_ns == f.stamp_ns
        np.testing.assert_array_equal(ours.rgb, f.rgb)
        np.testing.assert_array_equal(ours.depth_mm, f.depth_mm)
        a = {d.marker_id: d for d in detector.detect(ours.rgb, ours.info, ours.depth_mm)}
        b = {d.marker_id: d for d in detector.detect(f.rgb, f.info, f.depth_mm)}
        assert set(a) == set(b) and len(a) >= 3
        for mk in a:  # the same pixels, intrinsics through float64: the same poses
            assert pose_error(a[mk].camera_T_marker, b[mk].camera_T_marker)[0] < 1e-6
