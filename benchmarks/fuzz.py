"""Fuzz: the worst a peer can send, into a running demo cell and into ``resolve``; the access matrix.

Three parts, one run:

1. **Access matrix**: a fresh secure profile, the real router, every cell of
   ``schemas.security.access_matrix`` tried with each role's certificate (``cellsight.access_probe``):
   ``acl_cells_tested``, ``acl_violations``.
2. **A running cell**: the demo cell under ``cellsight run --record`` (the local profile: any
   process may put anything). After a fault-free window (the baseline), ``--messages`` fuzzed
   messages (hypothesis, ``fuzzed``) go onto the cameras' and ghost cameras' markers, status,
   camera_info and images, and (a quarter of them) onto the cell-wide keys (tf, estimates,
   objects, points, truth): well-formed protobuf whose fields are drawn from extremes (NaN,
   infinities, 1e300, subnormals, negative and far-future stamps, huge counts, ids of other cameras
   and of none) and from plausible values. ``processes_exited`` (any process of the cell not
   running at the end, or replaced) and ``supervisor_restarts`` must be 0;
   ``camera_error_over_baseline_max`` is each camera's median position error against the
   scenario's truth, as the estimator answers ``estimate/map`` (forged puts answer no query), in the
   window after the fuzz over the one before, the worst camera; ``rejected_by_reason_*`` are the
   estimator's refusals (its status).
3. **Logs**: every part the recorder wrote reads to its footer (``unreadable_logs``), and
   ``cellsight resolve`` of the recording and of a log holding every fuzzed message (as written by
   ``LogWriter``, with times MCAP can hold) ends with exit code 0 or 1 and no traceback
   (``resolve_exceptions``).

``--quick`` fuzzes 600 messages; the full run 10,000.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.common import Row, launch_demo_cell, main
from schemas import codec, keys
from schemas import messages as m
from schemas.limits import REASONS

CELL = "fuzz"
CAMERAS = ("cam1", "cam2", "cam3", "cam4")
GHOSTS = ("ghost_cam", "cam1x")
#: The demo's cameras move and are bumped in the first 15 s; the windows come after.
SETTLE_S, WINDOW_S = 20.0, 8.0

# ---------------------------------------------------------------- what is drawn

#: Floats a field may take: extremes first (hypothesis also shrinks towards them), then plausible ones.
EXTREMES = (
    0.0,
    -0.0,
    1.0,
    -1.0,
    1e300,
    -1e300,
    1e6,
    -1e6,
    5e-324,
    1e-40,
    101.0,
    float("nan"),
    float("inf"),
    float("-inf"),
)
floats = st.one_of(st.sampled_from(EXTREMES), st.floats(-5.0, 5.0), st.floats(allow_nan=True, allow_infinity=True))
uint32 = st.one_of(st.sampled_from((0, 1, 2**31, 2**32 - 1)), st.integers(0, 2**32 - 1))
uint64 = st.one_of(st.sampled_from((0, 2**63, 2**64 - 1)), st.integers(0, 2**64 - 1))
camera_ids = st.sampled_from(CAMERAS + GHOSTS + ("", "x" * 200, "a/b", "cam 1"))


@st.composite
def stamps(draw) -> int:
    """Mostly near now (so the rest of the message is what gets judged), else anything an int64 holds."""
    if draw(st.booleans()):
        return time.time_ns() + draw(st.integers(-2 * 10**9, 10**8))
    return draw(st.one_of(st.sampled_from((-5, 0, 1, 2**63 - 1, -(2**63))), st.integers(-(2**63), 2**63 - 1)))


@st.composite
def marker(draw, item: m.MarkerObservation) -> None:
    item.marker_id = draw(st.one_of(st.integers(0, 40), uint32))  # the demo's ids are small: some known
    item.side_m = draw(st.one_of(st.just(0.15), floats))
    item.corners_px.extend(draw(st.lists(floats, min_size=0, max_size=10)) if draw(st.booleans()) else [300.0] * 8)
    pose = item.camera_T_marker
    pose.x, pose.y = draw(st.one_of(st.just(0.1), floats)), draw(st.one_of(st.just(0.0), floats))
    pose.z = draw(st.one_of(st.floats(0.3, 4.0), floats))
    if draw(st.booleans()):
        pose.qw = 1.0
    else:
        pose.qx, pose.qy, pose.qz, pose.qw = (draw(floats) for _ in range(4))
    sigma = draw(st.one_of(st.just(0.003), floats))
    size = draw(st.sampled_from((36, 36, 36, 0, 35, 37)))
    with np.errstate(all="ignore"):  # sigma may be 1e300 or NaN: that is the point
        values = (np.eye(6) * sigma * sigma).reshape(36).tolist()[:size] + [draw(floats)] * max(size - 36, 0)
    if size == 36 and draw(st.booleans()):
        values[draw(st.integers(0, 35))] = draw(floats)
    item.covariance.extend(values)
    item.ambiguous = draw(st.booleans())


def own_or_other(camera: str) -> st.SearchStrategy[str]:
    """The key's own camera id half the time (so the rest of the message is what gets judged), else any."""
    return st.one_of(st.just(camera), camera_ids)


