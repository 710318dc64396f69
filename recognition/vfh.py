"""The Viewpoint Feature Histogram (Rusu et al., IROS 2010), bin for bin as the Point Cloud Library.

308 bins: f1, f2, f3 and distance (45 each) of every point's pair with the cluster centroid, then 128
bins of the angle between each normal and the viewing direction. The arithmetic follows PCL's
``VFHEstimation`` (``features/impl/vfh.hpp``) and ``computePairFeatures`` (``features/src/pfh.cpp``)
in float32, including its SSE summation order, so that points on a bin edge land where PCL puts them.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from recognition.errors import CloudError

F_BINS = 45
VP_BINS = 128
SIZE = 4 * F_BINS + VP_BINS  # 308
ROLL_BINS = 90
_F32 = np.float32
_D_PI = float(_F32(1.0) / (_F32(2.0) * _F32(np.pi)))  # PCL's float member d_pi_, used in double

Binning = Literal["pcl", "pcl17"]


def vfh(
    points: np.ndarray,
    normals: np.ndarray,
    viewpoint: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
    *,
    binning: Binning = "pcl",
    normalize_bins: bool = True,
    normalize_distance: bool = False,
    size_component: bool = False,
) -> np.ndarray:
    """VFH of one cluster. points, normals (N, 3), metres, camera frame; viewpoint (3,) metres.

    binning "pcl" is PCL >= 1.10.1 (f1, f2, f3 all binned by (f + pi) / 2 pi, so f2 and f3 fill only
    bins 15..29); "pcl17" is PCL 1.7, the paper's era (f2, f3 binned by (f + 1) / 2). The other flags
    are PCL's setters of the same names. Points whose point or normal is not finite are left out.
    Returns (308,) float32.
    """
    if binning not in ("pcl", "pcl17"):
        raise CloudError(f"unknown VFH binning {binning!r}; use 'pcl' (PCL >= 1.10.1) or 'pcl17' (PCL 1.7)")
    p = np.asarray(points, dtype=_F32).reshape(-1, 3)
    n = np.asarray(normals, dtype=_F32).reshape(-1, 3)
    if p.shape != n.shape:
        raise CloudError(f"VFH needs one normal per point: {len(p)} points, {len(n)} normals")
    keep = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(n), axis=1)
    p, n = p[keep], n[keep]
    if len(p) < 2:
        raise CloudError(f"VFH needs at least 2 points with finite normals, got {len(p)}")

    # Centroids: sequential float32 sums, as PCL's loops (np.sum would sum pairwise).
    centroid = (np.add.accumulate(p, axis=0)[-1] / _F32(len(p))).astype(_F32)
    normal_centroid = (np.add.accumulate(n, axis=0)[-1] / _F32(len(p))).astype(_F32)

    # Components as contiguous rows (3, N): column slices of (N, 3) are strided and slow.
    pt, nt = np.ascontiguousarray(p.T), np.ascontiguousarray(n.T)
    f1, f2, f3, f4, valid = _pair_features(centroid, normal_centroid, pt, nt)
    incr = _F32(100.0) / _F32(len(p) - 1) if normalize_bins else _F32(1.0)
    # PCL bins in double: nr_bins * ((f + M_PI) * d_pi_).
    if binning == "pcl":
        edges = [(f.astype(np.float64) + np.pi) * _D_PI for f in (f1, f2, f3)]
    else:
        edges = [
            (f1.astype(np.float64) + np.pi) * _D_PI,
            (f2.astype(np.float64) + 1.0) * 0.5,
            (f3.astype(np.float64) + 1.0) * 0.5,
        ]
    hists = [_accumulate(_bin_index(F_BINS * e, F_BINS)[valid], F_BINS, incr) for e in edges]
    if size_component:
        if normalize_distance:
            far = p[np.argmax(_norm3(p - centroid))]
            scale = _norm4(centroid - far, w=_F32(1.0))  # PCL: the centroid's w = 1 enters this norm
            raw = np.floor(F_BINS * (f4.astype(np.float64) / float(scale)))
        else:
            raw = np.floor(f4 * _F32(100) + _F32(0.5))
        hists.append(_accumulate(_bin_index(raw, F_BINS, floor=False)[valid], F_BINS, incr))
    else:
        hists.append(np.zeros(F_BINS, dtype=_F32))

    # Viewpoint component: the view direction is normalised as a 4-vector whose w is -1 (0 - 1).
    d = np.asarray(viewpoint, dtype=_F32).reshape(3) - centroid
    d = (d / _norm4(d, w=_F32(-1.0))).astype(_F32)
    alpha = (_dot(nt, d).astype(np.float64) + 1.0) * 0.5
    vp_incr = _F32(100.0 / len(p)) if normalize_bins else _F32(1.0)
    hists.append(_accumulate(_bin_index(alpha * VP_BINS, VP_BINS), VP_BINS, vp_incr))
    return np.concatenate(hists).astype(_F32)


def _pair_features(c: np.ndarray, nc: np.ndarray, p: np.ndarray, n: np.ndarray):
    """PCL's computePairFeatures between the centroid (c, nc: (3,)) and every point (p, n: (3, N)), float32.

    Returns f1, f2, f3, f4 (N,) and valid (N,): False where PCL skips the pair (zero distance, or
    dp parallel to the chosen normal).
    """
    dp = p - c[:, None]
    f4 = np.sqrt(_dot(dp, dp))
    with np.errstate(divide="ignore", invalid="ignore"):
        angle1 = _dot(dp, nc) / f4
        angle2 = _dot(n, dp) / f4
        swap = np.arccos(np.abs(angle1)) > np.arccos(np.abs(angle2))
        u = np.where(swap, n, nc[:, None])
        n_t = np.where(swap, nc[:, None], n)
        dp *= np.where(swap, _F32(-1), _F32(1))  # exact: a sign flip
        f3 = np.where(swap, -angle2, angle1)
        v = _cross(dp, u)
        v_norm = np.sqrt(_dot(v, v))
        v /= v_norm
        w = _cross(u, v)
        f2 = _dot(v, n_t)
        f1 = np.arctan2(_dot(w, n_t), _dot(u, n_t))
    valid = (f4 != 0) & (v_norm != 0)
    return f1, f2, f3, f4, valid


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Eigen's SSE dot of 4-vectors with w = 0, (a0 b0 + a2 b2) + (a1 b1 + 0), in float32.

    a, b: (3, N) rows or (3,) vectors.
    """
    return (a[0] * b[0] + a[2] * b[2]) + a[1] * b[1]


