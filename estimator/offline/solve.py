"""Offline batch re-solve of a stream of marker observations (pure: observations in, result out).

The stream goes through the same ``Estimator`` as the daemon, which builds the camera segments,
resolves planar-PnP flips per pair and detects moved cameras. Its fused pair factors are the
sufficient statistics of the log, so memory stays bounded however long the log is. At the end,
Levenberg-Marquardt (robust Huber factors, from the incremental solution) solves the whole
problem to convergence, and gtsam's ``Marginals`` give every pose's covariance. Per pair the
whitened residual is kept for the report. Object markers are not in the map: their observations
go to a caller's sink and are placed through the solved cameras afterwards (``place_objects``).
Frames of a moving camera, which the daemon leaves out, and object markers that several cameras
see at one instant join the batch as poses of their own (``estimator.keyframes``,
``estimator.links``), and the problem is solved again with them.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from estimator.config import EstimatorConfig
from estimator.estimate import through_camera
from estimator.graph import Estimator, camera_symbol, marker_symbol
from estimator.keyframes import MovingFrame, MovingFrames, add_keyframes, fit_of, select_keyframes, weighed
from estimator.links import ObjectLinks, add_links, block_sightings
from estimator.observation import ObservationRows
from schemas.geometry import cov_gtsam_to_ros, cov_ros_to_gtsam

log = logging.getLogger(__name__)
UPDATE_EVERY_NS = 200_000_000  # incremental updates while streaming (segments need a map to test against)


@dataclass(frozen=True)
class FrameBlock:
    """Consecutive marker frames of one camera: stamps (F,) int ns; ``arrays.frame`` indexes them."""

    camera_id: str
    stamps: np.ndarray
    arrays: ObservationRows


@dataclass(frozen=True)
class ObjectRows:
    """Object-marker observations of one camera's frames that belong to a static segment: stamps,
    segments and marker ids (N,), camera_T_marker (N, 4, 4), covariances (N, 6, 6; ROS order)."""

    camera_id: str
    stamps: np.ndarray
    segments: np.ndarray
    ids: np.ndarray
    poses: np.ndarray
    covariances: np.ndarray


@dataclass(frozen=True)
class SegmentResult:
    camera_id: str
    segment: int
    world_T_camera: np.ndarray
    covariance: np.ndarray  # 6x6, ROS order, body frame
    first_stamp_ns: int
    last_stamp_ns: int
    frames: int


@dataclass(frozen=True)
class KeyframeResult:
    """A moving camera's frame solved as a pose of its own."""

    camera_id: str
    stamp_ns: int
    world_T_camera: np.ndarray
    covariance: np.ndarray  # 6x6, ROS order, body frame
    markers: int  # markers whose factors placed it


@dataclass(frozen=True)
class PairResidual:
    camera_id: str
    segment: int
    marker_id: int
    observations: int
    rejected: int  # observations the pair rejected as outliers
    whitened_error: float  # sqrt(2 x factor error) at the solution: ~1 when consistent


@dataclass
class ResolveResult:
    segments: list[SegmentResult]
    markers: dict[int, tuple[np.ndarray, np.ndarray]]  # id -> (world_T_marker, ROS covariance)
    residuals: list[PairResidual]
    unanchored: list[str]  # cameras with no path to an anchor in the whole log
    observations: int
    frames: int
    flagged_anchors: list[int]
    final_error: float
    iterations: int
    frame_stamps: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # camera -> (stamp, segment)
    keyframes: list[KeyframeResult] = field(default_factory=list)  # in log order per camera
    object_links: int = 0  # object-marker instants that linked two or more cameras
    moving_frames_scale: float = 1.0  # the factor on the moving frames' covariances (``estimator.variance.inflation``)
    moving_frames_left_out: int = 0  # moving frames it left out (``KeyframeConfig.max_inflation``)


