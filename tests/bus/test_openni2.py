"""The OpenNI2 driver against the real runtime: Debian's libDummyDevice opens as URI 'Dummy'.

What cannot exist here is a physical Kinect; everything around it (libOpenNI2, the bindings,
our source, the driver process, zenoh) is the real code path.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from tests.helpers import wait_until

CLI = [sys.executable, "-m", "cellsight.cli"]


SOURCE_PROBE = """
import json
from drivers.openni2 import OpenNI2Source
src = OpenNI2Source("cam1", "Dummy")
frames = [src.read() for _ in range(5)]
src.close()
print(json.dumps({"stamps": [f.stamp_ns for f in frames], "rgb": list(frames[0].rgb.shape),
                  "depth": list(frames[0].depth_mm.shape), "fx": frames[0].info.K[0, 0], "width": frames[0].info.width}), flush=True)
import os
os._exit(0)  # libOpenNI2's native shutdown segfaults after a frame was read (see cellsight.cli)
"""


def test_dummy_device_frames_have_increasing_stamps() -> None:
    # Its own interpreter, as in production (one driver per process): the openni bindings'
    # Device destructor leaves a process in which the next zenoh session segfaults.
    out = subprocess.run([sys.executable, "-c", SOURCE_PROBE], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    stamps = got["stamps"]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    # The Dummy device runs 320x240 at 30 Hz: ~33 ms between device stamps.
    assert all(abs((b - a) / 1e6 - 33.3) < 5 for a, b in zip(stamps, stamps[1:]))
    assert got["rgb"] == [240, 320, 3] and got["depth"] == [240, 320]
    assert got["width"] == 320 and got["fx"] == 262.5  # Kinect v1 defaults scaled to 320x240


@pytest.mark.slow
def test_driver_process_publishes_dummy_frames_over_zenoh(
    client_transport: TransportConfig, router_endpoint: str
) -> None:
    proc = subprocess.Popen(
        CLI + ["driver", "openni2", "--camera", "kinect", "--uri", "Dummy", "--duration", "20", "-e", router_endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with Bus(client_transport, "demo") as bus:
            depth = bus.subscribe(keys.depth("demo", "kinect"), m.RawImage, capacity=100)
            markers = bus.subscribe(keys.markers("demo", "kinect"), m.MarkerObservations, capacity=100)
            wait_until(
                lambda: depth.received >= 10 and markers.received >= 10, 20.0, "10 frames from the driver process"
            )
            frames = depth.drain()
            obs = markers.drain()
    finally:
        proc.terminate()
        out, _ = proc.communicate(timeout=10)
    assert proc.returncode == 0, f"the driver did not stop cleanly on SIGTERM: {out[-2000:]}"
    stamps = [codec.timestamp_to_stamp(f.msg.timestamp) for f in frames]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "stamps must increase"
    assert codec.image_from_msg(frames[0].msg).shape == (240, 320)
    assert [o.msg.stamp_ns for o in obs] == sorted(o.msg.stamp_ns for o in obs)


@pytest.mark.slow
def test_no_device_is_a_clear_error_with_exit_code_2(router_endpoint: str) -> None:
    out = subprocess.run(
        CLI + ["driver", "openni2", "--camera", "k", "--uri", "no-such-device", "-e", router_endpoint],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    text = " ".join(out.stderr.split())
    assert "no-such-device" in text and "udev" in text and "libopenni2-dev" in text
