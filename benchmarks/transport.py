"""Frames through the bus: CPU of moving 4 cameras x 30 Hz of VGA RGB-D to 2 readers, shared memory vs plain bytes.

One router, four publisher processes (a 640x480 rgb8 and a 16UC1 image per frame, 1.5 MB, at
30 Hz, as a Kinect v1 driver sends them) and two reader processes that decode every frame into
protobuf messages, as the recorder and the recognition worker do. Each process reports its own
CPU time (user + system, ``getrusage``); the same run is made with ``transport.shared_memory``
on and off. The reference shared memory must beat is plain bytes on the same machine, same run.

Cross-host (root only: two hosts made of network namespaces, ``tests/hosts.py``): an edge host
runs ``cellsight run`` with ``role = "edge"`` and one simulated camera at 30 Hz (pre-rendered
frames), the cell host a router (shared memory off: another machine has none to share) and the
estimator. Bytes per second crossing the link for that camera: as deployed (images stay on the
edge host), with the cell's recorder keeping 2 images a second (``cellsight run --record``'s
default; it subscribes to an image only when one is due), and with a reader of every key on the
cell host (everything sent), the reference.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import time

import numpy as np

from benchmarks.common import Row, demo_cell_text, main
from schemas import codec, keys
from schemas.bus import Bus, TransportConfig, open_session

CELL = "bench"
CAMERAS = ("cam1", "cam2", "cam3", "cam4")
RATE_HZ = 30.0
READERS = 2
RECORDED_IMAGE_HZ = 2.0  # cellsight run --record's default


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def publisher(endpoint: str, shm: bool, camera: str, seconds: float) -> None:
    """Publish ``seconds`` of frames at RATE_HZ; print CPU seconds, frames and how many went through shared memory."""
    with Bus(TransportConfig(mode="client", connect=[endpoint], shared_memory=shm), CELL) as bus:
        color, depth = (
            bus.publisher(keys.color(CELL, camera), frames=True),
            bus.publisher(keys.depth(CELL, camera), frames=True),
        )
        rng = np.random.default_rng(0)
        c = codec.image_to_msg(rng.integers(0, 255, (480, 640, 3), dtype=np.uint8), 1, camera, "rgb8")
        d = codec.image_to_msg(rng.integers(0, 4000, (480, 640), dtype=np.uint16), 1, camera, "16UC1")
        time.sleep(1.0)  # readers are routed
        start, k = time.monotonic(), 0
        while time.monotonic() - start < seconds:
            color.put(c)
            depth.put(d)
            k += 1
            time.sleep(max(0.0, start + k / RATE_HZ - time.monotonic()))
        print(f"{cpu_s():.3f} {k} {color.shm_puts + depth.shm_puts}", flush=True)


def reader(endpoint: str, shm: bool, seconds: float) -> None:
    """Decode every frame for ``seconds``; print CPU seconds and frames received."""
    with Bus(TransportConfig(mode="client", connect=[endpoint], shared_memory=shm), CELL) as bus:
        sub = bus.subscribe(keys.everything(CELL), capacity=64, ring=True)
        end, n = time.monotonic() + seconds, 0
        while time.monotonic() < end:
            n += len(sub.drain())
            time.sleep(0.01)
        print(f"{cpu_s():.3f} {n}", flush=True)


def router(endpoint: str, shm: bool, seconds: float) -> None:
    session = open_session(TransportConfig(mode="router", connect=[], listen=[endpoint], shared_memory=shm))
    time.sleep(seconds)
    print(f"{cpu_s():.3f}", flush=True)
    session.close()


def one_run(shm: bool, seconds: float) -> dict[str, float]:
    from tests.conftest import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    me = [sys.executable, "-m", "benchmarks.transport", "--role"]
    flag = "1" if shm else "0"
    r = subprocess.Popen(me + ["router", endpoint, flag, str(seconds + 6)], stdout=subprocess.PIPE, text=True)
    time.sleep(1.0)
    readers = [
        subprocess.Popen(me + ["reader", endpoint, flag, str(seconds + 3)], stdout=subprocess.PIPE, text=True)
        for _ in range(READERS)
    ]
    time.sleep(0.5)
    pubs = [
        subprocess.Popen(me + ["publisher", endpoint, flag, str(seconds), cam], stdout=subprocess.PIPE, text=True)
        for cam in CAMERAS
    ]
    pub_out = [p.communicate(timeout=seconds + 60)[0].split() for p in pubs]
    read_out = [p.communicate(timeout=seconds + 60)[0].split() for p in readers]
    router_cpu = float(r.communicate(timeout=seconds + 60)[0].split()[0])
    sent = sum(int(o[1]) for o in pub_out) * 2  # color + depth
    return {
        "cpu_s_per_s_total": (sum(float(o[0]) for o in pub_out) + sum(float(o[0]) for o in read_out) + router_cpu)
        / seconds,
        "cpu_s_per_s_publishers": sum(float(o[0]) for o in pub_out) / seconds,
        "cpu_s_per_s_readers": sum(float(o[0]) for o in read_out) / seconds,
        "cpu_s_per_s_router": router_cpu / seconds,
        "images_sent": sent,
        "images_received_pct": 100.0 * sum(int(o[1]) for o in read_out) / (READERS * sent),
        "images_via_shm_pct": 100.0 * sum(int(o[2]) for o in pub_out) / sent,
    }


def cross_host(seconds: float, settle_s: float) -> dict[str, float]:
    """Bytes/s one edge camera puts on the link: images kept local, and everything sent."""
    import tempfile
    from pathlib import Path

    from cellsight.config import load_config
    from cellsight.scenario_config import cell_config_of
    from drivers.sim.scenario import load_scenario
    from tests.hosts import CELL_IP, can_make_hosts, in_ns, rx_bytes, stop_all, two_hosts

    if not can_make_hosts():
        return dict.fromkeys(
            (
                "cross_host_bytes_per_s_per_camera",
                "cross_host_recorded_bytes_per_s_per_camera",
                "cross_host_everything_bytes_per_s_per_camera",
            ),
            float("nan"),
        )
    endpoint = f"tcp/{CELL_IP}:7447"
    me = [sys.executable, "-m", "benchmarks.transport", "--role"]
    with two_hosts("csbench") as (cell, edge), tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        (tmp_path / "base.toml").write_text(
            f'[cell]\nname = "{CELL}"\n[transport]\nconnect = ["{endpoint}"]\nshared_memory = false\n'
        )
        # The edge camera must outlive the three windows: the demo scenario ends at 30 s.
        scenario = tmp_path / "scenario.toml"
        scenario.write_text(demo_cell_text(settle_s + 3 * seconds + 60))
        cfg = cell_config_of(load_scenario(scenario), scenario, load_config(tmp_path / "base.toml"))
        (tmp_path / "cell.toml").write_text(cfg.to_toml())
        edge_cfg = cfg.model_copy(
            update={
                "cell": cfg.cell.model_copy(update={"role": "edge", "upstream": [endpoint]}),
                "transport": cfg.transport.model_copy(
                    update={"connect": ["tcp/127.0.0.1:7447"], "shared_memory": True}
                ),
                "cameras": [c.model_copy(update={"prerender_frames": 30}) for c in cfg.cameras if c.id == "cam1"],
            }
        )
        (tmp_path / "edge.toml").write_text(edge_cfg.to_toml())
        procs = [in_ns(cell, me + ["router", endpoint, "0", str(3 * seconds + 120)])]
        time.sleep(1.0)
        procs.append(
            in_ns(
                cell, [sys.executable, "-m", "cellsight.cli", "estimator", "--cell-config", str(tmp_path / "cell.toml")]
            )
        )
        procs.append(
            in_ns(
                edge,
                [
                    sys.executable,
                    "-m",
                    "cellsight.cli",
                    "run",
                    str(tmp_path / "edge.toml"),
                    "--out",
                    str(tmp_path / "edge"),
                ],
            )
        )
        try:
            time.sleep(settle_s)  # pre-rendering, then the camera at its rate

            def rate() -> float:
                before, t0 = rx_bytes(cell), time.monotonic()
                time.sleep(seconds)
                return (rx_bytes(cell) - before) / (time.monotonic() - t0)

            kept = rate()
            recorder = in_ns(
                cell,
                [
                    sys.executable,
                    "-m",
                    "cellsight.cli",
                    "record",
                    "--out",
                    str(tmp_path / "cell.mcap"),
                    "--max-image-hz",
                    str(RECORDED_IMAGE_HZ),
                    "--cell-config",
                    str(tmp_path / "cell.toml"),
                ],
            )
            time.sleep(2.0)
            recorded = rate()
            stop_all([recorder])
            everything = in_ns(cell, me + ["reader", endpoint, "0", str(seconds + 10)])
            time.sleep(2.0)
            sent = rate()
            everything.wait(seconds + 30)
        finally:
            stop_all(procs)
    return {
        "cross_host_bytes_per_s_per_camera": kept,
        "cross_host_recorded_bytes_per_s_per_camera": recorded,
        "cross_host_everything_bytes_per_s_per_camera": sent,
        "cross_host_everything_over_kept_ratio": sent / kept,
    }


def run(quick: bool) -> dict[str, float]:
    seconds = 5.0 if quick else 30.0
    shm, plain = one_run(True, seconds), one_run(False, seconds)
    figures: dict[str, float] = {"seconds": seconds}
    figures.update({f"shm_{k}": v for k, v in shm.items()})
    figures.update({f"plain_{k}": v for k, v in plain.items()})
    figures["plain_over_shm_cpu_ratio"] = plain["cpu_s_per_s_total"] / shm["cpu_s_per_s_total"]
    figures.update(cross_host(5.0, 12.0) if quick else cross_host(15.0, 25.0))
    return figures


def _role(argv: list[str]) -> None:
    role, endpoint, flag, seconds = argv[:4]
    shm, secs = flag == "1", float(seconds)
    if role == "publisher":
        publisher(endpoint, shm, argv[4], secs)
    elif role == "reader":
        reader(endpoint, shm, secs)
    else:
        router(endpoint, shm, secs)


#: The rows of ``docs/performance.md`` this benchmark's recorded runs give.
ROWS = (
    Row(
        "shm_cpu_s_per_s_total",
        "4 cameras x 30 Hz of VGA RGB-D through the router to 2 decoding readers, CPU seconds "
        "per second of every process, shared memory (plain bytes in the same run: {plain_cpu_s_per_s_total})",
    ),
    Row("plain_over_shm_cpu_ratio", "plain bytes over shared memory, CPU", ">= 1", lambda v: v >= 1),
    Row("shm_images_received_pct", "images the readers received, shared memory", "100", lambda v: v >= 100),
    Row(
        "cross_host_bytes_per_s_per_camera",
        "an edge host's simulated camera at 30 Hz, bytes a second crossing the "
        "link to the cell host with images kept on the edge (markers, camera info, status); everything sent, same run: "
        "{cross_host_everything_bytes_per_s_per_camera}",
        "< 1 MB/s",
        lambda v: v < 1e6,
    ),
    Row(
        "cross_host_recorded_bytes_per_s_per_camera",
        "the same with the cell host's recorder keeping 2 images a second "
        "(`run --record`'s default): it subscribes to a camera's images only while one is due",
    ),
)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--role":
        _role(sys.argv[2:])
    else:
        main("transport", __doc__.splitlines()[0], run)
