"""Pictures people look at: camera snapshots with detected markers, depth in false colour, the
objects a scene was found to hold."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from cellsight.detect import draw_detections
from drivers.config import MarkerConfig
from drivers.markers import MarkerDetector
from drivers.sim.render import SimCell
from drivers.sim.scenario import Scenario
from recognition.align import facing_camera
from recognition.hypotheses import Detection
from recognition.models import ModelDatabase
from recognition.verify import VIRTUAL_K, fit_intrinsics, project, virtual_image

#: Each object's colour in a recognition picture (BGR), by its place among the database's ids: none
#: of them the pure red, green or blue of the axes.
OBJECT_COLOURS = (
    (0, 165, 255),
    (255, 0, 255),
    (255, 255, 0),
    (0, 255, 255),
    (180, 105, 255),
    (255, 128, 0),
    (128, 255, 128),
    (0, 90, 200),
)
#: A model point further than this behind the measured depth on its pixel is hidden by what the
#: sensor saw in front of it, and not drawn (m).
HIDDEN_M = 0.03


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
    det = MarkerDetector(
        MarkerConfig(dictionary=scenario.dictionary, sides_m={m.id: scenario.side_of(m) for m in scenario.markers})
    )
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


def draw_recognition(
    cloud: np.ndarray,
    rgb: np.ndarray | None,
    detections: Sequence[Detection],
    database: ModelDatabase,
    truth: Sequence[tuple[str, np.ndarray]] = (),
) -> np.ndarray:
    """The scene as a picture (BGR): its colour, else its depth in false colour, with each detection's
    model points that the camera would see drawn in the object's colour (``OBJECT_COLOURS``), the
    outline they make, the object's axes (x red, y green, z blue; at its origin, when that lies on
    the object) and its id and fitness; under them, in white, the outline of each annotated pose in
    ``truth`` (object id, camera_T_object), for a dataset's frames.

    cloud: the camera-frame scene (H, W, 3) organised, drawn at its own resolution, or (N, 3),
    drawn as ``recognition.verify``'s virtual camera sees it; rgb: its points' colours (uint8,
    the cloud's layout) or None."""
    pts = np.asarray(cloud, dtype=np.float64)
    organised = pts.ndim == 3 and min(pts.shape[:2]) > 1
    if organised:
        H, W = pts.shape[:2]
        K = fit_intrinsics(pts)
        z = np.where(np.isfinite(pts[..., 2]) & (pts[..., 2] > 0), pts[..., 2], np.nan)
        colour = None if rgb is None else np.asarray(rgb, np.uint8).reshape(H, W, 3)
    else:
        K = VIRTUAL_K
        z, nearest = virtual_image(pts)
        colour = None
        if rgb is not None:
            colour = np.zeros((*z.shape, 3), np.uint8)
            seen = nearest >= 0
            colour[seen] = np.asarray(rgb, np.uint8).reshape(-1, 3)[nearest[seen]]
    if colour is not None:
        out = np.ascontiguousarray(colour[..., ::-1])
    else:  # the colours spread over the scene's own depths, not a sensor's whole range
        far_mm = 1000.0 * float(np.nanpercentile(z, 99)) if np.isfinite(z).any() else 4500.0
        out = depth_colormap(np.nan_to_num(z * 1000.0).astype(np.uint16), max_mm=1.05 * far_mm)
    for object_id, T in truth:
        if (shown := _silhouette(database, object_id, T, K, z)) is not None:
            cv2.drawContours(out, shown[2], -1, (255, 255, 255), 1)
    ids = sorted(database.models)
    labels: list[tuple[str, int, int]] = []  # text, left, top of the silhouette
    for det in detections:
        model = database.models[det.object_id]
        bgr = OBJECT_COLOURS[ids.index(det.object_id) % len(OBJECT_COLOURS)]
        T = det.camera_T_object
        if (shown := _silhouette(database, det.object_id, T, K, z)) is None:
            continue
        (u, v), inside, contours = shown
        out[inside] = (0.65 * out[inside] + 0.35 * np.array(bgr)).astype(np.uint8)
        cv2.drawContours(out, contours, -1, bgr, 1)
        out[v, u] = bgr
        # A model from a captured cloud has its camera's frame: its origin is nowhere near it.
        if T[2, 3] > 0 and np.linalg.norm(model.centre) <= model.diameter_m:
            rvec, _ = cv2.Rodrigues(T[:3, :3])
            cv2.drawFrameAxes(out, K, np.zeros(5), rvec, T[:3, 3], 0.4 * model.diameter_m, 2)
        labels.append((f"{det.object_id} {det.fitness:.2f}", int(u.min()), int(v.min())))
    placed: list[tuple[int, int, int, int]] = []
    for text, x, top in labels:  # above the silhouette, raised past labels already there
        (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        y = top - 4
        while any(x < x1 and x + w + 2 > x0 and y - h - 3 < y1 and y + 2 > y0 for x0, y0, x1, y1 in placed):
            y -= h + 6
        y = max(y, h + 3)
        placed.append((x, y - h - 3, x + w + 2, y + 2))
        cv2.rectangle(out, placed[-1][:2], placed[-1][2:], (0, 0, 0), -1)
        cv2.putText(out, text, (x + 1, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def _silhouette(
    database: ModelDatabase, object_id: str, camera_T_object: np.ndarray, K: np.ndarray, z: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray, Sequence[np.ndarray]] | None:
    """Where a posed model shows in an image of depth z (H, W, m; NaN: none) seen through K: the
    pixels (columns, rows) of its points that face the camera and are not behind the measured depth
    by more than HIDDEN_M, the mask (H, W) they fill closed over the gaps between them (one voxel
    apart: that many pixels at their depth), and its outline's contours; None where none shows."""
    model = database.models[object_id]
    R, t = camera_T_object[:3, :3], camera_T_object[:3, 3]
    p = model.points[facing_camera(model.points, model.normals, camera_T_object)[0]] @ R.T + t
    u, v, ok = project(p, K, z.shape)
    u, v, p = u[ok], v[ok], p[ok]
    seen = ~(p[:, 2] > z[v, u] + HIDDEN_M)  # no depth there, or not behind it
    if not seen.any():
        return None
    u, v = u[seen], v[seen]
    mask = np.zeros(z.shape, np.uint8)
    mask[v, u] = 255
    gap = int(np.ceil(K[0, 0] * database.descriptor.voxel_m / float(np.median(p[seen, 2]))))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * max(gap, 2) + 1,) * 2)
    closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, disc)
    contours, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    return (u, v), closed > 0, contours
