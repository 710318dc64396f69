"""What every frame source yields, and the conversion of detections into wire messages."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drivers.markers import MarkerDetection
from schemas import codec
from schemas import messages as m


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame. rgb (H, W, 3) uint8; depth_mm (H, W) uint16 registered to rgb (None if absent).

    ``stamp_ns``: capture time, integer nanoseconds (Unix epoch for live sources).
    """

    camera_id: str
    stamp_ns: int
    rgb: np.ndarray
    depth_mm: np.ndarray | None
    info: codec.CameraInfo


class FrameSource(Protocol):
    """A sensor: ``read`` blocks until the next frame; None means the source has ended."""

    name: str

    def read(self) -> Frame | None: ...

    def close(self) -> None: ...


def observations_to_msg(
    camera_id: str, stamp_ns: int, info: codec.CameraInfo, detections: list[MarkerDetection], dictionary: str
) -> m.MarkerObservations:
    msg = m.MarkerObservations(
        camera_id=camera_id, stamp_ns=int(stamp_ns), image_width=info.width, image_height=info.height
    )
    outs = []
    for d in detections:
        o = msg.markers.add(
            marker_id=d.marker_id,
            dictionary=dictionary,
            side_m=d.side_m,
            reprojection_error_a_px=d.error_a_px,
            reprojection_error_b_px=d.error_b_px,
            depth_refined=d.depth_refined,
            ambiguous=d.ambiguous,
        )
        o.corners_px.extend(d.corners_px.astype(np.float32).ravel().tolist())
        outs += [o.candidate_a, o.candidate_b, o.camera_T_marker]
        o.covariance.extend(codec.covariance_to_list(d.covariance))
    if detections:
        codec.poses_to_msgs(
            np.stack([T for d in detections for T in (d.candidate_a, d.candidate_b, d.camera_T_marker)]), outs
        )
    return msg
