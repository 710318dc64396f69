"""Plausible bounds at the validation point of each message type (``schemas.limits``): what a
sensor can send passes, what it cannot is refused with its reason."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from schemas import codec, keys
from schemas import messages as m
from schemas.errors import DecodeError
from schemas.limits import REASONS, WireLimits
from schemas.log import LogWriter, ReadReport, read_log

NOW = 1_765_000_000_000_000_000  # 2025-12-06, ns


def observation(z: float = 2.0, sigma: float = 0.002, camera: str = "cam1", stamp: int = NOW) -> m.MarkerObservations:
    msg = m.MarkerObservations(camera_id=camera, stamp_ns=stamp, image_width=640, image_height=480)
    o = msg.markers.add(marker_id=3, side_m=0.2)
    o.corners_px.extend([0.0] * 8)
    o.camera_T_marker.z, o.camera_T_marker.qw = z, 1.0
    o.covariance.extend((np.eye(6) * sigma**2).reshape(36).tolist())
    return msg


def reason(fn) -> str:
    with pytest.raises(DecodeError) as exc:
        fn()
    assert exc.value.reason in REASONS
    return exc.value.reason


def decode(msg) -> object:
    return codec.decode(msg.SerializeToString(), type(msg))


@pytest.mark.parametrize("z", [1e300, 1e6, -101.0])
def test_a_marker_beyond_the_cell_is_refused_and_one_inside_passes(z: float) -> None:
    assert reason(lambda: decode(observation(z=z))) == "out_of_bounds"
    decode(observation(z=99.0))


@pytest.mark.parametrize("sigma, ok", [(1e-7, False), (2e-6, True), (0.5, True), (150.0, False)])
def test_a_covariance_claiming_more_or_less_than_a_sensor_can_is_refused(sigma: float, ok: bool) -> None:
    """Standard deviations between 1e-6 and the cell's size (m; rad up to 10): a factor of 1e-40
    variance is an information of 1e40, which no solver can combine with a 1 cm prior."""
    if ok:
        decode(observation(sigma=sigma))
    else:
        assert reason(lambda: decode(observation(sigma=sigma))) == "covariance"


def test_a_covariance_sharp_along_a_diagonal_direction_is_refused() -> None:
    """The bound is on the smallest eigenvalue, not only the diagonal: two positions nearly
    perfectly correlated claim a direction known to far better than a micrometre."""
    msg = observation(sigma=0.01)
    cov = np.eye(6) * 1e-4
    cov[0, 1] = cov[1, 0] = 1e-4 * (1 - 1e-12)
    msg.markers[0].covariance[:] = cov.reshape(36).tolist()
    assert reason(lambda: decode(msg)) == "covariance"


def test_ids_counts_and_sizes_are_bounded() -> None:
    msg = observation()
    msg.markers[0].marker_id = 10**6
    assert reason(lambda: decode(msg)) == "out_of_bounds"
    msg = observation()
    msg.markers[0].side_m = 50.0
    assert reason(lambda: decode(msg)) == "out_of_bounds"
    img = codec.image_to_msg(np.zeros((2, 2), np.uint16), NOW, "cam1", "16UC1")
    img.width = 100_000
    assert reason(lambda: decode(img)) == "out_of_bounds"
    many = m.PosesWithCovariance(stamp_ns=NOW)
    for _ in range(5):
        many.poses.add(child_frame_id="x").pose.qw = 1.0
    assert reason(lambda: codec.check_on_key(many, None, NOW, WireLimits(max_items=4))) == "too_many"
    codec.check_on_key(many, None, NOW, WireLimits(max_items=5))


def test_a_pose_list_beyond_the_cell_is_refused() -> None:
    msg = codec.poses_to_msg(NOW, [codec.StampedPose("world", "cam1", NOW, np.eye(4))])
    msg.poses[0].pose.x = 1e9
    assert reason(lambda: decode(msg)) == "out_of_bounds"


def test_a_message_must_name_the_camera_of_its_key() -> None:
    for msg in (observation(camera="ghost_cam"), m.DriverStatus(camera_id="ghost_cam", stamp_ns=NOW)):
        assert reason(lambda: codec.check_on_key(msg, "cam1", NOW)) == "id_mismatch"
        codec.check_on_key(msg, "ghost_cam", NOW)


@pytest.mark.parametrize(
    "stamp, ok",
    [
        (-5, False),
        (0, False),
        (NOW - 3600 * 10**9, True),
        (NOW + 3600 * 10**9, True),
        (NOW + 2 * 86400 * 10**9, False),
        (2**63 - 1, False),
    ],
)
def test_stamps_lie_in_the_window_of_the_receivers_clock(stamp: int, ok: bool) -> None:
    """Up to a day ahead (a sensor clock stepped by an hour is taken back onto its timeline by the
    estimator); any positive stamp behind (a replay publishes a log's original stamps); a camera's
    frame must carry one."""
    msg = observation(stamp=stamp)
    if ok:
        codec.check_on_key(msg, "cam1", NOW)
    else:
        assert reason(lambda: codec.check_on_key(msg, "cam1", NOW)) == "stamp"


def test_an_unset_stamp_is_no_stamp_where_one_is_optional_and_an_age_limit_applies_when_set() -> None:
    codec.check_on_key(m.EstimatorStatus(), None, NOW)  # before the first frame the estimator has no clock
    old = observation(stamp=NOW - 10 * 86400 * 10**9)
    codec.check_on_key(old, "cam1", NOW)
    assert reason(lambda: codec.check_on_key(old, "cam1", NOW, WireLimits(max_stamp_age_s=86400.0))) == "stamp"


def test_a_time_mcap_cannot_hold_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    w = LogWriter(path)
    key = keys.markers("c", "cam1")
    w.write(key, observation(), NOW)
    assert reason(lambda: w.write_raw(key, m.MarkerObservations, observation().SerializeToString(), NOW, -5)) == "stamp"
    w.write(key, observation(stamp=NOW + 1), NOW + 1)
    w.close()
    report = ReadReport()
    assert [lm.msg.stamp_ns for lm in read_log(path, None, report)] == [NOW, NOW + 1]
    assert report.stopped_early is None


def test_a_log_reader_refuses_what_a_live_receiver_refuses_and_counts_it(tmp_path: Path) -> None:
    """The recorder's receive time (log_time) is the reader's clock."""
    path = tmp_path / "log.mcap"
    key = keys.markers("c", "cam1")
    with_time = time.time_ns()
    w = LogWriter(path)
    w.write(key, observation(stamp=with_time), with_time)
    w.write(key, observation(camera="ghost", stamp=with_time + 1), with_time + 1)
    w.write(key, observation(z=1e6, stamp=with_time + 2), with_time + 2)
    w.close()
    report = ReadReport()
    assert len(list(read_log(path, None, report))) == 1
    assert report.refused == {(key, "id_mismatch"): 1, (key, "out_of_bounds"): 1}
