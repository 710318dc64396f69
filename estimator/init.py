"""Initial values: breadth-first placement outward from the anchors over the camera-marker graph.

Before anything enters the solver, every camera and marker reachable from an anchor gets a world
pose; everything else is in a component without an anchor and stays out (iSAM2 raises on such
components and batch LM puts them metres off). A camera that sees three or more placed markers is
placed from the marker centres alone (Kabsch), which no rotation flip can disturb.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from schemas.geometry import invert_pose, kabsch

CameraKey = tuple[str, int]  # (camera id, segment)


def place(
    anchors: Mapping[int, np.ndarray],
    pairs: Mapping[tuple[CameraKey, int], np.ndarray],
    placed_cameras: Mapping[CameraKey, np.ndarray] | None = None,
    placed_markers: Mapping[int, np.ndarray] | None = None,
) -> tuple[dict[CameraKey, np.ndarray], dict[int, np.ndarray]]:
    """World poses for every camera and marker connected to an anchor.

    ``pairs`` maps (camera, marker) to the mean ``camera_T_marker``; already placed poses (the
    current estimate) are kept and extended. Returns (world_T_camera, world_T_marker).
    """
    cams: dict[CameraKey, np.ndarray] = dict(placed_cameras or {})
    marks: dict[int, np.ndarray] = dict(placed_markers or {})
    marks.update(anchors)
    by_camera: dict[CameraKey, dict[int, np.ndarray]] = {}
    for (cam, marker), T in pairs.items():
        by_camera.setdefault(cam, {})[marker] = T
    changed = True
    while changed:
        changed = False
        for cam, seen in by_camera.items():
            if cam in cams:
                continue
            known = [mk for mk in seen if mk in marks]
            if not known:
                continue
            T = kabsch(np.array([seen[k][:3, 3] for k in known]), np.array([marks[k][:3, 3] for k in known]))
            if T is None:  # one or two markers: compose through the nearest one
                k = min(known, key=lambda mk: np.linalg.norm(seen[mk][:3, 3]))
                T = marks[k] @ invert_pose(seen[k])
            cams[cam] = T
            changed = True
        for (cam, marker), T in pairs.items():
            if cam in cams and marker not in marks:
                marks[marker] = cams[cam] @ T
                changed = True
    return cams, marks
