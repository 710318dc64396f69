"""``cellsight markers detect``: the marker front-end on one image file, as a result object."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.config import MarkerConfig
from drivers.errors import DriverError
from drivers.markers import MarkerDetection, MarkerDetector
from schemas.codec import CameraInfo
from schemas.geometry import quat_from_matrix


def pose_json(T: np.ndarray) -> dict[str, list[float]]:
    """A 4x4 pose as the JSON the one-shot commands print: position (m) and quaternion (x y z w)."""
    return {
        "position_m": np.round(T[:3, 3], 4).tolist(),
        "quaternion_xyzw": np.round(quat_from_matrix(T[:3, :3]), 5).tolist(),
    }


@dataclass(frozen=True)
class DetectResult:
    """What ``cellsight markers detect`` found in one image: each marker's corners (px) and pose in
    the camera frame (m), with the intrinsics used."""

    image: Path
    info: CameraInfo
    detections: list[MarkerDetection]

    def rows(self) -> list[dict]:
        out = []
        for d in self.detections:
            out.append(
                {
                    "id": d.marker_id,
                    "corners_px": np.round(d.corners_px, 2).tolist(),
                    **pose_json(d.camera_T_marker),
                    "reprojection_error_px": [round(d.error_a_px, 3), round(d.error_b_px, 3)],
                    "depth_refined": d.depth_refined,
                    "ambiguous": d.ambiguous,
                    "sigma_position_m": np.round(np.sqrt(np.diag(d.covariance)[:3]), 4).tolist(),
                }
            )
        return out

    def to_json(self) -> str:
        return json.dumps({"image": str(self.image), "markers": self.rows()})

    def to_text(self) -> str:
        lines = [f"{self.image}: {len(self.detections)} markers"]
        for r in self.rows():
            x, y, z = r["position_m"]
            flag = " depth" if r["depth_refined"] else (" ambiguous" if r["ambiguous"] else "")
            lines.append(
                f"  id {r['id']:4d}  at ({x:+.3f}, {y:+.3f}, {z:+.3f}) m  reproj {r['reprojection_error_px'][0]:.2f} px{flag}"
            )
        return "\n".join(lines)


def read_camera_info(path: Path, width: int, height: int) -> CameraInfo:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise DriverError(f"{path}: cannot open camera info file")
    K, D = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    fs.release()
    if K is None:
        raise DriverError(f"{path}: no camera_matrix in the file")
    return CameraInfo(width, height, K, np.zeros(5) if D is None else D.ravel())


def detect_file(
    image: Path, dictionary: str, camera_info: Path | None, size_m: float, depth: Path | None, annotate: Path | None
) -> DetectResult:
    bgr = cv2.imread(str(image), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DriverError(f"{image}: not a readable image")
    if not size_m > 0:
        raise DriverError(f"marker size must be positive, got {size_m}")
    h, w = bgr.shape[:2]
    info = read_camera_info(camera_info, w, h) if camera_info else CameraInfo.kinect_v1(w, h)
    depth_mm = None
    if depth is not None:
        depth_mm = cv2.imread(str(depth), cv2.IMREAD_ANYDEPTH)
        if depth_mm is None or depth_mm.dtype != np.uint16:
            raise DriverError(f"{depth}: expected a 16-bit depth PNG in millimetres")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    dets = MarkerDetector(MarkerConfig(dictionary=dictionary, side_m=size_m)).detect(rgb, info, depth_mm)
    if annotate is not None:
        cv2.imwrite(str(annotate), draw_detections(bgr, info, dets))
    return DetectResult(image, info, dets)


def draw_detections(bgr: np.ndarray, info: CameraInfo, dets: list[MarkerDetection]) -> np.ndarray:
    """The image with marker outlines, ids and pose axes drawn (BGR in, BGR out)."""
    out = bgr.copy()
    if dets:
        cv2.aruco.drawDetectedMarkers(
            out,
            [d.corners_px.reshape(1, 4, 2).astype(np.float32) for d in dets],
            np.array([[d.marker_id] for d in dets]),
        )
    for d in dets:
        rvec, _ = cv2.Rodrigues(d.camera_T_marker[:3, :3])
        cv2.drawFrameAxes(out, info.K, info.D, rvec, d.camera_T_marker[:3, 3], d.side_m * 0.5, 2)
    return out