@st.composite
def marker_observations(draw, camera: str) -> m.MarkerObservations:
    msg = m.MarkerObservations(
        camera_id=draw(own_or_other(camera)),
        stamp_ns=draw(stamps()),
        image_width=draw(uint32),
        image_height=draw(uint32),
    )
    for _ in range(draw(st.sampled_from((0, 1, 2, 3, 5, 40)))):
        draw(marker(msg.markers.add()))
    return msg


@st.composite
def driver_status(draw, camera: str) -> m.DriverStatus:
    return m.DriverStatus(
        camera_id=draw(own_or_other(camera)),
        stamp_ns=draw(stamps()),
        state=draw(st.integers(0, 5)),
        source="fuzz",
        rate_hz=draw(floats),
        frames=draw(uint64),
        dropped=draw(uint64),
        message=draw(st.text(max_size=50)),
    )


@st.composite
def camera_info(draw, camera: str) -> m.CameraCalibration:
    msg = m.CameraCalibration(
        frame_id=draw(own_or_other(camera)), width=draw(uint32), height=draw(uint32), distortion_model="plumb_bob"
    )
    if draw(st.booleans()):
        codec.stamp_to_timestamp(draw(stamps()), msg.timestamp)
    msg.K.extend(
        draw(st.lists(floats, min_size=0, max_size=12))
        if draw(st.booleans())
        else [525.0, 0, 320, 0, 525.0, 240, 0, 0, 1]
    )
    msg.D.extend(draw(st.lists(floats, max_size=8)))
    return msg


