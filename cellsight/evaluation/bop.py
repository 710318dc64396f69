"""Annotated RGB-D frames in the BOP format: read a dataset, write one, score detections against it.

BOP (Hodan et al., "BOP: Benchmark for 6D Object Pose Estimation", ECCV 2018) is how public pose
datasets ship (LM, LM-O, T-LESS, YCB-V, TUD-L, ...): ``models/obj_NNNNNN.ply`` (mm) with
``models_info.json``; per scene ``SPLIT/NNNNNN/`` with ``depth/``, ``rgb/``, ``scene_camera.json``
(``cam_K``, ``depth_scale``: mm per depth unit), ``scene_gt.json`` (``obj_id``, ``cam_R_m2c``,
``cam_t_m2c`` in mm) and optionally ``scene_gt_info.json`` (``visib_fract``). Everything leaves this
module in metres.

Ground truth is for measuring (``benchmarks.bop``, tests); nothing in recognition or the service
reads it.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from cellsight.errors import DatasetError
from cellsight.scene_files import read_depth_image, read_registered_rgb
from recognition.cloud import depth_to_cloud
from recognition.errors import CloudError
from recognition.pipeline import Recognizer, support_plane
from schemas.geometry import invert_pose

log = logging.getLogger(__name__)

#: The images BOP's challenges evaluate on, where a dataset names them (test split only): the
#: 2019 list of the classic datasets, else the 2024 one of the newer (HOPEv2, HANDAL, ...).
TARGETS_FILES = ("test_targets_bop19.json", "test_targets_bop24.json")
#: Where a dataset keeps its models, the first present taken when none is named: most ship
#: ``models/``; T-LESS ships ``models_cad/`` and ``models_reconst/``; every one ``models_eval/``.
MODEL_FOLDERS = ("models", "models_cad", "models_reconst", "models_eval")
#: A recognition is right when its ADD-S (mean distance to the closest model point) is below this share of the diameter.
ADDS_SHARE = 0.1


def object_id(obj_id: int) -> str:
    """The database id of BOP object ``obj_id``: its model file's stem, ``obj_000001``."""
    return f"obj_{obj_id:06d}"


@dataclass(frozen=True)
class BopModel:
    """One object's model file (mm), its diameter (m, from ``models_info.json``; None if not given)
    and whether the file holds faces (a mesh) or only points."""

    object_id: str
    path: Path
    diameter_m: float | None
    is_mesh: bool


@dataclass(frozen=True)
class BopInstance:
    """One annotated object in a frame: camera_T_object (4, 4, m) and the visible share of its
    silhouette (``visib_fract``, None where the dataset has no ``scene_gt_info.json``)."""

    object_id: str
    camera_T_object: np.ndarray
    visible_share: float | None


