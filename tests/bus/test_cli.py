"""The ``cellsight`` command as a user runs it: separate processes, real bus, real files."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from google.protobuf.message import Message

from schemas import codec, geometry, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig

CLI = [sys.executable, "-m", "cellsight.cli"]


def run(args: list[str], timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + args, capture_output=True, text=True, timeout=timeout)


def publish_until_exit(
    proc: subprocess.Popen, endpoint: str, cell: str, messages: dict[str, Message]
) -> tuple[str, str]:
    """Keep publishing ``messages`` (key -> message) until the CLI process, which must first
    subscribe, has printed and exited; its (stdout, stderr)."""
    try:
        with Bus(TransportConfig(connect=[endpoint]), cell) as bus:
            pubs = [(bus.publisher(key), msg) for key, msg in messages.items()]
            while proc.poll() is None:
                for pub, msg in pubs:
                    pub.put(msg)
                time.sleep(0.1)
        return proc.communicate(timeout=10)
    finally:
        proc.kill()


def test_help_lists_the_commands() -> None:
    out = run(["--help"])
    assert out.returncode == 0
    for cmd in ("config", "bus", "router"):
        assert cmd in out.stdout


def test_config_check_names_the_broken_field(tmp_path: Path) -> None:
    bad = tmp_path / "cell.toml"
    bad.write_text('[estimator]\nhuber_k = -2\n[[cameras]]\nid = "cam1"\nrate_hz = "fast"\n')
    out = run(["config", "check", str(bad)])
    assert out.returncode == 2
    assert str(bad) in out.stderr and "estimator.huber_k" in out.stderr and "cameras.0.rate_hz" in out.stderr


def test_config_check_accepts_a_good_file_and_prints_defaults(tmp_path: Path) -> None:
    good = tmp_path / "cell.toml"
    good.write_text('[cell]\nname = "lab"\n[[cameras]]\nid = "cam1"\n')
    out = run(["config", "check", str(good)])
    assert out.returncode == 0, out.stderr
    assert 'name = "lab"' in out.stdout and "huber_k = 1.345" in out.stdout


def test_config_check_rejects_broken_toml(tmp_path: Path) -> None:
    bad = tmp_path / "cell.toml"
    bad.write_text("[cell\nname=")
    out = run(["config", "check", str(bad)])
    assert out.returncode == 2 and "not valid TOML" in out.stderr


@pytest.mark.slow
def test_bus_echo_prints_a_message_from_another_process(router_endpoint: str) -> None:
    key = keys.markers("demo", "cam7")
    msg = m.MarkerObservations(camera_id="cam7", stamp_ns=123456789)
    obs = msg.markers.add(marker_id=42, dictionary="DICT_APRILTAG_36h11", side_m=0.15)
    obs.corners_px.extend(range(8))
    codec.pose_to_msg(geometry.make_pose(t=[0.1, 0.2, 1.5]), obs.camera_T_marker)
    obs.covariance.extend(codec.covariance_to_list(np.eye(6) * 1e-4))
    proc = subprocess.Popen(
        CLI + ["bus", "echo", key, "--once", "--json", "--timeout", "20", "--connect", router_endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    out, err = publish_until_exit(proc, router_endpoint, "demo", {key: msg})
    assert proc.returncode == 0, err
    line = json.loads(out.strip().splitlines()[0])
    assert line["key"] == key and line["type"] == "cellsight.MarkerObservations"
    assert line["message"]["markers"][0]["marker_id"] == 42
    assert line["message"]["stamp_ns"] == "123456789"


@pytest.mark.slow
def test_bus_echo_times_out_with_exit_1(router_endpoint: str) -> None:
    out = run(["bus", "echo", "cellsight/demo/**", "--timeout", "1", "--connect", router_endpoint])
    assert out.returncode == 1 and "no message" in out.stderr


@pytest.mark.slow
def test_status_shows_cameras_with_poses_and_objects(router_endpoint: str) -> None:
    proc = subprocess.Popen(
        CLI + ["status", "--duration", "3", "--cell", "lab", "--connect", router_endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    status = m.EstimatorStatus(stamp_ns=1, observations=7)
    status.cameras.add(camera_id="cam1", state=m.CameraState.LOCALIZED, position_sigma_m=0.004)
    cameras = codec.poses_to_msg(1, [codec.StampedPose("world", "cam1", 1, geometry.make_pose(t=[1.25, -0.5, 2.0]))])
    objects = m.ObjectDetections(stamp_ns=1)
    crate = objects.objects.add(object_id="crate", fitness=0.93, rmse_m=0.0052, camera_ids=["cam1"])
    codec.pose_to_msg(geometry.make_pose(t=[0.1, 0.2, 0.75]), crate.world_T_object)
    out, err = publish_until_exit(
        proc,
        router_endpoint,
        "lab",
        {keys.estimate_status("lab"): status, keys.estimate_cameras("lab"): cameras, keys.objects("lab"): objects},
    )
    assert proc.returncode == 0, err
    cam1 = next(line for line in out.splitlines() if "cam1" in line and "localized" in line)
    assert "+1.250, -0.500, +2.000" in cam1 and "4.0" in cam1
    crate_row = next(line for line in out.splitlines() if "crate" in line)
    assert "+0.100, +0.200, +0.750" in crate_row and "0.93" in crate_row and "5.2" in crate_row
