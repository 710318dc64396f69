"""The model database: per object a model cloud, and per view a VFH, a roll histogram and the view pose.

On disk (``cellsight model build`` writes it)::

    DIR/database.json        format, descriptor parameters, object ids
    DIR/<object>/model.ply   model points with normals, object frame, metres
    DIR/<object>/views.npz   vfh (V, 308), roll (V, 90), centroid (V, 3), view_T_object (V, 4, 4)
    DIR/<object>/model.json  source, diameter, view count

Views come from three sources: a mesh rendered from viewpoints on a tessellated sphere; a point cloud
(its own capture viewpoint, plus sphere viewpoints through hidden-point removal); and multi-view
recordings merged on a marker board (``recognition.recording``).
"""

from __future__ import annotations

import itertools
import json
import logging
import multiprocessing
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import open3d as o3d
from pydantic import ValidationError

from recognition.cloud import (
    camera_rays,
    depth_to_cloud,
    estimate_normals,
    finite_points,
    image_window,
    voxel_downsample_coloured,
)
from recognition.config import DescriptorConfig
from recognition.descriptor import describe, prepare
from recognition.errors import ModelError
from recognition.texture import texture_colours
from recognition.verify import chroma_ranges
from recognition.vfh import ROLL_BINS, SIZE
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose, look_at_matrix, make_pose

log = logging.getLogger(__name__)
FORMAT = 1
#: Fewest points a view needs to describe anything.
MIN_VIEW_POINTS = 30
#: Distances (m) a mesh or point model is seen from for its views: a cell's cameras at 2 m, and
#: close, as datasets' frames are taken (a view's descriptor changes with the perspective:
#: ``benchmarks.bop`` near the camera 0.884 with views from 2 m alone, 0.913 with both).
VIEW_DISTANCES_M = (2.0, 0.8)
#: Sizes (m, bounding-box diagonal) an object a cell's cameras recognise can have: outside them a
#: model file is in other units (libraries ship millimetres too), not a smaller or larger object.
OBJECT_SIZE_M = (0.005, 5.0)


@dataclass(frozen=True)
class Views:
    """Per-view descriptors of one object. vfh (V, 308); roll (V, 90); centroid (V, 3) m in the view's
    camera frame; view_T_object (V, 4, 4)."""

    vfh: np.ndarray
    roll: np.ndarray
    centroid: np.ndarray
    view_T_object: np.ndarray

    def __len__(self) -> int:
        return len(self.vfh)


@dataclass(frozen=True)
class ObjectModel:
    """One object: points, normals (M, 3) in its own frame, metres; its views; diameter (m); the
    points' colours (M, 3) rgb 0-1, when the source has them (verification then judges colour; black
    is too dark to judge, so it also stands for a point whose colour no source saw)."""

    object_id: str
    points: np.ndarray
    normals: np.ndarray
    views: Views
    source: str
    colours: np.ndarray | None = None

    @cached_property
    def chroma_range(self) -> np.ndarray | None:
        """Each point's colours as verification judges them (``recognition.verify.chroma_ranges``), (M, 4)."""
        return None if self.colours is None else chroma_ranges(self.points, self.colours)

    @property
    def stands_on_z(self) -> bool:
        """Whether the object stands on its frame's +z (meshes, whole-surface points, recordings on a
        board: the upright test applies); a captured cloud's frame is its camera's."""
        return self.source != "cloud"

    @cached_property
    def centre(self) -> np.ndarray:
        """The points' mean (3,), object frame, m."""
        return self.points.mean(axis=0)

    @cached_property
    def diameter_m(self) -> float:
        """Largest distance between two model points (bounded from the axis-aligned box)."""
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        return float(np.linalg.norm(hi - lo))


