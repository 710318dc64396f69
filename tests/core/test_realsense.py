"""The RealSense driver through librealsense's own pipeline, with no camera: rendered frames of the
demo cell go into a software device shaped like a D4xx, are recorded with ``rs.recorder``, and
the driver plays the recording back through ``rs.pipeline`` and ``rs.align`` as it would a device."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cellsight.scenario_config import cell_config_of
from drivers.errors import DriverError
from drivers.frames import Frame
from drivers.markers import MarkerDetector
from drivers.realsense import RealSenseSource, write_recording
from drivers.sim.scenario import load_scenario
from drivers.sim.source import SimSource
from schemas.geometry import pose_error

EPOCH_NS = 1_700_000_000_000_000_000


def rendered(camera: str, frames: int) -> list[Frame]:
    source = SimSource(load_scenario(), camera, epoch_ns=EPOCH_NS, realtime=False)
    return [source.read() for _ in range(frames)]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Frame]]:
    frames = rendered("cam1", 12)
    return write_recording(tmp_path_factory.mktemp("rs") / "cam1.db3", frames, serial="123456"), frames


def played_back(path: Path) -> list[Frame]:
    source = RealSenseSource("cam1", recording=path, real_time=False)
    frames = []
    while (f := source.read()) is not None:
        frames.append(f)
    source.close()
    return frames


def made_from(frame: Frame, frames: list[Frame]) -> Frame:
    """The rendered frame a played one came from (every render has noise of its own)."""
    return min(frames, key=lambda s: int(np.abs(s.rgb.astype(np.int16) - frame.rgb).sum()))


@pytest.mark.slow
def test_a_recording_plays_back_the_frames_pixel_for_pixel(recording: tuple[Path, list[Frame]]) -> None:
    path, frames = recording
    source = RealSenseSource("cam1", recording=path, real_time=False)
    assert source.serial == "123456" and source.depth_scale_m == pytest.approx(0.001)
    np.testing.assert_allclose(source.info.K, frames[0].info.K, atol=1e-4)  # librealsense keeps float32
    source.close()
    played = played_back(path)
    assert len(played) >= len(frames) - 1
    # Stamps: the device clock (ms from the first frame) mapped onto the host's, spacing kept.
    np.testing.assert_allclose(np.diff([f.stamp_ns for f in played]) / 1e6, 1000 / 30, atol=0.01)
    for f in played:
        src = made_from(f, frames)
        np.testing.assert_array_equal(f.rgb, src.rgb)
        # Aligned to colour (rs.align) through identity extrinsics: depth keeps its values; the
        # aligner's pixel-edge rounding leaves a few per cent empty and moves values at depth edges.
        kept = (f.depth_mm == src.depth_mm) | (f.depth_mm == 0)
        assert kept.mean() > 0.98 and (f.depth_mm == src.depth_mm).mean() > 0.9


def test_markers_from_the_recording_match_the_sim_drivers(recording: tuple[Path, list[Frame]]) -> None:
    """Same ids in every frame, poses within the front-end's own noise: the colour pixels are the
    same; depth differs where alignment leaves a pixel empty, which moves a depth-refined pose by
    up to about a millimetre (2 mm, 0.1 deg: ``benchmarks.markers``' p95 at 3 m is 2.1 mm)."""
    path, frames = recording
    detector = MarkerDetector(cell_config_of(load_scenario()).markers)
    for f in played_back(path)[-5:]:
        src = made_from(f, frames)
        ours = {d.marker_id: d for d in detector.detect(f.rgb, f.info, f.depth_mm)}
        sims = {d.marker_id: d for d in detector.detect(src.rgb, src.info, src.depth_mm)}
        assert set(ours) == set(sims) and len(ours) >= 3
        for mk in ours:
            mm, deg = pose_error(ours[mk].camera_T_marker, sims[mk].camera_T_marker)
            assert mm < 2.0 and deg < 0.1, (mk, mm, deg)


def test_a_missing_recording_or_device_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(DriverError, match="not a RealSense recording"):
        RealSenseSource("x", recording=tmp_path / "nothing.db3")
    with pytest.raises(DriverError, match="no RealSense 000000000000 on this host; devices found: none"):
        RealSenseSource("x", serial="000000000000")


def test_without_pyrealsense2_the_error_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # as if the extra were not installed
    with pytest.raises(DriverError, match=r"pip install 'cellsight\[realsense\]'"):
        RealSenseSource("x", serial="1")
