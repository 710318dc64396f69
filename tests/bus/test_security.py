"""The secure deployment profile on loopback: real zenoh sessions, mutual TLS with generated
certificates, access control at the router."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from cellsight.access_probe import probe
from cellsight.config import CellConfig
from cellsight.launch import router_endpoint
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig, open_session
from schemas.errors import BusError
from schemas.rmw_zenoh import NodeName, Ros2Node, topic_key
from schemas.ros2 import DETECTIONS, ros2_types
from schemas.security import Profile, access_matrix, write_profile
from tests.conftest import free_port
from tests.helpers import wait_until

CELL = "demo"


@pytest.fixture()
def profile(tmp_path: Path) -> Iterator[Profile]:
    """A fresh authority and configs, and the router running from its own config."""
    p = write_profile(tmp_path / "secure", CELL, listen=f"tls/127.0.0.1:{free_port()}")
    router = open_session(TransportConfig(zenoh_config=p.router_config))
    try:
        yield p
    finally:
        router.close()


def _as(p: Profile, role: str) -> Bus:
    return Bus(TransportConfig(zenoh_config=p.role_configs[role]), CELL)


def test_each_role_publishes_only_its_own_topics_and_everyone_reads(profile: Profile) -> None:
    got: list[str] = []
    lock = threading.Lock()

    def seen(key: str, payload: bytes, _ns: int) -> None:
        with lock:
            got.append(key)

    viewer, driver, estimator, recognition, other_viewer = (
        _as(profile, r) for r in ("viewer", "driver", "estimator", "recognition", "viewer")
    )
    try:
        viewer.subscribe_raw(f"{keys.ROOT}/{CELL}/**", seen)
        estimator.session.declare_queryable(
            keys.estimate_map(CELL), lambda q: q.reply(q.key_expr, m.Map().SerializeToString())
        )
        driver.session.declare_queryable(
            keys.estimate_map(CELL), lambda q: q.reply(q.key_expr, m.Map().SerializeToString())
        )
        estimator.declare_alive("estimator", "main")
        wait_until(lambda: len(viewer.alive()) == 1, 5.0, "the estimator's liveliness token")
        # Each session puts what it may not before what it may: zenoh keeps one session's order, so
        # a denied message that got through would arrive before the last allowed one.
        denied = {
            driver: [keys.estimate_cameras(CELL), keys.objects(CELL)],
            recognition: [keys.tf(CELL), keys.markers(CELL, "cam1")],
            other_viewer: [keys.tf(CELL), keys.objects(CELL)],
        }
        allowed = {
            driver: [keys.markers(CELL, "cam1")],
            estimator: [keys.estimate_cameras(CELL), keys.tf(CELL)],
            recognition: [keys.objects(CELL)],
        }
        for bus, ks in denied.items():
            for k in ks:
                bus.session.put(k, b"not allowed")
        for bus, ks in allowed.items():
            for k in ks:
                bus.session.put(k, b"allowed")
        expected = sorted(k for ks in allowed.values() for k in ks)
        wait_until(lambda: len(got) >= len(expected), 5.0, "every allowed message")
        with lock:
            assert sorted(got) == expected, f"received {sorted(got)}, expected only the allowed {expected}"
        replies = viewer.query(keys.estimate_map(CELL), timeout_s=2.0)
        assert len(replies) == 1, "only the estimator may answer estimate/map"
    finally:
        for bus in (viewer, driver, estimator, recognition, other_viewer):
            bus.close()


@pytest.mark.slow
def test_every_cell_of_the_access_matrix_holds_at_the_real_router(profile: Profile) -> None:
    """Each role's certificate tries every cell of the matrix (``docs/deployment.md``) through the
    real router (the edge role through a real edge router): every disallowed put, token and answer
    is refused, every allowed one delivered. With the ACL before the deny rules, a driver's put on
    ``estimate/status`` (``*/status`` matched it) and any role's token under ``alive/estimator``
    got through: 27 violations."""
    result = probe(profile, CELL, f"tls/127.0.0.1:{free_port()}")
    assert result.cells == len(access_matrix(CELL)) > 250
    assert not result.violations, [(c.role, c.family, c.operation, what) for c, what in result.violations]


@pytest.mark.slow
def test_a_driver_cannot_forge_the_estimators_status_nor_its_liveliness(profile: Profile) -> None:
    """The two findings as an operator met them: a driver certificate's put on ``estimate/status``
    reached ``cellsight status``, and a robot's ``alive/estimator/main`` token listed an estimator."""
    viewer, driver, robot = (_as(profile, r) for r in ("viewer", "driver", "robot"))
    got: list[str] = []
    try:
        viewer.subscribe_raw(f"{keys.ROOT}/{CELL}/**", lambda key, _p, _ns: got.append(key))
        time.sleep(0.3)
        forged = m.EstimatorStatus(stamp_ns=time.time_ns())
        forged.cameras.add(camera_id="cam1", state=m.CameraState.LOCALIZED, position_sigma_m=1e-4)
        driver.session.put(keys.estimate_status(CELL), forged.SerializeToString())
        driver.session.put(keys.estimate_markers(CELL), b"x")
        robot.session.liveliness().declare_token(keys.alive(CELL, "estimator", "main"))
        driver.session.put(keys.status(CELL, "cam1"), b"allowed")  # after the denied ones: one session's order is kept
        wait_until(lambda: keys.status(CELL, "cam1") in got, 5.0, "the driver's own status")
        time.sleep(0.3)
        assert got == [keys.status(CELL, "cam1")]
        assert viewer.alive() == []
    finally:
        for bus in (viewer, driver, robot):
            bus.close()


