"""Scene segmentation: remove dominant planes (RANSAC), then Euclidean clusters with size limits."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from recognition.cloud import Neighbours, radius_neighbours
from recognition.errors import CloudError

#: RANSAC hypotheses are scored on at most this many points (a seeded random sample): a plane that
#: holds a tenth of the scene holds a tenth of the sample, and a frame's table has ~10k voxels.
PLANE_SAMPLE = 3000
#: A plane after the first is removed when it spans more than any object and holds this share of
#: the scene (a floor or wall in view).
STRUCTURE_SHARE = 0.01
#: A piece split off a cluster under this share of it is a crumb of a noisy surface, not an object.
SPLIT_CRUMB = 0.05


def remove_planes(
    points: np.ndarray,
    distance_m: float,
    max_planes: int,
    min_fraction: float,
    noise_per_m2: float = 0.0,
    seed: int = 0,
    min_extent_m: float = np.inf,
) -> tuple[np.ndarray, np.ndarray]:
    """Mask (N,) of the points that are neither on nor behind a dominant plane (camera at the origin),
    and the planes found (P, 4): a, b, c, d with a x + b y + c z + d = 0, the normal towards the camera.

    Up to max_planes planes are found, largest first. The first is removed if its RANSAC inliers are
    at least min_fraction of all points (the table, or a floor), with everything behind it; each
    further one if its inliers are STRUCTURE_SHARE of the points and one connected patch of them
    spans more than min_extent_m (wider than any object: a wall, the table of a room seen from its
    corner), so that a box face stays. A point is removed when it lies within max(distance_m,
    noise_per_m2 * z^2) of a removed plane: depth noise grows with the square of range, and a fixed
    band leaves the far end of a table behind as clutter. Seeded.
    """
    keep = np.ones(len(points), dtype=bool)
    planes: list[tuple[float, float, float, float]] = []
    o3d.utility.random.seed(seed)
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, dtype=np.float64)
    band = np.maximum(distance_m, noise_per_m2 * pts[:, 2] ** 2)
    for _ in range(max_planes):
        rest = np.flatnonzero(keep)
        if len(rest) < max(3, min(min_fraction, STRUCTURE_SHARE) * len(pts)):
            break
        sample = rest if len(rest) <= PLANE_SAMPLE else np.sort(rng.choice(rest, PLANE_SAMPLE, replace=False))
        plane, inliers = ransac_plane(pts[sample], distance_m)
        a, b, c, d = plane
        if d < 0:  # orient the normal towards the camera: the origin has positive signed distance
            a, b, c, d = -a, -b, -c, -d
        signed = pts[rest] @ np.array([a, b, c]) + d
        share = len(inliers) * len(rest) / (len(sample) * len(pts))  # of all points
        dominant = share >= min_fraction and not planes
        if not dominant and not (
            planes
            and share >= STRUCTURE_SHARE
            and patch_extent(pts[rest[np.abs(signed) < distance_m]], np.array([a, b, c])) > min_extent_m
        ):
            break
        keep[rest[(signed < band[rest]) & (dominant | (signed > -band[rest]))]] = False
        planes.append((a, b, c, d))
    return keep, np.array(planes, dtype=np.float64).reshape(-1, 4)


def ransac_plane(points: np.ndarray, distance_m: float) -> tuple[np.ndarray, list[int]]:
    """Open3D's RANSAC plane (a, b, c, d) of points (N, 3) and its inliers, on one thread. Its
    ``segment_plane`` runs its hypotheses on threads (``OMP_NUM_THREADS`` does not reach them):
    seeded, it still gave another plane now and then on two cores with the other one busy (2 planes
    in 20 runs on a demo frame's points), and with it another answer for a marginal frame."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        plane, inliers = pcd.segment_plane(distance_m, ransac_n=3, num_iterations=200)
    finally:
        o3d.utility.set_max_threads(threads)
    return np.asarray(plane), inliers


def patch_extent(points: np.ndarray, normal: np.ndarray, cell_m: float = 0.02) -> float:
    """The width (m) of the largest connected patch of points (N, 3) lying on a plane of the given
    normal: the longer side of its bounding box in the plane (never more than the patch's largest
    point-to-point distance, so an object's face never reads wider than the object)."""
    if len(points) == 0:
        return 0.0
    n = normal / np.linalg.norm(normal)
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    cells = np.floor(points @ np.stack([u, np.cross(n, u)]).T / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    image = np.zeros(cells.max(axis=0) + 1, np.uint8)
    image[cells[:, 0], cells[:, 1]] = 1
    _, _, stats, _ = cv2.connectedComponentsWithStats(image, connectivity=8)
    biggest = stats[1:][np.argmax(stats[1:, cv2.CC_STAT_AREA])]
    # stats are in OpenCV's (x = columns, y = rows): either way the longer side.
    return float(max(biggest[cv2.CC_STAT_WIDTH], biggest[cv2.CC_STAT_HEIGHT]) * cell_m)


@dataclass(frozen=True)
class PointGraph:
    """A cloud's point pairs closer than radius_m: edges (i, j) with i < j, (E,) int64 each, and
    their squared lengths (E,) float32, m^2; size points."""

    size: int
    radius_m: float
    i: np.ndarray
    j: np.ndarray
    sq_len_m2: np.ndarray

    @classmethod
    def empty(cls, radius_m: float) -> PointGraph:
        """The graph of no points."""
        none = np.zeros(0, dtype=np.int64)
        return cls(0, radius_m, none, none, np.zeros(0, dtype=np.float32))

    @classmethod
    def of(cls, points: np.ndarray, radius_m: float) -> PointGraph:
        """The graph of points (N, 3) closer than radius_m (m)."""
        return cls.from_neighbours(radius_neighbours(points, radius_m))

    @classmethod
    def from_neighbours(cls, nb: Neighbours) -> PointGraph:
        rows = np.repeat(np.arange(len(nb.splits) - 1), np.diff(nb.splits))
        once = rows < nb.index  # each pair once, no self-loops
        return cls(len(nb.splits) - 1, nb.radius_m, rows[once], nb.index[once], nb.sq_dist_m2[once])

    def subgraph(self, members: np.ndarray, radius_m: float | None = None) -> PointGraph:
        """The graph among the points members (M,) (renumbered 0..M-1 in that order), optionally
        only the edges up to radius_m."""
        radius = self.radius_m if radius_m is None else radius_m
        if radius > self.radius_m:
            raise CloudError(f"the graph holds pairs up to {self.radius_m} m, not {radius} m")
        local = np.full(self.size, -1, dtype=np.int64)
        local[members] = np.arange(len(members))
        a, b = local[self.i], local[self.j]
        keep = (a >= 0) & (b >= 0)
        if radius < self.radius_m:
            keep &= self.sq_len_m2 <= np.float32(radius) ** 2
        a, b = a[keep], b[keep]
        return PointGraph(len(members), radius, np.minimum(a, b), np.maximum(a, b), self.sq_len_m2[keep])


def components(size: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Connected components of the graph on size nodes with edges (i, j): each node's label is the
    smallest node of its component, (size,) int64.

    Vectorised union-find: every round hooks the larger root of each edge that still joins two
    components under the smaller one, then points every node straight at its root. Roots only
    ever point down, so there are no cycles, and the smallest node of a component stays its root.
    """
    parent = np.arange(size, dtype=np.int64)
    while len(i):
        a, b = parent[i], parent[j]
        joins = a != b
        i, j, a, b = i[joins], j[joins], a[joins], b[joins]
        parent[np.maximum(a, b)] = np.minimum(a, b)
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
    return parent


def euclidean_clusters(
    points: np.ndarray, tolerance_m: float, min_points: int, max_points: int, graph: PointGraph | None = None
) -> list[np.ndarray]:
    """Index arrays of the connected components of the tolerance_m neighbour graph, largest first.

    PCL's EuclideanClusterExtraction. Clusters outside [min_points, max_points] are dropped. graph:
    the points' pairs up to at least tolerance_m, when the caller has them (they cost a radius search).
    """
    if len(points) == 0:
        return []
    if graph is None:
        graph = PointGraph.of(points, tolerance_m)
    elif graph.size != len(points):
        raise CloudError(f"a graph of {graph.size} points given for a cloud of {len(points)}")
    elif graph.radius_m != tolerance_m:
        graph = graph.subgraph(np.arange(graph.size), tolerance_m)
    labels = components(graph.size, graph.i, graph.j)
    order = np.argsort(labels, kind="stable")  # one pass, not one scan per label: fine tolerances give many
    clusters = np.split(order, np.flatnonzero(np.diff(labels[order])) + 1)
    clusters = [c for c in clusters if min_points <= len(c) <= max_points]
    return sorted(clusters, key=len, reverse=True)


def split_oversized(
    points: np.ndarray,
    clusters: list[np.ndarray],
    max_extent_m: float,
    tolerance_m: float,
    min_tolerance_m: float,
    min_points: int,
    graph: PointGraph | None = None,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Clusters larger than any object (2-98 % bounding-box diagonal over max_extent_m) re-clustered with a
    tighter tolerance, down to min_tolerance_m: objects standing close together merge at the
    tolerance a noisy far surface needs, and come apart at a smaller one. Largest first.

    A split also sheds crumbs, pieces under SPLIT_CRUMB of the cluster: not clusters of their own
    (too small to match a whole view, they would cost a full match each). Returned apart, all the
    crumbs of one split together: the fragments of a small object half hidden among larger ones
    are among them. graph: the points' pairs up to at least tolerance_m, when the caller has them.
    """
    out: list[np.ndarray] = []
    shed: list[np.ndarray] = []
    todo = [(c, tolerance_m) for c in clusters]
    while todo:
        idx, tol = todo.pop()
        pts = points[idx]
        lo, hi = np.percentile(pts, [2, 98], axis=0)  # robust to flying pixels at depth edges
        extent = float(np.linalg.norm(hi - lo))
        finer = tol * 0.7
        if extent <= max_extent_m or finer < min_tolerance_m:
            out.append(idx)
            continue
        sub = None if graph is None else graph.subgraph(idx, finer)
        parts = euclidean_clusters(pts, finer, 1, len(idx), sub)
        big = np.array([len(p) >= max(min_points, SPLIT_CRUMB * len(idx)) for p in parts])
        if not big.any():
            out.append(idx)  # shattered: a single noisy surface, not several objects
            continue
        todo.extend(
            (idx[p], finer) for p, b in zip(parts, big) if b
        )  # one piece (without its crumbs) is tried finer still
        if not big.all():
            shed.append(idx[np.concatenate([p for p, b in zip(parts, big) if not b])])
    return sorted(out, key=len, reverse=True), shed
