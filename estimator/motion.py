"""Did a camera move? A rigid fit of one frame's marker positions against where they were.

The per-marker test in ``Estimator._camera_is_still`` asks whether most markers shifted beyond
noise. A camera that turns while it shifts can cancel the shift at its markers: 4 cm and 1 deg
at 2.5 m leaves each marker 6-8 mm from its mean, under that test's threshold, while the camera's
pose is 4 cm off. The markers still say so together: their shifts are the image of one rigid
motion, and a least-squares fit of that motion (6 dof, every marker weighted by its covariance)
measures it with the evidence of all of them. Positions only, so a marker's rotation flip cannot
fool it.

Frames: ``p`` are the markers' positions in the camera's frame before (its pairs' means), ``q``
in this frame; the fitted motion (R, t) maps one onto the other, q = R p + t, so the camera's
origin moved by -R^T t (|t|) and turned by |rotvec(R)|.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.geometry import skew

#: Chi-square with 6 dof at 1 - 1e-6: a still camera's frame passes it once in a million, and a
#: move needs it on ``bump_frames`` consecutive frames.
RIGID_CHI2 = 41.0
#: Chi-square with 3 dof at 99.9 %: a marker whose residual after the fit exceeds it is not part
#: of the rigid motion (it was itself moved, or misdetected) and the fit is redone without it.
INLIER_CHI2 = 16.27
MIN_MARKERS = 4  # a rigid fit of fewer positions leaves too little to judge the residuals by


@dataclass(frozen=True)
class RigidMotion:
    """A fitted camera motion: its evidence ``chi2`` (the drop in the markers' chi-square that the
    motion explains, 6 dof), the camera's shift (m) and turn (rad), and the markers it fits."""

    chi2: float
    shift_m: float
    angle_rad: float
    inliers: int

    def is_move(self, threshold_m: float, range_m: float) -> bool:
        """Beyond noise, and beyond ``threshold_m`` (m) at the camera's origin or, turned, at
        ``range_m`` (m, the markers' typical distance)."""
        return self.chi2 > RIGID_CHI2 and max(self.shift_m, self.angle_rad * range_m) > threshold_m


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a x b of (N, 3) or (3,) and (N, 3), by components: a third of numpy's cross here."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _normal_equations(p: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid fit's normal equations about no motion, x = (w, t): G (N, 6, 3) = J_i^T W_i with
    J_i = [-[p_i]x, I] (so that b = sum G_i r_i) and H (6, 6) = sum J_i^T W_i J_i."""
    S = skew(p)  # [p_i]x, so that S @ v = p_i x v
    G = np.concatenate([S @ W, W], axis=1)  # (-[p]x)^T = [p]x
    H = np.empty((6, 6))
    H[:3, :3] = -(G[:, :3] @ S).sum(axis=0)
    H[:3, 3:] = G[:, :3].sum(axis=0)
    H[3:, :3] = H[:3, 3:].T
    H[3:, 3:] = W.sum(axis=0)
    return G, H


def _fit(p: np.ndarray, r: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, float]:
    """The Gauss-Newton step x = (w, t) (6,) minimising sum |r_i - (w x p_i + t)|^2_{W_i}, and the
    chi-square it explains (x . b). Zeros if degenerate."""
    G, H = _normal_equations(p, W)
    b = np.einsum("nij,nj->i", G, r)
    try:
        x = np.linalg.solve(H, b)
    except np.linalg.LinAlgError:
        return np.zeros(6), 0.0
    return x, float(x @ b)


@dataclass(frozen=True)
class RigidScreen:
    """The rigid fit's normal equations for one camera's view (which markers, in which row order),
    kept while the view is unchanged: for settled pairs the weights and lever arms barely change,
    so a frame's screen is two products with its residuals. Only a frame that passes it gets the
    full fit (``rigid_motion``), which drops unexplained markers and measures the motion."""

    ids: np.ndarray  # (N,) marker ids in row order
    G: np.ndarray  # (N, 6, 3)
    H_inv: np.ndarray  # (6, 6)

    @classmethod
    def of(cls, ids: np.ndarray, p: np.ndarray, covs: np.ndarray) -> RigidScreen | None:
        """From marker positions ``p`` (N, 3), m, and their covariances (N, 3, 3), m^2; None if
        too few markers for a fit."""
        if len(p) < MIN_MARKERS:
            return None
        G, H = _normal_equations(p, np.linalg.inv(covs))
        return cls(ids.copy(), G, np.linalg.pinv(H))

    def chi2(self, r: np.ndarray) -> float:
        """Chi-square (6 dof) that the best rigid motion explains of residuals ``r`` (N, 3), m."""
        b = np.einsum("nij,nj->i", self.G, r)
        return float(b @ self.H_inv @ b)


def rigid_motion(p: np.ndarray, q: np.ndarray, covs: np.ndarray) -> RigidMotion | None:
    """The small rigid motion taking marker positions ``p`` (N, 3) to ``q`` (N, 3), in m, with
    ``covs`` (N, 3, 3) the covariances of q - p (m^2) in the same frame. Linearised about no motion
    (a move large enough for that to matter is caught by the per-marker test first). Markers the
    motion does not explain are dropped once and the fit redone; None when fewer than
    ``MIN_MARKERS`` (or fewer than half) remain."""
    if len(p) < MIN_MARKERS:
        return None
    r = q - p
    W = np.linalg.inv(covs)
    x, chi2 = _fit(p, r, W)
    e = r - _cross(x[:3], p) - x[3:]
    keep = np.einsum("ni,nij,nj->n", e, W, e) < INLIER_CHI2
    n = int(keep.sum())
    if n < max(MIN_MARKERS, (len(p) + 1) // 2):
        return None
    if n < len(p):
        x, chi2 = _fit(p[keep], r[keep], W[keep])
    return RigidMotion(chi2=chi2, shift_m=float(np.linalg.norm(x[3:])), angle_rad=float(np.linalg.norm(x[:3])), inliers=n)