def test_on_ros2_keys_only_the_estimator_puts_tf_only_recognition_objects_and_a_robot_reads(tmp_path: Path) -> None:
    """rmw_zenoh's wire under the secure profile: the real ROS 2 publishers (``Ros2Node``) of each
    role, and a robot with its own certificate that reads them and sees the ROS 2 graph."""
    p = write_profile(tmp_path / "secure", CELL, listen=f"tls/127.0.0.1:{free_port()}", ros2_domain=7)
    router = open_session(TransportConfig(zenoh_config=p.router_config))
    types = ros2_types("jazzy")
    robot, other_robot, estimator, recognition, driver = (
        _as(p, r) for r in ("robot", "robot", "estimator", "recognition", "driver")
    )
    got: list[str] = []
    lock = threading.Lock()

    def seen(key: str, payload: bytes, _ns: int) -> None:
        with lock:
            got.append(key.split("/")[1] + "/" + key.split("/")[2])

    nodes = []
    try:
        robot.subscribe_raw("7/**", seen)
        est, rec = (
            Ros2Node(b.session, NodeName(7, name), types) for b, name in ((estimator, "est"), (recognition, "rec"))
        )
        nodes += [est, rec]
        wait_until(
            lambda: len([r for r in robot.session.liveliness().get("@ros2_lv/7/**", timeout=1.0) if r.ok]) >= 2,
            5.0,
            "the robot to see both nodes in the ROS 2 graph",
        )
        tf = types.tf_message(1, [("world", "cam1_color_optical_frame", np.eye(4))])
        objects = types.detections(m.ObjectDetections(stamp_ns=1))
        # Denied first (one session's order is kept, so one that got through would arrive early).
        rec.publisher("/tf", "tf2_msgs/msg/TFMessage").put(tf)
        est.publisher("/cellsight/objects", DETECTIONS).put(objects)
        other_robot.session.put(
            topic_key(7, "/tf", "tf2_msgs/msg/TFMessage", types.type_hash("tf2_msgs/msg/TFMessage")), b"spoof"
        )
        driver.session.put(topic_key(7, "/cellsight/cam1/pose", "x/msg/Y", "H"), b"spoof")
        est.publisher("/tf", "tf2_msgs/msg/TFMessage").put(tf)
        est.publisher("/cellsight/cam1/pose", "geometry_msgs/msg/PoseWithCovarianceStamped").put(
            types.pose_with_covariance(1, "world", np.eye(4), None)
        )
        rec.publisher("/cellsight/objects", DETECTIONS).put(objects)
        expected = ["cellsight/cam1", "cellsight/objects", "tf/tf2_msgs::msg::dds_::TFMessage_"]
        wait_until(lambda: len(got) >= len(expected), 5.0, "every allowed ROS 2 message")
        time.sleep(0.3)
        with lock:
            assert sorted(got) == expected, f"the robot received {sorted(got)}, expected only {expected}"
    finally:
        for node in nodes:
            node.close()
        for bus in (robot, other_robot, estimator, recognition, driver):
            bus.close()
        router.close()


