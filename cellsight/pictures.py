"""Pictures people look at: camera snapshots with detected markers, depth in false colour."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from cellsight.detect import draw_detections
from drivers.config import MarkerConfig
from drivers.markers import MarkerDetector
from drivers.sim.render import SimCell
from drivers.sim.scenario import Scenario


def depth_colormap(depth_mm: np.ndarray, max_mm: float = 4500.0) -> np.ndarray:
    """False-colour BGR depth; no-return pixels black."""
    vis = cv2.applyColorMap(cv2.convertScaleAbs(depth_mm, alpha=255.0 / max_mm), cv2.COLORMAP_TURBO)
    vis[depth_mm == 0] = 0
    return vis


def write_snapshot(scenario: Scenario, out: Path, t_s: float) -> list[Path]:
    """For every camera: ``<id>_rgb.png``, ``<id>_depth.png`` (false colour), ``<id>_depth_mm.png``
    (16-bit millimetres, for tools) and ``<id>_markers.png`` (detections drawn)."""
    out.mkdir(parents=True, exist_ok=True)
    cell = SimCell(scenario)
    det = MarkerDetector(MarkerConfig(dictionary=scenario.dictionary, sides_m={m.id: scenario.side_of(m) for m in scenario.markers}))
    written = []
    for cam in scenario.cameras:
        f = cell.render(cam.id, t_s, 0)
        bgr = cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR)
        paths = [out / f"{cam.id}_{n}.png" for n in ("rgb", "depth", "depth_mm", "markers")]
        cv2.imwrite(str(paths[0]), bgr)
        cv2.imwrite(str(paths[1]), depth_colormap(f.depth_mm))
        cv2.imwrite(str(paths[2]), f.depth_mm)
        cv2.imwrite(str(paths[3]), draw_detections(bgr, f.info, det.detect(f.rgb, f.info, f.depth_mm)))
        written += paths
    return written
