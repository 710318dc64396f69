"""Every zenoh key expression of the wire contract (docs/architecture.md section 4), built by functions.

Call sites never concatenate key strings; they call these. ``message_type`` maps any concrete key
back to the protobuf class that travels on it, which the recorder, ``bus echo`` and the decoders
use.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass

from google.protobuf.message import Message

from schemas import messages as m
from schemas.errors import KeyError_

ROOT = "cellsight"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$")

# Per-camera topics (relative to cellsight/<cell>/<camera>/) and their message types.
CAMERA_TOPICS: dict[str, type[Message]] = {
    "color/image_raw": m.RawImage,
    "depth/image_raw": m.RawImage,
    "camera_info": m.CameraCalibration,
    "markers": m.MarkerObservations,
    "status": m.DriverStatus,
}
# Cell-wide topics (relative to cellsight/<cell>/).
CELL_TOPICS: dict[str, type[Message]] = {
    "tf": m.FrameTransforms,
    "estimate/cameras": m.PosesWithCovariance,
    "estimate/markers": m.PosesWithCovariance,
    "estimate/status": m.EstimatorStatus,
    "estimate/map": m.Map,
    "objects": m.ObjectDetections,
    "objects/scene": m.SceneUpdate,
    "points": m.PointCloud,
    "truth/cameras": m.PosesWithCovariance,
    # Not "truth/markers": every camera's observations, ``<cell>/*/markers`` (the estimator's
    # subscription), would match it, and drivers would compute the truth for a reader that drops it.
    "truth/marker_poses": m.PosesWithCovariance,
    "truth/objects": m.PosesWithCovariance,
}
# Names a camera may not take, because they would collide with cell-wide topics.
RESERVED = frozenset({"tf", "estimate", "objects", "points", "truth", "alive"})


def check_name(name: str, what: str = "name") -> str:
    """Return ``name`` if it is usable as one key chunk (cell, camera, component), else raise."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise KeyError_(f"invalid {what} {name!r}: use letters, digits, '_', '-', '.' (no '/', '*', '$')")
    return name


def marker_frame(marker_id: int) -> str:
    """Child frame id of a marker's pose in transforms and pose lists."""
    return f"marker_{marker_id}"


def object_frame(object_id: str) -> str:
    """Child frame id of a recognised object's pose in transforms, scenes and pose lists."""
    return f"object_{object_id}"


def _camera(cell: str, camera: str, topic: str) -> str:
    check_name(camera, "camera id")
    if camera in RESERVED:
        raise KeyError_(f"camera id {camera!r} is reserved for cell-wide topics")
    return f"{ROOT}/{check_name(cell, 'cell name')}/{camera}/{topic}"


def _cell(cell: str, topic: str) -> str:
    return f"{ROOT}/{check_name(cell, 'cell name')}/{topic}"


def camera_topic(cell: str, camera: str, topic: str) -> str:
    """Any per-camera topic's key (one of ``CAMERA_TOPICS``)."""
    if topic not in CAMERA_TOPICS:
        raise KeyError_(f"unknown camera topic {topic!r}; known: {sorted(CAMERA_TOPICS)}")
    return _camera(cell, camera, topic)


def cell_topic(cell: str, topic: str) -> str:
    """Any cell-wide topic's key (one of ``CELL_TOPICS``)."""
    if topic not in CELL_TOPICS:
        raise KeyError_(f"unknown cell topic {topic!r}; known: {sorted(CELL_TOPICS)}")
    return _cell(cell, topic)


def color(cell: str, camera: str) -> str:
    return _camera(cell, camera, "color/image_raw")


def depth(cell: str, camera: str) -> str:
    return _camera(cell, camera, "depth/image_raw")


def camera_info(cell: str, camera: str) -> str:
    return _camera(cell, camera, "camera_info")


def markers(cell: str, camera: str) -> str:
    return _camera(cell, camera, "markers")


def status(cell: str, camera: str) -> str:
    return _camera(cell, camera, "status")