@dataclass(frozen=True)
class BopFrame:
    """One RGB-D frame: depth (and colour, if any) files, intrinsics K (3, 3, px), metres per depth
    unit, its annotated objects, and the camera's pose in the dataset's world (4, 4, m) where
    ``scene_camera.json`` gives one (``cam_R_w2c``, ``cam_t_w2c``)."""

    scene_id: int
    image_id: int
    depth_path: Path
    rgb_path: Path | None
    K: np.ndarray
    depth_scale_m: float
    truth: tuple[BopInstance, ...]
    world_T_camera: np.ndarray | None = None

    def load(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The organised cloud (H, W, 3, m; NaN without depth) and the registered colour (H, W, 3
        uint8 rgb), or None when the frame has no colour image of the depth's size."""
        depth = read_depth_image(self.depth_path)
        rgb = None
        if self.rgb_path is not None:
            try:
                rgb = read_registered_rgb(self.rgb_path, self.depth_path, depth.shape)
            except CloudError as exc:
                log.debug("frame %d/%d recognised on depth alone: %s", self.scene_id, self.image_id, exc)
        return depth_to_cloud(depth, self.K, self.depth_scale_m), rgb


@dataclass(frozen=True)
class BopDataset:
    """A BOP dataset's models and the frames of one split (the challenge's targets where listed)."""

    root: Path
    split: str
    models: dict[str, BopModel]
    frames: list[BopFrame]

    @classmethod
    def open(cls, root: str | Path, split: str = "test", models_dir: str | None = None) -> BopDataset:
        """The dataset at ``root``: every model of ``models_dir`` (None: the first of MODEL_FOLDERS
        it has), the frames of every scene folder of ``split``. A DatasetError names the file and
        field that are missing or malformed."""
        root = Path(root)
        if not root.is_dir():
            raise DatasetError(f"{root}: no such dataset folder")
        folders = sorted(p.name for p in root.iterdir() if p.is_dir())
        if models_dir is None:
            models_dir = next((m for m in MODEL_FOLDERS if m in folders), None)
            if models_dir is None:
                raise DatasetError(
                    f"{root} has none of the model folders {', '.join(MODEL_FOLDERS)} "
                    f"(folders: {', '.join(folders) or 'none'}); name the one to use"
                )
            log.info("%s: models from %s/", root, models_dir)
        elif models_dir not in folders:
            raise DatasetError(f"{root} has no model folder {models_dir!r} (folders: {', '.join(folders) or 'none'})")
        models = _models(root / models_dir)
        split_dir = root / split
        if not split_dir.is_dir():
            have = [f for f in folders if f not in MODEL_FOLDERS and f != models_dir]
            raise DatasetError(f"{root} has no split {split!r} (folders: {', '.join(have) or 'none'})")
        listed = next((root / f for f in TARGETS_FILES if (root / f).is_file()), None)
        targets = _targets(listed) if split.startswith("test") and listed is not None else None
        frames: list[BopFrame] = []
        for scene_dir in sorted(p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit()):
            frames += _scene_frames(scene_dir, models, targets)
        if not frames:
            raise DatasetError(f"{split_dir}: no frames (scene folders NNNNNN with scene_camera.json and depth/)")
        return cls(root, split, models, frames)


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(f"{path} is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: not JSON ({exc})") from None


def _ply_faces(path: Path) -> int:
    """The face count a PLY header declares (0 for a point cloud)."""
    with path.open("rb") as f:
        header = f.read(4096)
    if not header.startswith(b"ply"):
        raise DatasetError(f"{path}: not a PLY file")
    m = re.search(rb"element face (\d+)", header.split(b"end_header")[0])
    return int(m.group(1)) if m else 0


def _models(models_dir: Path) -> dict[str, BopModel]:
    info = _read_json(models_dir / "models_info.json")
    if not isinstance(info, dict) or not info:
        raise DatasetError(f"{models_dir / 'models_info.json'}: expected an object of obj_id -> model info")
    models = {}
    for key, value in info.items():
        if not key.isdigit():
            raise DatasetError(f"{models_dir / 'models_info.json'}: key {key!r} is no obj_id")
        oid = object_id(int(key))
        path = models_dir / f"{oid}.ply"
        if not path.is_file():
            raise DatasetError(f"{path} is missing (listed in models_info.json)")
        diameter = value.get("diameter") if isinstance(value, dict) else None
        models[oid] = BopModel(oid, path, None if diameter is None else float(diameter) / 1000.0, _ply_faces(path) > 0)
    return models


def _targets(path: Path) -> set[tuple[int, int]]:
    """(scene_id, im_id) of the challenge's target images, as the file at ``path`` lists them."""
    rows = _read_json(path)
    try:
        return {(int(r["scene_id"]), int(r["im_id"])) for r in rows}
    except (TypeError, KeyError, ValueError):
        raise DatasetError(f"{path}: expected a list of objects with scene_id and im_id") from None


def _pose(row: dict, where: str, rotation: str = "cam_R_m2c", translation: str = "cam_t_m2c") -> np.ndarray:
    """The 4x4 pose (m) of a BOP rotation (9 numbers, row-wise) and translation (3, mm)."""
    try:
        R = np.asarray(row[rotation], dtype=np.float64).reshape(3, 3)
        t = np.asarray(row[translation], dtype=np.float64).reshape(3)
    except (KeyError, ValueError, TypeError):
        raise DatasetError(f"{where}: {rotation} must be 9 numbers and {translation} 3 (mm)") from None
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))) or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise DatasetError(f"{where}: {rotation} is no rotation")
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t / 1000.0
    return T


