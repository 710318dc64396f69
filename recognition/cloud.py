"""Point clouds from registered depth, voxel downsampling and PCL-style normals.

Clouds are float32 (N, 3) arrays in metres in the camera frame (x right, y down, z forward);
organised clouds are (H, W, 3) with NaN where the sensor returned nothing, as PCL stores them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from open3d.core import nns

from recognition.errors import CloudError

#: Neighbours a covariance needs to define a plane; fewer gives a NaN normal, as in PCL.
MIN_NORMAL_NEIGHBOURS = 3


def depth_to_cloud(depth: np.ndarray, K: np.ndarray, depth_scale: float = 0.001) -> np.ndarray:
    """Back-project a depth image into an organised cloud.

    depth (H, W) integer or float sensor units, 0 = no return; K (3, 3) pinhole intrinsics in pixels;
    depth_scale metres per unit (0.001 for 16UC1 millimetres). Returns (H, W, 3) float32 metres, NaN
    where depth is 0. The arithmetic is PCL's ImageGrabber's, in float32, so that the result matches
    the PCDs PCL writes from the same frames.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2 or depth.size == 0:
        raise CloudError(f"depth image must be a non-empty (H, W) array, got shape {depth.shape}")
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CloudError("intrinsics K must be a finite 3x3 matrix with positive focal lengths")
    h, w = depth.shape
    z = depth.astype(np.float32) * np.float32(depth_scale)
    z[~(z > 0)] = np.nan  # x and y follow: NaN times anything
    inv_fx, inv_fy = np.float32(1.0 / K[0, 0]), np.float32(1.0 / K[1, 1])
    u = np.arange(w, dtype=np.float32) - np.float32(K[0, 2])
    v = np.arange(h, dtype=np.float32) - np.float32(K[1, 2])
    cloud = np.empty((h, w, 3), dtype=np.float32)
    np.multiply(u[None, :] * z, inv_fx, out=cloud[..., 0])
    np.multiply(v[:, None] * z, inv_fy, out=cloud[..., 1])
    cloud[..., 2] = z
    return cloud


def camera_rays(
    K: np.ndarray, width: int, height: int, world_T_camera: np.ndarray, window: tuple[int, int, int, int] | None = None
) -> np.ndarray:
    """Rays for Open3D's RaycastingScene, one per pixel, (H * W, 6) float32: origin, direction.

    Directions have z = 1 in the camera frame, so a hit's t is the pixel's depth; pixel (u, v) looks
    along ((u - cx) / fx, (v - cy) / fy, 1), the convention of depth_to_cloud and OpenCV (Open3D's
    own create_rays_pinhole aims half a pixel off, at u + 0.5). ``window`` (u0, v0, u1, v1), end
    exclusive: only those pixels' rays, row by row, ((v1 - v0) * (u1 - u0), 6).
    """
    u0, v0, u1, v1 = window if window is not None else (0, 0, width, height)
    u, v = np.meshgrid(np.arange(u0, u1, dtype=np.float64), np.arange(v0, v1, dtype=np.float64))
    dirs = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1).reshape(-1, 3)
    dirs = dirs @ np.asarray(world_T_camera)[:3, :3].T
    origin = np.broadcast_to(np.asarray(world_T_camera)[:3, 3], dirs.shape)
    return np.hstack([origin, dirs]).astype(np.float32)


def image_window(
    K: np.ndarray, width: int, height: int, camera_T_points: np.ndarray, margin_px: int = 2
) -> tuple[int, int, int, int]:
    """The pixels (u0, v0, u1, v1; end exclusive) that can see any of the points (N, 3) in the
    camera frame, and so anything inside their convex hull (a bounding box's 8 corners): their
    projections' box grown by ``margin_px``. The whole image when a point is not in front."""
    p = np.asarray(camera_T_points, dtype=np.float64)
    if len(p) == 0 or np.any(p[:, 2] <= 1e-6):
        return 0, 0, width, height
    u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
    v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
    u0, u1 = (
        int(np.clip(np.floor(u.min()) - margin_px, 0, width)),
        int(np.clip(np.ceil(u.max()) + margin_px + 1, 0, width)),
    )
    v0, v1 = (
        int(np.clip(np.floor(v.min()) - margin_px, 0, height)),
        int(np.clip(np.ceil(v.max()) + margin_px + 1, 0, height)),
    )
    return u0, v0, max(u1, u0), max(v1, v0)