def _norm4(a: np.ndarray, w: np.float32) -> np.float32:
    """Eigen's norm of the 4-vector (a, w) in float32, in SSE order."""
    return _F32(np.sqrt((a[0] * a[0] + a[2] * a[2]) + (a[1] * a[1] + w * w)))


def _norm3(a: np.ndarray) -> np.ndarray:
    """Eigen's scalar norm of 3-vectors, (x^2 + y^2) + z^2 in float32."""
    return np.sqrt((a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1]) + a[..., 2] * a[..., 2])


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of (3, N) rows."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _bin_index(x: np.ndarray, bins: int, floor: bool = True) -> np.ndarray:
    """Clamp to [0, bins); NaN (undefined features) maps to 0 but is masked out by the caller."""
    x = np.nan_to_num(np.floor(x) if floor else x, nan=0.0, posinf=bins - 1, neginf=0.0)
    return np.clip(x, 0, bins - 1).astype(np.int64)


def _accumulate(index: np.ndarray, bins: int, incr: np.float32) -> np.ndarray:
    """Histogram built by adding incr once per sample in float32, as PCL's loop does."""
    counts = np.bincount(index, minlength=bins)
    sums = np.concatenate([[_F32(0)], np.add.accumulate(np.full(int(counts.max(initial=0)), incr, dtype=_F32))])
    return sums[counts].astype(_F32)