def _image(folder: Path, image_id: int) -> Path | None:
    return next((p for p in (folder / f"{image_id:06d}{ext}" for ext in (".png", ".jpg", ".tif")) if p.is_file()), None)


def _scene_frames(scene_dir: Path, models: dict[str, BopModel], targets: set[tuple[int, int]] | None) -> list[BopFrame]:
    scene_id = int(scene_dir.name)
    cameras = _read_json(scene_dir / "scene_camera.json")
    gt_path, info_path = scene_dir / "scene_gt.json", scene_dir / "scene_gt_info.json"
    gt = _read_json(gt_path) if gt_path.is_file() else {}
    info = _read_json(info_path) if info_path.is_file() else {}
    if not all(isinstance(x, dict) for x in (cameras, gt, info)):
        raise DatasetError(f"{scene_dir}: scene_camera/scene_gt/scene_gt_info must map image ids to entries")
    if not all(k.isdigit() for k in cameras):
        raise DatasetError(f"{scene_dir / 'scene_camera.json'}: its keys must be image ids")
    frames = []
    for key, cam in sorted(cameras.items(), key=lambda kv: int(kv[0])):
        image_id = int(key)
        if targets is not None and (scene_id, image_id) not in targets:
            continue
        where = f"{scene_dir / 'scene_camera.json'} image {image_id}"
        try:
            K = np.asarray(cam["cam_K"], dtype=np.float64).reshape(3, 3)
            depth_scale = float(cam.get("depth_scale", 1.0))
        except (KeyError, ValueError, TypeError, AttributeError):
            raise DatasetError(f"{where}: cam_K must be 9 numbers and depth_scale a number (mm per unit)") from None
        if not depth_scale > 0:
            raise DatasetError(f"{where}: depth_scale {depth_scale:g} must be positive (mm per depth unit)")
        depth = _image(scene_dir / "depth", image_id)
        if depth is None:
            raise DatasetError(f"{scene_dir / 'depth'}: no image {image_id:06d}")
        truth = []
        rows, shares = (
            gt.get(key, []),
            [r.get("visib_fract") if isinstance(r, dict) else None for r in info.get(key, [])],
        )
        for i, row in enumerate(rows):
            if not isinstance(row, dict) or not str(row.get("obj_id", "")).isdigit():
                raise DatasetError(f"{gt_path} image {image_id}: entry {i} has no obj_id")
            oid = object_id(int(row["obj_id"]))
            if oid not in models:
                raise DatasetError(f"{gt_path} image {image_id}: obj_id {row['obj_id']} has no model")
            share = shares[i] if len(shares) == len(rows) else None
            truth.append(
                BopInstance(oid, _pose(row, f"{gt_path} image {image_id}"), None if share is None else float(share))
            )
        world_T_camera = invert_pose(_pose(cam, where, "cam_R_w2c", "cam_t_w2c")) if "cam_R_w2c" in cam else None
        frames.append(
            BopFrame(
                scene_id,
                image_id,
                depth,
                _image(scene_dir / "rgb", image_id),
                K,
                depth_scale / 1000.0,
                tuple(truth),
                world_T_camera,
            )
        )
    return frames


def adds_m(points: np.ndarray, camera_T_estimate: np.ndarray, camera_T_truth: np.ndarray) -> float:
    """ADD-S (m): the mean distance from each model point (N, 3) at the true pose to the closest model
    point at the estimated one. Symmetric shapes score their symmetric poses as right."""
    a = points @ camera_T_truth[:3, :3].T + camera_T_truth[:3, 3]
    b = points @ camera_T_estimate[:3, :3].T + camera_T_estimate[:3, 3]
    pa = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(a.astype(np.float64)))
    return float(
        np.mean(
            pa.compute_point_cloud_distance(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(b.astype(np.float64))))
        )
    )