def all_cameras(cell: str, topic: str) -> str:
    """Wildcard over every camera for one per-camera topic, e.g. ``cellsight/demo/*/markers``."""
    if topic not in CAMERA_TOPICS:
        raise KeyError_(f"unknown camera topic {topic!r}; known: {sorted(CAMERA_TOPICS)}")
    return f"{ROOT}/{check_name(cell, 'cell name')}/*/{topic}"


def tf(cell: str) -> str:
    return _cell(cell, "tf")


def estimate_cameras(cell: str) -> str:
    return _cell(cell, "estimate/cameras")


def estimate_markers(cell: str) -> str:
    return _cell(cell, "estimate/markers")


def estimate_status(cell: str) -> str:
    return _cell(cell, "estimate/status")


def estimate_map(cell: str) -> str:
    return _cell(cell, "estimate/map")


def objects(cell: str) -> str:
    return _cell(cell, "objects")


def objects_scene(cell: str) -> str:
    return _cell(cell, "objects/scene")


def points(cell: str) -> str:
    """The cameras' depth fused into one world-frame cloud (foxglove.PointCloud), for viewing."""
    return _cell(cell, "points")


def truth(cell: str, what: str) -> str:
    """Simulator ground truth: ``what`` is cameras, marker_poses or objects. Tests and benchmarks only."""
    if f"truth/{what}" not in CELL_TOPICS:
        raise KeyError_(f"unknown truth topic {what!r}; use cameras, marker_poses or objects")
    return _cell(cell, f"truth/{what}")


def alive(cell: str, component: str, ident: str) -> str:
    """Liveliness token of one process, e.g. ``cellsight/demo/alive/driver/cam1``."""
    return _cell(cell, f"alive/{check_name(component, 'component')}/{check_name(ident, 'id')}")


def alive_all(cell: str) -> str:
    return _cell(cell, "alive/**")


def everything(cell: str) -> str:
    """Every key of one cell (what the recorder subscribes to)."""
    return _cell(cell, "**")


def everything_but_images(cell: str) -> list[str]:
    """Key expressions for every key of one cell but the cameras' images, no two matching one key
    (a message arrives once): the per-camera wildcards, and the cell-wide topics none of them covers
    (``*/status`` is ``estimate/status`` too)."""
    per_camera = [t for t, msg_type in CAMERA_TOPICS.items() if msg_type is not m.RawImage]
    covered = [t for t in CELL_TOPICS if t.count("/") == 1 and t.split("/")[1] in per_camera]
    return [all_cameras(cell, t) for t in per_camera] + [_cell(cell, t) for t in CELL_TOPICS if t not in covered]


def images(cell: str, camera: str) -> list[str]:
    """The camera's image keys (colour, depth)."""
    return [_camera(cell, camera, t) for t, msg_type in CAMERA_TOPICS.items() if msg_type is m.RawImage]


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key split into its parts; ``camera`` is None for cell-wide topics."""

    cell: str
    camera: str | None
    topic: str
    message_type: type[Message]


@functools.lru_cache(maxsize=4096)  # a cell has a few dozen keys; every message of a log parses one
def parse(key: str) -> ParsedKey:
    """Split a concrete key and find its message type; raise ``KeyError_`` if it is not ours."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != ROOT:
        raise KeyError_(f"not a cellsight key: {key!r}")
    cell, rest = parts[1], "/".join(parts[2:])
    if rest in CELL_TOPICS:
        return ParsedKey(cell, None, rest, CELL_TOPICS[rest])
    camera, topic = parts[2], "/".join(parts[3:])
    if topic in CAMERA_TOPICS and camera not in RESERVED:
        return ParsedKey(cell, camera, topic, CAMERA_TOPICS[topic])
    raise KeyError_(f"unknown cellsight topic in key {key!r}")


def message_type(key: str) -> type[Message]:
    """The protobuf class carried on a concrete key."""
    return parse(key).message_type
