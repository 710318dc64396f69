"""``cellsight recognize``: the recognition pipeline on one scene file, as a result object."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cellsight.detect import pose_json
from cellsight.errors import RunError
from cellsight.scene_files import load_scene
from recognition.config import RecognitionConfig
from recognition.hypotheses import Detection
from recognition.models import ModelDatabase
from recognition.pipeline import Recognizer

PICTURE_SUFFIXES = (".png", ".jpg")


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


def recognize_file(
    scene: Path, db: ModelDatabase, config: RecognitionConfig, picture: Path | None = None, **intrinsics
) -> RecognizeResult:
    """The database's objects in one scene file (``load_scene``'s ``intrinsics``); with ``picture``
    (.png or .jpg), the scene with them drawn (``cellsight.evaluation.pictures.draw_recognition``) written there."""
    if picture is not None and picture.suffix.lower() not in PICTURE_SUFFIXES:
        raise RunError(f"picture {picture}: give a file ending in {' or '.join(PICTURE_SUFFIXES)}")
    cloud, rgb = load_scene(scene, **intrinsics)
    finite = int(np.all(np.isfinite(cloud.reshape(-1, 3)), axis=1).sum())
    detections = Recognizer(db, config).recognize(cloud, rgb=rgb)
    if picture is not None:
        from cellsight.evaluation.pictures import draw_recognition  # the simulator's renderer comes with it

        picture.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(picture), draw_recognition(cloud, rgb, detections, db)):
            raise RunError(f"picture {picture}: could not be written")
    return RecognizeResult(scene, finite, detections, picture)