def resolve(
    blocks: Iterable[FrameBlock],
    config: EstimatorConfig,
    progress: Callable[[int], None] | None = None,
    objects: Callable[[ObjectRows], None] | None = None,
) -> ResolveResult:
    """Batch-solve a stream of frame blocks, in capture order per camera.

    Blocks of a few dozen frames let the estimator fold a settled camera's observations in with
    numpy (``Estimator.add_frames``) instead of one Python call per marker. ``objects`` receives
    each block's object-marker observations from static frames, to be placed through the solved
    cameras afterwards (``place_objects``); they are not part of the map.
    """
    est = Estimator(config, keep_history=True)  # every segment is reported
    moving = MovingFrames(config.keyframes)
    links = ObjectLinks(config.links)
    last_update = None
    n_frames = n_obs = 0
    stamps: dict[str, list[tuple[int, int]]] = {}
    seg_span: dict[tuple[str, int], list[int]] = {}
    for block in blocks:
        cam = block.camera_id
        segs = est.add_frames(cam, block.stamps, block.arrays)
        if objects is not None and est.object_markers:
            _object_rows(block, segs, est.object_markers, objects)
        if config.keyframes.enabled:
            _moving_frames(block, segs, est.object_markers, moving, est.tracks[cam].segment)
        if config.links.enabled and est.object_markers:
            block_sightings(cam, block.stamps, block.arrays, segs, est.object_markers, links)
        for stamp, seg in zip(block.stamps.tolist(), segs):
            if seg is None:
                continue
            stamps.setdefault(cam, []).append((stamp, seg))
            span = seg_span.setdefault((cam, seg), [stamp, stamp, 0])
            span[1], span[2] = stamp, span[2] + 1
        n_frames += len(block.stamps)
        n_obs += len(block.arrays.ids)
        stamp = int(block.stamps[-1])
        if last_update is None or stamp - last_update >= UPDATE_EVERY_NS:
            est.update(stamp)
            last_update = stamp
            if progress is not None:
                progress(n_obs)
    if last_update is not None:
        est.update(
            last_update + int(config.refresh_s * 1e9) + 1, refresh_all=True
        )  # every pair's final mean in the graph
    graph = est.factor_graph()
    if graph.size() == 0 or est.values.size() == 0:
        return ResolveResult([], {}, [], sorted(est.tracks), n_obs, n_frames, [], 0.0, 0, stamps)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(200)
    params.setRelativeErrorTol(1e-9)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, est.values, params)
    values = optimizer.optimize()
    robust = gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k)
    segment_keys = {seg: camera_symbol(i) for seg, i in est.camera_index.items() if values.exists(camera_symbol(i))}
    added, scale, left_out = _add_moving_frames(graph, values, est, moving.frames, segment_keys, robust)
    linked = add_links(graph, values, links, segment_keys, config.max_fused, robust)
    if added or linked:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = optimizer.optimize()
    marginals = gtsam.Marginals(graph, values)
    segments = []
    for (cam, seg), index in sorted(est.camera_index.items()):
        key = camera_symbol(index)
        if not values.exists(key):
            continue
        first, last, count = seg_span.get((cam, seg), [0, 0, 0])
        segments.append(
            SegmentResult(
                cam,
                seg,
                values.atPose3(key).matrix(),
                cov_gtsam_to_ros(marginals.marginalCovariance(key)),
                first,
                last,
                count,
            )
        )
    markers = {}
    for mk in sorted({m for (_, m) in est.pairs} | set(est.anchors)):
        key = marker_symbol(mk)
        if values.exists(key):
            markers[mk] = (values.atPose3(key).matrix(), cov_gtsam_to_ros(marginals.marginalCovariance(key)))
    residuals = []
    for ((cam, seg), mk), pair in sorted(est.pairs.items()):
        ck, mkey = camera_symbol(est.camera_index[(cam, seg)]), marker_symbol(mk)
        if not (values.exists(ck) and values.exists(mkey)) or pair.n == 0:
            continue
        cov = cov_ros_to_gtsam(pair.factor_covariance(config.max_fused, est.rotation_floor_rad))
        factor = gtsam.BetweenFactorPose3(
            ck, mkey, gtsam.Pose3(pair.mean(exact=True)), gtsam.noiseModel.Gaussian.Covariance(cov)
        )
        residuals.append(PairResidual(cam, seg, mk, pair.n, pair.rejected, math.sqrt(2.0 * factor.error(values))))
    keyframes = [
        KeyframeResult(
            f.camera_id, f.stamp_ns, values.atPose3(k).matrix(), cov_gtsam_to_ros(marginals.marginalCovariance(k)), n
        )
        for k, f, n in added
    ]
    placed = {cam for cam, _ in segment_keys}
    flagged = est.estimate(last_update or 0, with_covariance=False).flagged_anchors
    return ResolveResult(
        segments,
        markers,
        residuals,
        sorted(set(est.tracks) - placed),
        n_obs,
        n_frames,
        flagged,
        float(graph.error(values)),
        int(optimizer.iterations()),
        stamps,
        keyframes,
        linked,
        scale,
        left_out,
    )


