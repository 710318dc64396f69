"""Scenario files: the geometry, markers, cameras and motions of a simulated cell (TOML).

See the README's "Scenario files" section for a complete example; ``demo_cell.toml`` beside this
module is the built-in demo. Poses use ``schemas.spec.PoseSpec`` (position + one orientation).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.config import IntrinsicsConfig
from drivers.errors import ScenarioError
from schemas.codec import CameraInfo
from schemas.geometry import make_pose, rpy_matrix
from schemas.keys import check_name
from schemas.spec import PoseSpec, format_validation_error, read_toml

DEMO_CELL = Path(__file__).with_name("demo_cell.toml")
Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class BoxSpec(_Strict):
    """An axis-aligned (in its own frame) box: a table, a shelf, a wall panel."""

    size: Vec3
    pose: PoseSpec = Field(default_factory=PoseSpec)
    color: Vec3 = (0.6, 0.6, 0.6)

    @model_validator(mode="after")
    def _positive(self) -> BoxSpec:
        if min(self.size) <= 0:
            raise ValueError(f"box size must be positive, got {self.size}")
        return self


class ObjectMotion(_Strict):
    """Back-and-forth slide between the object's pose and ``to`` (world offset, m), ``period_s`` long."""

    kind: Literal["static", "slide"] = "static"
    offset: Vec3 = (0.0, 0.0, 0.0)
    period_s: float = Field(default=10.0, gt=0)


class ObjectSpec(_Strict):
    id: str
    shape: Literal["box", "cylinder", "sphere", "mesh"] = "box"
    size: Vec3 = (0.1, 0.1, 0.1)  # box: x y z; cylinder: radius, radius, height; sphere: radius
    mesh: Path | None = None  # .ply / .obj / .stl, metres, for shape = "mesh"
    pose: PoseSpec = Field(default_factory=PoseSpec)  # world_T_object; object origin at its base centre
    color: Vec3 = (0.8, 0.3, 0.2)
    motion: ObjectMotion = Field(default_factory=ObjectMotion)

    @model_validator(mode="after")
    def _valid(self) -> ObjectSpec:
        check_name(self.id, "object id")
        if self.shape == "mesh" and self.mesh is None:
            raise ValueError(f"object {self.id}: shape 'mesh' needs a mesh file")
        if min(self.size) <= 0:
            raise ValueError(f"object {self.id}: size must be positive")
        return self

    def still(self) -> ObjectSpec:
        """The object standing still where it starts."""
        return self.model_copy(update={"motion": self.motion.model_copy(update={"kind": "static"})})

    def laid_on_side(self, base_xy: tuple[float, float], yaw_deg: float, table_z: float) -> ObjectSpec:
        """The object still, lying on a table at height table_z (m): turned a quarter about its x
        axis (its height along the table), its base centre above base_xy (m), turned by yaw_deg."""
        up = self.size[0] if self.shape == "cylinder" else 0.5 * self.size[1]  # its y (a cylinder's radius) is now up
        pose = PoseSpec(
            position=(float(base_xy[0]), float(base_xy[1]), table_z + up), rpy_deg=(90.0, 0.0, float(yaw_deg))
        )
        return self.still().model_copy(update={"pose": pose})

    def world_T_object(self, t_s: float) -> np.ndarray:
        T = self.pose.matrix()
        if self.motion.kind == "slide":
            phase = 0.5 - 0.5 * math.cos(2 * math.pi * t_s / self.motion.period_s)
            T[:3, 3] += phase * np.asarray(self.motion.offset)
        return T


class MarkerSpec(_Strict):
    """A printed fiducial. ``pose`` is world_T_marker, or object_T_marker when ``object`` is set."""

    id: int = Field(ge=0)
    role: Literal["anchor", "static", "object"] = "static"
    side_m: float | None = Field(default=None, gt=0, description="default: the scenario's marker_side_m")
    pose: PoseSpec
    object: str | None = None
    sigma_position_m: float = Field(default=0.001, gt=0, description="anchors: surveyed position sigma")
    sigma_rotation_deg: float = Field(default=0.1, gt=0, description="anchors: surveyed rotation sigma")

    @model_validator(mode="after")
    def _role(self) -> MarkerSpec:
        if (self.role == "object") != (self.object is not None):
            raise ValueError(f"marker {self.id}: role 'object' and an 'object' id go together")
        return self