@dataclass
class ModelDatabase:
    """Object models sharing one descriptor configuration."""

    descriptor: DescriptorConfig
    models: dict[str, ObjectModel]

    def add(self, model: ObjectModel) -> None:
        if len(model.views) == 0:
            raise ModelError(f"object {model.object_id!r}: no usable view (too few points seen from every viewpoint)")
        self.models[model.object_id] = model

    def view_table(self) -> tuple[Views, list[str]]:
        """Every object's views stacked into one ``Views`` (V rows), and each row's object id."""
        owners = [oid for oid, mdl in self.models.items() for _ in range(len(mdl.views))]
        if not owners:
            empty = Views(
                np.zeros((0, SIZE), np.float32), np.zeros((0, ROLL_BINS)), np.zeros((0, 3)), np.zeros((0, 4, 4))
            )
            return empty, []
        fields = [
            np.concatenate([getattr(mdl.views, f) for mdl in self.models.values()])
            for f in ("vfh", "roll", "centroid", "view_T_object")
        ]
        return Views(*fields), owners

    def save(self, directory: str | Path) -> Path:
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        for oid, mdl in self.models.items():
            od = d / oid
            od.mkdir(exist_ok=True)
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(mdl.points.astype(np.float64)))
            pcd.normals = o3d.utility.Vector3dVector(mdl.normals.astype(np.float64))
            if mdl.colours is not None:
                pcd.colors = o3d.utility.Vector3dVector(mdl.colours.astype(np.float64))
            o3d.io.write_point_cloud(str(od / "model.ply"), pcd)
            v = mdl.views
            np.savez(od / "views.npz", vfh=v.vfh, roll=v.roll, centroid=v.centroid, view_T_object=v.view_T_object)
            meta = {"object_id": oid, "source": mdl.source, "diameter_m": mdl.diameter_m, "views": len(v)}
            (od / "model.json").write_text(json.dumps(meta, indent=2) + "\n")
        index = {"format": FORMAT, "descriptor": self.descriptor.model_dump(), "objects": sorted(self.models)}
        (d / "database.json").write_text(json.dumps(index, indent=2) + "\n")
        return d

    @classmethod
    def load(cls, directory: str | Path) -> ModelDatabase:
        d = Path(directory)
        index_file = d / "database.json"
        if not index_file.is_file():
            raise ModelError(f"{d} is not a model database (no database.json); build one with `cellsight model build`")
        try:
            index = json.loads(index_file.read_text())
            if index.get("format") != FORMAT:
                raise ModelError(f"{index_file}: format {index.get('format')!r}, this version reads {FORMAT}")
            db = cls(DescriptorConfig.model_validate(index["descriptor"]), {})
            for oid in index["objects"]:
                db.add(_load_model(d / oid, oid))
        except (KeyError, TypeError, json.JSONDecodeError, ValidationError) as exc:
            raise ModelError(f"{index_file} is damaged: {exc}") from exc
        return db


def _load_model(od: Path, oid: str) -> ObjectModel:
    pcd = o3d.io.read_point_cloud(str(od / "model.ply"))
    if not pcd.has_points() or not pcd.has_normals():
        raise ModelError(f"{od / 'model.ply'}: missing, empty or without normals")
    try:
        with np.load(od / "views.npz") as z:
            views = Views(z["vfh"], z["roll"], z["centroid"], z["view_T_object"])
    except (OSError, KeyError, ValueError) as exc:
        raise ModelError(f"{od / 'views.npz'} is unreadable: {exc}") from exc
    n = len(views.vfh)
    shapes = {"vfh": (n, SIZE), "roll": (n, ROLL_BINS), "centroid": (n, 3), "view_T_object": (n, 4, 4)}
    for name, shape in shapes.items():
        if getattr(views, name).shape != shape or not np.all(np.isfinite(getattr(views, name))):
            raise ModelError(f"{od / 'views.npz'}: {name} should be finite with shape {shape}")
    meta = json.loads((od / "model.json").read_text()) if (od / "model.json").is_file() else {}
    colours = np.asarray(pcd.colors, np.float32) if pcd.has_colors() else None
    return ObjectModel(
        oid,
        np.asarray(pcd.points, np.float32),
        np.asarray(pcd.normals, np.float32),
        views,
        str(meta.get("source", "")),
        colours,
    )


