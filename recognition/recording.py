"""Object models from recordings: a camera walks round an object standing on a marker board.

Each recorded frame is posed by the board markers it sees (``board_pose``: Kabsch on their
centres, which planar-PnP flips cannot disturb), its points inside the board's object box become
one view in the object frame, and the views, thinned to distinct viewing directions, are merged
into the model: the real captured views are its descriptors, their union its ICP cloud. This is
how the paper built its models with RoboEarth's recorder.

``model_from_views`` is the pure core; ``read_board_views`` streams a log (any camera's depth,
camera_info and marker observations, as the drivers publish them, and colour where it was
recorded: the model then has the object's colour as these sensors see it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recognition.cloud import PointIndex, depth_to_cloud, estimate_normals, voxel_downsample, voxel_downsample_coloured
from recognition.config import BoardConfig, DescriptorConfig
from recognition.errors import ModelError
from recognition.models import MIN_VIEW_POINTS, ObjectModel, describe_views
from schemas import codec, geometry, keys
from schemas import messages as m
from schemas.log import ReadReport, read_log

log = logging.getLogger(__name__)
#: A board pose whose marker centres miss their board positions by more than this (RMS, m) is wrong.
MAX_BOARD_RMS_M = 0.01


@dataclass(frozen=True)
class BoardView:
    """One frame of the capture: the object's points (N, 3) in the camera frame, metres, and
    camera_T_object (4, 4). stamp_ns: the frame's capture time (ns). colours: the points' rgb
    (N, 3) uint8, when the frame's colour was recorded."""

    camera_id: str
    stamp_ns: int
    points: np.ndarray
    camera_T_object: np.ndarray
    colours: np.ndarray | None = None


def board_pose(ids: np.ndarray, camera_T_markers: np.ndarray, board: BoardConfig) -> np.ndarray | None:
    """camera_T_board from the board markers among ``ids`` (their poses (N, 4, 4)); None with fewer
    than three or when their centres do not fit the board."""
    where = {mk.marker_id: mk.board_T_marker.matrix()[:3, 3] for mk in board.markers}
    seen = [i for i, mid in enumerate(ids) if int(mid) in where]
    if len(seen) < 3:
        return None
    on_board = np.array([where[int(ids[i])] for i in seen])
    in_camera = camera_T_markers[seen, :3, 3]
    camera_T_board = geometry.kabsch(on_board, in_camera)
    if camera_T_board is None:  # markers in a line
        return None
    moved = on_board @ camera_T_board[:3, :3].T + camera_T_board[:3, 3]
    rms = float(np.sqrt(np.mean(np.sum((moved - in_camera) ** 2, axis=1))))
    return camera_T_board if rms <= MAX_BOARD_RMS_M else None


def _inside(pts: np.ndarray, camera_T_object: np.ndarray, board: BoardConfig) -> np.ndarray:
    """Which camera-frame points (N, 3) are finite and inside the board's object box (N,) bool."""
    object_T_camera = geometry.invert_pose(camera_T_object)
    board_T_object = board.board_T_object.matrix()
    with np.errstate(invalid="ignore"):
        in_board = (pts @ object_T_camera[:3, :3].T + object_T_camera[:3, 3]) @ board_T_object[
            :3, :3
        ].T + board_T_object[:3, 3]
        return np.all((in_board >= board.object_min) & (in_board <= board.object_max), axis=1)


def select_views(views: Iterable[BoardView], min_angle_deg: float, max_views: int) -> list[BoardView]:
    """Views whose viewing direction (camera position seen from the object) is at least min_angle_deg
    from every view kept before, in order, at most max_views."""
    kept: list[BoardView] = []
    dirs: list[np.ndarray] = []
    cos_min = np.cos(np.radians(min_angle_deg))
    for v in views:
        if len(v.points) < MIN_VIEW_POINTS:
            continue
        d = geometry.invert_pose(v.camera_T_object)[:3, 3]
        d = d / np.linalg.norm(d)
        if all(float(d @ e) < cos_min for e in dirs):
            kept.append(v)
            dirs.append(d)
            if len(kept) == max_views:
                break
    return kept