class CameraMotion(_Strict):
    """One motion of a camera mount. Several may be listed; they compose in order.

    - ``tilt``: Kinect motor move: pitch about the optical x axis to ``amplitude_deg`` (|a| <= 27),
      ramping linearly between ``start_s`` and ``end_s``.
    - ``sweep``: the motor sweeping: pitch ``amplitude_deg`` x sin(2 pi (t - start_s) / period_s).
    - ``slide``: translate by ``offset`` (world, m) linearly between ``start_s`` and ``end_s``.
    - ``bump``: at ``start_s`` the mount jumps by ``rotation_deg`` (rpy, camera frame) and ``offset`` (world, m).
    - ``orbit``: from ``start_s`` the mount circles the vertical axis through ``centre`` (world, m)
      once per ``period_s``, still looking the same way relative to the axis (a model capture).
    """

    kind: Literal["tilt", "sweep", "slide", "bump", "orbit"]
    amplitude_deg: float = Field(default=10.0, ge=-27, le=27)
    period_s: float = Field(default=8.0, gt=0)
    offset: Vec3 = (0.0, 0.0, 0.0)
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)
    centre: Vec3 = (0.0, 0.0, 0.0)
    start_s: float = Field(default=0.0, ge=0)
    end_s: float = Field(default=1.0, ge=0)

    def apply(self, world_T_mount: np.ndarray, t_s: float) -> np.ndarray:
        T = world_T_mount.copy()
        span = max(self.end_s - self.start_s, 1e-9)
        frac = min(max((t_s - self.start_s) / span, 0.0), 1.0)
        if self.kind == "tilt":
            T = T @ make_pose(rpy_matrix(math.radians(self.amplitude_deg) * frac, 0.0, 0.0))
        elif self.kind == "sweep" and t_s >= self.start_s:
            a = math.radians(self.amplitude_deg) * math.sin(2 * math.pi * (t_s - self.start_s) / self.period_s)
            T = T @ make_pose(rpy_matrix(a, 0.0, 0.0))
        elif self.kind == "slide":
            T[:3, 3] += frac * np.asarray(self.offset)
        elif self.kind == "bump" and t_s >= self.start_s:
            T = T @ make_pose(rpy_matrix(*np.radians(self.rotation_deg)))
            T[:3, 3] += np.asarray(self.offset)
        elif self.kind == "orbit" and t_s >= self.start_s:
            Rz = rpy_matrix(0.0, 0.0, 2 * math.pi * (t_s - self.start_s) / self.period_s)
            c = np.asarray(self.centre, dtype=float)
            T = make_pose(Rz, c - Rz @ c) @ T
        return T


class CameraSpec(_Strict):
    id: str
    width: int = Field(default=640, gt=0)
    height: int = Field(default=480, gt=0)
    rate_hz: float = Field(default=30.0, gt=0)
    intrinsics: IntrinsicsConfig | None = None
    pose: PoseSpec  # world_T_camera of the mount (optical frame)
    motion: list[CameraMotion] = Field(default_factory=list)

    @model_validator(mode="after")
    def _id(self) -> CameraSpec:
        check_name(self.id, "camera id")
        return self

    def moved_in(self, distance_m: float, height_m: float, look_at: Vec3) -> CameraSpec:
        """The camera still, moved along its horizontal line to the world z axis until distance_m
        from it (m), height_m up, looking at look_at (m)."""
        xy = distance_m * np.array(self.pose.position[:2]) / np.hypot(*self.pose.position[:2])
        return self.model_copy(
            update={"pose": PoseSpec(position=(float(xy[0]), float(xy[1]), height_m), look_at=look_at), "motion": []}
        )

    def camera_info(self) -> CameraInfo:
        if self.intrinsics is None:
            return CameraInfo.kinect_v1(self.width, self.height)
        i = self.intrinsics
        return CameraInfo(
            self.width, self.height, np.array([[i.fx, 0, i.cx], [0, i.fy, i.cy], [0, 0, 1.0]]), np.array(i.distortion)
        )

    def world_T_camera(self, t_s: float) -> np.ndarray:
        T = self.pose.matrix()
        for motion in self.motion:
            T = motion.apply(T, t_s)
        return T

    def moving_at(self, t_s: float, dt_s: float) -> bool:
        """Whether the camera moves between ``t_s - dt_s`` and ``t_s`` (for render caching)."""
        return not np.allclose(self.world_T_camera(t_s), self.world_T_camera(max(t_s - dt_s, 0.0)), atol=1e-9)


class NoiseSpec(_Strict):
    """Kinect v1 noise model and RGB degradations. Set ``enabled = false`` for noise-free renders."""

    enabled: bool = True
    baseline_m: float = Field(default=0.075, gt=0, description="IR projector-camera baseline")
    disparity_step_px: float = Field(default=0.125, ge=0, description="disparity quantisation (1/8 px)")
    sigma_z_at_1m_m: float = Field(default=0.0014, ge=0, description="depth sigma at 1 m; grows with z^2")
    min_range_m: float = Field(default=0.5, gt=0)
    max_range_m: float = Field(default=4.5, gt=0)
    grazing_cos: float = Field(default=0.12, ge=0, lt=1, description="drop depth where cos(incidence) is below")
    edge_jump_m: float = Field(default=0.04, gt=0, description="drop depth next to jumps larger than this x z")
    flying_pixels: bool = Field(
        default=False,
        description="next to those jumps return a depth between the near and the far surface (a mixed "
        "pixel, as time-of-flight and some stereo sensors give) instead of none",
    )
    white_balance: Vec3 = Field(
        default=(1.0, 1.0, 1.0),
        description="gain of each colour channel (r, g, b): a colour cast from the camera's white balance",
    )
    saturation: float = Field(
        default=1.0,
        ge=0,
        description="colour saturation against the scene's (below 1: washed out, as many sensors' colour is)",
    )
    rgb_shift_px: tuple[int, int] = Field(
        default=(0, 0),
        description="colour image shifted this many pixels (x, y) against the depth: a registration error",
    )
    rgb_sigma: float = Field(default=2.0, ge=0, description="RGB noise, 8-bit levels")
    blur_sigma_px: float = Field(default=0.6, ge=0)


