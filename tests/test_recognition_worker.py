"""The recognition worker over real zenoh sessions: frames and tf in, fused world poses out."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from cellsight.model_build import database_from_scenario
from cellsight.scenario_config import demo_config
from drivers.sim.render import SimCell
from drivers.sim.scenario import load_scenario
from recognition.pipeline import Detection
from recognition.worker import RecognitionWorker, WorldDetection, fuse
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.codec import make_pose
from tests.helpers import assert_pose_close, rotation_angle_deg, wait_until

CELL = "demo"


def det(camera: str, oid: str, xyz, yaw_deg: float = 0.0, fitness: float = 0.9, rmse: float = 0.005) -> WorldDetection:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), xyz)
    return WorldDetection(camera, 1, T, Detection(oid, T, fitness, 1.0, rmse, 100))


def test_fuse_averages_agreeing_cameras_and_outvotes_the_rest() -> None:
    fused = {o.object_id: o for o in fuse([
        det("cam1", "crate", (0.0, 0.0, 0.75), yaw_deg=0.0, rmse=0.004),
        det("cam2", "crate", (0.02, 0.0, 0.75), yaw_deg=180.0, rmse=0.008),  # the symmetric twin
        det("cam3", "crate", (0.3, 0.0, 0.75), rmse=0.002, fitness=0.2),  # far off: not the same
        det("cam1", "can", (1.0, 1.0, 0.75)),
    ])}  # fmt: skip
    assert sorted(fused) == ["can", "crate"]
    crate = fused["crate"]
    assert crate.camera_ids == ["cam1", "cam2"]
    # Weights fitness x coverage / rmse^2: cam1 counts 4x cam2, so x = 0.02 / 5.
    np.testing.assert_allclose(crate.world_T_object[:3, 3], [0.004, 0.0, 0.75], atol=1e-9)
    assert rotation_angle_deg(crate.world_T_object[:3, :3], np.eye(3)) < 1e-9, "rotation of the best, never averaged"


@pytest.fixture(scope="module")
def demo_database():
    cfg = demo_config()
    return cfg, database_from_scenario(load_scenario(), cfg.recognition.descriptor)


def test_worker_publishes_world_poses_from_frames_and_tf(client_transport: TransportConfig, demo_database) -> None:
    cfg, db = demo_database
    scenario = load_scenario()
    frame = SimCell(scenario).render("cam2", 1.0, 30)
    got: list[m.ObjectDetections] = []
    scenes: list[m.SceneUpdate] = []
    with Bus(client_transport, CELL) as worker_bus, Bus(client_transport, CELL) as client:
        worker = RecognitionWorker(worker_bus, cfg.recognition, db)
        client.subscribe(keys.objects(CELL), m.ObjectDetections, callback=lambda r: got.append(r.msg))
        client.subscribe(keys.objects_scene(CELL), m.SceneUpdate, callback=lambda r: scenes.append(r.msg))
        stop = threading.Event()
        thread = threading.Thread(target=worker.run, args=(stop,))
        thread.start()
        try:
            time.sleep(0.5)  # routes
            depth_pub = client.publisher(keys.depth(CELL, "cam2"), frames=True)
            client.publisher(keys.camera_info(CELL, "cam2")).put(frame.info.to_msg(frame.stamp_ns, "cam2"))
            # The estimator's part, here from the simulator: where cam2 is.
            client.publisher(keys.tf(CELL)).put(codec.transforms_to_msg(frame.stamp_ns, [("world", "cam2", frame.world_T_camera)]))
            # A frame that does not match camera_info first: skipped, the worker carries on.
            depth_pub.put(codec.image_to_msg(frame.depth_mm[:100], frame.stamp_ns, "cam2", "16UC1"))
            wait_until(lambda: worker.errors == 1, 10.0, "the bad frame to be rejected")
            worker.last_run.clear()
            depth_pub.put(codec.image_to_msg(frame.depth_mm, frame.stamp_ns, "cam2", "16UC1"))
            wait_until(lambda: len(got) > 0 and len(scenes) > 0, 20.0, "object detections and their 3-D scene")
        finally:
            stop.set()
            thread.join()
    assert thread.is_alive() is False and worker.errors == 1
    assert sorted(e.id for e in scenes[-1].entities) == ["object_can", "object_crate", "object_tote"]
    found = {o.object_id: o for o in got[-1].objects}
    assert sorted(found) == ["can", "crate", "tote"]
    for obj in scenario.objects:
        o = found[obj.id]
        assert list(o.camera_ids) == ["cam2"] and o.rmse_m < 0.01
        # 2 cm: a few times the measured median error (3-6 mm), far below the objects' size.
        T, truth = codec.pose_from_msg(o.world_T_object), obj.world_T_object(1.0)
        assert_pose_close(T, truth, pos_tol_m=0.02, rot_tol_deg=180.0, what=obj.id)
        assert T[2, 2] > np.cos(np.radians(5)), f"{obj.id} must stand upright"
        if obj.shape == "box":  # yaw up to the box's half turn
            yaw = np.degrees(np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(truth[1, 0], truth[0, 0]))
            assert abs((yaw + 90) % 180 - 90) < 5.0, f"{obj.id}: yaw off by {yaw:.1f} deg"