@pytest.mark.slow
def test_a_client_without_a_certificate_is_refused(profile: Profile) -> None:
    """Server-side TLS alone (it trusts the router) is not enough: the router wants a client certificate."""
    transport = TransportConfig(
        connect=[profile.endpoint],
        overrides={"transport/link/tls/root_ca_certificate": str(profile.ca_certificate), "connect/timeout_ms": 500},
    )
    with pytest.raises(BusError, match="cannot open zenoh session"):
        open_session(transport)


@pytest.mark.slow
def test_a_certificate_from_another_authority_is_refused(profile: Profile, tmp_path: Path) -> None:
    stranger = write_profile(tmp_path / "stranger", CELL, listen=profile.endpoint)
    transport = TransportConfig(zenoh_config=stranger.role_configs["estimator"], overrides={"connect/timeout_ms": 500})
    with pytest.raises(BusError, match="cannot open zenoh session"):
        open_session(transport)


def test_the_default_local_profile_stays_on_loopback() -> None:
    """`cellsight run` starts its router on loopback, and every other process is a client (which
    never listens) of that router."""
    endpoint = router_endpoint(CellConfig())
    assert endpoint == "tcp/127.0.0.1:7447"
    assert TransportConfig.router([endpoint]).to_zenoh().get_json("listen/endpoints") == '["tcp/127.0.0.1:7447"]'
    client = TransportConfig().to_zenoh()
    assert client.get_json("mode") == '"client"'
    assert client.get_json("connect/endpoints") == '["tcp/127.0.0.1:7447"]'


@pytest.mark.slow
def test_an_edge_router_passes_its_cameras_topics_and_the_cell_drops_anything_else_from_it(profile: Profile) -> None:
    """The edge router only authenticates; the cell's router holds it to what a driver may put. A
    process on the edge host (with the driver's certificate) puts markers and, as a compromised host
    might, tf and objects: only the markers reach the cell."""
    edge_listen = f"tls/127.0.0.1:{free_port()}"
    edge_router = open_session(TransportConfig(zenoh_config=profile.edge_router_config, listen=[edge_listen]))
    viewer = _as(profile, "viewer")
    on_edge = Bus(TransportConfig(zenoh_config=profile.role_configs["driver"], connect=[edge_listen]), CELL)
    got: list[str] = []
    try:
        viewer.subscribe_raw(f"{keys.ROOT}/{CELL}/**", lambda key, _p, _ns: got.append(key))
        wait_until(
            lambda: on_edge.session.put(keys.status(CELL, "probe"), b"") or got,
            10.0,
            "the edge host's messages at the cell, router to router",
        )
        got.clear()
        for k in (keys.tf(CELL), keys.objects(CELL), keys.estimate_cameras(CELL), keys.markers(CELL, "cam1")):
            on_edge.session.put(k, b"x")  # denied first: one session's order is kept
        wait_until(lambda: keys.markers(CELL, "cam1") in got, 5.0, "the edge camera's markers")
        time.sleep(0.3)
        arrived = [k for k in got if k != keys.status(CELL, "probe")]  # late probes may still come in
        assert arrived == [keys.markers(CELL, "cam1")], f"the cell received {arrived} from the edge host"
    finally:
        on_edge.close()
        viewer.close()
        edge_router.close()
