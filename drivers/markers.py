"""Marker front-end (pure core): detect fiducials, solve both IPPE poses, refine with depth, covariance.

    detections = MarkerDetector(MarkerConfig()).detect(rgb, camera_info, depth_mm)

Each ``MarkerDetection`` carries both planar-PnP (IPPE) solutions with their reprojection errors,
the chosen ``camera_T_marker`` and a 6x6 covariance in ROS order (x y z rx ry rz) expressed in
the marker frame, which is gtsam's Pose3 tangent convention (after reordering).

Covariance model (why each term): lateral position error is the corner noise back-projected,
sigma ~ z sigma_px / (f sqrt(4)); depth along the ray comes from the apparent size,
sigma ~ z^2 sigma_px / (f s); in-plane rotation from the edge directions, sigma ~ sigma_px / w_px;
out-of-plane tilt is planar PnP's weak direction, sigma ~ sigma_px z / (f s) / sin(view angle),
floored because near-frontal views carry almost no perspective. A depth-refined pose replaces the
depth and tilt terms by those of the plane fit (Kinect sigma_z ~ 1.4 mm z^2 averaged over the quad,
floored by the sensor's bias).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.config import MarkerConfig
from drivers.errors import DriverError
from schemas.codec import CameraInfo
from schemas.geometry import so3_exp

# Kinect v1: depth noise sigma_z = K z^2 (Khoshelham & Elberink 2012) plus 1/8 px disparity
# quantisation over a 7.5 cm baseline; and a bias floor per fitted plane.
KINECT_SIGMA_Z_1M = 0.0014
KINECT_BASELINE_M = 0.075
KINECT_DISPARITY_STEP_PX = 0.125
PLANE_BIAS_FLOOR_M = 0.0004
PLANE_TILT_FLOOR_RAD = math.radians(0.4)
# Depth errors inside one quad are correlated (quantisation steps are spatially structured), so a
# plane fit averages over fewer independent pixels than it has: n_eff = n / PLANE_CORRELATION.
PLANE_CORRELATION = 6.0
# Scale factors on the first-order PnP terms, measured once on the simulated demo cell
# (python -m benchmarks.markers reports the coverage they give); 1.0 would be the bare formula.
PNP_POSITION_FACTOR = 1.2
PNP_TILT_FACTOR = 0.45
PNP_INPLANE_FACTOR = 1.3


@dataclass(frozen=True)
class MarkerDetection:
    """One marker in one image. Poses are 4x4 camera_T_marker; covariance 6x6 ROS order, marker frame."""

    marker_id: int
    side_m: float
    corners_px: np.ndarray  # (4, 2) TL, TR, BR, BL
    candidate_a: np.ndarray  # best IPPE solution
    error_a_px: float
    candidate_b: np.ndarray
    error_b_px: float
    camera_T_marker: np.ndarray
    covariance: np.ndarray
    depth_refined: bool
    ambiguous: bool


def load_dictionary(name_or_path: str) -> cv2.aruco.Dictionary:
    """A predefined dictionary by OpenCV name, or a custom one from an OpenCV YAML file."""
    code = getattr(cv2.aruco, name_or_path, None)
    if isinstance(code, int):
        return cv2.aruco.getPredefinedDictionary(code)
    path = Path(name_or_path)
    if path.suffix in (".yml", ".yaml") and path.is_file():
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        d = cv2.aruco.Dictionary()
        ok = d.readDictionary(fs.root())
        fs.release()
        if ok:
            return d
        raise DriverError(f"{path}: not an OpenCV aruco dictionary file")
    raise DriverError(
        f"unknown marker dictionary {name_or_path!r}: give an OpenCV name (DICT_APRILTAG_36h11, DICT_6X6_250, ...) or a .yml file"
    )


def marker_object_points(side_m: float) -> np.ndarray:
    """Corners of a marker in its own frame (OpenCV order TL, TR, BR, BL; z out of the face)."""
    h = side_m / 2.0
    return np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]], dtype=np.float64)


def kinect_sigma_z(z: np.ndarray | float, f_px: float) -> np.ndarray:
    """Per-pixel depth sigma (m) at range z (m, any shape): Gaussian disparity noise and uniform quantisation."""
    step = np.multiply(z, z) * KINECT_DISPARITY_STEP_PX / (f_px * KINECT_BASELINE_M)
    return np.hypot(KINECT_SIGMA_Z_1M * np.multiply(z, z), step / math.sqrt(12.0))


def _diagonal_intersections(C: np.ndarray) -> np.ndarray:
    """Images (M, 2) of the marker centres of quads C (M, 4, 2): where the diagonals cross (exact
    under perspective; the corners' mean for a degenerate quad)."""
    p, r = C[:, 0], C[:, 2] - C[:, 0]
    q, s = C[:, 1], C[:, 3] - C[:, 1]
    denom = r[:, 0] * s[:, 1] - r[:, 1] * s[:, 0]
    ok = np.abs(denom) >= 1e-9
    t = ((q[:, 0] - p[:, 0]) * s[:, 1] - (q[:, 1] - p[:, 1]) * s[:, 0]) / np.where(ok, denom, 1.0)
    return np.where(ok[:, None], p + t[:, None] * r, C.mean(1))


@dataclass(frozen=True)
class PlaneFit:
    """Plane n.x = d in the camera frame (n toward the camera), from N depth points with RMS residual."""

    normal: np.ndarray
    d: float
    n_points: int
    rms_m: float
    extent_m: float


@dataclass(frozen=True)
class PlaneFits:
    """The planes of M quads as arrays (the fields of ``PlaneFit`` stacked); ``ok`` (M,) False where a
    quad has none."""

    normal: np.ndarray  # (M, 3)
    d: np.ndarray  # (M,) m
    n_points: np.ndarray  # (M,)
    rms_m: np.ndarray  # (M,)
    extent_m: np.ndarray  # (M,)
    ok: np.ndarray  # (M,) bool

    @staticmethod
    def of(planes: list[PlaneFit | None]) -> PlaneFits:
        """Single fits (None: no plane) stacked; a missing plane's row holds placeholders."""
        fits = [p or PlaneFit(np.array([0.0, 0.0, -1.0]), -1.0, 0, 0.0, 0.0) for p in planes]
        return PlaneFits(
            np.array([p.normal for p in fits], dtype=float).reshape(-1, 3),
            np.array([p.d for p in fits], dtype=float),
            np.array([p.n_points for p in fits], dtype=float),
            np.array([p.rms_m for p in fits], dtype=float),
            np.array([p.extent_m for p in fits], dtype=float),
            np.array([p is not None for p in planes], dtype=bool),
        )

    def __getitem__(self, i: int) -> PlaneFit | None:
        if not self.ok[i]:
            return None
        return PlaneFit(
            self.normal[i], float(self.d[i]), int(self.n_points[i]), float(self.rms_m[i]), float(self.extent_m[i])
        )

    def take(self, idx: np.ndarray) -> PlaneFits:
        """The planes of quads ``idx`` (indices or a mask), in that order."""
        return PlaneFits(
            self.normal[idx], self.d[idx], self.n_points[idx], self.rms_m[idx], self.extent_m[idx], self.ok[idx]
        )

    def where(self, keep: np.ndarray) -> PlaneFits:
        """The same planes, those where ``keep`` (M,) is False dropped."""
        return PlaneFits(self.normal, self.d, self.n_points, self.rms_m, self.extent_m, self.ok & keep)


def fit_plane(depth_mm: np.ndarray, corners: np.ndarray, info: CameraInfo, shrink: float = 0.8) -> PlaneFit | None:
    """One quad's plane; see ``fit_planes``."""
    return fit_planes(depth_mm, [corners], info, shrink)[0]


def _quad_pixels(
    depth_mm: np.ndarray, corners: np.ndarray, shrink: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Columns, rows (int) and depths (m) of the measured pixels inside each shrunken quad of corners
    (M, 4, 2), quad after quad, and how many each quad has (M,)."""
    centre = corners.mean(1, keepdims=True)
    quads = (centre + shrink * (corners - centre)).astype(np.int32)
    lo = np.maximum(quads.min(1), 0)
    hi = np.minimum(quads.max(1) + 1, [depth_mm.shape[1], depth_mm.shape[0]])
    local = quads - lo[:, None, :]
    us, vs, zs = [], [], []
    counts = np.zeros(len(quads), int)
    for i, ((x0, y0), (x1, y1)) in enumerate(zip(lo.tolist(), hi.tolist())):
        if x1 - x0 < 3 or y1 - y0 < 3:
            continue
        inside = np.zeros((y1 - y0, x1 - x0), depth_mm.dtype)
        cv2.fillConvexPoly(inside, local[i], np.iinfo(depth_mm.dtype).max)
        z = inside & depth_mm[y0:y1, x0:x1]  # the depth inside the quad, 0 outside it
        v, u = np.nonzero(z)
        us.append(u)
        vs.append(v)
        zs.append(z[v, u])
        counts[i] = len(u)
    if not us:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), counts
    u, v = np.concatenate(us), np.concatenate(vs)
    return u + np.repeat(lo[:, 0], counts), v + np.repeat(lo[:, 1], counts), np.concatenate(zs) * 1e-3, counts


class _Segments:
    """Consecutive runs of samples, one per quad: run i is [starts[i], starts[i] + counts[i])."""

    def __init__(self, counts: np.ndarray) -> None:
        self.counts = counts
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self._full = counts > 0

    def sums(self, rows: np.ndarray) -> np.ndarray:
        """Sums (k, m) of each row of ``rows`` (k, n) over each run. One reduceat over contiguous
        rows: a tenth of the time of a weighted bincount per row."""
        out = np.zeros((len(rows), len(self.counts)))
        out[:, self._full] = np.add.reduceat(rows, self.starts[self._full], axis=1)  # reduceat misreads empty runs
        return out

    def spread(self, values: np.ndarray) -> np.ndarray:
        """Per-run values (..., m) repeated for each sample of the run: (..., n). (np.repeat: a
        fifth of the time of indexing by each sample's run.)"""
        return np.repeat(values, self.counts, axis=-1)


def _segment_lines(xyw: np.ndarray, runs: _Segments, keep: np.ndarray) -> np.ndarray:
    """Least-squares w = a x + b y + c over the kept samples of each run, xyw (3, n): (m, 3).

    Normal equations on centred coordinates, all runs at once (a quad spans a few hundredths
    in x and y, so centring keeps the 2x2 system well conditioned).
    """
    k = keep.astype(np.float64)
    n = np.maximum(runs.sums(k[None])[0], 1.0)
    mean = runs.sums(xyw * k) / n  # (3, m): x, y, w
    d = xyw - runs.spread(mean)
    sxx, syy, sxy, sxw, syw = runs.sums(d[[0, 1, 0, 0, 1]] * d[[0, 1, 1, 2, 2]] * k)
    det = sxx * syy - sxy * sxy
    det = np.where(np.abs(det) > 1e-300, det, 1e-300)
    a = (syy * sxw - sxy * syw) / det
    b = (sxx * syw - sxy * sxw) / det
    return np.stack([a, b, mean[2] - a * mean[0] - b * mean[1]], axis=1)


def _plane_w(p: np.ndarray, xyw: np.ndarray, runs: _Segments) -> np.ndarray:
    """Each sample's w on its run's plane w = a x + b y + c, p (m, 3): (n,)."""
    a, b, c = runs.spread(p.T)
    return a * xyw[0] + b * xyw[1] + c


def _segment_medians(r: np.ndarray, bounds: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Median of r over the kept samples of each segment [bounds[i], bounds[i + 1]) (0 where none is kept)."""
    out = np.zeros(len(bounds) - 1)
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        kept = r[a:b][keep[a:b]]
        if len(kept):  # np.median's own overhead is most of its cost on a quad's thousand pixels
            lo, hi = (len(kept) - 1) // 2, len(kept) // 2
            part = np.partition(kept, (lo, hi))
            out[i] = 0.5 * (part[lo] + part[hi])
    return out


def fit_planes(depth_mm: np.ndarray, corners: list[np.ndarray], info: CameraInfo, shrink: float = 0.8) -> PlaneFits:
    """Planes through the depth pixels inside each (shrunken) marker quad, fitted in inverse depth.

    A plane n.X = d seen through normalised image coordinates (x, y) has inverse depth
    1/z = (n / d) . (x, y, 1): linear in the pixel. The Kinect measures disparity f b / z with
    Gaussian noise of the same size everywhere, so ordinary least squares in 1/z is the unbiased
    fit. A fit of the back-projected points in metres is not: their noise grows as z^2 and runs
    along the rays, and ranges came out up to 3 mm long at 4 m. Two trimming passes drop flying
    pixels at the quad's edge; the cut never goes below the sensor's own noise, or a near-frontal
    quad whose pixels mostly share one quantisation level would keep only those.

    All quads of a frame are fitted together (numpy over the concatenated pixels, one segment per
    quad): per-quad Python calls cost more than the arithmetic. ``ok`` is False where a quad has
    fewer than 12 usable pixels or its plane does not face the camera.
    """
    m = len(corners)
    if m == 0:
        return PlaneFits.of([])
    u, v, z, counts = _quad_pixels(depth_mm, np.asarray(corners, np.float64), shrink)
    if counts.max() < 12:
        return PlaneFits.of([None] * m)
    runs = _Segments(counts)
    bounds = np.concatenate([runs.starts, [counts.sum()]])
    xyw = np.stack([(u - info.K[0, 2]) / info.K[0, 0], (v - info.K[1, 2]) / info.K[1, 1], 1.0 / np.maximum(z, 1e-9)])
    f = 0.5 * (info.K[0, 0] + info.K[1, 1])
    noise_w = kinect_sigma_z(1.0, f)  # the sensor's 1/z sigma (1/m), the same at every range
    enough = counts >= 12
    keep = np.ones(len(z), bool)
    for _ in range(2):
        p = _segment_lines(xyw, runs, keep)
        res = np.abs(xyw[2] - _plane_w(p, xyw, runs))
        cut = 3.0 * np.maximum(1.4826 * _segment_medians(res, bounds, keep), noise_w)
        keep = res < runs.spread(cut)  # every pixel judged again against the refitted plane
        enough &= runs.sums(keep[None].astype(np.float64))[0] >= 12
    p = _segment_lines(xyw, runs, keep)
    k = keep.astype(np.float64)
    n = np.maximum(runs.sums(k[None])[0], 1.0)
    norm = np.linalg.norm(p, axis=1)
    # Residuals as distances from the plane (m), as a metric fit would report them: a pixel off by
    # dw in 1/z is off by dz = dw z^2 along its ray (x, y, 1), and by dz |n . (x, y, 1)| from the plane.
    w, fitted = xyw[2], _plane_w(p, xyw, runs)
    off = (w - fitted) / w**2 * fitted / runs.spread(norm)
    rms = np.sqrt(runs.sums((k * off**2)[None])[0] / n)
    # Extent: the largest spread of the kept points (m), from each quad's 3x3 scatter.
    pts = np.vstack([xyw[:2], np.ones(len(w))]) / w  # (3, n)
    d = pts - runs.spread(runs.sums(pts * k) / n)
    i, j = np.triu_indices(3)
    upper = runs.sums(d[i] * d[j] * k)  # (6, m)
    scatter = np.zeros((m, 3, 3))
    scatter[:, i, j] = scatter[:, j, i] = upper.T
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(scatter)[:, -1], 0.0) / n)
    ok = enough & (p[:, 2] > 0)  # enough pixels, and the plane faces the camera
    return PlaneFits(-p / norm[:, None], -1.0 / norm, n, rms, spread * 2 * math.sqrt(3), ok)


@dataclass(frozen=True)
class Sigmas:
    """Standard deviations of M observations, arrays (M,): lateral and along-ray position (m), tilt
    and in-plane rotation (rad)."""

    lateral: np.ndarray
    ray: np.ndarray
    tilt: np.ndarray
    inplane: np.ndarray


def pnp_sigmas(camera_T_marker: np.ndarray, side_m: np.ndarray, f_px: float, pixel_sigma: float) -> Sigmas:
    """Uncertainty of planar-PnP poses (M, 4, 4) of markers with sides (M,) (m) from corner noise
    alone; see the module docstring."""
    t = camera_T_marker[:, :3, 3]
    z = np.maximum(np.linalg.norm(t, axis=1), 0.05)
    cos_view = np.abs(np.einsum("mi,mi->m", camera_T_marker[:, :3, 2], t)) / z
    sin_view = np.sqrt(np.maximum(1.0 - cos_view**2, 0.0))
    w_px = f_px * side_m / z
    return Sigmas(
        lateral=PNP_POSITION_FACTOR * z * pixel_sigma / (f_px * 2.0),
        ray=PNP_POSITION_FACTOR * z * z * pixel_sigma / (f_px * side_m),
        tilt=PNP_TILT_FACTOR * 2.0 * pixel_sigma * z / (f_px * side_m) / np.maximum(sin_view, 0.25),
        inplane=PNP_INPLANE_FACTOR * pixel_sigma / w_px,
    )


def plane_sigmas(z: np.ndarray, f_px: float, planes: PlaneFits) -> tuple[np.ndarray, np.ndarray]:
    """(range sigma m, normal sigma rad), each (M,), of depth-plane fits at ranges z (M,) (m) over
    ``planes.n_points`` pixels."""
    n = np.maximum(planes.n_points / PLANE_CORRELATION, 1.0)
    sig = kinect_sigma_z(z, f_px)
    ray = np.hypot(sig / np.sqrt(n), PLANE_BIAS_FLOOR_M * z * z)
    tilt = np.hypot(sig / (np.maximum(planes.extent_m, 0.01) * np.sqrt(n)) * 4.0, PLANE_TILT_FLOOR_RAD)
    return ray, tilt


def covariance_from_sigmas(camera_T_marker: np.ndarray, s: Sigmas) -> np.ndarray:
    """Covariances (M, 6, 6) of poses (M, 4, 4), ROS order (x y z rx ry rz), in the marker frame
    (gtsam's body convention)."""
    t = camera_T_marker[:, :3, 3]
    R = camera_T_marker[:, :3, :3]
    ray = t / np.maximum(np.linalg.norm(t, axis=1), 1e-9)[:, None]
    P = ray[:, :, None] * ray[:, None, :]
    cov_t_cam = s.lateral[:, None, None] ** 2 * (np.eye(3) - P) + s.ray[:, None, None] ** 2 * P
    cov = np.zeros((len(t), 6, 6))
    cov[:, :3, :3] = np.swapaxes(R, 1, 2) @ cov_t_cam @ R
    cov[:, 3, 3] = cov[:, 4, 4] = s.tilt**2
    cov[:, 5, 5] = s.inplane**2
    return cov


def covariance_models(
    camera_T_marker: np.ndarray, side_m: np.ndarray, info: CameraInfo, pixel_sigma: float, planes: PlaneFits
) -> np.ndarray:
    """Covariances (M, 6, 6) of M observations (poses (M, 4, 4), sides (M,) m): PnP alone, or fused
    with the depth plane fit where ``planes.ok``."""
    f = 0.5 * (info.K[0, 0] + info.K[1, 1])
    s = pnp_sigmas(camera_T_marker, side_m, f, pixel_sigma)
    ray, tilt = plane_sigmas(np.linalg.norm(camera_T_marker[:, :3, 3], axis=1), f, planes)
    fused_tilt = 1.0 / np.sqrt(1.0 / s.tilt**2 + 1.0 / tilt**2)
    s = Sigmas(s.lateral, np.where(planes.ok, ray, s.ray), np.where(planes.ok, fused_tilt, s.tilt), s.inplane)
    return covariance_from_sigmas(camera_T_marker, s)


def covariance_model(
    camera_T_marker: np.ndarray, side_m: float, info: CameraInfo, pixel_sigma: float, plane: PlaneFit | None
) -> np.ndarray:
    """Covariance (6, 6) of one observation, PnP alone or fused with a depth plane fit."""
    return covariance_models(camera_T_marker[None], np.array([side_m]), info, pixel_sigma, PlaneFits.of([plane]))[0]


EDGE_MIN_CONTRAST = 20.0  # grey levels between the border and the margin for an edge sample to count
EDGE_SAMPLES = 24  # profiles across each side, over its middle 70 % (away from the corners)
EDGE_OFFSETS = 21  # grey-level samples along each profile


def _edge_points(gray: np.ndarray, C: np.ndarray, modules: int) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel points (L = 4M, S, 2) on the outer edge of each marker side (side i runs from
    corner i to i + 1 of C (M, 4, 2)) and which of them were found (L, S): on each profile across
    the side, where the grey level crosses halfway from the dark border to the light margin."""
    A = C.reshape(-1, 2)
    side = (np.roll(C, -1, axis=1) - C).reshape(-1, 2)
    length = np.maximum(np.linalg.norm(side, axis=1), 1e-9)
    normal = np.stack([side[:, 1], -side[:, 0]], axis=1) / length[:, None]
    outward = np.sign(np.einsum("ij,ij->i", normal, (C - C.mean(1, keepdims=True)).reshape(-1, 2)))
    normal *= np.where(outward == 0, 1.0, outward)[:, None]
    reach = np.clip(0.8 * length / modules, 1.0, 3.0)  # stay inside the border module: the pattern starts after it
    offs = np.linspace(-1.0, 1.0, EDGE_OFFSETS)[None, :] * reach[:, None]  # (L, O)
    on_side = A[:, None, :] + np.linspace(0.15, 0.85, EDGE_SAMPLES)[None, :, None] * side[:, None, :]  # (L, S, 2)
    # The x and y maps built apart: numpy's broadcasting over a last axis of 2 costs several times
    # the arithmetic. Profiles as rows (L * S, O); indexing below is flat (take_along_axis builds
    # index arrays that cost more than the arithmetic here).
    mx, my = ((on_side[:, :, None, k] + offs[:, None, :] * normal[:, None, None, k]).astype(np.float32) for k in (0, 1))
    prof = cv2.remap(gray, mx.reshape(-1, EDGE_OFFSETS), my.reshape(-1, EDGE_OFFSETS), cv2.INTER_LINEAR)
    lo, hi = prof.min(axis=1), prof.max(axis=1)
    mid = 0.5 * (lo + hi)
    rising = (prof[:, :-1] <= mid[:, None]) & (prof[:, 1:] > mid[:, None])  # dark -> light going outward
    found = (hi - lo >= EDGE_MIN_CONTRAST) & (np.count_nonzero(rising, axis=1) == 1)  # one clean edge, else skipped
    j = rising.argmax(axis=1)
    at = np.arange(len(prof)) * EDGE_OFFSETS + j
    p0, p1 = prof.ravel()[at], prof.ravel()[at + 1]
    step = (offs[:, 1] - offs[:, 0]).repeat(EDGE_SAMPLES)
    d = offs.repeat(EDGE_SAMPLES, axis=0).ravel()[at] + (mid - p0) / np.maximum(p1 - p0, 1e-6) * step
    d = d.reshape(len(side), EDGE_SAMPLES)
    return on_side + d[..., None] * normal[:, None, :], found.reshape(len(side), EDGE_SAMPLES)


def _principal_lines(P: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted total-least-squares lines through point sets P (L, K, 2) with weights w (L, K):
    centroids (L, 2) and unit directions (L, 2), from the closed-form eigenvector of each 2x2 scatter."""
    n = np.maximum(w.sum(axis=1), 1e-9)
    m = (w[..., None] * P).sum(axis=1) / n[:, None]
    D = P - m[:, None, :]
    sxx, syy, sxy = ((w * D[..., 0] ** 2).sum(1), (w * D[..., 1] ** 2).sum(1), (w * D[..., 0] * D[..., 1]).sum(1))
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # angle of the largest spread
    return m, np.stack([np.cos(theta), np.sin(theta)], axis=1)


def _robust_lines(pts: np.ndarray, found: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lines (centroids, directions) through each side's found points, refitted twice without the
    points over 3 robust sigmas off (a partly hidden edge), and how many points each kept."""
    w = found.astype(np.float64)
    for _ in range(2):
        m, t = _principal_lines(pts, w)
        off = np.abs(np.einsum("lsk,lk->ls", pts - m[:, None, :], np.stack([-t[:, 1], t[:, 0]], axis=1)))
        ranked = np.sort(np.where(w > 0, off, np.inf), axis=1)  # the kept points' offsets first
        med = ranked[np.arange(len(ranked)), np.maximum(w.sum(axis=1).astype(int) - 1, 0) // 2]
        w = w * (off <= np.maximum(3.0 * 1.4826 * np.where(np.isfinite(med), med, 0.0), 0.05)[:, None])
    m, t = _principal_lines(pts, w)
    return m, t, w.sum(axis=1)


def refine_corners_on_edges(gray: np.ndarray, corners: list[np.ndarray], modules: int) -> list[np.ndarray]:
    """Corners (4, 2) of each marker where lines fitted to its four outer border edges meet.

    OpenCV's corners sit on the thresholded contour (half a pixel inside) or come from a window
    that, on a small marker, also sees the inner pattern's edges: both pull every corner inward,
    by 0.26-0.5 px on the demo cell, and the same way in every frame of a static view. The outer
    edge of the black border is clean along its whole length, and a line through a few dozen
    sub-pixel points on it never sees the pattern. ``gray`` float32; ``modules``: the marker's width
    in modules (data bits plus border). All markers of a frame go through numpy together. A marker
    whose edges are not found keeps its corners.
    """
    if not corners:
        return []
    C = np.stack(corners).astype(np.float64)  # (M, 4, 2)
    m, t, kept = _robust_lines(*_edge_points(gray, C, modules))
    m, t = m.reshape(-1, 4, 2), t.reshape(-1, 4, 2)
    # Corner i joins the side before it (i-1 -> i) and the side after it (i -> i+1): m0 + a t0 = m1 + b t1.
    m0, t0, m1, t1 = np.roll(m, 1, axis=1), np.roll(t, 1, axis=1), m, t
    det = t0[..., 1] * t1[..., 0] - t0[..., 0] * t1[..., 1]  # of [t0, -t1]
    r = m1 - m0
    a = (r[..., 1] * t1[..., 0] - r[..., 0] * t1[..., 1]) / np.where(np.abs(det) < 0.1, 1.0, det)
    Q = m0 + a[..., None] * t0
    good = (
        (kept >= 4).reshape(-1, 4).all(axis=1)
        & (np.abs(det) >= 0.1).all(axis=1)  # edges found, not parallel
        & (np.abs(Q - C).max(axis=(1, 2)) <= 3.0)
    )  # beyond that an edge fit went astray
    return [q if g else c for q, c, g in zip(Q, corners, good)]


_REFINEMENT = {
    "edges": cv2.aruco.CORNER_REFINE_NONE,  # OpenCV's contour corners start the edge fit
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


# Adaptive-threshold windows (px): 3 and 11. OpenCV's default ladder, 3, 13 and 23, costs 4.0 ms a
# demo frame against 2.4; on the demo frames (444 markers, 20-150 px wide) and the 526 markers of the
# real photos in data/markers both find the same markers, edge-refined corners within 0.25 px. Small
# markers need the 3 px window, large ones a wider one; a YAML file's values take precedence.
THRESHOLD_WINDOWS_PX = (3, 11)


def detector_parameters(config: MarkerConfig) -> cv2.aruco.DetectorParameters:
    """OpenCV detector parameters: our threshold windows, the YAML file's values over them, then the
    configured corner refinement."""
    params = cv2.aruco.DetectorParameters()
    lo, hi = THRESHOLD_WINDOWS_PX
    params.adaptiveThreshWinSizeMin, params.adaptiveThreshWinSizeMax, params.adaptiveThreshWinSizeStep = lo, hi, hi - lo
    if config.detector_params is not None:
        fs = cv2.FileStorage(str(config.detector_params), cv2.FILE_STORAGE_READ)
        ok = fs.isOpened() and params.readDetectorParameters(fs.root())
        fs.release()
        if not ok:
            raise DriverError(f"{config.detector_params}: not a readable OpenCV DetectorParameters YAML file")
    params.cornerRefinementMethod = _REFINEMENT[config.corner_refinement]
    return params


class MarkerDetector:
    """Detects markers of one dictionary and estimates their poses. No I/O; reusable across frames."""

    def __init__(self, config: MarkerConfig) -> None:
        self.config = config
        self.dictionary = load_dictionary(config.dictionary)
        self._detector = cv2.aruco.ArucoDetector(self.dictionary, detector_parameters(config))

    def find(self, image: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """Ids (N,) and corners [(4, 2)] of every marker in an RGB or grey image."""
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        corners, ids, _ = self._detector.detectMarkers(image)
        if ids is None:
            return np.zeros(0, int), []
        found = [c.reshape(4, 2).astype(np.float64) for c in corners]
        if self.config.corner_refinement == "edges":
            found = refine_corners_on_edges(image.astype(np.float32), found, self.dictionary.markerSize + 2)
        return ids.ravel().astype(int), found

    def detect(self, image: np.ndarray, info: CameraInfo, depth_mm: np.ndarray | None = None) -> list[MarkerDetection]:
        """Every marker in the image with both IPPE poses, the chosen pose and its covariance.

        ``depth_mm`` (H, W) uint16 registered to the image refines the pose when
        ``config.use_depth``; images must match ``info``'s size.
        """
        if image.shape[:2] != (info.height, info.width):
            raise DriverError(
                f"image is {image.shape[1]}x{image.shape[0]} but camera info says {info.width}x{info.height}"
            )
        if depth_mm is not None and depth_mm.shape[:2] != image.shape[:2]:
            raise DriverError(
                f"depth {depth_mm.shape[1]}x{depth_mm.shape[0]} does not match the image {image.shape[1]}x{image.shape[0]}"
            )
        if depth_mm is not None and depth_mm.dtype != np.uint16:
            raise DriverError(f"depth is {depth_mm.dtype}, expected uint16 millimetres")
        ids, corners = self.find(image)
        if len(ids) == 0:
            return []
        use_depth = depth_mm is not None and self.config.use_depth
        planes = fit_planes(depth_mm, corners, info) if use_depth else PlaneFits.of([None] * len(ids))
        return self._poses(ids, corners, info, planes)

    def _poses(
        self, ids: np.ndarray, corners: list[np.ndarray], info: CameraInfo, planes: PlaneFits
    ) -> list[MarkerDetection]:
        """Both IPPE solutions of every marker (the better first), the depth refinement where its plane
        is usable, covariances; numpy over the frame's markers (per-marker Python cost more than the sums)."""
        sides = np.array([self.config.side_for(int(i)) for i in ids])
        solved, rvecs, tvecs, errs = [], [], [], []
        for k, (c, side) in enumerate(zip(corners, sides)):
            n, r, t, e = cv2.solvePnPGeneric(
                marker_object_points(side), c, info.K, info.D, flags=cv2.SOLVEPNP_IPPE_SQUARE
            )
            if n == 0:
                continue
            e = np.asarray(e, float).ravel()
            order = np.argsort(e, kind="stable")[[0, -1]]  # a single solution stands as both
            solved.append(k)
            rvecs += [np.ravel(r[i]) for i in order]
            tvecs += [np.ravel(t[i]) for i in order]
            errs.append(e[order])
        if not solved:
            return []
        keep = np.array(solved)
        T = np.tile(np.eye(4), (2 * len(keep), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = so3_exp(np.array(rvecs)), np.array(tvecs)
        Ta, Tb, err = T[0::2], T[1::2], np.array(errs)
        C = np.stack([corners[k] for k in keep])
        sides, planes = sides[keep], planes.take(keep)
        f = 0.5 * (info.K[0, 0] + info.K[1, 1])
        # A plane rougher than sensor noise is occluded or straddles a depth edge: PnP alone there.
        planes = planes.where(planes.rms_m <= 2.0 * kinect_sigma_z(-planes.d, f) + 0.003)
        chosen = np.where(planes.ok[:, None, None], self._refine(Ta, Tb, C, sides, info, planes), Ta)
        ambiguous = ~planes.ok & (err[:, 1] < np.maximum(2.0 * err[:, 0], err[:, 0] + self.config.pixel_sigma))
        cov = covariance_models(chosen, sides, info, self.config.pixel_sigma, planes)
        return [
            MarkerDetection(
                int(ids[k]),
                float(sides[i]),
                corners[k],
                Ta[i],
                float(err[i, 0]),
                Tb[i],
                float(err[i, 1]),
                chosen[i],
                cov[i],
                bool(planes.ok[i]),
                bool(ambiguous[i]),
            )
            for i, k in enumerate(keep)
        ]

    def _refine(
        self, Ta: np.ndarray, Tb: np.ndarray, C: np.ndarray, sides: np.ndarray, info: CameraInfo, planes: PlaneFits
    ) -> np.ndarray:
        """Poses (M, 4, 4): for each marker the IPPE solution its depth plane agrees with, the tilt
        fused with the plane's, the range from the plane (meaningful where ``planes.ok``)."""
        nearer_a = np.einsum("mi,mi->m", Ta[:, :3, 2], planes.normal) >= np.einsum(
            "mi,mi->m", Tb[:, :3, 2], planes.normal
        )
        chosen = np.where(nearer_a[:, None, None], Ta, Tb)
        f = 0.5 * (info.K[0, 0] + info.K[1, 1])
        pnp = pnp_sigmas(chosen, sides, f, self.config.pixel_sigma)
        _, plane_tilt = plane_sigmas(np.linalg.norm(chosen[:, :3, 3], axis=1), f, planes)
        # Rotate the face normal toward the plane's by the inverse-variance weight of the plane.
        weight = pnp.tilt**2 / (pnp.tilt**2 + plane_tilt**2)
        a, b = chosen[:, :3, 2], planes.normal
        axis = np.cross(a, b)
        sin = np.linalg.norm(axis, axis=1)  # under 90 deg: the chosen solution is the one nearer the plane's normal
        scale = np.where(
            sin > 1e-12, weight * np.arctan2(sin, np.einsum("mi,mi->m", a, b)) / np.maximum(sin, 1e-12), 0.0
        )
        out = chosen.copy()
        out[:, :3, :3] = so3_exp(axis * scale[:, None]) @ chosen[:, :3, :3]
        # Range: intersect the ray through the marker centre's image with the plane.
        uv = _diagonal_intersections(C)
        undist = cv2.undistortPoints(uv.reshape(-1, 1, 2), info.K, info.D).reshape(-1, 2)
        ray = np.concatenate([undist, np.ones((len(undist), 1))], axis=1)
        denom = np.einsum("mi,mi->m", planes.normal, ray)
        hit = np.abs(denom) > 1e-6
        out[:, :3, 3] = np.where(hit[:, None], ray * (planes.d / np.where(hit, denom, 1.0))[:, None], chosen[:, :3, 3])
        return out