@dataclass
class FrameScore:
    """One frame's detections against its annotations: per annotated instance whether a detection
    of its object lies within ADD-S 0.1 d (``found``, in ``frame.truth``'s order; ``matched``: that
    detection's index, None for none), and the detections that matched no instance (``false``: a
    wrong pose, or an object not annotated)."""

    found: list[bool] = field(default_factory=list)
    matched: list[int | None] = field(default_factory=list)
    false: list[str] = field(default_factory=list)


def score(
    truth: tuple[BopInstance, ...],
    detections: list[tuple[str, np.ndarray]],
    points: dict[str, np.ndarray],
    diameters: dict[str, float],
) -> FrameScore:
    """Match detections (object id, camera_T_object) to annotated instances, each at most once.
    points: each object's surface samples (N, 3, m); diameters (m)."""
    result, used = FrameScore(), set()
    for inst in truth:
        hit = next(
            (
                j
                for j, (oid, T) in enumerate(detections)
                if j not in used
                and oid == inst.object_id
                and adds_m(points[oid], T, inst.camera_T_object) < ADDS_SHARE * diameters[oid]
            ),
            None,
        )
        result.found.append(hit is not None)
        result.matched.append(hit)
        if hit is not None:
            used.add(hit)
    result.false = [oid for j, (oid, _) in enumerate(detections) if j not in used]
    return result


def level_world_pose(recognizer: Recognizer, cloud: np.ndarray, world_T_camera: np.ndarray | None) -> np.ndarray | None:
    """A frame's world pose (4, 4) if its world's z is up, as recognition takes it: a plane the
    frame shows (a table, the floor; ``Recognizer.prepare`` without a pose) is level in it. Else
    None: the frame is then recognised as without a pose. A dataset's world need not have z up (a
    marker board on a wall), and given a pose, recognition stands objects on its z: a wrong up would
    turn every object down."""
    if world_T_camera is None:
        return None
    return (
        world_T_camera if support_plane(recognizer.prepare(cloud).planes, world_T_camera[2, :3]) is not None else None
    )


def depth_of_organised(cloud: np.ndarray, focal_px: float) -> tuple[np.ndarray, np.ndarray]:
    """An organised cloud (H, W, 3, m, camera frame) as the depth image it was back-projected from:
    depth (H, W, m; NaN without a return) and K (3, 3) with the given focal length and the principal
    point that reproduces the cloud's x and y (the median over its points)."""
    z = cloud[..., 2]
    ok = np.isfinite(z) & (z > 0)
    if not ok.any():
        raise DatasetError("the organised cloud has no point in front of the camera")
    v, u = np.nonzero(ok)
    cx = float(np.median(u - focal_px * cloud[..., 0][ok] / z[ok]))
    cy = float(np.median(v - focal_px * cloud[..., 1][ok] / z[ok]))
    return np.where(ok, z, np.nan), np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])


