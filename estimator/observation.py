"""The estimator's input: one marker seen by one camera at one time."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.codec import MarkerArrays


@dataclass(frozen=True)
class Observation:
    """``camera_T_marker`` (4x4) with its 6x6 covariance (ROS order x y z rx ry rz, marker frame).

    ``alternative`` is the other planar-PnP (IPPE) solution, used when the chosen one turns out to
    be a flip; ``stamp_ns`` is the capture time in integer nanoseconds.
    """

    camera_id: str
    stamp_ns: int
    marker_id: int
    camera_T_marker: np.ndarray
    covariance: np.ndarray
    alternative: np.ndarray | None = None
    ambiguous: bool = False


def observations_of(camera_id: str, stamp_ns: int, a: MarkerArrays) -> list[Observation]:
    """Rows of marker arrays (one frame's) as estimator observations."""
    return [
        Observation(camera_id, stamp_ns, int(a.ids[i]), a.poses[i], a.covariances[i], a.alternatives[i], bool(a.ambiguous[i]))
        for i in range(len(a.ids))
    ]
