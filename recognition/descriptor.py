"""One cluster -> everything the matcher needs: downsampled points, normals, VFH, roll histogram."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recognition.align import roll_histogram
from recognition.cloud import estimate_normals, voxel_downsample
from recognition.config import DescriptorConfig
from recognition.errors import CloudError
from recognition.vfh import vfh


@dataclass(frozen=True)
class ClusterDescription:
    """A cluster in its camera frame: points, normals (N, 3) m; vfh (308,); roll (90,); centroid (3,) m."""

    points: np.ndarray
    normals: np.ndarray
    vfh: np.ndarray
    roll: np.ndarray
    centroid: np.ndarray


def prepare(points: np.ndarray, params: DescriptorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Downsample and estimate viewpoint-facing normals (camera at the origin); drop NaN normals."""
    pts = voxel_downsample(points, params.voxel_m)
    normals, _ = estimate_normals(pts, params.normal_radius_m)
    ok = np.all(np.isfinite(normals), axis=1)
    return pts[ok], normals[ok]


def describe(points: np.ndarray, normals: np.ndarray, params: DescriptorConfig) -> ClusterDescription:
    """Descriptors of a prepared cluster (points and normals in a camera frame, camera at the origin)."""
    if len(points) < 3:
        raise CloudError(f"a cluster needs at least 3 points with normals, got {len(points)}")
    return ClusterDescription(
        points=points,
        normals=normals,
        vfh=vfh(points, normals, binning=params.binning),
        roll=roll_histogram(points, normals),
        centroid=points.mean(axis=0),
    )
