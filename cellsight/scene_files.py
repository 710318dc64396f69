"""Scene files as recognition reads them: a cloud (PCD, PLY) or a depth image with its intrinsics,
and a colour image registered to it. ``cellsight recognize`` and the BOP reader share them."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from recognition.cloud import depth_to_cloud, read_coloured_cloud
from recognition.errors import CloudError
from schemas.codec import CameraInfo

MAX_SCENE_RANGE_M = 20.0  # a scene cloud's median range beyond this is in other units (millimetres)


def load_scene(
    scene: Path,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    scale: float | None = None,
    rgb: Path | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """A camera-frame cloud (m) from a PCD/PLY, or from a 16-bit depth PNG/TIFF with intrinsics
    (Kinect v1 defaults for any that are not given), and its points' colours (uint8 rgb, the
    cloud's layout) when the file has them, or from ``rgb``: a colour image registered to the depth
    image (the same size). ``scale``: metres per unit of the file (default 1 for a cloud, 0.001 for
    a depth image in millimetres)."""
    if scale is not None and not scale > 0:
        raise CloudError(f"scale {scale:g}: metres per unit of the scene must be positive")
    if scene.suffix.lower() in (".pcd", ".ply"):
        if rgb is not None:
            raise CloudError(f"{scene}: a cloud file carries its own colours; --rgb goes with a depth image")
        cloud, colours = read_coloured_cloud(scene, organised=scene.suffix.lower() == ".pcd")
        if scale is not None:
            cloud = cloud * np.float32(scale)
        pts = cloud.reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        median = float(np.median(np.linalg.norm(pts, axis=1))) if len(pts) else 0.0
        if median > MAX_SCENE_RANGE_M:
            raise CloudError(
                f"{scene}: its points lie {median:.4g} from the camera (median) and scenes are in metres "
                f"(a depth camera sees up to {MAX_SCENE_RANGE_M:g} m): in millimetres? give --scale 0.001"
            )
        return cloud, colours
    depth = read_depth_image(scene)
    colours = None if rgb is None else read_registered_rgb(rgb, scene, depth.shape)
    K = CameraInfo.kinect_v1(depth.shape[1], depth.shape[0]).K
    for (r, c), v in (((0, 0), fx), ((1, 1), fy), ((0, 2), cx), ((1, 2), cy)):
        if v is not None:
            K[r, c] = v
    return depth_to_cloud(depth, K, 0.001 if scale is None else scale), colours


def read_depth_image(path: Path) -> np.ndarray:
    """A single-channel depth image (H, W) as stored (16-bit units), or a CloudError naming it."""
    depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if depth is None or depth.ndim != 2:
        raise CloudError(f"{path}: not a PCD/PLY cloud nor a single-channel depth image")
    return depth


def read_registered_rgb(path: Path, depth_path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A colour image registered to the depth image at depth_path, of its size ``shape`` (H, W), as
    (H, W, 3) uint8 rgb; a CloudError if it is no image or of another size."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise CloudError(f"{path}: not a colour image (PNG, JPEG)")
    if bgr.shape[:2] != shape:
        raise CloudError(
            f"{path} is {bgr.shape[1]}x{bgr.shape[0]} but the depth image {depth_path} is "
            f"{shape[1]}x{shape[0]}: the colour must be registered to the depth"
        )
    return np.ascontiguousarray(bgr[..., ::-1])