def _add_moving_frames(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    est: Estimator,
    frames: list[MovingFrame],
    segment_keys: dict[tuple[str, int], int],
    robust: gtsam.noiseModel.mEstimator.Base,
) -> tuple[list[tuple[int, MovingFrame, int]], float, int]:
    """``add_keyframes`` against the static solution ``values``: its markers place the frames, its
    solved segments (``segment_keys``) are the views a frame must differ from, and how its pairs
    fit weighs the frames (``weigh_by_fit``). Returns the frames added, the factor on their
    covariances and how many were left out for it."""
    markers = {m for (_, m) in est.pairs} | set(est.anchors)
    solved = {mk: values.atPose3(marker_symbol(mk)).matrix() for mk in markers if values.exists(marker_symbol(mk))}
    segment_poses: dict[str, list[np.ndarray]] = {}
    for (cam, _), key in segment_keys.items():
        segment_poses.setdefault(cam, []).append(values.atPose3(key).matrix())
    config = est.config.keyframes
    selected = select_keyframes(frames, solved, segment_poses, est.rotation_floor_rad, config)
    if not selected:
        return [], 1.0, 0
    factor, left_out = weighed(est.static_fit(values), fit_of(selected), config)
    if left_out:
        log.info(
            "%d moving frames left out: the static pairs fit %.3g times better than the frames against what each claims",
            len(selected),
            factor,
        )
        return [], factor, len(selected)
    if factor > 1.0:
        log.info(
            "%d moving frames enter with their covariances x %.3g: the static pairs fit better than they claim",
            len(selected),
            factor,
        )
    return add_keyframes(graph, values, selected, est.rotation_floor_rad, robust, covariance_scale=factor), factor, 0


def _moving_frames(
    block: FrameBlock, segs: list[int | None], object_markers: set[int], sink: MovingFrames, segment_now: int
) -> None:
    """The static markers seen in the block's frames that joined no segment (the camera moved).
    ``segment_now``: the camera's segment after the block; a moving frame's move is the segment
    it left (one before the next static frame's, if the camera settled within the block)."""
    a = block.arrays
    for f in [i for i, g in enumerate(segs) if g is None]:
        rows = (a.frame == f) & ~np.isin(a.ids, list(object_markers))
        later = next((g for g in segs[f + 1 :] if g is not None), None)
        move = segment_now if later is None else later - 1
        sink.add(
            MovingFrame(
                block.camera_id,
                int(block.stamps[f]),
                a.ids[rows],
                a.poses[rows],
                a.alternatives[rows],
                a.covariances[rows],
                move,
            )
        )


def _object_rows(
    block: FrameBlock, segs: list[int | None], object_markers: set[int], sink: Callable[[ObjectRows], None]
) -> None:
    seg_of_frame = np.array([-1 if g is None else g for g in segs], dtype=np.int64)
    a = block.arrays
    keep = np.isin(a.ids, list(object_markers)) & (seg_of_frame[a.frame] >= 0)
    if keep.any():
        f = a.frame[keep]
        sink(
            ObjectRows(
                block.camera_id, block.stamps[f], seg_of_frame[f], a.ids[keep], a.poses[keep], a.covariances[keep]
            )
        )


def place_objects(
    rows: ObjectRows, segments: dict[tuple[str, int], SegmentResult]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """world_T_marker (M, 4, 4) and covariances (M, 6, 6; ROS order, marker frame) of the rows
    whose segment was solved, and the mask (N,) of those rows."""
    solved = np.array([(rows.camera_id, int(g)) in segments for g in rows.segments], dtype=bool)
    if not solved.any():
        return np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), solved
    segs = [segments[(rows.camera_id, int(g))] for g in rows.segments[solved]]
    wTc = np.stack([s.world_T_camera for s in segs])
    cam_cov = np.stack([s.covariance for s in segs])
    T, cov = through_camera(wTc, cam_cov, rows.poses[solved], rows.covariances[solved])
    return T, cov, solved
