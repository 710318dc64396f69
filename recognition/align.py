"""Camera-roll histogram, roll alignment and ICP: from a VFH match to a full 6-DoF pose.

VFH is invariant to rotation about the line of sight through the cluster centroid (the camera
roll). The camera roll histogram (Aldoma et al., 2011) recovers it: rotate each cluster so that its
centroid lies on +z, histogram the direction of the normals projected on the xy plane (weighted by
the projected length), and circularly cross-correlate the scene's histogram with the model view's.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import open3d as o3d

from recognition.cloud import PointIndex
from recognition.verify import project
from recognition.vfh import ROLL_BINS
from schemas.geometry import rotation_between, rpy_matrix


def align_to_z(direction: np.ndarray) -> np.ndarray:
    """Smallest rotation R (3, 3) with R @ direction/|direction| = +z."""
    return rotation_between(direction, np.array([0.0, 0.0, 1.0]))


def roll_histogram(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Camera roll histogram (90 bins of 4 deg) of a cluster in its camera frame, summing to 1."""
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    ok = np.all(np.isfinite(n), axis=1)
    R = align_to_z(p[ok].mean(axis=0))
    m = n[ok] @ R.T
    angle = np.arctan2(m[:, 1], m[:, 0])
    weight = np.hypot(m[:, 0], m[:, 1])
    index = np.clip(np.floor((angle + np.pi) / (2 * np.pi) * ROLL_BINS).astype(int), 0, ROLL_BINS - 1)
    hist = np.bincount(index, weight, minlength=ROLL_BINS)
    total = hist.sum()
    return hist / total if total > 0 else hist


def roll_correlations(scene_hist: np.ndarray, view_hists: np.ndarray) -> np.ndarray:
    """Circular cross-correlation (by FFT) of the scene's roll histogram (90,) with each view's (V, 90):
    (V, 90), entry k the match when the view is rolled by k bins."""
    scene = np.fft.fft(scene_hist)
    return np.real(np.fft.ifft(scene[None, :] * np.conj(np.fft.fft(np.atleast_2d(view_hists), axis=1)), axis=1))


def roll_peaks(corr: np.ndarray, peaks: int = 3, ratio: float = 0.7) -> list[list[float]]:
    """Roll angles (rad) at the local maxima of each correlation row (V, 90) that are at least
    ``ratio`` of that row's best, best first, each refined to sub-bin precision with a parabola
    through its neighbours; [0.0] for a row with none."""
    corr = np.atleast_2d(corr)
    left, right = np.roll(corr, 1, axis=1), np.roll(corr, -1, axis=1)
    is_peak = (corr >= left) & (corr > right) & (corr >= ratio * corr.max(axis=1, keepdims=True))
    k = np.argsort(np.where(is_peak, -corr, np.inf), axis=1, kind="stable")[:, :peaks]
    c, lft, rgt = (np.take_along_axis(a, k, axis=1) for a in (corr, left, right))
    denom = lft - 2 * c + rgt
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(denom < 0, 0.5 * (lft - rgt) / denom, 0.0)
    angles = (k + offset) * (2 * np.pi / ROLL_BINS)
    found = np.take_along_axis(is_peak, k, axis=1)
    return [row[ok].tolist() or [0.0] for row, ok in zip(angles, found)]


def roll_candidates(scene_hist: np.ndarray, view_hist: np.ndarray, peaks: int = 3, ratio: float = 0.7) -> list[float]:
    """Roll angles (rad) that turn the view's histogram into the scene's, best first."""
    return roll_peaks(roll_correlations(scene_hist, view_hist), peaks, ratio)[0]


