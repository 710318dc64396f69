"""Online links: an object marker seen by two cameras at one instant joins the daemon's graph.

The small wall cell of ``test_bounded_history`` (anchor 0 and markers 1-3 on the wall y = 2,
cameras a and b 0.6 m apart) plus marker 9 on an object sliding in front of them, seen by both
on the same frame clock; b sees two wall markers only. Known answers: with links b's rotation is
better determined (the object's positions at different instants constrain it) and both cameras
still agree with the truth within their covariance; the graph holds at most ``max_live``
instants; a camera that moves takes its segment's instants out with it. Those take every instant
(``min_gain`` 0); the gate's own tests come last.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np
import pytest

from estimator.config import LinkConfig
from estimator.graph import Estimator
from estimator.links import Sighting, instant_gain
from estimator.observation import Observation
from estimator.symbols import camera_symbol
from schemas.geometry import invert_pose, make_pose, rpy_matrix
from tests.core.test_bounded_history import COV, RATE, SIGMA_M, SIGMA_RAD, cam_pose, config, frame

OBJECT = 9
SEEN = {"a": [0, 1, 2, 3], "b": [0, 3]}


def object_marker(t_s: float) -> np.ndarray:
    """Marker 9 on an object 1 m in front of the wall, sliding 0.4 m along it and back every 4 s."""
    return make_pose(rpy_matrix(np.pi / 2, 0.0, 0.0), [0.6 + 0.2 * np.sin(np.pi * t_s / 2), 1.0, 0.8])


def run(
    est: Estimator,
    seconds: float,
    poses: dict[str, np.ndarray],
    rng: np.random.Generator,
    start: int = 0,
    object_at: Callable[[float], np.ndarray] = object_marker,
) -> int:
    """Frames of both cameras at 30 Hz from frame index ``start``, the object marker at
    ``object_at(t_s)``, an update every 3; returns the next index."""
    k = start
    for k in range(start, start + int(seconds * RATE)):
        stamp = k * 1_000_000_000 // RATE
        for cid, wTc in poses.items():
            obs = frame(cid, stamp, wTc, SEEN[cid], rng)
            T = invert_pose(wTc) @ object_at(k / RATE)
            noisy = T @ make_pose(rpy_matrix(*(rng.normal(size=3) * SIGMA_RAD)), rng.normal(size=3) * SIGMA_M)
            est.add_frame(cid, stamp, obs + [Observation(cid, stamp, OBJECT, noisy, COV)])
        if k % 3 == 0:
            est.update(stamp)
    return k + 1


def rotation_variance(est: Estimator, cid: str) -> float:
    """Trace of the marginal rotation covariance (rad^2) of camera ``cid``'s current segment."""
    key = camera_symbol(est.camera_index[(cid, est.tracks[cid].segment)])
    return float(np.trace(est.isam.marginalCovariance(key)[:3, :3]))  # gtsam order: rotation first


def test_links_enter_the_graph_bounded_and_tighten_the_cameras() -> None:
    poses = {"a": cam_pose(0.3), "b": cam_pose(0.9)}
    results = {}
    for online in (True, False):
        est = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=online, max_live=20, min_gain=0.0)))
        run(est, 8.0, poses, np.random.default_rng(5))
        results[online] = est
    linked, plain = results[True], results[False]
    assert plain.live_links is None and plain.counters.links == 0
    # Five instants a second, less the last half second's and those at the ends of the slide,
    # where the object moves under NEW_VIEW_M between instants (30 of 37).
    assert linked.counters.links > 20
    assert len(linked.live_links.live) == 20  # bounded: the oldest left the graph
    objects = [k for k in linked.isam.calculateEstimate().keys() if gtsam.Symbol(k).chr() == ord("o")]
    assert len(objects) == 20, "a dropped instant's variable must leave iSAM2 with its factors"
    for cid in ("a", "b"):
        for est in (linked, plain):
            pose = est.estimate(8_000_000_000).cameras[cid].pose
            d = pose.T[:3, 3] - poses[cid][:3, 3]
            assert d @ np.linalg.solve(pose.covariance[:3, :3], d) <= 16.27, f"{cid}: {1e3 * d} mm off"  # 3 dof, 99.9 %
    # The links add information. Not much: a camera's sightings of one marker count at most
    # max_fused (4) frames together, as a static pair's do (0.79 here, deterministic to 1e-3).
    assert rotation_variance(linked, "b") < 0.9 * rotation_variance(plain, "b"), (
        rotation_variance(linked, "b"),
        rotation_variance(plain, "b"),
    )