def sphere_viewpoints(subdivisions: int = 1) -> np.ndarray:
    """Unit directions of a tessellated icosahedron: 12, 42, 162 ... views for 0, 1, 2 subdivisions."""
    ico = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    if subdivisions > 0:
        ico = ico.subdivide_loop(subdivisions)
    v = np.asarray(ico.vertices)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _object_T_view(centre: np.ndarray, direction: np.ndarray, distance_m: float) -> np.ndarray:
    """Pose of a virtual camera at centre + distance * direction looking at centre (up: object +z)."""
    position = centre + distance_m * direction
    up = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    return make_pose(look_at_matrix(position, centre, up), position)


def describe_views(
    clouds: Iterable[tuple[np.ndarray, np.ndarray]], params: DescriptorConfig, progress: Callable[[], None] | None
) -> Views:
    """Describe each (points in the view's camera frame, view_T_object) pair that has enough points."""
    vfhs, rolls, cents, poses = [], [], [], []
    for pts, view_T_object in clouds:
        if progress:
            progress()
        if len(pts) < MIN_VIEW_POINTS:
            continue
        p, n = prepare(pts, params)
        if len(p) < MIN_VIEW_POINTS:
            continue
        desc = describe(p, n, params)
        vfhs.append(desc.vfh)
        rolls.append(desc.roll)
        cents.append(desc.centroid)
        poses.append(view_T_object)
    if not vfhs:
        return Views(np.zeros((0, SIZE), np.float32), np.zeros((0, ROLL_BINS)), np.zeros((0, 3)), np.zeros((0, 4, 4)))
    return Views(np.stack(vfhs), np.stack(rolls), np.stack(cents), np.stack(poses))


def check_size(object_id: str, points: np.ndarray) -> None:
    """A ModelError naming the likely unit if the points (N, 3) span no object size in metres."""
    lo, hi = OBJECT_SIZE_M
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) if len(points) else 0.0
    if lo <= size <= hi:
        return
    hint = next(
        (
            f": in {unit}? scale it by {factor:g}"
            for unit, factor in (("millimetres", 1e-3), ("centimetres", 1e-2))
            if lo <= size * factor <= hi
        ),
        "",
    )
    raise ModelError(
        f"object {object_id!r} is {size:.4g} across, and models are in metres (an object here is {lo:g}-{hi:g} m){hint}"
    )


def model_from_mesh(
    object_id: str,
    mesh: o3d.geometry.TriangleMesh,
    params: DescriptorConfig,
    *,
    distances_m: Sequence[float] = VIEW_DISTANCES_M,
    subdivisions: int = 1,
    camera: CameraInfo | None = None,
    progress: Callable[[], None] | None = None,
) -> ObjectModel:
    """Render a mesh (object frame, metres) from viewpoints on tessellated spheres around its centre,
    one sphere per distance (m).

    Each view is a noise-free depth image from a virtual Kinect (default intrinsics), back-projected
    exactly as a live frame is, so model and scene descriptors are computed alike. The mesh's vertex
    colours, if it has them, become the model's colours.
    """
    if len(mesh.triangles) == 0:
        raise ModelError(f"object {object_id!r}: the mesh has no triangles")
    check_size(object_id, np.asarray(mesh.vertices))
    camera = camera or CameraInfo.kinect_v1()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    box = mesh.get_axis_aligned_bounding_box()
    centre, corners = box.get_center(), np.asarray(box.get_box_points())

    def rendered():
        for distance_m, direction in itertools.product(distances_m, sphere_viewpoints(subdivisions)):
            object_T_view = _object_T_view(centre, direction, distance_m)
            view_T_object = invert_pose(object_T_view)
            # Only the pixels where the object's box projects (a few % of the image) can see it.
            u0, v0, u1, v1 = image_window(
                camera.K, camera.width, camera.height, corners @ view_T_object[:3, :3].T + view_T_object[:3, 3]
            )
            if u1 <= u0 or v1 <= v0:
                yield np.zeros((0, 3), np.float32), view_T_object
                continue
            rays = o3d.core.Tensor(camera_rays(camera.K, camera.width, camera.height, object_T_view, (u0, v0, u1, v1)))
            t_hit = scene.cast_rays(rays)["t_hit"].numpy().reshape(v1 - v0, u1 - u0)
            K = camera.K.copy()
            K[:2, 2] -= (u0, v0)  # the window's own principal point
            yield (
                finite_points(depth_to_cloud(np.where(np.isfinite(t_hit), t_hit, 0.0), K, depth_scale=1.0)),
                view_T_object,
            )

    views = describe_views(rendered(), params, progress)
    area = mesh.get_surface_area()
    o3d.utility.random.seed(0)  # the same mesh gives the same model, run after run
    sample = mesh.sample_points_uniformly(max(1000, int(4 * area / params.voxel_m**2)), use_triangle_normal=True)
    sample = sample.voxel_down_sample(params.voxel_m)
    normals = np.asarray(sample.normals)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colours = np.asarray(sample.colors, np.float32) if mesh.has_vertex_colors() else None
    return ObjectModel(
        object_id, np.asarray(sample.points, np.float32), normals.astype(np.float32), views, "mesh", colours
    )


