"""Scene segmentation: remove dominant planes (RANSAC), then Euclidean clusters with size limits."""

from __future__ import annotations

import numpy as np
import open3d as o3d

#: RANSAC hypotheses are scored on at most this many points (a seeded random sample): a plane that
#: holds a tenth of the scene holds a tenth of the sample, and a frame's table has ~10k voxels.
PLANE_SAMPLE = 3000
#: A piece split off a cluster under this share of it is a crumb of a noisy surface, not an object.
SPLIT_CRUMB = 0.05


def remove_planes(
    points: np.ndarray,
    distance_m: float,
    max_planes: int,
    min_fraction: float,
    noise_per_m2: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Mask (N,) of the points that are neither on nor behind a dominant plane (camera at the origin).

    Up to max_planes planes are found, largest first, each only if its RANSAC inliers are at least
    min_fraction of all points (so a box face is not taken for the table). A point is removed when it
    lies behind the plane or within max(distance_m, noise_per_m2 * z^2) of it: depth noise grows with
    the square of range, and a fixed band leaves the far end of a table behind as clutter. Seeded.
    """
    keep = np.ones(len(points), dtype=bool)
    o3d.utility.random.seed(seed)
    rng = np.random.default_rng(seed)
    pts = np.asarray(points, dtype=np.float64)
    band = np.maximum(distance_m, noise_per_m2 * pts[:, 2] ** 2)
    for _ in range(max_planes):
        rest = np.flatnonzero(keep)
        if len(rest) < max(3, min_fraction * len(pts)):
            break
        sample = rest if len(rest) <= PLANE_SAMPLE else np.sort(rng.choice(rest, PLANE_SAMPLE, replace=False))
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sample]))
        plane, inliers = pcd.segment_plane(distance_m, ransac_n=3, num_iterations=200)
        if len(inliers) < min_fraction * len(pts) * len(sample) / len(rest):
            break
        a, b, c, d = plane
        if d < 0:  # orient the normal towards the camera: the origin has positive signed distance
            a, b, c, d = -a, -b, -c, -d
        signed = pts[rest] @ np.array([a, b, c]) + d
        keep[rest[signed < band[rest]]] = False
    return keep


def euclidean_clusters(points: np.ndarray, tolerance_m: float, min_points: int, max_points: int) -> list[np.ndarray]:
    """Index arrays of the connected components of the tolerance_m neighbour graph, largest first.

    PCL's EuclideanClusterExtraction: DBSCAN with one point per core is exactly that graph's
    components. Clusters outside [min_points, max_points] are dropped.
    """
    if len(points) == 0:
        return []
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    labels = np.asarray(pcd.cluster_dbscan(tolerance_m, min_points=1))
    order = np.argsort(labels, kind="stable")  # one pass, not one scan per label: fine tolerances give many
    clusters = np.split(order, np.cumsum(np.bincount(labels))[:-1])
    clusters = [c for c in clusters if min_points <= len(c) <= max_points]
    return sorted(clusters, key=len, reverse=True)


def split_oversized(
    points: np.ndarray, clusters: list[np.ndarray], max_extent_m: float, tolerance_m: float, min_tolerance_m: float,
    min_points: int,
) -> list[np.ndarray]:
    """Clusters larger than any object (2-98 % bounding-box diagonal over max_extent_m) re-clustered with a
    tighter tolerance, down to min_tolerance_m: objects standing close together merge at the
    tolerance a noisy far surface needs, and come apart at a smaller one. Largest first.

    A split also sheds crumbs, pieces of one noisy surface under SPLIT_CRUMB of the cluster: they are
    dropped, not made clusters of their own (too small to match, they cost a full match each).
    """
    out: list[np.ndarray] = []
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
        parts = euclidean_clusters(pts, finer, 1, len(idx))
        real = [p for p in parts if len(p) >= max(min_points, SPLIT_CRUMB * len(idx))]
        if not real:
            out.append(idx)  # shattered: a single noisy surface, not several objects
            continue
        todo.extend((idx[p], finer) for p in real)  # one piece (without its crumbs) is tried finer still
    return sorted(out, key=len, reverse=True)