class Scenario(_Strict):
    name: str = "cell"
    seed: int = 0
    duration_s: float = Field(default=30.0, gt=0)
    dictionary: str = "DICT_APRILTAG_36h11"
    marker_side_m: float = Field(default=0.15, gt=0)
    floor_size: tuple[float, float] = (3.0, 3.0)
    floor_color: Vec3 = (0.45, 0.45, 0.42)
    # World-frame box where objects can be (m): what recognition searches once cameras are localized.
    workspace: tuple[Vec3, Vec3] | None = None
    boxes: list[BoxSpec] = Field(default_factory=list)
    objects: list[ObjectSpec] = Field(default_factory=list)
    markers: list[MarkerSpec] = Field(default_factory=list)
    cameras: list[CameraSpec] = Field(default_factory=list)
    noise: NoiseSpec = Field(default_factory=NoiseSpec)

    def still(self) -> Scenario:
        """The scenario with every object standing still where it starts."""
        return self.model_copy(update={"objects": [o.still() for o in self.objects]})

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        for what, ids in (
            ("camera", [c.id for c in self.cameras]),
            ("marker", [m.id for m in self.markers]),
            ("object", [o.id for o in self.objects]),
        ):
            dupes = sorted({i for i in ids if ids.count(i) > 1})
            if dupes:
                raise ValueError(f"duplicate {what} ids: {dupes}")
        objects = {o.id for o in self.objects}
        for mk in self.markers:
            if mk.object is not None and mk.object not in objects:
                raise ValueError(f"marker {mk.id} is attached to unknown object {mk.object!r}")
        return self

    def side_of(self, marker: MarkerSpec) -> float:
        return marker.side_m or self.marker_side_m

    def camera(self, camera_id: str) -> CameraSpec:
        for c in self.cameras:
            if c.id == camera_id:
                return c
        raise ScenarioError(
            f"scenario {self.name!r} has no camera {camera_id!r}; it has {[c.id for c in self.cameras]}"
        )

    def world_T_marker(self, marker: MarkerSpec, t_s: float) -> np.ndarray:
        T = marker.pose.matrix()
        if marker.object is None:
            return T
        obj = next(o for o in self.objects if o.id == marker.object)
        return obj.world_T_object(t_s) @ T


def footprint(obj: ObjectSpec, xy: np.ndarray, yaw: float) -> np.ndarray:
    """The object's outline on the table (K, 2), m, a convex polygon: a box's rectangle, a round
    object's circumscribed 16-gon, a mesh's bounding circle's."""
    if obj.shape == "box":
        hx, hy = 0.5 * obj.size[0], 0.5 * obj.size[1]
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    else:
        r = obj.size[0] if obj.shape in ("cylinder", "sphere") else 0.5 * float(np.hypot(obj.size[0], obj.size[1]))
        a = np.arange(16) * (2 * np.pi / 16)
        local = r / np.cos(np.pi / 16) * np.column_stack([np.cos(a), np.sin(a)])
    c, s_ = np.cos(yaw), np.sin(yaw)
    return local @ np.array([[c, s_], [-s_, c]]) + xy


def apart(a: np.ndarray, b: np.ndarray, gap: float) -> bool:
    """Whether convex polygons a and b (K, 2) are at least ``gap`` apart along one of their edge
    normals (separating axes): then no point of one is within ``gap`` of the other."""
    for poly in (a, b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.column_stack([edges[:, 1], -edges[:, 0]]) / np.linalg.norm(edges, axis=1)[:, None]
        pa, pb = a @ normals.T, b @ normals.T
        if np.any((pb.min(axis=0) - pa.max(axis=0) >= gap) | (pa.min(axis=0) - pb.max(axis=0) >= gap)):
            return True
    return False


def load_scenario(path: Path | None = None) -> Scenario:
    """Load a scenario TOML (None: the built-in demo cell); raise ``ScenarioError`` naming the field."""
    path = DEMO_CELL if path is None else Path(path)
    data = read_toml(path, ScenarioError, "scenario file")
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(format_validation_error(f"{path} (scenario)", exc)) from exc
    for obj in scenario.objects:
        if obj.mesh is not None and not obj.mesh.is_absolute():
            obj.mesh = path.parent / obj.mesh
        if obj.mesh is not None and not obj.mesh.is_file():
            raise ScenarioError(f"{path}: object {obj.id}: mesh file {obj.mesh} does not exist")
    return scenario