def model_from_cloud(
    object_id: str,
    points: np.ndarray,
    params: DescriptorConfig,
    *,
    viewpoint: np.ndarray | tuple = (0.0, 0.0, 0.0),
    distance_m: float = 1.0,
    subdivisions: int = 1,
    colours: np.ndarray | None = None,
    progress: Callable[[], None] | None = None,
) -> ObjectModel:
    """A model from a point cloud (object frame = the cloud's frame, metres).

    The first view is the cloud as captured from ``viewpoint`` (a PCD's VIEWPOINT; the origin for a
    sensor capture). Further views come from sphere viewpoints through hidden-point removal, kept
    only when most of what they see faces them (a partial scan seen from behind is not a view).
    colours: the points' rgb (N, 3) uint8, if the capture has them.
    """
    pts, colours = _finite(points, colours)
    if len(pts) < MIN_VIEW_POINTS:
        raise ModelError(f"object {object_id!r}: the cloud has {len(pts)} finite points, need {MIN_VIEW_POINTS}")
    check_size(object_id, pts)
    vp = np.asarray(viewpoint, dtype=np.float64)
    model_pts, model_colours = voxel_downsample_coloured(pts, colours, params.voxel_m)
    model_normals, _ = estimate_normals(model_pts, params.normal_radius_m, vp)
    ok = np.all(np.isfinite(model_normals), axis=1)
    model_pts, model_normals = model_pts[ok], model_normals[ok]
    centre = model_pts.mean(axis=0)
    pts_normals, _ = estimate_normals(pts, params.normal_radius_m, vp)

    def seen():
        view_T_object = np.eye(4)
        view_T_object[:3, 3] = -vp
        yield pts - vp, view_T_object  # the capture itself (its camera's rotation is the cloud frame's)
        yield from _hidden_point_views(pts, pts_normals, centre, distance_m, subdivisions)

    views = describe_views(seen(), params, progress)
    return ObjectModel(
        object_id, model_pts, model_normals, views, "cloud", None if model_colours is None else model_colours[ok]
    )


def model_from_points(
    object_id: str,
    points: np.ndarray,
    params: DescriptorConfig,
    *,
    distances_m: Sequence[float] = VIEW_DISTANCES_M,
    subdivisions: int = 1,
    colours: np.ndarray | None = None,
    progress: Callable[[], None] | None = None,
) -> ObjectModel:
    """A model from points over an object's whole surface (object frame, metres), as model libraries
    ship them: views from sphere viewpoints (one sphere per distance, m) through hidden-point
    removal, normals pointing away from the points' centroid (right for convex shapes and most
    boxes and bottles). colours: the points' rgb (N, 3) uint8, if the file has them."""
    pts, colours = _finite(points, colours)
    if len(pts) < MIN_VIEW_POINTS:
        raise ModelError(f"object {object_id!r}: the points have {len(pts)} finite ones, need {MIN_VIEW_POINTS}")
    check_size(object_id, pts)
    centre = pts.mean(axis=0)
    model_pts, model_colours = voxel_downsample_coloured(pts, colours, params.voxel_m)
    inward, _ = estimate_normals(model_pts, params.normal_radius_m, centre)  # faced to the centroid ...
    ok = np.all(np.isfinite(inward), axis=1)
    pts_inward, _ = estimate_normals(pts, params.normal_radius_m, centre)
    views = describe_views(
        (view for d in distances_m for view in _hidden_point_views(pts, -pts_inward, centre, d, subdivisions)),
        params,
        progress,
    )
    kept_colours = None if model_colours is None else model_colours[ok]
    return ObjectModel(object_id, model_pts[ok], -inward[ok], views, "points", kept_colours)  # ... and turned outward


