"""Well-formed messages with absurd content, on a real zenoh bus: each finding of the wire review
(finite but absurd values, ids that are not the key's, stamps MCAP cannot hold) is refused where
it enters, counted by key and reason, and shown; nothing that was running stops."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pytest

from cellsight.evaluation.synthetic import NoiseSettings, estimator_config, frame_observations, observations_msg
from cellsight.record import Recorder
from cellsight.status import StatusBoard
from drivers.sim.scenario import CameraSpec, MarkerSpec, Scenario
from estimator.service import EstimatorService
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from schemas.log import ReadReport, read_log
from schemas.spec import PoseSpec
from tests.helpers import wait_until

CELL = "wire"


def scene() -> Scenario:
    wall = lambda i, x, role="static": MarkerSpec(  # noqa: E731
        id=i, role=role, side_m=0.25, pose=PoseSpec(position=(x, 2.0, 1.0), normal=(0.0, -1.0, 0.0))
    )
    return Scenario(
        markers=[wall(0, -0.6, "anchor"), wall(1, 0.0), wall(2, 0.6), wall(3, 1.2)],
        cameras=[CameraSpec(id="cam1", pose=PoseSpec(position=(0.0, 0.0, 1.2), look_at=(0.3, 2.0, 1.0)))],
    )


def good_frames(s: Scenario, n: int, start_ns: int, camera: str = "cam1") -> list[m.MarkerObservations]:
    rng = np.random.default_rng(0)
    out = []
    for k in range(n):
        stamp = start_ns + int(k * 1e9 / 30)
        out.append(observations_msg(camera, stamp, frame_observations(s, "cam1", 0.0, stamp, rng, NoiseSettings())))
    return out


@pytest.mark.slow
def test_absurd_positions_and_a_ghost_camera_are_refused_and_the_estimator_runs_on(
    client_transport: TransportConfig,
) -> None:
    """z = 1e300 (finite) made the estimator exit on its own output check; z = 1e6 m made iSAM2's
    system indeterminate; ``ghost_cam`` on cam1's key became a camera. Now each is refused at the
    subscription or the frame check, counted by key and reason in the estimator's status, and
    ``cellsight status`` lists the refusals."""
    s = scene()
    now = time.time_ns()
    frames = good_frames(s, 60, now - 2_000_000_000)
    far = good_frames(s, 1, now - 3_000_000_000)[0]  # the camera's first frame: iSAM2 met it (ill-posed)
    for o in far.markers:
        o.camera_T_marker.z = 1e300
    very_far, ghost = (good_frames(s, 1, now - 1_000_000_000)[0] for _ in range(2))
    very_far.markers[1].camera_T_marker.z = 1e6
    ghost.camera_id = "ghost_cam"
    with (
        Bus(client_transport, CELL) as svc_bus,
        Bus(client_transport, CELL) as driver,
        Bus(client_transport, CELL) as viewer,
    ):
        svc = EstimatorService(svc_bus, estimator_config(s, update_hz=20.0))
        board = StatusBoard(viewer)
        pub = driver.publisher(keys.markers(CELL, "cam1"))
        time.sleep(0.5)  # routes
        driver.session.put(keys.markers(CELL, "cam1"), far.SerializeToString())
        for k, msg in enumerate(frames):
            pub.put(msg)
            if k == 30:
                for bad in (very_far, ghost):
                    driver.session.put(keys.markers(CELL, "cam1"), bad.SerializeToString())
        wait_until(lambda: svc._sub.received + sum(svc._sub.bad.values()) >= 63, 5.0, "every frame at the estimator")
        svc.step()
        svc._last_map = -1.0  # the next step publishes the status now
        est = svc.step()
        wait_until(lambda: board.estimator is not None and board.estimator.rejections, 5.0, "the estimator's status")
        refused = board.refused()
    assert set(est.cameras) == {"cam1"}, "a message's camera_id must be its key's"
    assert est.cameras["cam1"].pose is not None
    key = keys.markers(CELL, "cam1")
    assert refused[key, "out_of_bounds"] == 2 and refused[key, "id_mismatch"] == 1, refused


@pytest.mark.slow
def test_a_negative_stamp_is_refused_by_the_recorder_and_the_log_reads_to_its_end(
    client_transport: TransportConfig, tmp_path: Path
) -> None:
    """``stamp_ns = -5`` made the MCAP writer fail half-way through a record: the log could not be read
    past it and the run's summary was built from a quarter of its messages. Now the message is
    refused and counted, and every message after it is in the log."""
    path = tmp_path / "log.mcap"
    s = scene()
    frames = good_frames(s, 40, time.time_ns() - 2_000_000_000)
    frames[20].stamp_ns = -5
    frames[25].stamp_ns = 2**63 - 1  # far future: a year from now is not a clock
    with Bus(client_transport, CELL) as rec_bus, Bus(client_transport, CELL) as pub_bus:
        rec = Recorder(rec_bus, path)
        pub = pub_bus.publisher(keys.markers(CELL, "cam1"))
        time.sleep(0.5)
        for msg in frames:
            pub.put(msg)
        wait_until(lambda: rec.messages + sum(rec.refused.values()) >= 40, 5.0, "every message at the recorder")
        rec.close()
    report = ReadReport()
    stamps = [lm.msg.stamp_ns for lm in read_log(path, None, report)]
    assert report.stopped_early is None, "a cleanly stopped recording has its footer"
    assert stamps == [f.stamp_ns for k, f in enumerate(frames) if k not in (20, 25)]
    assert rec.refused == {(keys.markers(CELL, "cam1"), "stamp"): 2}


@pytest.mark.slow
def test_ten_thousand_unknown_marker_ids_write_a_few_lines_not_ten_thousand(
    client_transport: TransportConfig, caplog
) -> None:
    s = scene()
    msg = good_frames(s, 1, time.time_ns())[0]
    with Bus(client_transport, CELL) as svc_bus:
        svc = EstimatorService(svc_bus, estimator_config(s))
        items = []
        for k in range(10_000):
            frame = m.MarkerObservations()
            frame.CopyFrom(msg)
            frame.stamp_ns += k * 1000
            for j, item in enumerate(frame.markers):
                item.marker_id = 100 + 4 * k + j
            items.append(frame)
        from schemas.bus import Received

        with caplog.at_level(logging.WARNING, logger="estimator"):
            svc.ingest([Received(keys.markers(CELL, "cam1"), f, f.stamp_ns) for f in items])
    unknown = [r for r in caplog.records if "not in the configuration" in r.getMessage()]
    assert svc.estimator.counters.unknown_markers == sum(len(f.markers) for f in items)
    assert len(unknown) == 10, len(unknown)
