"""Ray-cast RGB-D rendering of a scenario with Open3D, plus the Kinect v1 noise model.

Two ``RaycastingScene``s: the static one (floor, boxes, static markers) is cast once per camera
pose and cached; the dynamic one (objects and their markers) is rebuilt when objects move and cast
only inside the objects' projected bounding box. Per-frame cost for a static camera is then the
noise model alone.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from drivers.errors import ScenarioError
from drivers.sim.scenario import MarkerSpec, ObjectSpec, Scenario
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose

log = logging.getLogger(__name__)
INVALID = o3d.t.geometry.RaycastingScene.INVALID_ID
TEXTURE_PX_PER_MODULE = 10


@dataclass(frozen=True)
class SimFrame:
    """One rendered frame. rgb (H, W, 3) uint8; depth_mm (H, W) uint16, 0 = no return."""

    camera_id: str
    stamp_ns: int
    rgb: np.ndarray
    depth_mm: np.ndarray
    info: CameraInfo
    world_T_camera: np.ndarray


@dataclass
class _Layer:
    """Clean render of one scene for one camera: z (m, inf = miss), cos of incidence, albedo."""

    z: np.ndarray
    cos: np.ndarray
    color: np.ndarray


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """OpenCV predefined dictionary by name (e.g. 'DICT_APRILTAG_36h11'); clear error if unknown."""
    code = getattr(cv2.aruco, name, None)
    if not isinstance(code, int):
        raise ScenarioError(f"unknown marker dictionary {name!r}; use an OpenCV name such as DICT_APRILTAG_36h11")
    return cv2.aruco.getPredefinedDictionary(code)


def marker_texture(dictionary: cv2.aruco.Dictionary, marker_id: int) -> tuple[np.ndarray, float]:
    """Grey texture of a marker with a one-module white quiet zone; returns it and quad/side ratio."""
    modules = dictionary.markerSize + 2
    if marker_id >= dictionary.bytesList.shape[0]:
        raise ScenarioError(f"marker id {marker_id} is not in a dictionary of {dictionary.bytesList.shape[0]} markers")
    img = cv2.aruco.generateImageMarker(dictionary, marker_id, modules * TEXTURE_PX_PER_MODULE, borderBits=1)
    pad = TEXTURE_PX_PER_MODULE
    img = cv2.copyMakeBorder(img, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    return img.astype(np.float32) / 255.0, (modules + 2) / modules


def _box_mesh(size, T: np.ndarray) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-np.asarray(size) / 2.0)
    return mesh.transform(T)


def object_mesh(obj: ObjectSpec) -> o3d.geometry.TriangleMesh:
    """Mesh in the object frame (origin at the base centre, z up)."""
    if obj.shape == "box":
        mesh = o3d.geometry.TriangleMesh.create_box(*obj.size)
        mesh.translate([-obj.size[0] / 2, -obj.size[1] / 2, 0.0])
    elif obj.shape == "cylinder":
        mesh = o3d.geometry.TriangleMesh.create_cylinder(obj.size[0], obj.size[2], resolution=32)
        mesh.translate([0.0, 0.0, obj.size[2] / 2])
    elif obj.shape == "sphere":
        mesh = o3d.geometry.TriangleMesh.create_sphere(obj.size[0], resolution=20)
        mesh.translate([0.0, 0.0, obj.size[0]])
    else:
        mesh = o3d.io.read_triangle_mesh(str(obj.mesh))
        if len(mesh.triangles) == 0:
            raise ScenarioError(f"object {obj.id}: mesh file {obj.mesh} has no triangles (missing or unreadable)")
    return mesh


def _quad_mesh(half: float, T: np.ndarray) -> o3d.geometry.TriangleMesh:
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], dtype=float)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]]))
    return mesh.transform(T)


class _Scene:
    """A RaycastingScene with per-geometry materials: a flat colour, or a marker texture."""

    def __init__(self) -> None:
        self.scene = o3d.t.geometry.RaycastingScene()
        self.colors: dict[int, np.ndarray] = {}
        self.markers: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}  # id -> (marker_T_world, texture, half)
        self.points: list[np.ndarray] = []

    def add(self, mesh: o3d.geometry.TriangleMesh, color) -> int:
        gid = self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        self.colors[gid] = np.asarray(color, dtype=np.float32)
        self.points.append(np.asarray(mesh.vertices))
        return gid

    def add_marker(self, world_T_marker: np.ndarray, texture: np.ndarray, quad_side: float) -> None:
        gid = self.add(_quad_mesh(quad_side / 2, world_T_marker), (1.0, 1.0, 1.0))
        self.markers[gid] = (invert_pose(world_T_marker), texture, quad_side / 2)

    def cast(self, rays: np.ndarray, origin: np.ndarray, dirs: np.ndarray, light: np.ndarray) -> _Layer:
        """Cast (N, 6) rays; dirs (N, 3) world directions with unit z in the camera frame."""
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy()
        normals = ans["primitive_normals"].numpy()
        hit = gid != INVALID
        z = np.where(hit, t, np.inf).astype(np.float32)
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        cos = np.abs(np.einsum("ij,ij->i", normals, unit)).astype(np.float32)
        color = np.zeros((len(t), 3), np.float32)
        for g, c in self.colors.items():
            sel = gid == g
            if not sel.any():
                continue
            if g in self.markers:
                marker_T_world, tex, half = self.markers[g]
                p = origin + t[sel, None] * dirs[sel]
                pm = p @ marker_T_world[:3, :3].T + marker_T_world[:3, 3]
                size = tex.shape[0]
                u = ((pm[:, 0] / half + 1.0) * 0.5 * size - 0.5).astype(np.float32)
                v = ((1.0 - pm[:, 1] / half) * 0.5 * size - 0.5).astype(np.float32)
                color[sel] = _sample(tex, u, v)[:, None]
            else:
                color[sel] = c
        # Lambert shading from an overhead light plus ambient: enough for markers to have contrast.
        lambert = np.abs(normals @ light).astype(np.float32)
        color *= (0.45 + 0.55 * lambert)[:, None]
        return _Layer(z, cos, color)


class SimCell:
    """Renders any camera of a scenario at any time. Deterministic for a given seed and frame index."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.dictionary = aruco_dictionary(scenario.dictionary)
        self._textures = {m.id: marker_texture(self.dictionary, m.id) for m in scenario.markers}
        self._light = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
        self.static = self._build_static()
        self._dynamic: _Scene | None = None
        self._dynamic_key: tuple | None = None
        self._cache: dict[str, tuple[np.ndarray, _Layer]] = {}
        self._rays: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------ scene building

    def _build_static(self) -> _Scene:
        s = _Scene()
        fx, fy = self.scenario.floor_size
        floor = _box_mesh((fx, fy, 0.01), np.eye(4))
        floor.translate([0, 0, -0.005])
        s.add(floor, self.scenario.floor_color)
        for box in self.scenario.boxes:
            s.add(_box_mesh(box.size, box.pose.matrix()), box.color)
        for mk in self.scenario.markers:
            if mk.object is None:
                self._add_marker(s, mk, 0.0)
        return s

    def _add_marker(self, s: _Scene, mk: MarkerSpec, t_s: float) -> None:
        tex, ratio = self._textures[mk.id]
        s.add_marker(self.scenario.world_T_marker(mk, t_s), tex, self.scenario.side_of(mk) * ratio)

    def _dynamic_scene(self, t_s: float) -> _Scene | None:
        if not self.scenario.objects:
            return None
        poses = [o.world_T_object(t_s) for o in self.scenario.objects]
        key = tuple(np.round(np.concatenate([p[:3].ravel() for p in poses]), 9))
        if key != self._dynamic_key:
            s = _Scene()
            for obj, T in zip(self.scenario.objects, poses):
                s.add(object_mesh(obj).transform(T), obj.color)
            for mk in self.scenario.markers:
                if mk.object is not None:
                    self._add_marker(s, mk, t_s)
            self._dynamic, self._dynamic_key = s, key
        return self._dynamic

    # ------------------------------------------------------------ rendering

    def _camera_dirs(self, cam_id: str, info: CameraInfo) -> np.ndarray:
        """(H*W, 3) camera-frame ray directions with z = 1, cached per camera."""
        if cam_id not in self._rays:
            u, v = np.meshgrid(np.arange(info.width), np.arange(info.height))
            x = (u - info.K[0, 2]) / info.K[0, 0]
            y = (v - info.K[1, 2]) / info.K[1, 1]
            self._rays[cam_id] = np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3)
        return self._rays[cam_id]

    def _static_layer(self, cam_id: str, info: CameraInfo, world_T_camera: np.ndarray) -> _Layer:
        cached = self._cache.get(cam_id)
        if cached is not None and np.array_equal(cached[0], world_T_camera):
            return cached[1]
        dirs = self._camera_dirs(cam_id, info) @ world_T_camera[:3, :3].T
        origin = world_T_camera[:3, 3]
        rays = np.hstack([np.broadcast_to(origin, dirs.shape), dirs]).astype(np.float32)
        layer = self.static.cast(rays, origin, dirs, self._light)
        self._cache[cam_id] = (world_T_camera.copy(), layer)
        return layer

    def _dynamic_roi(self, dyn: _Scene, info: CameraInfo, world_T_camera: np.ndarray) -> np.ndarray | None:
        """Flat pixel indices inside the projected bounding box of the dynamic geometry."""
        pts = np.vstack(dyn.points)
        lo, hi = pts.min(0), pts.max(0)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        cam_T_world = invert_pose(world_T_camera)
        pc = corners @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
        if np.all(pc[:, 2] <= 0.05):
            return None
        if np.any(pc[:, 2] <= 0.05):  # box straddles the camera plane: cast everything
            u0, v0, u1, v1 = 0, 0, info.width, info.height
        else:
            uv = pc[:, :2] / pc[:, 2:3] * [info.K[0, 0], info.K[1, 1]] + [info.K[0, 2], info.K[1, 2]]
            u0, v0 = np.maximum(np.floor(uv.min(0)).astype(int) - 1, 0)
            u1, v1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 2, [info.width, info.height])
        if u1 <= u0 or v1 <= v0:
            return None
        vv, uu = np.meshgrid(np.arange(v0, v1), np.arange(u0, u1), indexing="ij")
        return (vv * info.width + uu).ravel()

    def clean(self, cam_id: str, t_s: float) -> tuple[_Layer, CameraInfo, np.ndarray]:
        """Noise-free render: the composed layer, intrinsics and world_T_camera at ``t_s``."""
        cam = self.scenario.camera(cam_id)
        info = cam.camera_info()
        world_T_camera = cam.world_T_camera(t_s)
        static = self._static_layer(cam_id, info, world_T_camera)
        dyn = self._dynamic_scene(t_s)
        idx = None if dyn is None else self._dynamic_roi(dyn, info, world_T_camera)
        if idx is None:
            return static, info, world_T_camera
        dirs = self._camera_dirs(cam_id, info)[idx] @ world_T_camera[:3, :3].T
        origin = world_T_camera[:3, 3]
        rays = np.hstack([np.broadcast_to(origin, dirs.shape), dirs]).astype(np.float32)
        d = dyn.cast(rays, origin, dirs, self._light)
        closer = d.z < static.z[idx]
        out = _Layer(static.z.copy(), static.cos.copy(), static.color.copy())
        sel = idx[closer]
        out.z[sel], out.cos[sel], out.color[sel] = d.z[closer], d.cos[closer], d.color[closer]
        return out, info, world_T_camera

    def render(self, cam_id: str, t_s: float, frame_index: int) -> SimFrame:
        """A noisy RGB-D frame of camera ``cam_id`` at scenario time ``t_s`` (seconds)."""
        layer, info, world_T_camera = self.clean(cam_id, t_s)
        cam_index = [c.id for c in self.scenario.cameras].index(cam_id)
        rng = np.random.default_rng((self.scenario.seed, cam_index, frame_index))
        depth = kinect_depth(layer.z, layer.cos, info, self.scenario.noise, rng)
        rgb = shade_rgb(layer.color, info, self.scenario.noise, rng)
        return SimFrame(cam_id, int(round(t_s * 1e9)), rgb, depth, info, world_T_camera)