class BopWriter:
    """Writes a BOP dataset (models in mm, one split) from arrays in metres; ``close`` writes the
    JSON files. For datasets made here: the simulated cell's frames, real frames re-packed."""

    def __init__(self, root: str | Path, split: str = "test") -> None:
        self.root, self.split = Path(root), split
        (self.root / "models").mkdir(parents=True, exist_ok=True)
        self._info: dict[str, dict] = {}
        self._scenes: dict[int, tuple[dict, dict, dict]] = {}  # scene -> (camera, gt, gt_info)

    def add_model(
        self,
        obj_id: int,
        vertices_m: np.ndarray,
        triangles: np.ndarray | None = None,
        colours: np.ndarray | None = None,
    ) -> None:
        """A mesh (vertices (V, 3) m, triangles (T, 3)) or, without triangles, a point model; colours (V, 3) rgb 0-1."""
        v = np.asarray(vertices_m, np.float64) * 1000.0
        path = self.root / "models" / f"{object_id(obj_id)}.ply"
        if triangles is not None and len(triangles):
            geom = o3d.geometry.TriangleMesh(
                o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(np.asarray(triangles, np.int32))
            )
            if colours is not None:
                geom.vertex_colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64))
            o3d.io.write_triangle_mesh(str(path), geom)
        else:
            geom = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v))
            if colours is not None:
                geom.colors = o3d.utility.Vector3dVector(np.asarray(colours, np.float64))
            o3d.io.write_point_cloud(str(path), geom)
        hull = v[np.unique(np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v)).compute_convex_hull()[1]))]
        diameter = float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)))
        lo, hi = v.min(axis=0), v.max(axis=0)
        self._info[str(obj_id)] = {
            "diameter": diameter,
            "min_x": lo[0],
            "min_y": lo[1],
            "min_z": lo[2],
            "size_x": hi[0] - lo[0],
            "size_y": hi[1] - lo[1],
            "size_z": hi[2] - lo[2],
        }

    def add_frame(
        self,
        scene_id: int,
        image_id: int,
        depth_m: np.ndarray,
        K: np.ndarray,
        truth: list[tuple[int, np.ndarray, float | None]],
        rgb: np.ndarray | None = None,
        depth_scale_mm: float = 0.2,
        world_T_camera: np.ndarray | None = None,
    ) -> None:
        """depth_m (H, W, m; 0 or NaN: no return) stored as 16-bit units of depth_scale_mm; truth:
        (obj_id, camera_T_object (4, 4, m), visible share or None); rgb (H, W, 3) uint8;
        world_T_camera (4, 4, m) if the camera's pose in a world frame is known."""
        scene = self.root / self.split / f"{scene_id:06d}"
        for sub in ("depth", "rgb"):
            (scene / sub).mkdir(parents=True, exist_ok=True)
        units = np.nan_to_num(np.asarray(depth_m, np.float64) * 1000.0 / depth_scale_mm, nan=0.0)
        if units.max(initial=0) > np.iinfo(np.uint16).max:
            raise DatasetError(
                f"depth up to {np.nanmax(depth_m):.2f} m overflows 16 bits at {depth_scale_mm} mm a unit"
            )
        cv2.imwrite(str(scene / "depth" / f"{image_id:06d}.png"), np.round(units).astype(np.uint16))
        if rgb is not None:
            cv2.imwrite(str(scene / "rgb" / f"{image_id:06d}.png"), np.ascontiguousarray(rgb[..., ::-1]))
        camera, gt, info = self._scenes.setdefault(scene_id, ({}, {}, {}))
        camera[str(image_id)] = {"cam_K": np.asarray(K, np.float64).reshape(-1).tolist(), "depth_scale": depth_scale_mm}
        if world_T_camera is not None:
            camera_T_world = invert_pose(world_T_camera)
            camera[str(image_id)] |= {
                "cam_R_w2c": camera_T_world[:3, :3].reshape(-1).tolist(),
                "cam_t_w2c": (camera_T_world[:3, 3] * 1000.0).tolist(),
            }
        gt[str(image_id)] = [
            {"obj_id": int(o), "cam_R_m2c": T[:3, :3].reshape(-1).tolist(), "cam_t_m2c": (T[:3, 3] * 1000.0).tolist()}
            for o, T, _ in truth
        ]
        info[str(image_id)] = [{"visib_fract": s} for _, _, s in truth if s is not None]

    def close(self) -> Path:
        (self.root / "models" / "models_info.json").write_text(json.dumps(self._info, indent=1))
        for scene_id, (camera, gt, info) in self._scenes.items():
            scene = self.root / self.split / f"{scene_id:06d}"
            (scene / "scene_camera.json").write_text(json.dumps(camera, indent=1))
            (scene / "scene_gt.json").write_text(json.dumps(gt, indent=1))
            if all(len(info[k]) == len(gt[k]) for k in gt):
                (scene / "scene_gt_info.json").write_text(json.dumps(info, indent=1))
        return self.root