def finite_points(cloud: np.ndarray) -> np.ndarray:
    """The finite points of an organised or flat cloud, as (N, 3) float32."""
    pts = np.asarray(cloud, dtype=np.float32).reshape(-1, 3)
    return pts[np.all(np.isfinite(pts), axis=1)]


def read_cloud(path: str | Path, *, organised: bool = False) -> np.ndarray:
    """Points of a PCD, PLY or XYZ file in float32 metres (every PCD encoding, LZF-compressed included).

    organised=True keeps a PCD's HEIGHT x WIDTH layout and its NaN points: (H, W, 3). Otherwise the
    finite points only: (N, 3).
    """
    return read_coloured_cloud(path, organised=organised)[0]


def read_coloured_cloud(path: str | Path, *, organised: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """``read_cloud``'s points and their colours, uint8 rgb of the same layout ((H, W, 3) or (N, 3)),
    or None when the file has none."""
    path = Path(path)
    if not path.is_file():
        raise CloudError(f"cloud file {path} does not exist")
    if path.suffix.lower() not in (".pcd", ".ply", ".xyz"):
        raise CloudError(f"cloud file {path}: use a .pcd, .ply or .xyz file")
    if path.suffix.lower() == ".pcd":
        width, height = _pcd_size(path)
    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except RuntimeError as exc:
        raise CloudError(f"cloud file {path} is unreadable: {exc}") from exc
    if "positions" not in pcd.point or len(pcd.point.positions) == 0:
        raise CloudError(f"cloud file {path} holds no points (empty or not a point cloud)")
    pts = pcd.point.positions.numpy().astype(np.float32, copy=False)
    rgb = _rgb8(pcd.point.colors.numpy()) if "colors" in pcd.point else None
    if not organised:
        finite = np.all(np.isfinite(pts), axis=1)
        if not finite.any():
            raise CloudError(f"cloud file {path} holds no finite points")
        return pts[finite], None if rgb is None else rgb[finite]
    if path.suffix.lower() in (".ply", ".xyz"):
        width, height = len(pts), 1
    if width * height != len(pts):
        raise CloudError(f"cloud file {path}: WIDTH x HEIGHT = {width}x{height} but {len(pts)} points")
    return pts.reshape(height, width, 3), None if rgb is None else rgb.reshape(height, width, 3)


def _rgb8(colours: np.ndarray) -> np.ndarray:
    """Open3D's colours as uint8 rgb: PCD files give uint8, PLY files float 0-1."""
    if colours.dtype == np.uint8:
        return colours
    return np.clip(np.nan_to_num(colours.astype(np.float64)) * 255.0 + 0.5, 0, 255).astype(np.uint8)


#: PCD header lines in the order the format fixes, the ones our checks need.
_PCD_FIELD_LINES = ("FIELDS", "SIZE", "TYPE", "COUNT")


def _pcd_size(path: Path) -> tuple[int, int]:
    """WIDTH and HEIGHT from a PCD header, after checking the header is consistent: Open3D's reader
    crashes the process (SIGSEGV) on some damaged headers: more FIELDS than SIZEs, or normal_y
    without normal_x."""
    lines: dict[str, list[str]] = {}
    with path.open("rb") as f:
        for _ in range(30):
            raw = f.readline()
            if not raw:
                break
            words = raw.decode("ascii", "replace").split()
            if not words or words[0].startswith("#"):
                continue
            lines[words[0]] = words[1:]
            if words[0] == "DATA":
                break

    def bad(what: str) -> CloudError:
        return CloudError(f"cloud file {path}: damaged PCD header: {what}")

    missing = [k for k in (*_PCD_FIELD_LINES, "WIDTH", "HEIGHT", "POINTS", "DATA") if k not in lines]
    if missing:
        raise bad(f"no {', '.join(missing)} line")
    fields = lines["FIELDS"]
    if not fields or any(len(lines[k]) != len(fields) for k in _PCD_FIELD_LINES):
        raise bad(f"FIELDS, SIZE, TYPE and COUNT must list one entry per field ({len(fields)} fields)")
    if not all(name.isascii() and name.isprintable() for name in fields):
        raise bad(f"field names {fields!r} are not plain text")
    if not {"x", "y", "z"} <= set(fields):
        raise bad(f"fields {fields} lack x, y or z")
    normals = {"normal_x", "normal_y", "normal_z"} & set(fields)
    if normals and len(normals) != 3:  # Open3D crashes on a partial set
        raise bad(f"fields {fields} hold only {sorted(normals)} of normal_x, normal_y, normal_z")
    if not all(size in ("1", "2", "4", "8") for size in lines["SIZE"]) or not all(
        t in ("F", "I", "U") for t in lines["TYPE"]
    ):
        raise bad(f"SIZE {lines['SIZE']} / TYPE {lines['TYPE']} are not 1/2/4/8 bytes of F, I or U")
    counts = [*lines["COUNT"], *lines["WIDTH"], *lines["HEIGHT"], *lines["POINTS"]]
    if len(counts) != len(fields) + 3 or not all(c.isdigit() for c in counts):
        raise bad("COUNT, WIDTH, HEIGHT and POINTS must be non-negative integers")
    width, height, points = int(lines["WIDTH"][0]), int(lines["HEIGHT"][0]), int(lines["POINTS"][0])
    if width * height != points:
        raise bad(f"WIDTH x HEIGHT = {width}x{height} but POINTS {points}")
    if lines["DATA"] not in (["ascii"], ["binary"], ["binary_compressed"]):
        raise bad(f"DATA {' '.join(lines['DATA'])!r} is not ascii, binary or binary_compressed")
    return width, height


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Centroid of the points in each voxel of side voxel_m (m). (N, 3) -> (M, 3) float32."""
    return voxel_downsample_coloured(points, None, voxel_m)[0]


def voxel_downsample_coloured(
    points: np.ndarray, colours: np.ndarray | None, voxel_m: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """``voxel_downsample``, and the mean colour of each voxel's points (colours (N, 3) rgb 0-1 ->
    (M, 3) float32; None stays None)."""
    if voxel_m <= 0:
        raise CloudError(f"voxel size must be positive, got {voxel_m} m")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    if colours is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colours, dtype=np.float64))
    down = pcd.voxel_down_sample(voxel_m)
    return np.asarray(down.points, dtype=np.float32), np.asarray(
        down.colors, dtype=np.float32
    ) if colours is not None else None


@dataclass(frozen=True)
class Neighbours:
    """Each point's neighbours within radius_m, itself included, in no particular order (CSR).

    Point q's neighbours are index[splits[q]:splits[q + 1]], at squared distances sq_dist_m2 (m^2)
    of the same slice. index (E,) int64, sq_dist_m2 (E,) float32, splits (N + 1,) int64.
    """

    radius_m: float
    index: np.ndarray
    sq_dist_m2: np.ndarray
    splits: np.ndarray

    def within(self, radius_m: float) -> Neighbours:
        """The same neighbourhoods cut down to radius_m (at most this one's radius)."""
        if radius_m > self.radius_m:
            raise CloudError(f"neighbours were searched within {self.radius_m} m, not {radius_m} m")
        if radius_m == self.radius_m:
            return self
        near = self.sq_dist_m2 <= np.float32(radius_m) ** 2
        kept_before = np.concatenate([[0], np.cumsum(near, dtype=np.int64)])  # kept entries before each one
        splits = kept_before[self.splits]
        return Neighbours(radius_m, self.index[near], self.sq_dist_m2[near], splits)


def radius_neighbours(points: np.ndarray, radius_m: float) -> Neighbours:
    """Every point's neighbours within radius_m (itself included). points (N, 3) metres."""
    pts = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    search = nns.NearestNeighborSearch(pts)
    search.fixed_radius_index(radius_m)
    idx, sq_dist, splits = search.fixed_radius_search(pts, radius_m, sort=False)
    return Neighbours(radius_m, idx.numpy().astype(np.int64), sq_dist.numpy(), splits.numpy().astype(np.int64))


class PointIndex:
    """Exact nearest neighbours among fixed points (N, 3), m: one k-d tree (OpenCV's FLANN, a single
    tree searched with no limit on checks, so exact), built once and asked many times. Open3D's ICP
    and its registration evaluation build a tree per call, which costs more than their searches."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        self._tree = cv2.flann_Index(self.points, {"algorithm": 4, "leaf_max_size": 10}) if len(self.points) else None
        self._lo, self._hi = (self.points.min(axis=0), self.points.max(axis=0)) if len(self.points) else (None, None)

    def nearest(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each query point's (M, 3) nearest point: its index (M,) int64 (-1 when there are no points)
        and squared distance (M,) float32, m^2."""
        q = np.ascontiguousarray(query, dtype=np.float32).reshape(-1, 3)
        if self._tree is None or len(q) == 0:
            return np.full(len(q), -1, np.int64), np.full(len(q), np.inf, np.float32)
        idx, sq_dist = self._tree.knnSearch(q, 1, params={"checks": -1})
        return idx[:, 0].astype(np.int64), sq_dist[:, 0]

    def within(self, query: np.ndarray, radius_m: float) -> np.ndarray:
        """Mask (M,) of the query points (M, 3) with a point within radius_m."""
        q = np.ascontiguousarray(query, dtype=np.float32).reshape(-1, 3)
        out = np.zeros(len(q), dtype=bool)
        if self._tree is None:
            return out
        # Only points in the points' box grown by the radius can have one: an exact search for a
        # far point's nearest costs the most.
        r = np.float32(radius_m)
        near = np.flatnonzero(np.all((q >= self._lo - r) & (q <= self._hi + r), axis=1))
        out[near] = self.nearest(q[near])[1] <= r * r
        return out


def smallest_eigenpair(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest eigenvalue (N,) and its unit eigenvector (N, 3) of symmetric 3x3 matrices (N, 3, 3).

    Closed form (the trigonometric solution of the characteristic cubic), ~10x faster than a batched
    np.linalg.eigh on small matrices. The vector is the largest cross product of two rows of
    A - lambda I, which are orthogonal to it.
    """
    q = np.trace(cov, axis1=1, axis2=2) / 3.0
    shifted = cov - q[:, None, None] * np.eye(3)
    p = np.sqrt(np.einsum("nij,nij->n", shifted, shifted) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    r = np.clip(np.linalg.det(shifted / safe[:, None, None]) / 2.0, -1.0, 1.0)
    smallest = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    m = cov - smallest[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], axis=1)
    norms = np.linalg.norm(crosses, axis=2)
    pick = np.argmax(norms, axis=1)
    rows = np.arange(len(cov))
    best = norms[rows, pick]
    vec = crosses[rows, pick] / np.where(best > 0, best, 1.0)[:, None]
    vec[best == 0] = (0.0, 0.0, 1.0)  # isotropic or degenerate: every direction is an eigenvector
    return smallest, vec


def estimate_normals(
    points: np.ndarray,
    radius_m: float,
    viewpoint: np.ndarray | tuple = (0.0, 0.0, 0.0),
    neighbours: Neighbours | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Normals as PCL's NormalEstimation computes them, vectorised.

    For each point: the covariance of its neighbours within radius_m, the eigenvector of the smallest
    eigenvalue as the normal, flipped to face the viewpoint (n . (viewpoint - p) >= 0); curvature is
    lambda_min / sum(lambda). Points with fewer than 3 neighbours get NaN, as in PCL.
    points (N, 3) metres -> normals (N, 3) float32, curvature (N,) float32. neighbours: the points'
    own, searched within at least radius_m, when the caller already has them.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0:
        raise CloudError("cannot estimate normals of an empty cloud")
    if radius_m <= 0:
        raise CloudError(f"normal radius must be positive, got {radius_m} m")
    nb = radius_neighbours(pts, radius_m) if neighbours is None else neighbours.within(radius_m)
    if len(nb.splits) != len(pts) + 1:
        raise CloudError(f"neighbours of {len(nb.splits) - 1} points given for a cloud of {len(pts)}")
    idx, splits = nb.index, nb.splits
    counts = np.diff(splits)
    # First and second moments per neighbourhood in one pass over rows of components: each point's
    # neighbours are one run of idx (every point is its own neighbour, so no run is empty).
    g = np.ascontiguousarray(pts.T)[:, idx]  # (3, E)
    a, b = [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]
    terms = np.empty((9, len(idx)))
    terms[:3] = g
    for k, (i, j) in enumerate(zip(a, b)):
        np.multiply(g[i], g[j], out=terms[3 + k])
    sums = np.add.reduceat(terms, splits[:-1], axis=1) / np.maximum(counts, 1)
    mean, second = sums[:3], sums[3:]
    cov = np.empty((len(pts), 3, 3))
    for k, (i, j) in enumerate(zip(a, b)):
        cov[:, i, j] = cov[:, j, i] = second[k] - mean[i] * mean[j]
    smallest, normals = smallest_eigenpair(cov)
    flip = np.einsum("ij,ij->i", normals, np.asarray(viewpoint, dtype=np.float64) - pts) < 0
    normals[flip] *= -1.0
    total = np.trace(cov, axis1=1, axis2=2)  # the sum of the eigenvalues
    curvature = np.divide(np.abs(smallest), total, out=np.zeros(len(pts)), where=total > 0)
    bad = counts < MIN_NORMAL_NEIGHBOURS
    normals[bad] = np.nan
    curvature[bad] = np.nan
    return normals.astype(np.float32), curvature.astype(np.float32)
