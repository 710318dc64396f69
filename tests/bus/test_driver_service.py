"""A driver process's loop over a real router: what it publishes, and to whom."""

from __future__ import annotations

import cv2

from drivers.config import MarkerConfig
from drivers.service import DriverService, use_opencv_threads
from drivers.sim.scenario import load_scenario
from drivers.sim.source import SimSource
from schemas import keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from tests.helpers import wait_until

CELL = "drv"


def test_images_are_built_only_while_someone_subscribes(client_transport: TransportConfig) -> None:
    """Marker observations always go out; a frame's colour and depth only while a subscriber matches
    them (copying 1.5 MB a frame for nobody cost a driver as much as its message building)."""
    scenario = load_scenario()
    cam = scenario.cameras[0].id
    with Bus(client_transport, CELL) as drv_bus, Bus(client_transport, CELL) as client:
        source = SimSource(scenario, cam, realtime=False, prerender=1)
        driver = DriverService(drv_bus, source, cam, MarkerConfig(dictionary=scenario.dictionary))
        got: dict[str, int] = {"markers": 0, "color": 0, "depth": 0}

        def count(what: str):
            return lambda _r: got.__setitem__(what, got[what] + 1)

        client.subscribe(keys.markers(CELL, cam), m.MarkerObservations, callback=count("markers"))
        wait_until(lambda: driver._pub["markers"].wanted(), 5.0, "the markers subscriber to be matched")
        for _ in range(3):
            driver.step()
        wait_until(lambda: got["markers"] >= 3, 5.0, "three frames of marker observations")
        assert driver._pub["color"].published == driver._pub["depth"].published == 0

        client.subscribe(keys.color(CELL, cam), m.RawImage, callback=count("color"))
        client.subscribe(keys.depth(CELL, cam), m.RawImage, callback=count("depth"))
        wait_until(
            lambda: driver._pub["color"].wanted() and driver._pub["depth"].wanted(),
            5.0,
            "the image subscribers to be matched",
        )
        for _ in range(3):
            driver.step()
        wait_until(lambda: got["color"] >= 3 and got["depth"] >= 3, 5.0, "three colour and depth images")
        assert driver._pub["color"].published == driver._pub["depth"].published == 3


def test_truth_is_computed_only_while_someone_scores_against_it(client_transport: TransportConfig) -> None:
    scenario = load_scenario()
    cam = scenario.cameras[0].id
    with Bus(client_transport, CELL) as drv_bus, Bus(client_transport, CELL) as client:
        source = SimSource(scenario, cam, realtime=False, prerender=1)
        driver = DriverService(drv_bus, source, cam, MarkerConfig(dictionary=scenario.dictionary), publish_images=False)
        truth = driver._truth_pubs
        for _ in range(3):
            driver.step()
        assert sum(p.published for p in truth.values()) == 0
        # The estimator's subscription to every camera's markers wants none of the truth.
        client.subscribe(keys.all_cameras(CELL, "markers"), m.MarkerObservations)
        wait_until(lambda: driver._pub["markers"].wanted(), 5.0, "the markers subscriber to be matched")
        for _ in range(3):
            driver.step()
        assert sum(p.published for p in truth.values()) == 0
        seen: list[str] = []
        for what in ("cameras", "marker_poses"):
            client.subscribe(
                keys.truth(CELL, what), m.PosesWithCovariance, callback=lambda r, what=what: seen.append(what)
            )
        wait_until(
            lambda: truth["cameras"].wanted() and truth["marker_poses"].wanted(),
            5.0,
            "the truth subscribers to be matched",
        )
        for _ in range(3):
            driver.step()
        wait_until(
            lambda: seen.count("cameras") >= 3 and "marker_poses" in seen,
            5.0,
            "every frame's camera truth and the map's",
        )
        assert (
            truth["cameras"].published == 3 and truth["marker_poses"].published >= 1 and truth["objects"].published == 0
        )


def test_opencv_threads_zero_is_opencvs_default_pool_not_none() -> None:
    """``markers.opencv_threads``: 1 is one thread; 0 is OpenCV's pool over every core (OpenCV's own
    setNumThreads(0) would switch threading off)."""
    before = cv2.getNumThreads()
    try:
        use_opencv_threads(1)
        assert cv2.getNumThreads() == 1
        use_opencv_threads(0)
        assert cv2.getNumThreads() == cv2.getNumberOfCPUs()
    finally:
        cv2.setNumThreads(before)
