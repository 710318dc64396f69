"""Shared fixtures: a real zenoh router on loopback and client transports that reach it."""

from __future__ import annotations

import os

# Open3D's parallel reductions (normals, ICP, clustering) sum in thread order, so with several
# threads a marginal frame can be found in one run and missed in the next; one thread makes every
# test repeatable (and on two cores is no slower). Set before numpy or Open3D start their pools;
# processes a test launches inherit it.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import socket  # noqa: E402
import subprocess  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from schemas.bus import TransportConfig, open_session  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
REAL_DATA = ROOT / "data"  # public real data, each source's licence and provenance beside it


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def loopback_router() -> Iterator[str]:
    """A zenoh router listening on a free loopback port, multicast off; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(TransportConfig.router([endpoint]))
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture()
def router_endpoint() -> Iterator[str]:
    with loopback_router() as endpoint:
        yield endpoint


@pytest.fixture()
def client_transport(router_endpoint: str) -> TransportConfig:
    return TransportConfig(mode="client", connect=[router_endpoint])


@pytest.fixture()
def real_data() -> Path:
    if not REAL_DATA.is_dir():
        pytest.fail(f"real test data missing: expected {REAL_DATA} (part of the repository)")
    return REAL_DATA


@pytest.fixture()
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 16 MiB tmpfs mounted in tmp_path: a disk that really fills (writes fail with ENOSPC).
    Mounting needs root, which the set-up and CI run as."""
    where = tmp_path / "disk"
    where.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(where)], capture_output=True, text=True
    )
    if mounted.returncode != 0:
        # Set-up and CI run as root, where this must work; elsewhere say so rather than skip quietly.
        pytest.fail(f"cannot mount a small tmpfs to fill: {mounted.stderr.strip()} (needs root, as set-up and CI run)")
    try:
        yield where
    finally:
        subprocess.run(["umount", "--lazy", str(where)], check=True)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests are laid out by layer: ``core`` (pure cores), ``bus`` (services on a real zenoh bus),
    ``e2e`` (several processes, whole pipelines). Every end-to-end test is slow, and they run one
    after another on one pytest-xdist worker (``--dist loadgroup``), so that two whole cells never
    share the two cores (the demo run beside other work once left its sliding tote's last pose
    43 mm off, against 30 allowed)."""
    for item in items:
        if "e2e" in item.path.parts:
            item.add_marker(pytest.mark.slow)
            item.add_marker(pytest.mark.xdist_group("e2e"))


#: The ROS 2 message definitions the rmw_zenoh tests' third-party peer (zenoh-ros2-sdk) needs.
ROS2_MESSAGES = (
    "tf2_msgs/msg/TFMessage",
    "geometry_msgs/msg/TransformStamped",
    "geometry_msgs/msg/Transform",
    "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Quaternion",
    "std_msgs/msg/Header",
    "builtin_interfaces/msg/Time",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/PoseWithCovariance",
    "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/Point",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CameraInfo",
    "sensor_msgs/msg/RegionOfInterest",
    "sensor_msgs/msg/PointCloud2",
    "sensor_msgs/msg/PointField",
    "vision_msgs/msg/Detection3DArray",
    "vision_msgs/msg/Detection3D",
    "vision_msgs/msg/ObjectHypothesisWithPose",
    "vision_msgs/msg/ObjectHypothesis",
    "vision_msgs/msg/BoundingBox3D",
)


@pytest.fixture(scope="session")
def ros2_messages(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """zenoh-ros2-sdk's message registry (one per process) pointed at .msg files written from the
    definitions rosbags ships and the vision_msgs ones we ship, each type's own section of its
    generated definition: the SDK would fetch them from git otherwise, and tests never touch the network."""
    from zenoh_ros2_sdk.message_registry import get_registry

    from schemas.ros2 import ros2_types

    root = tmp_path_factory.mktemp("ros2_msgs")
    store = ros2_types("jazzy").store
    for name in ROS2_MESSAGES:
        package, kind, msg = name.split("/")
        (root / package / kind).mkdir(parents=True, exist_ok=True)
        (root / package / kind / f"{msg}.msg").write_text(
            store.generate_msgdef(name, ros_version=2)[0].split("=" * 80)[0].strip() + "\n"
        )
    registry = get_registry(str(root))
    if registry.messages_dir != root:
        pytest.fail(f"zenoh-ros2-sdk's registry was set up elsewhere first ({registry.messages_dir})")
    return root


@pytest.fixture(scope="session")
def ros2_router() -> Iterator[str]:
    """A loopback router for the tests that use zenoh-ros2-sdk: the SDK keeps one zenoh session per
    process, connected to the first router it is given, so those tests share this one."""
    with loopback_router() as endpoint:
        yield endpoint


@pytest.fixture(scope="session")
def demo_models() -> dict:
    """The demo cell's object models (object id -> ``ObjectModel``) with the default descriptor,
    built once (several seconds): read-only, make a ``ModelDatabase`` of your own from them."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.scenario import load_scenario
    from recognition.config import RecognitionConfig

    return dict(database_from_scenario(load_scenario(), RecognitionConfig().descriptor).models)