def model_from_views(
    object_id: str, views: list[BoardView], params: DescriptorConfig, progress: Callable[[], None] | None = None
) -> ObjectModel:
    """Merge posed views into a model: each view's descriptors as captured, their union as the cloud."""
    if not views:
        raise ModelError(f"object {object_id!r}: no frame of the recording saw three board markers and the object")
    merged = []
    for v in views:
        object_T_camera = geometry.invert_pose(v.camera_T_object)
        merged.append(v.points @ object_T_camera[:3, :3].T + object_T_camera[:3, 3])
    pts = voxel_downsample(np.concatenate(merged), params.voxel_m)
    colours = _colours_at(pts, [(p, v.colours) for p, v in zip(merged, views) if v.colours is not None], params.voxel_m)
    centre = pts.mean(axis=0)
    normals, _ = estimate_normals(pts, params.normal_radius_m, centre)
    ok = np.all(np.isfinite(normals), axis=1)
    # Faced to the centre by estimate_normals; a captured object is seen from outside: flip them.
    described = describe_views(((v.points, v.camera_T_object) for v in views), params, progress)
    model = ObjectModel(
        object_id, pts[ok], -normals[ok], described, "recording", None if colours is None else colours[ok]
    )
    log.info("%s: model from %d recorded views, %d points", object_id, len(model.views), len(model.points))
    return model


def _colours_at(points: np.ndarray, coloured: list[tuple[np.ndarray, np.ndarray]], voxel_m: float) -> np.ndarray | None:
    """Colours (M, 3) rgb 0-1 of model points (M, 3) from the views recorded with colour (their
    points in the object frame, their rgb8): the mean colour of the nearest voxel those views saw,
    black (too dark to judge) where none of them saw within a voxel. None without such views."""
    if not coloured:
        return None
    seen, rgb = voxel_downsample_coloured(
        np.concatenate([p for p, _ in coloured]), np.concatenate([c for _, c in coloured]) / 255.0, voxel_m
    )
    nearest, sq_dist = PointIndex(seen).nearest(points)
    return np.where((sq_dist <= voxel_m**2)[:, None], rgb[nearest], 0.0).astype(np.float32)


def read_board_views(log_path: Path, board: BoardConfig, report: ReadReport | None = None) -> Iterator[BoardView]:
    """Every frame of a log whose depth, camera_info and marker observations all arrived and whose
    markers place the board. Drivers publish a frame's colour and depth before its markers (same
    stamp); a frame's colour, when recorded at the depth's size, colours its points."""
    board_T_object = board.board_T_object.matrix()
    infos: dict[str, codec.CameraInfo] = {}
    depths: dict[str, m.RawImage] = {}
    colours: dict[str, m.RawImage] = {}
    for lm in read_log(log_path, None, report):
        topic = keys.parse(lm.key)
        if topic.camera is None:
            continue
        if topic.topic == "camera_info":
            infos[topic.camera] = codec.CameraInfo.from_msg(lm.msg)
        elif topic.topic == "depth/image_raw":
            depths[topic.camera] = lm.msg
        elif topic.topic == "color/image_raw":
            colours[topic.camera] = lm.msg
        elif topic.topic == "markers":
            depth, info = depths.get(topic.camera), infos.get(topic.camera)
            if depth is None or info is None or codec.timestamp_to_stamp(depth.timestamp) != lm.msg.stamp_ns:
                continue
            a = codec.marker_arrays(lm.msg, check=False)  # read_log validated it
            camera_T_board = board_pose(a.ids, a.poses, board)
            if camera_T_board is None:
                continue
            camera_T_object = camera_T_board @ board_T_object
            pts = depth_to_cloud(codec.image_from_msg(depth), info.K, depth_scale=0.001).reshape(-1, 3)
            inside = _inside(pts, camera_T_object, board)
            rgb = _rgb(colours.get(topic.camera), lm.msg.stamp_ns, (info.height, info.width))
            yield BoardView(
                topic.camera,
                lm.msg.stamp_ns,
                pts[inside],
                camera_T_object,
                None if rgb is None else rgb.reshape(-1, 3)[inside],
            )


def _rgb(msg: m.RawImage | None, stamp_ns: int, shape: tuple[int, int]) -> np.ndarray | None:
    """A recorded colour frame of this stamp as (H, W, 3) rgb8, if it is one of the depth's size."""
    if msg is None or codec.timestamp_to_stamp(msg.timestamp) != stamp_ns or msg.encoding not in ("rgb8", "bgr8"):
        return None
    rgb = codec.rgb_from_msg(msg)
    return rgb if rgb.shape[:2] == shape else None


def model_from_recording(
    object_id: str,
    log_path: Path,
    board: BoardConfig,
    params: DescriptorConfig,
    progress: Callable[[], None] | None = None,
) -> ObjectModel:
    """``read_board_views`` -> ``select_views`` -> ``model_from_views``."""
    report = ReadReport()
    views = select_views(read_board_views(log_path, board, report), board.min_view_angle_deg, board.max_views)
    if report.stopped_early:
        log.warning("%s: read up to the damage only (%s)", log_path, report.stopped_early)
    return model_from_views(object_id, views, params, progress)
