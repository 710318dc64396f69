"""Assertion helpers with explicit tolerances, in the style of gtsam's own tests."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from google.protobuf.message import Message
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from cellsight.launch import STOP_BOUND_S
from schemas.geometry import pose_error


def assert_pose_close(
    T_a: np.ndarray, T_b: np.ndarray, pos_tol_m: float, rot_tol_deg: float, what: str = "pose"
) -> None:
    """Fail unless the two 4x4 poses agree within the translation and rotation tolerances."""
    dp_mm, dr = pose_error(T_a, T_b)
    assert dp_mm <= pos_tol_m * 1000 and dr <= rot_tol_deg, (
        f"{what}: position off by {dp_mm:.3f} mm (tol {pos_tol_m * 1000:.3f}), "
        f"rotation off by {dr:.4f} deg (tol {rot_tol_deg:.4f})"
    )


def wait_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``pred`` every 20 ms until true; fail with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def logged_messages(path: Path, log_time_order: bool = True) -> Iterator[tuple[str, Message]]:
    """(topic, decoded protobuf) of every message in an MCAP file, through mcap's own reader and
    the schemas embedded in the file: an independent check of what our writer wrote."""
    with path.open("rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            log_time_order=log_time_order
        ):
            yield channel.topic, msg


def ros2_subscriber(endpoint: str, topic: str, msg_type: str) -> tuple[object, list]:
    """A zenoh-ros2-sdk subscriber (an rmw_zenoh peer nobody here wrote) through the router at
    ``endpoint`` (``tcp/127.0.0.1:PORT``): it and the list its decoded messages go into."""
    from zenoh_ros2_sdk import ROS2Subscriber

    got: list = []
    sub = ROS2Subscriber(
        topic=topic,
        msg_type=msg_type,
        callback=got.append,
        router_ip="127.0.0.1",
        router_port=int(endpoint.rsplit(":", 1)[1]),
    )
    return sub, got


def ros_matrix(translation, rotation) -> np.ndarray:
    """4x4 pose of a ROS translation/position (x y z) and rotation/orientation (x y z w), as decoded
    from CDR by a ROS 2 implementation; through our own message so the quaternion is checked."""
    from schemas import codec

    return codec.pose_from_msg(
        codec.m.Pose(
            x=translation.x,
            y=translation.y,
            z=translation.z,
            qx=rotation.x,
            qy=rotation.y,
            qz=rotation.z,
            qw=rotation.w,
        )
    )


def stop_launcher(proc: subprocess.Popen, run_dir: Path, sig: int = signal.SIGTERM) -> None:
    """Stop a ``cellsight run`` launcher as an operator would (``sig``), allowing it its own worst
    case (``STOP_BOUND_S``) plus a margin for a loaded machine. If it is still running then, kill it
    and every process it started (they run in sessions of their own), and fail naming them."""
    proc.send_signal(sig)
    try:
        proc.wait(STOP_BOUND_S + 15.0)
        return
    except subprocess.TimeoutExpired:
        pass
    manifest = run_dir / "processes.json"
    children = json.loads(manifest.read_text()) if manifest.exists() else []
    alive = []
    for child in children:
        try:
            os.killpg(child["pid"], signal.SIGKILL)
            alive.append(child["name"])
        except (ProcessLookupError, PermissionError, KeyError, TypeError):
            pass
    proc.kill()
    _, err = proc.communicate()
    raise AssertionError(
        f"the launcher did not stop within {STOP_BOUND_S + 15.0:.0f} s; killed it and {alive}; "
        f"it said: {(err or '')[-1500:]}"
    )
