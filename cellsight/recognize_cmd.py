"""``cellsight recognize``: the recognition pipeline on one scene file, as a result object."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cellsight.detect import pose_json
from cellsight.errors import RunError
from recognition.cloud import depth_to_cloud, read_coloured_cloud
from recognition.config import RecognitionConfig
from recognition.errors import CloudError
from recognition.hypotheses import Detection
from recognition.models import ModelDatabase
from recognition.pipeline import Recognizer
from schemas.codec import CameraInfo

PICTURE_SUFFIXES = (".png", ".jpg")
MAX_SCENE_RANGE_M = 20.0  # a scene cloud's median range beyond this is in other units (millimetres)


@dataclass(frozen=True)
class RecognizeResult:
    """What ``cellsight recognize`` found in one scene, in the camera frame."""

    scene: Path
    points: int
    detections: list[Detection]
    picture: Path | None = None  # the scene with what was found drawn on it, when asked for

    def rows(self) -> list[dict]:
        return [
            {
                "object_id": d.object_id,
                **pose_json(d.camera_T_object),
                "fitness": round(d.fitness, 3),
                "coverage": round(d.coverage, 3),
                "rmse_m": round(d.rmse_m, 5),
                "cluster_points": d.points,
            }
            for d in self.detections
        ]

    def to_json(self) -> str:
        picture = None if self.picture is None else str(self.picture)
        out = {"scene": str(self.scene), "points": self.points, "detections": self.rows(), "picture": picture}
        return json.dumps(out, indent=2)

    def to_text(self) -> str:
        lines = [f"{self.scene}: {self.points} points, {len(self.detections)} object(s) (camera frame)"]
        for r in self.rows():
            x, y, z = r["position_m"]
            lines.append(
                f"  {r['object_id']:<12} at ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  q {r['quaternion_xyzw']}  "
                f"fitness {r['fitness']:.2f}  coverage {r['coverage']:.2f}  rmse {1000 * r['rmse_m']:.1f} mm"
            )
        if self.picture is not None:
            lines.append(f"  picture: {self.picture}")
        return "\n".join(lines)


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


def recognize_file(
    scene: Path, db: ModelDatabase, config: RecognitionConfig, picture: Path | None = None, **intrinsics
) -> RecognizeResult:
    """The database's objects in one scene file (``load_scene``'s ``intrinsics``); with ``picture``
    (.png or .jpg), the scene with them drawn (``cellsight.pictures.draw_recognition``) written there."""
    if picture is not None and picture.suffix.lower() not in PICTURE_SUFFIXES:
        raise RunError(f"picture {picture}: give a file ending in {' or '.join(PICTURE_SUFFIXES)}")
    cloud, rgb = load_scene(scene, **intrinsics)
    finite = int(np.all(np.isfinite(cloud.reshape(-1, 3)), axis=1).sum())
    detections = Recognizer(db, config).recognize(cloud, rgb=rgb)
    if picture is not None:
        from cellsight.pictures import draw_recognition  # the simulator's renderer comes with it

        picture.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(picture), draw_recognition(cloud, rgb, detections, db)):
            raise RunError(f"picture {picture}: could not be written")
    return RecognizeResult(scene, finite, detections, picture)