def kinect_depth(z: np.ndarray, cos: np.ndarray, info: CameraInfo, noise, rng: np.random.Generator) -> np.ndarray:
    """Depth in millimetres (uint16, 0 = no return) from clean z (m) with the Kinect v1 model.

    Disparity d = f b / z gets Gaussian noise of ``sigma_z_at_1m * f b`` px (so sigma_z grows with
    z^2) and is quantised to ``disparity_step_px``; returns vanish outside the range, at grazing
    incidence and next to depth jumps (with ``flying_pixels``, there they lie at a random depth
    between the nearest and farthest surface of their 3 x 3 neighbourhood instead).
    """
    h, w = info.height, info.width
    zz = z.reshape(h, w).astype(np.float64)
    valid = np.isfinite(zz) & (zz >= noise.min_range_m) & (zz <= noise.max_range_m)
    if not noise.enabled:
        return np.where(valid, np.round(zz * 1000.0), 0).astype(np.uint16)
    fb = info.K[0, 0] * noise.baseline_m
    zs = np.where(valid, zz, 1.0)
    # Depth edges: the projector's pattern breaks up next to jumps (Kinect shadows and flying pixels).
    zf = np.where(np.isfinite(zz), zz, 1e3)
    jump = np.zeros_like(valid)
    tol = noise.edge_jump_m * zf
    dx = np.abs(np.diff(zf, axis=1)) > tol[:, 1:]
    dy = np.abs(np.diff(zf, axis=0)) > tol[1:, :]
    jump[:, 1:] |= dx
    jump[:, :-1] |= dx
    jump[1:, :] |= dy
    jump[:-1, :] |= dy
    d = fb / zs + rng.normal(0.0, noise.sigma_z_at_1m_m * fb, size=zs.shape)
    if noise.flying_pixels:
        # A mixed return: somewhere on the line of sight between the surfaces either side of the jump.
        near, far = _neighbourhood_range(np.where(valid, zz, np.nan))
        mixed = jump & valid & np.isfinite(near)
        share = rng.random(size=zs.shape)
        d[mixed] += fb / (near + share * (far - near))[mixed] - fb / zs[mixed]
        jump &= ~mixed
    if noise.disparity_step_px > 0:
        d = np.round(d / noise.disparity_step_px) * noise.disparity_step_px
    zn = fb / np.maximum(d, 1e-6)
    valid &= cos.reshape(h, w) >= noise.grazing_cos
    valid &= ~jump
    return np.where(valid, np.round(zn * 1000.0), 0).clip(0, 65535).astype(np.uint16)


