"""A bounded fuzz (``benchmarks.fuzz`` runs the long one): messages hypothesis draws over every field
of the camera topics, into a running estimator, recorder and status board on a real bus, and
into ``resolve``. Nothing raises, nothing stops, the recording reads to its footer, and the
estimate of the real camera is what it was."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

from benchmarks.fuzz import generate
from cellsight.config import CellConfig
from cellsight.evaluation.resolve_report import run_resolve
from cellsight.evaluation.synthetic import NoiseSettings, estimator_config, frame_observations, observations_msg
from cellsight.record import Recorder
from cellsight.scenario_config import cell_config_of
from cellsight.status import StatusBoard
from drivers.sim.scenario import CameraSpec, MarkerSpec, Scenario
from estimator.service import EstimatorService
from schemas import keys
from schemas.bus import Bus, TransportConfig
from schemas.log import LogWriter, ReadReport, read_log
from schemas.spec import PoseSpec
from tests.helpers import wait_until

CELL = "fuzz"  # the benchmark's cell: its keys


def scene() -> Scenario:
    wall = lambda i, x, role="static": MarkerSpec(  # noqa: E731
        id=i, role=role, side_m=0.15, pose=PoseSpec(position=(x, 2.0, 1.0), normal=(0.0, -1.0, 0.0))
    )
    return Scenario(
        markers=[wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2, "anchor")],
        cameras=[CameraSpec(id="cam1", pose=PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.3, 2.0, 1.0)))],
    )


@pytest.fixture(scope="module")
def fuzzed() -> list[tuple[str, bytes]]:
    return generate(400, seed=7)


def run_cell(
    transport: TransportConfig, tmp_path: Path, messages: list[tuple[str, bytes]]
) -> tuple[np.ndarray, EstimatorService, Path]:
    """cam1's frames at 30 Hz with ``messages`` spread between them, into a running estimator, a
    recorder and a status board; returns cam1's final pose, the service and the recording."""
    s = scene()
    rng = np.random.default_rng(0)
    path = tmp_path / f"log{len(list(tmp_path.glob('*.mcap')))}.mcap"
    with Bus(transport, CELL) as svc_bus, Bus(transport, CELL) as driver, Bus(transport, CELL) as viewer:
        svc = EstimatorService(svc_bus, estimator_config(s, update_hz=20.0))
        rec = Recorder(viewer, path)
        board = StatusBoard(viewer)
        stop = threading.Event()
        failed: list[BaseException] = []

        def run() -> None:
            try:
                svc.run(stop)
            except BaseException as exc:  # the test's failure, not the thread's death
                failed.append(exc)

        thread = threading.Thread(target=run)
        thread.start()
        pub = driver.publisher(keys.markers(CELL, "cam1"))
        try:
            time.sleep(0.5)
            start, t0 = time.time_ns(), time.monotonic()
            raw = {}
            for k in range(30 + len(messages) // 10):
                time.sleep(max(t0 + k / 30 - time.monotonic(), 0.0))  # a driver's pace, stamped as sent
                stamp = start + int(k * 1e9 / 30)
                pub.put(
                    observations_msg(
                        "cam1", stamp, frame_observations(s, "cam1", 0.0, stamp, rng, NoiseSettings()), side_m=0.15
                    )
                )
                for key, payload in messages[max(k - 30, 0) * 10 : max(k - 29, 0) * 10]:
                    raw.setdefault(key, driver.session.declare_publisher(key)).put(payload)
            wait_until(lambda: rec.messages >= 30, 5.0, "the recorder")
            time.sleep(0.5)
            board.table(viewer.alive())  # draws whatever arrived
            after = svc.estimator.estimate(svc.clock.now()).cameras["cam1"].pose.T
        finally:
            stop.set()
            thread.join(10)
            rec.close()
    assert not failed, failed
    assert not thread.is_alive()
    return after, svc, path


@pytest.mark.slow
def test_fuzzed_messages_stop_nothing_and_leave_the_estimate_as_it_was(
    client_transport: TransportConfig, tmp_path: Path, fuzzed: list[tuple[str, bytes]]
) -> None:
    """The same frames of cam1 with the fuzz between them, and with as many undecodable payloads on
    the same keys (the control): cam1 ends where the control does, within its noise."""
    truth = scene().camera("cam1").world_T_camera(0.0)[:3, 3]
    control, _, _ = run_cell(client_transport, tmp_path, [(k, b"\xff") for k, _ in fuzzed])
    after, svc, log = run_cell(client_transport, tmp_path, fuzzed)
    err_control, err_fuzzed = (float(np.linalg.norm(T[:3, 3] - truth)) for T in (control, after))
    assert err_fuzzed <= 1.2 * err_control + 0.0005, (err_control, err_fuzzed)
    assert sum(svc._sub.rejected.values()) + sum(svc.rejected.values()) > 0
    report = ReadReport()
    for _ in read_log(log, None, report):
        pass
    assert report.stopped_early is None


@pytest.mark.slow
def test_resolve_of_a_log_holding_every_fuzzed_message_ends_without_an_exception(
    tmp_path: Path, fuzzed: list[tuple[str, bytes]]
) -> None:
    s = scene()
    cfg = cell_config_of(s, base=CellConfig.model_validate({"cell": {"name": CELL}}))
    log = tmp_path / "log.mcap"
    w = LogWriter(log, metadata={"config": cfg.to_toml()})
    rng = np.random.default_rng(1)
    now = time.time_ns()
    for k in range(60):
        stamp = now + int(k * 1e9 / 30)
        w.write(
            keys.markers(CELL, "cam1"),
            observations_msg("cam1", stamp, frame_observations(s, "cam1", 0.0, stamp, rng, NoiseSettings()), 0.15),
            stamp,
        )
    for k, (key, payload) in enumerate(fuzzed):
        w.write_raw(key, keys.message_type(key), payload, now + k, now + k)
    w.close()
    run = run_resolve(log, tmp_path / "out", cfg)
    assert run.result.frames >= 60
    assert run.read.refused, "the fuzzed messages were not judged (test set-up)"