def rot_z(angle: float | np.ndarray) -> np.ndarray:
    """Rotation (3, 3) about z by ``angle`` rad; (..., 3, 3) for an array of angles."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(np.shape(angle) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1], R[..., 2, 2] = c, -s, s, c, 1.0
    return R


def views_to_scene(
    scene_centroid: np.ndarray, view_centroids: np.ndarray, view_to_z: np.ndarray, rolls: np.ndarray
) -> np.ndarray:
    """camera_T_view (K, 4, 4): puts each model view's cloud (in its virtual camera) onto the scene cluster.

    Both clusters are turned so that their centroids lie on +z (view_to_z (K, 3, 3) is
    ``align_to_z`` of each view centroid (K, 3), m), the view is rolled by rolls (K,) rad about z,
    and the centroids are made to coincide.
    """
    R = align_to_z(scene_centroid).T @ rot_z(np.asarray(rolls, dtype=np.float64)) @ view_to_z
    T = np.zeros((len(rolls), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = np.asarray(scene_centroid) - np.einsum("kij,kj->ki", R, view_centroids)
    T[:, 3, 3] = 1.0
    return T


#: ``damped_icp`` solves (H + ICP_DAMPING * max(diag H) I) x = -g each step: small enough to leave a
#: well-posed step as it is, large enough to hold what a small curved patch does not pin (1e-4 to
#: 1e-2 all held a mug's true pose; 0 and 1e-6 did not).
ICP_DAMPING = 1e-3
#: A step that moves the points along their pairs' normals by less than this (m, RMS) ends it.
CONVERGED_M = 1e-4
_DIAGONAL = np.diag_indices(6)
#: Open3D's fine fit ran off when its fitness ends more than this below the start's: the damped one
#: then fits from the same start.
RAN_OFF = 0.1


@dataclass(frozen=True)
class IcpResult:
    """camera_T_object (4, 4); fitness = inlier fraction of the visible model points (0..1); RMSE m."""

    camera_T_object: np.ndarray
    fitness: float
    rmse_m: float


@dataclass(frozen=True)
class ImageBounds:
    """The image a scene was measured in: pinhole K (3, 3) and size (H, W) px."""

    K: np.ndarray
    size: tuple[int, int]

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Mask (...,) of camera-frame points (..., 3) in front of the camera that project into the image."""
        z = points[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.K[0, 0] * points[..., 0] / z + self.K[0, 2]
            v = self.K[1, 1] * points[..., 1] / z + self.K[1, 2]
            return (z > 0) & (u >= 0) & (u < self.size[1]) & (v >= 0) & (v < self.size[0])


def facing_camera(
    model_points: np.ndarray, model_normals: np.ndarray, camera_T_objects: np.ndarray, image: ImageBounds | None = None
) -> np.ndarray:
    """Mask (S, N) of the model points (N, 3), object frame, whose normal faces the camera at each
    pose (S, 4, 4): a cheap visibility cull; with the image, only those landing inside it (an object
    cut by the frame's border is not missing what lies beyond it)."""
    T = np.asarray(camera_T_objects, dtype=np.float64).reshape(-1, 4, 4)
    R, t = T[:, :3, :3], T[:, :3, 3]
    # n_cam . -p_cam = -(R n) . (R p + t) = -(n . p) - (R n) . t
    n_dot_p = np.einsum("ij,ij->i", model_normals, model_points)
    facing = -n_dot_p[None, :] - np.einsum("sij,nj,si->sn", R, model_normals, t) > 0
    if image is not None:
        facing &= image.inside(model_points @ R.transpose(0, 2, 1) + t[:, None, :])
    return facing


@dataclass(frozen=True)
class Surface:
    """What ICP aligns a model onto: scene points (N, 3, camera frame, m) with unit normals (N, 3)
    and the same as an Open3D cloud, built once for every fit onto them; their index is built when
    first asked for (Open3D's ICP alone, as the fused refit runs it, never does)."""

    points: np.ndarray
    normals: np.ndarray
    cloud: o3d.geometry.PointCloud

    @classmethod
    def of(cls, points: np.ndarray, normals: np.ndarray) -> Surface:
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        cloud = _cloud(points)
        cloud.normals = o3d.utility.Vector3dVector(normals)
        return cls(points, normals, cloud)

    @cached_property
    def index(self) -> PointIndex:
        return PointIndex(self.points)


def icp_pass(
    source_points: np.ndarray,
    surface: Surface,
    camera_T_object: np.ndarray,
    distance_m: float,
    iterations: int = 30,
    max_shift_m: float = np.inf,
) -> IcpResult:
    """One point-to-plane ICP (Open3D's) of model points (M, 3), object frame, from the start pose
    onto the surface. Fitness and RMSE are ICP's own, at distance_m, over those points: pass the
    ones facing the camera. A result that moved more than max_shift_m from the start (ICP sliding
    off a degenerate cluster) scores 0 at the start pose."""
    start = np.asarray(camera_T_object, dtype=np.float64)
    failed = IcpResult(start, 0.0, float("inf"))
    if len(source_points) < 3:
        return failed
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=iterations)
    reg = o3d.pipelines.registration.registration_icp(
        _cloud(source_points), surface.cloud, distance_m, start, est, crit
    )
    pose = np.asarray(reg.transformation)
    if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:3, 3] - start[:3, 3]) > max_shift_m:
        return failed
    return IcpResult(pose, float(reg.fitness), float(reg.inlier_rmse) if reg.fitness > 0 else float("inf"))