def test_a_camera_that_moves_takes_its_links_with_it() -> None:
    poses = {"a": cam_pose(0.3), "b": cam_pose(0.9)}
    rng = np.random.default_rng(7)
    est = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=True, max_live=50, min_gain=0.0)))
    k = run(est, 4.0, poses, rng)
    assert est.live_links.live and all(
        f.segment == ("a", 0) for i in est.live_links.live for f in i.factors if f.segment[0] == "a"
    )
    poses["a"] = cam_pose(0.3, make_pose(rpy_matrix(0.0, np.radians(1.0), 0.0), [0.03, 0.0, 0.0]))
    run(est, 4.0, poses, rng, start=k)
    assert est.tracks["a"].segment == 1
    segments = {f.segment for i in est.live_links.live for f in i.factors}
    assert ("a", 0) not in segments and ("a", 1) in segments, segments
    e = est.estimate(k * 1_000_000_000 // RATE + 4_000_000_000)
    for cid in ("a", "b"):
        d = e.cameras[cid].pose.T[:3, 3] - poses[cid][:3, 3]
        assert np.linalg.norm(d) < 0.005, f"{cid} {1e3 * d} mm off after a's move"


def test_a_still_object_links_once() -> None:
    """Instants of an object that stands still repeat one view: its noise would average over them
    but a bias would not, so only the first enters (then one per NEW_VIEW_M the object moves)."""
    poses = {"a": cam_pose(0.3), "b": cam_pose(0.9)}
    est = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=True, min_gain=0.0)))
    run(est, 4.0, poses, np.random.default_rng(3), object_at=lambda t_s: object_marker(0.0))
    assert est.counters.links == 1
    # Refused ones count as judged: a still object is weighed once, not at every instant (b sees all four markers)
    SEEN["b"] = [0, 1, 2, 3]
    try:
        gated = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=True)))
        run(gated, 4.0, poses, np.random.default_rng(3), object_at=lambda t_s: object_marker(0.0))
    finally:
        SEEN["b"] = [0, 3]
    assert (gated.counters.links, gated.counters.links_refused) == (0, 1), gated.counters


def sighting(camera_T_marker: np.ndarray, position_sigma_m: float) -> Sighting:
    cov = np.diag([position_sigma_m**2] * 3 + [0.01] * 3)
    return Sighting("x", 0, 0, camera_T_marker, camera_T_marker, cov)


def test_instant_gain_known_answers() -> None:
    """Two cameras whose positions are independent with sigma p each, sightings of sigma m each:
    the difference of where they put the marker has variance 2 p^2 per axis and the instant
    measures it with 2 m^2, so it removes 2 p^2 / (2 p^2 + 2 m^2) of it; cameras that move as one
    (fully correlated) leave nothing to learn; a third, unknown, camera makes it ~1."""
    T = np.stack(
        [make_pose(rpy_matrix(0.1, 0.2, 0.3), [0.0, 0.0, 0.0]), make_pose(rpy_matrix(-0.2, 0.0, 1.0), [1.0, 0.0, 0.0])]
    )
    s = [sighting(make_pose(np.eye(3), [0.0, 0.0, 0.0]), 0.002)] * 2  # at each camera's origin: rotation plays no part
    p = 0.003
    joint = np.zeros((12, 12))
    joint[3:6, 3:6] = joint[9:12, 9:12] = np.eye(3) * p**2  # gtsam order: rotation, then translation
    assert abs(instant_gain(T, s, [1.0, 1.0], joint) - 2 * p**2 / (2 * p**2 + 2 * 0.002**2)) < 1e-12
    assert abs(instant_gain(T, s, [4.0, 4.0], joint) - 2 * p**2 / (2 * p**2 + 8 * 0.002**2)) < 1e-12  # repeats weigh in
    # camera poses perturbed in their own frames: identical perturbations mean one world offset only if
    # the rotations agree, so take equal rotations for the correlated case
    same = np.stack([T[0], T[0]])
    correlated = np.tile(np.eye(6) * p**2, (2, 2))
    assert instant_gain(same, s, [1.0, 1.0], correlated) == 0.0
    three = np.zeros((18, 18))
    three[:12, :12] = joint
    three[12:, 12:] = np.eye(6) * 1e6
    assert instant_gain(np.concatenate([T, T[:1]]), [s[0]] * 3, [1.0] * 3, three) > 0.999


@pytest.mark.slow
def test_links_enter_only_where_they_add() -> None:
    """b seeing two wall markers (its rotation about the line through them weak): the first
    instant removes most of what the graph does not know and enters, and the later ones, which
    would add little, stay out; b seeing all four: none enters. What enters still tightens b."""
    poses = {"a": cam_pose(0.3), "b": cam_pose(0.9)}
    for seen_b, entered in (([0, 3], (1, 3)), ([0, 1, 2, 3], (0, 0))):
        SEEN["b"] = seen_b
        try:
            gated = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=True)))
            run(gated, 8.0, poses, np.random.default_rng(5))
            plain = Estimator(config(object_markers=[OBJECT], links=LinkConfig(online=False)))
            run(plain, 8.0, poses, np.random.default_rng(5))
        finally:
            SEEN["b"] = [0, 3]
        assert entered[0] <= gated.counters.links <= entered[1], (seen_b, gated.counters)
        assert gated.counters.links_refused > 25, (seen_b, gated.counters)  # of the ~35 new views
        if gated.counters.links:
            assert rotation_variance(gated, "b") < 0.9 * rotation_variance(plain, "b")
