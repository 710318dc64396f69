"""8 simulated cameras on this machine under ``cellsight run``: frame drops and stamp-to-pose latency.

The demo cell with four more Kinects (mid-wall, 2 m up) runs as separate processes (router,
8 drivers, estimator). This process subscribes like a consumer would: colour frames counted
without decoding, driver statuses for the frames each driver says it published, and the
estimator's status. Stamp-to-pose latency = arrival time of an estimator status minus the
capture stamp of the newest frame it has folded in, per localized camera (includes the 10 Hz
update period). On 2 cores each rendered camera runs far below 30 Hz: the renderers drop frames
at the source (newest wins); ``drop_rate`` counts only what was published and never arrived.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from benchmarks.common import demo_cell_text, main
from drivers.sim.scenario import load_scenario
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig

EXTRA = [
    ("cam5", (0.0, -1.45, 2.0), (0.0, 0.5, 0.7)),
    ("cam6", (1.45, 0.0, 2.0), (-0.5, 0.0, 0.7)),
    ("cam7", (0.0, 1.45, 2.0), (0.0, -0.5, 0.7)),
    ("cam8", (-1.45, 0.0, 2.0), (0.5, 0.0, 0.7)),
]


def scenario_toml(path: Path) -> None:
    """The demo cell, static (motions removed, 1 h long), plus four cameras, as a scenario file."""
    text = demo_cell_text(3600.0)
    text = "\n".join(line for line in text.splitlines() if not line.startswith("motion = [{ kind"))
    for cid, pos, look in EXTRA:
        text += f'\n[[cameras]]\nid = "{cid}"\npose = {{ position = {list(pos)}, look_at = {list(look)} }}\n'
    path.write_text(text)
    load_scenario(path)  # fail here, not in eight driver processes


def run(quick: bool) -> dict[str, float]:
    from tests.conftest import free_port

    duration = 20.0 if quick else 60.0
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scenario_toml(tmp / "scenario.toml")
        (tmp / "cell.toml").write_text(
            f'[cell]\nname = "load"\nscenario = "scenario.toml"\n[transport]\nconnect = ["tcp/127.0.0.1:{port}"]\n'
        )
        proc = subprocess.Popen(
            [sys.executable, "-m", "cellsight.cli", "run", str(tmp / "cell.toml"), "--out", str(tmp / "run")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        received: Counter[str] = Counter()
        published: dict[str, int] = {}
        latency_ms: list[float] = []
        try:
            deadline = time.monotonic() + 30
            bus = None
            while bus is None and time.monotonic() < deadline:
                try:
                    bus = Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), "load")
                except Exception:  # the router is still starting
                    time.sleep(0.5)
            if bus is None:
                raise RuntimeError("the cell did not come up within 30 s")
            bus.subscribe_raw(
                keys.all_cameras("load", "color/image_raw"), lambda k, p, t: received.update([k.split("/")[2]])
            )
            bus.subscribe(
                keys.all_cameras("load", "status"),
                m.DriverStatus,
                callback=lambda r: published.__setitem__(r.msg.camera_id, r.msg.frames),
            )

            def on_status(r) -> None:
                for c in r.msg.cameras:
                    if c.state == m.CameraState.LOCALIZED and c.last_stamp_ns:
                        latency_ms.append((r.receive_ns - c.last_stamp_ns) / 1e6)

            bus.subscribe(keys.estimate_status("load"), m.EstimatorStatus, callback=on_status)
            time.sleep(duration)
            # The drivers' STOPPED statuses (sent on SIGTERM) carry their final published counts.
            proc.send_signal(signal.SIGTERM)
            proc.wait(60)
            time.sleep(0.5)
            bus.close()
        finally:
            if proc.poll() is None:
                proc.kill()
    pub, rec = sum(published.values()), sum(received.values())
    lat = np.array(latency_ms) if latency_ms else np.array([np.nan])
    return {
        "cameras": float(len(published)),
        "seconds": duration,
        "frames_published": float(pub),
        "frames_received": float(rec),
        "drop_rate": float(max(pub - rec, 0) / pub) if pub else float("nan"),
        "frames_per_s_per_camera": float(pub / max(len(published), 1) / duration),
        "stamp_to_pose_ms_p50": float(np.nanmedian(lat)),
        "stamp_to_pose_ms_p99": float(np.nanpercentile(lat, 99)),
    }


if __name__ == "__main__":
    main("load", __doc__.splitlines()[0], run)