@st.composite
def image(draw, camera: str) -> m.RawImage:
    w, h = draw(st.sampled_from(((4, 3), (0, 3), (2**31, 1), (640, 480))))
    encoding = draw(st.sampled_from(("16UC1", "rgb8", "bgr8", "mono8", "yuv422", "")))
    msg = m.RawImage(
        frame_id=draw(own_or_other(camera)),
        width=w,
        height=h,
        encoding=encoding,
        step=draw(st.sampled_from((w * 2, w * 3, 0, 7))),
    )
    seconds = draw(st.one_of(st.just(time.time_ns() // 10**9), st.integers(-(2**63), 2**63 - 1)))
    msg.timestamp.seconds, msg.timestamp.nanos = seconds, draw(st.integers(0, 999_999_999))
    msg.data = bytes(draw(st.sampled_from((0, 24, 36, 100))))
    return msg


#: Camera topics a driver may put, and what is drawn for each.
TOPICS = {
    "markers": marker_observations,
    "status": driver_status,
    "camera_info": camera_info,
    "depth/image_raw": image,
    "color/image_raw": image,
}


frame_ids = st.sampled_from(("world", "cam1", "marker_0", "object_can", "", "x" * 200))


@st.composite
def pose(draw, msg: m.Pose) -> None:
    msg.x, msg.y, msg.z = (
        draw(st.one_of(st.floats(-3.0, 3.0), floats)),
        draw(floats),
        draw(st.one_of(st.floats(-3.0, 3.0), floats)),
    )
    if draw(st.booleans()):
        msg.qw = 1.0
    else:
        msg.qx, msg.qy, msg.qz, msg.qw = (draw(floats) for _ in range(4))


@st.composite
def poses(draw) -> m.PosesWithCovariance:
    """Camera, marker or truth poses, as the estimator or the simulator publishes them."""
    msg = m.PosesWithCovariance(stamp_ns=draw(stamps()))
    for _ in range(draw(st.sampled_from((0, 1, 3, 40)))):
        item = msg.poses.add(parent_frame_id="world", child_frame_id=draw(frame_ids), stamp_ns=draw(stamps()))
        draw(pose(item.pose))
        if draw(st.booleans()):
            sigma = draw(st.one_of(st.just(0.002), floats))
            with np.errstate(all="ignore"):
                item.covariance.extend(
                    (np.eye(6) * sigma * sigma).reshape(36).tolist()[: draw(st.sampled_from((36, 36, 35)))]
                )
    return msg


@st.composite
def transforms(draw) -> m.FrameTransforms:
    msg = m.FrameTransforms()
    for _ in range(draw(st.sampled_from((0, 1, 5)))):
        tr = msg.transforms.add(parent_frame_id="world", child_frame_id=draw(frame_ids))
        codec.stamp_to_timestamp(draw(stamps()), tr.timestamp)
        tr.translation.x, tr.translation.y, tr.translation.z = draw(floats), draw(floats), draw(floats)
        tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = (
            draw(floats),
            draw(floats),
            draw(floats),
            draw(floats),
        )
    return msg


@st.composite
def objects(draw) -> m.ObjectDetections:
    msg = m.ObjectDetections(stamp_ns=draw(stamps()))
    for _ in range(draw(st.sampled_from((0, 1, 3)))):
        det = msg.objects.add(object_id=draw(st.sampled_from(("can", "crate", "", "a/b"))), fitness=draw(floats), rmse_m=draw(floats),
                              stamp_ns=draw(stamps()))  # fmt: skip
        det.camera_ids.extend(draw(st.lists(camera_ids, max_size=3)))
        draw(pose(det.world_T_object))
    return msg


@st.composite
def estimator_status(draw) -> m.EstimatorStatus:
    msg = m.EstimatorStatus(
        stamp_ns=draw(stamps()), observations=draw(uint64), rejected=draw(uint64), update_ms=draw(floats)
    )
    for _ in range(draw(st.sampled_from((0, 1, 4)))):
        msg.cameras.add(
            camera_id=draw(camera_ids),
            state=draw(st.integers(0, 4)),
            position_sigma_m=draw(floats),
            last_stamp_ns=draw(stamps()),
        )
    return msg


@st.composite
def cloud(draw) -> m.PointCloud:
    n = draw(st.sampled_from((0, 3, 100)))
    xyz = np.array([[draw(floats) for _ in range(3)]] * n, dtype=np.float32).reshape(-1, 3) if n else np.zeros((0, 3))
    msg = codec.points_to_msg(
        draw(stamps()), "world", np.nan_to_num(xyz) if draw(st.booleans()) else xyz, np.zeros((n, 4), np.uint8)
    )
    if draw(st.booleans()):
        msg.data = msg.data[: draw(st.integers(0, len(msg.data)))]
    return msg


#: Cell-wide topics, and what is drawn for each: under the secure profile only their owner may put
#: them, on a cell without it anyone can.
CELL_TOPICS = {"tf": transforms, "estimate/cameras": poses, "estimate/markers": poses, "estimate/status": estimator_status,
               "objects": objects, "points": cloud, "truth/cameras": poses, "truth/marker_poses": poses}  # fmt: skip


@st.composite
def fuzzed(draw, cell: str = CELL, cell_wide: bool = True) -> tuple[str, bytes]:
    """(key, payload): a camera topic of a real or ghost camera, or (``cell_wide``) a cell-wide
    topic, and a message drawn for it."""
    if cell_wide and draw(st.integers(0, 3)) == 0:
        topic = draw(st.sampled_from(sorted(CELL_TOPICS)))
        key, strategy = keys.cell_topic(cell, topic), CELL_TOPICS[topic]()
    else:
        topic, camera = draw(st.sampled_from(sorted(TOPICS))), draw(st.sampled_from(CAMERAS + GHOSTS))
        key, strategy = keys.camera_topic(cell, camera, topic), TOPICS[topic](camera)
    try:
        with np.errstate(all="ignore"):
            payload = draw(strategy).SerializeToString()
    except (ValueError, OverflowError):  # protobuf refuses to hold some values (a uint32 field's range): garbage then
        payload = bytes(draw(st.binary(max_size=64)))
    return key, payload


def generate(n: int, seed: int) -> list[tuple[str, bytes]]:
    """``n`` fuzzed messages, drawn by hypothesis from ``fuzzed`` (repeatable for one seed)."""
    out: list[tuple[str, bytes]] = []

    @settings(max_examples=n, database=None, derandomize=False, deadline=None, suppress_health_check=list(HealthCheck))
    @given(fuzzed())
    def draw(item: tuple[str, bytes]) -> None:
        out.append(item)

    import hypothesis

    hypothesis.seed(seed)(draw)()
    return out[:n]


# ---------------------------------------------------------------- the runs


def acl_figures(tmp: Path) -> dict[str, float]:
    from cellsight.access_probe import probe
    from schemas.bus import TransportConfig, open_session
    from schemas.security import write_profile
    from tests.conftest import free_port

    profile = write_profile(tmp / "secure", CELL, listen=f"tls/127.0.0.1:{free_port()}")
    router = open_session(TransportConfig(zenoh_config=profile.router_config))
    try:
        result = probe(profile, CELL, f"tls/127.0.0.1:{free_port()}")
    finally:
        router.close()
    for cell, what in result.violations:
        print(f"ACL violation: {cell.role} {cell.operation} {cell.family}: {what}", file=sys.stderr)
    return {"acl_cells_tested": result.cells, "acl_violations": len(result.violations)}


class Errors:
    """Each camera's position error (m) against its true pose, per answer of the estimator's
    ``estimate/map`` queryable (polled: forged puts on ``estimate/cameras`` answer no query, and
    the truth comes from the scenario file, not from ``truth/`` keys the fuzz also puts on)."""

    def __init__(self, truth: dict[str, np.ndarray]) -> None:
        self.truth = truth
        self.samples: dict[str, list[tuple[float, float]]] = defaultdict(list)
        self.status: m.EstimatorStatus | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def poll(self, bus, period_s: float = 0.25) -> None:
        def loop() -> None:
            while not self._stop.wait(period_s):
                for reply in bus.query(keys.estimate_map(CELL), timeout_s=1.0):
                    now = time.monotonic()
                    self.status = reply.msg.status
                    for cam, p in codec.poses_from_msg(reply.msg.cameras).items():
                        if cam in self.truth:
                            self.samples[cam].append((now, float(np.linalg.norm(p.T[:3, 3] - self.truth[cam][:3, 3]))))

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)

    def median(self, cam: str, lo: float, hi: float) -> float:
        window = [e for t, e in list(self.samples[cam]) if lo <= t < hi]
        return float(np.median(window)) if window else float("nan")


def cell_figures(tmp: Path, messages: list[tuple[str, bytes]], rate_hz: float) -> tuple[dict[str, float], Path]:
    from benchmarks.soak import processes
    from drivers.sim.scenario import load_scenario
    from schemas.bus import Bus, TransportConfig

    proc, run_dir, port = launch_demo_cell(tmp, CELL, SETTLE_S + 2 * WINDOW_S + len(messages) / rate_hz + 60)
    scenario = load_scenario(tmp / "scenario.toml")  # the demo's cameras are still after 14 s
    errors, bus = Errors({c.id: c.world_T_camera(SETTLE_S) for c in scenario.cameras}), None
    try:
        t0 = time.monotonic()
        bus = Bus(TransportConfig(connect=[f"tcp/127.0.0.1:{port}"]), CELL)
        errors.poll(bus)
        before = processes(run_dir)
        time.sleep(max(t0 + SETTLE_S + WINDOW_S - time.monotonic(), 0.0))
        fuzz_from = time.monotonic()
        pubs = {}
        for k, (key, payload) in enumerate(messages):
            if key not in pubs:
                pubs[key] = bus.session.declare_publisher(key)
            pubs[key].put(payload)
            time.sleep(max(fuzz_from + (k + 1) / rate_hz - time.monotonic(), 0.0))
        fuzz_to = time.monotonic()
        time.sleep(WINDOW_S + 1.0)
        after = processes(run_dir)
        manifest = json.loads((run_dir / "processes.json").read_text())
        alive = {p["name"]: Path(f"/proc/{p['pid']}").exists() for p in manifest}
        proc.send_signal(signal.SIGTERM)
        proc.wait(120)
    finally:
        errors.stop()
        if bus is not None:
            bus.close()
        if proc.poll() is None:
            proc.kill()
    ratios = {
        cam: errors.median(cam, fuzz_to + 1.0, fuzz_to + 1.0 + WINDOW_S)
        / errors.median(cam, fuzz_from - WINDOW_S, fuzz_from)
        for cam in CAMERAS
    }
    reasons: Counter[str] = Counter()
    for r in errors.status.rejections if errors.status is not None else []:
        reasons[r.reason] += r.count
    figures = {
        "fuzzed_messages": len(messages),
        "fuzz_rate_hz": len(messages) / max(fuzz_to - fuzz_from, 1e-9),
        "processes_exited": sum(not ok for ok in alive.values()) + sum(before.get(n) != after.get(n) for n in before),
        "supervisor_restarts": sum(p["restarts"] for p in manifest),
        "camera_error_over_baseline_max": max(ratios.values()),
        **{
            f"camera_error_mm_after_{cam}": 1000 * errors.median(cam, fuzz_to + 1.0, fuzz_to + 1.0 + WINDOW_S)
            for cam in CAMERAS
        },
        **{f"rejected_by_reason_{reason}": reasons.get(reason, 0) for reason in REASONS},
        "rejected_total": sum(reasons.values()),
    }
    return figures, run_dir


def log_figures(run_dir: Path, messages: list[tuple[str, bytes]]) -> dict[str, float]:
    """Every recorded part reads to its footer; resolve of the recording and of every fuzzed message."""
    from schemas.log import LogWriter, ReadReport, read_log

    parts = sorted(run_dir.glob("log*.mcap"))
    unreadable = 0
    for part in parts:
        report = ReadReport()
        for _ in read_log(part, None, report):
            pass
        unreadable += report.stopped_early is not None
    every = run_dir / "every_fuzzed.mcap"
    from cellsight.evaluation.resolve_report import peek_config

    cfg = peek_config(parts[0]) if parts else None
    w = LogWriter(every, metadata={"config": cfg.to_toml()} if cfg is not None else None)
    now = time.time_ns()
    for k, (key, payload) in enumerate(messages):
        w.write_raw(key, keys.message_type(key), payload, now + k, now + k)  # times MCAP holds; stamps inside as drawn
    w.close()
    exceptions = 0
    for log in parts[:1] + [every]:
        out = subprocess.run(
            [sys.executable, "-m", "cellsight.cli", "resolve", str(log), "--out", str(log.with_suffix(".resolved"))],
            capture_output=True,
            text=True,
            timeout=1800,
        )
        if out.returncode not in (0, 1) or "Traceback" in out.stderr:
            exceptions += 1
            print(f"resolve {log.name}: exit {out.returncode}\n{out.stderr[-2000:]}", file=sys.stderr)
    return {"log_parts": len(parts), "unreadable_logs": unreadable, "resolve_exceptions": exceptions}


def run(quick: bool, args: argparse.Namespace | None = None) -> dict[str, float]:
    n = 600 if quick else (args.messages if args is not None else 10_000)
    messages = generate(n, seed=args.seed if args is not None else 0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        figures = acl_figures(tmp)
        cell, run_dir = cell_figures(tmp, messages, rate_hz=200.0 if quick else 500.0)
        figures |= cell | log_figures(run_dir, messages)
    return figures


#: The rows of ``docs/performance.md`` this benchmark's recorded runs give.
ROWS = (
    Row(
        "acl_violations",
        "cells of the access matrix (role x key family x put / subscribe / liveliness / query / "
        "answer) whose outcome at the real secure router differs from what the roles grant, of {acl_cells_tested}",
        "0",
        lambda v: v == 0,
    ),
    Row(
        "processes_exited",
        "processes of the running demo cell (`run --record`) not running, or replaced, after "
        "{fuzzed_messages} hypothesis-drawn messages ({fuzz_rate_hz} a second) on camera and cell-wide keys",
        "0",
        lambda v: v == 0,
    ),
    Row("supervisor_restarts", "restarts the cell's supervisor made meanwhile", "0", lambda v: v == 0),
    Row(
        "camera_error_over_baseline_max",
        "each camera's median position error against the scenario's truth (from the "
        "estimator's `estimate/map` answers) in the 8 s after the fuzz over the 8 s before, the worst camera",
        "<= 1.2",
        lambda v: v <= 1.2,
    ),
    Row("unreadable_logs", "recorded parts ({log_parts}) that do not read to their footer", "0", lambda v: v == 0),
    Row(
        "resolve_exceptions",
        "resolve of the recording and of a log holding every fuzzed message ending in a "
        "traceback or an exit code other than 0 and 1",
        "0",
        lambda v: v == 0,
    ),
    Row(
        "rejected_total",
        "the estimator's refusals: malformed {rejected_by_reason_malformed}, stamp "
        "{rejected_by_reason_stamp}, out of bounds {rejected_by_reason_out_of_bounds}, covariance "
        "{rejected_by_reason_covariance}, not rigid {rejected_by_reason_not_rigid}, not finite "
        "{rejected_by_reason_not_finite}, id mismatch {rejected_by_reason_id_mismatch}",
    ),
)


def _args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--messages", type=int, default=10_000, help="fuzzed messages in the full run (default 10,000)")
    parser.add_argument("--seed", type=int, default=0, help="hypothesis seed of the drawn messages")


if __name__ == "__main__":
    main("fuzz", __doc__.splitlines()[0], run, _args)