def _neighbourhood_range(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest finite depth (H, W) of each pixel's 3 x 3 neighbourhood in z (H, W;
    NaN where nothing), NaN where it has none: OpenCV's min and max filters, exact."""
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(np.isnan(z), np.inf, z), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    far = cv2.dilate(np.where(np.isnan(z), -np.inf, z), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return np.where(np.isinf(near), np.nan, near), np.where(np.isinf(far), np.nan, far)


def shade_rgb(color: np.ndarray, info: CameraInfo, noise, rng: np.random.Generator) -> np.ndarray:
    """8-bit RGB from linear albedo x shading (H*W, 3): white balance, saturation, optical blur, sensor
    noise and a registration shift against the depth (``NoiseSpec``)."""
    img = color.reshape(info.height, info.width, 3) * 255.0
    if noise.enabled and tuple(noise.white_balance) != (1.0, 1.0, 1.0):
        img = img * np.asarray(noise.white_balance, dtype=img.dtype)
    if noise.enabled and noise.saturation != 1.0:
        grey = img.mean(axis=2, keepdims=True)  # each pixel's own grey: the same brightness, no hue
        img = grey + noise.saturation * (img - grey)
    if noise.enabled and noise.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), noise.blur_sigma_px)
    if noise.enabled and noise.rgb_sigma > 0:
        img = img + rng.normal(0.0, noise.rgb_sigma, size=img.shape).astype(np.float32)
    if noise.enabled and tuple(noise.rgb_shift_px) != (0, 0):
        shift = np.float32([[1, 0, noise.rgb_shift_px[0]], [0, 1, noise.rgb_shift_px[1]]])
        img = cv2.warpAffine(
            np.ascontiguousarray(img, dtype=np.float32),
            shift,
            (info.width, info.height),
            borderMode=cv2.BORDER_REPLICATE,
        )
    return np.clip(img, 0, 255).astype(np.uint8)


def _sample(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The texture (S, S) bilinearly sampled at pixel coordinates u, v (N,) float32: (N,). OpenCV's
    remap takes maps under 32,767 rows, so the N points go in rows of 1,024 (a marker close to the
    camera covers more pixels than that)."""
    n, width = len(u), 1024
    rows = -(-n // width)
    maps = [np.pad(a, (0, rows * width - n)).reshape(rows, width) for a in (u, v)]
    return cv2.remap(tex, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1)[:n]