def icp_passes(
    source_points: np.ndarray,
    facing: np.ndarray,
    surface: Surface,
    starts: np.ndarray,
    distance_m: float,
    iterations: int,
    max_shift_m: float = np.inf,
) -> list[IcpResult]:
    """``icp_pass`` from every start (S, 4, 4) at once, each with its own model points (the rows of
    ``facing`` (S, M) over the points (M, 3), object frame): Open3D's point-to-plane ICP (pairs the
    nearest surface point within distance_m, a linearised least-squares step per start, stop when
    neither fitness nor RMSE changes by 1e-6), with the surface's one index for every start and
    iteration: Open3D builds a k-d tree of the surface per call, which costs more than a short
    pass. A start left with fewer pairs than unknowns (6) fails: Open3D's steps run off there."""
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 4, 4)
    poses = starts.copy()
    n_starts = len(poses)
    owner, point = np.nonzero(facing)  # start and model point of each posed point, grouped by start
    counts = np.bincount(owner, minlength=n_starts)
    src = np.asarray(source_points, dtype=np.float64)[point]
    active = counts >= 3
    fitness, sq_sum = np.zeros(n_starts), np.zeros(n_starts)
    pairs = np.zeros(n_starts)

    def paired(live: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The live starts' posed points (grouped by start), their nearest surface points, whether
        they pair, and whose they are; the live starts' scores updated."""
        mine = np.flatnonzero(live[owner])
        who = owner[mine]
        p = np.einsum("nij,nj->ni", poses[who, :3, :3], src[mine]) + poses[who, :3, 3]
        idx, sq = surface.index.nearest(p)
        ok = sq <= distance_m**2
        pairs[live] = np.bincount(who[ok], minlength=n_starts)[live]
        sq_sum[live] = np.bincount(who[ok], sq[ok].astype(np.float64), minlength=n_starts)[live]
        fitness[live] = pairs[live] / counts[live]
        return p, idx, ok, who

    p, idx, ok, who = paired(active)
    starved = np.zeros(n_starts, dtype=bool)
    for _ in range(iterations):
        starved |= active & (pairs < 6)
        live = active & ~starved
        if not live.any():
            break
        sel = np.flatnonzero(ok & live[who])  # grouped by start, as the points are
        q, n, ps = surface.points[idx[sel]], surface.normals[idx[sel]], p[sel]
        J = _plane_jacobian(ps, n)  # Open3D's linearisation: small turns about the camera's origin
        r = np.einsum("ij,ij->i", ps - q, n)
        first = np.r_[0, np.flatnonzero(np.diff(who[sel])) + 1]  # each live start's first pair
        JtJ = np.add.reduceat((J[:, :, None] * J[:, None, :]).reshape(-1, 36), first).reshape(-1, 6, 6)
        Jtr = np.add.reduceat(J * r[:, None], first)
        x = np.zeros((n_starts, 6))
        try:
            x[live] = np.linalg.solve(JtJ, -Jtr[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a singular system (points on one line): its least-norm step
            x[live] = [np.linalg.lstsq(a, -b, rcond=None)[0] for a, b in zip(JtJ, Jtr)]
        update = np.tile(np.eye(4), (n_starts, 1, 1))
        update[:, :3, :3] = rpy_matrix(x[:, 0], x[:, 1], x[:, 2])  # Open3D's: Rz Ry Rx
        update[:, :3, 3] = x[:, 3:]
        poses[live] = update[live] @ poses[live]
        before = fitness.copy(), np.sqrt(sq_sum / np.maximum(pairs, 1))
        p, idx, ok, who = paired(live)
        rmse = np.sqrt(sq_sum / np.maximum(pairs, 1))
        # Open3D stops a pass once neither its fitness nor its RMSE changed by 1e-6.
        active &= ~(live & (np.abs(before[0] - fitness) < 1e-6) & (np.abs(before[1] - rmse) < 1e-6))
    out = []
    for s, (start, pose) in enumerate(zip(starts, poses)):
        if (
            counts[s] < 3
            or starved[s]
            or not np.all(np.isfinite(pose))
            or np.linalg.norm(pose[:3, 3] - start[:3, 3]) > max_shift_m
        ):
            out.append(IcpResult(start, 0.0, float("inf")))
        else:
            out.append(
                IcpResult(pose, float(fitness[s]), float(np.sqrt(sq_sum[s] / pairs[s])) if pairs[s] else float("inf"))
            )
    return out


def damped_icp(
    source_points: np.ndarray,
    surface: Surface,
    camera_T_object: np.ndarray,
    distance_m: float,
    iterations: int = 30,
    max_shift_m: float = np.inf,
) -> IcpResult:
    """``icp_pass`` with each Gauss-Newton step damped (Levenberg-Marquardt, ``ICP_DAMPING``) and
    taken about the pairs' centroid, where rotation and translation decouple; it stops once a step
    moves the points along their pairs' normals by under ``CONVERGED_M`` (RMS: sliding along a
    symmetry, a can turning about its axis, changes no residual). Fitness and RMSE at the final pose.

    Undamped, a small curved patch (a mug's side: 40 points at 0.9 m) leaves directions the normal
    equations barely pin, and the noise alone sends the step along them: Open3D's ICP left a mug's
    true pose by 9 cm in 8 iterations."""
    start = np.asarray(camera_T_object, dtype=np.float64)
    failed = IcpResult(start, 0.0, float("inf"))
    source = np.asarray(source_points, dtype=np.float64).reshape(-1, 3)
    if len(source) < 3:
        return failed
    pose = start.copy()
    for _ in range(iterations):
        p = source @ pose[:3, :3].T + pose[:3, 3]
        idx, sq_dist = surface.index.nearest(p)
        pair = sq_dist <= distance_m**2
        if pair.sum() < 6:  # fewer pairs than unknowns
            break
        if _damped_step(pose, p[pair], surface.points[idx[pair]], surface.normals[idx[pair]]) < CONVERGED_M:
            break
    if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:3, 3] - start[:3, 3]) > max_shift_m:
        return failed
    fitness, rmse = fit_at(source, surface, pose, distance_m)
    return IcpResult(pose, fitness, rmse) if fitness > 0 else failed


def projective_icp(
    model_points: np.ndarray,
    model_normals: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    camera_T_object: np.ndarray,
    tolerance_m: float,
    noise_per_m2: float,
    iterations: int = 15,
) -> np.ndarray | None:
    """The pose (4, 4) at which the model's points (M, 3, object frame, outward normals (M, 3))
    facing the camera best lie on a depth image (H, W, m, NaN: none; pinhole K (3, 3)), from
    camera_T_object; None with fewer than 20 pairs at some step.

    Each point is paired with the measured surface on its own ray (the pixel it lands on, as
    ``recognition.verify`` judges it) when within ``tolerance_m + noise_per_m2 * z^2`` of it, and
    the damped point-to-plane step of ``damped_icp`` is taken along the model's normals: the fit
    verification judges, pixel by pixel, rather than one to a cluster's points (which in clutter
    holds what stands beside the object too); what stands in front of it is out of reach."""
    pose = np.asarray(camera_T_object, dtype=np.float64).copy()
    H, W = depth.shape
    measured = depth.reshape(-1)
    for _ in range(iterations):
        p = model_points @ pose[:3, :3].T + pose[:3, 3]
        n = model_normals @ pose[:3, :3].T
        u, v, ok = project(p, K, (H, W))
        ok &= np.einsum("ij,ij->i", n, p) < 0  # facing the camera at the origin
        z = measured[v[ok] * W + u[ok]]
        p, n = p[ok], n[ok]
        pair = np.abs(z - p[:, 2]) <= tolerance_m + noise_per_m2 * p[:, 2] ** 2  # False where no depth (NaN)
        if pair.sum() < 20:
            return None
        p = p[pair]
        q = p * (z[pair] / p[:, 2])[:, None]  # the measured point on the model point's ray
        if _damped_step(pose, p, q, n[pair]) < CONVERGED_M:
            break
    return pose if np.all(np.isfinite(pose)) else None


def _damped_step(pose: np.ndarray, p: np.ndarray, q: np.ndarray, n: np.ndarray) -> float:
    """One damped Gauss-Newton step (``ICP_DAMPING``) of posed points p (N, 3) towards the planes
    through their pairs q (N, 3) with unit normals n (N, 3), taken about the points' centroid and
    applied to ``pose`` (4, 4) in place; returns how far it moved the points along the normals (m, RMS)."""
    centre = p.mean(axis=0)
    J = _plane_jacobian(p - centre, n)
    H = J.T @ J
    H[_DIAGONAL] += ICP_DAMPING * H[_DIAGONAL].max()
    step = np.linalg.solve(H, -J.T @ np.einsum("ij,ij->i", n, p - q))
    turn = cv2.Rodrigues(step[:3])[0]
    pose[:3, :3], pose[:3, 3] = turn @ pose[:3, :3], turn @ (pose[:3, 3] - centre) + centre + step[3:]
    return float(np.sqrt(np.mean((J @ step) ** 2)))


def _plane_jacobian(a: np.ndarray, n: np.ndarray) -> np.ndarray:
    """d(residual) / (small turn, shift) (N, 6) of point-to-plane residuals: points at a (N, 3,
    from the turn's centre) against planes with unit normals n (N, 3): (a x n, n)."""
    J = np.empty((len(a), 6))
    J[:, 0] = a[:, 1] * n[:, 2] - a[:, 2] * n[:, 1]
    J[:, 1] = a[:, 2] * n[:, 0] - a[:, 0] * n[:, 2]
    J[:, 2] = a[:, 0] * n[:, 1] - a[:, 1] * n[:, 0]
    J[:, 3:] = n
    return J


def fit_at(source: np.ndarray, surface: Surface, pose: np.ndarray, distance_m: float) -> tuple[float, float]:
    """Share of the points (M, 3, object frame) posed by ``pose`` with a surface point within
    distance_m, and their RMS distance (m; inf if none)."""
    _, sq_dist = surface.index.nearest(source @ pose[:3, :3].T + pose[:3, 3])
    inliers = sq_dist[sq_dist <= distance_m**2].astype(np.float64)
    return len(inliers) / max(len(sq_dist), 1), float(np.sqrt(inliers.mean())) if len(inliers) else float("inf")


def refine_icp(
    model_points: np.ndarray,
    model_normals: np.ndarray,
    surface: Surface,
    camera_T_object: np.ndarray,
    max_distance_m: float,
    iterations: int = 30,
    max_shift_m: float = np.inf,
    image: ImageBounds | None = None,
) -> IcpResult:
    """The model points facing the camera at the start fitted at max_distance_m by Open3D's ICP
    (``icp_pass``) and, if that ran off (its fitness ``RAN_OFF`` below the start's), by the damped
    one (``damped_icp``) from the same start; each result scored again with the points facing the
    camera at its pose, so that the fitness counts the surface the camera should actually see
    (within the image, when given); the better (fitness, then RMSE).

    Open3D's undamped steps run off a small curved patch; damped ones keep a pose where the visible
    faces leave a direction free (a crate seen by its sides alone, under a tote, kept the height the
    coarse screen left it at, 4 cm into the table), and cost ~2 ms a fit in numpy: they are the
    fallback, not the rule."""
    facing = facing_camera(model_points, model_normals, camera_T_object, image)[0]
    source = model_points[facing]
    start = np.asarray(camera_T_object, dtype=np.float64)
    ran_off = fit_at(source, surface, start, max_distance_m)[0] - RAN_OFF
    best = IcpResult(start, 0.0, float("inf"))
    for icp in (icp_pass, damped_icp):
        fit = icp(source, surface, start, max_distance_m, iterations, max_shift_m)
        T = fit.camera_T_object
        facing = facing_camera(model_points, model_normals, T, image)[0]
        if fit.fitness > 0 and facing.sum() >= 3:
            res = IcpResult(T, *fit_at(model_points[facing], surface, T, max_distance_m))
            if (res.fitness, -res.rmse_m) > (best.fitness, -best.rmse_m):
                best = res
        if best.fitness >= ran_off:
            break
    return best


def model_to_scene_rmse(model_points: np.ndarray, camera_T_object: np.ndarray, scene_points: np.ndarray) -> float:
    """RMS distance (m) from each posed model point (object frame, (M, 3)) to its nearest scene point
    ((N, 3), camera frame): PCL's acceptance measure for a recognised pose."""
    model = _cloud(model_points).transform(np.asarray(camera_T_object, dtype=np.float64))
    d = np.asarray(model.compute_point_cloud_distance(_cloud(scene_points)))
    return float(np.sqrt(np.mean(d**2)))


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
