"""The seed paper's chain method, the baseline the estimator must beat.

Each camera is placed by composing single relative poses along the shortest path of camera-marker
links to an anchor (the paper's R = R_r R_l^T, T = T_r - R T_l between two views of one marker,
which is the same as composing world_T_marker with the inverse of camera_T_marker). Each link uses
the time-averaged observation of that camera-marker pair, i.e. the same data the estimator fuses;
nothing is weighted, and only one path counts.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from schemas.geometry import invert_pose


def chain_solve(anchors: dict[int, np.ndarray], pairs: dict[tuple[str, int], np.ndarray]) -> dict[str, np.ndarray]:
    """world_T_camera for every camera with a path to an anchor (breadth first: fewest links)."""
    cams_of: dict[int, list[str]] = {}
    marks_of: dict[str, list[int]] = {}
    for cam, mk in pairs:
        cams_of.setdefault(mk, []).append(cam)
        marks_of.setdefault(cam, []).append(mk)
    markers = dict(anchors)
    cameras: dict[str, np.ndarray] = {}
    queue = deque(("m", mk) for mk in anchors)
    while queue:
        kind, node = queue.popleft()
        if kind == "m":
            for cam in cams_of.get(node, []):
                if cam not in cameras:
                    cameras[cam] = markers[node] @ invert_pose(pairs[(cam, node)])
                    queue.append(("c", cam))
        else:
            for mk in marks_of.get(node, []):
                if mk not in markers:
                    markers[mk] = cameras[node] @ pairs[(node, mk)]
                    queue.append(("m", mk))
    return cameras