def _finite(points: np.ndarray, colours: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """The finite points (N, 3) float64 and their colours as rgb 0-1 (N, 3), or None."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(pts), axis=1)
    if colours is None:
        return pts[finite], None
    rgb = np.asarray(colours).reshape(-1, 3)
    if len(rgb) != len(pts):
        raise ModelError(f"{len(rgb)} colours for {len(pts)} points: one rgb triple per point")
    return pts[finite], rgb[finite].astype(np.float64) / 255.0


def _hidden_point_views(pts: np.ndarray, normals: np.ndarray, centre: np.ndarray, distance_m: float, subdivisions: int):
    """(points in the view's camera frame, view_T_object) of each sphere viewpoint whose visible
    points (hidden-point removal) mostly face it: a partial scan seen from behind is not a view."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    for direction in sphere_viewpoints(subdivisions):
        object_T_view = _object_T_view(centre, direction, distance_m)
        _, visible = pcd.hidden_point_removal(object_T_view[:3, 3], distance_m * 100)
        idx = np.asarray(visible)
        facing = np.einsum("ij,ij->i", normals[idx], object_T_view[:3, 3] - pts[idx]) > 0
        if len(idx) == 0 or facing.mean() < 0.5:
            continue
        view_T_object = invert_pose(object_T_view)
        yield pts[idx] @ view_T_object[:3, :3].T + view_T_object[:3, 3], view_T_object


def read_mesh(path: str | Path) -> o3d.geometry.TriangleMesh:
    """A triangle mesh (PLY, OBJ, STL, OFF, glTF) in metres; clear error if unreadable or empty.

    Open3D's mesh readers trust the file: a damaged binary PLY (a face list whose count or vertex
    index points past the data) kills the process with SIGSEGV. The read therefore runs in a fresh
    child process and its death becomes a ModelError. The children are forked from a fork server
    that imported Open3D once (about two seconds), so each further read costs milliseconds.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"mesh file {path} does not exist")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])  # takes effect when the server starts, on the first read
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        try:
            vertices, triangles, colours = pool.submit(_mesh_arrays, str(path)).result()
        except BrokenProcessPool as exc:
            raise ModelError(f"mesh file {path} is damaged: Open3D's reader crashed on it") from exc
    if len(triangles) == 0:
        raise ModelError(f"mesh file {path} holds no triangles (unreadable, or a point cloud: use --cloud)")
    if not np.all(np.isfinite(vertices)):
        raise ModelError(f"mesh file {path} has non-finite vertices")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise ModelError(f"mesh file {path} has faces indexing vertices that do not exist ({len(vertices)} vertices)")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    if len(colours) == len(vertices):
        mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
    return mesh


def _mesh_arrays(path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64, triangles (T, 3) int32 and vertex colours (V, 3) rgb 0-1 (or (0, 3))
    of a mesh file, from its texture when it has one instead (runs in read_mesh's child)."""
    mesh = o3d.io.read_triangle_mesh(path)
    colours = np.asarray(mesh.vertex_colors).copy()
    if len(colours) == 0 and len(mesh.vertices):
        try:
            colours = texture_colours(mesh, path)
        except (OSError, ValueError, IndexError) as exc:  # a damaged texture part: the shape still reads
            log.warning("%s: its texture coordinates cannot be read (%s); the model has no colours", path, exc)
            colours = None
        colours = np.zeros((0, 3)) if colours is None else colours
    return np.asarray(mesh.vertices).copy(), np.asarray(mesh.triangles).copy(), colours
