"""Did a camera move? One frame's marker positions against where they were expected.

``frame_moved`` (``any_frame_moved`` for a block of frames) asks first whether most markers
shifted beyond noise and ``bump_position_m``; ``Estimator._camera_is_still`` gathers the expected
positions (a pair's mean, or the map's prediction) and keeps the count of suspect frames.

A camera that turns while it shifts can cancel the shift at its markers: 4 cm and 1 deg at 2.5 m
leaves each marker 6-8 mm from its mean, under that test's threshold, while the camera's pose is
4 cm off. The markers still say so together: their shifts are the image of one rigid
motion, and a least-squares fit of that motion (6 dof, every marker weighted by its covariance)
measures it with the evidence of all of them. Positions only, so a marker's rotation flip cannot
fool it.

Frames: ``p`` are the markers' positions in the camera's frame before (its pairs' means), ``q``
in this frame; the fitted motion (R, t) maps one onto the other, q = R p + t, so the camera's
origin moved by -R^T t (|t|) and turned by |rotvec(R)|.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from estimator.observation import ObservationRows
from schemas.geometry import mahalanobis_sq, skew

log = logging.getLogger(__name__)

#: Chi-square with 6 dof at 1 - 1e-6: a still camera's frame passes it once in a million, and a
#: move needs it on ``bump_frames`` consecutive frames.
RIGID_CHI2 = 41.0
#: Chi-square with 3 dof at 99.9 %: a marker whose residual after the fit exceeds it is not part
#: of the rigid motion (it was itself moved, or misdetected) and the fit is redone without it.
INLIER_CHI2 = 16.27
MIN_MARKERS = 4  # a rigid fit of fewer positions leaves too little to judge the residuals by
#: Chi-square with 3 dof at 99.9 %: one marker's position shift beyond noise.
MOVE_CHI2 = 16.27


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
    return RigidMotion(
        chi2=chi2, shift_m=float(np.linalg.norm(x[3:])), angle_rad=float(np.linalg.norm(x[:3])), inliers=n
    )


def rigid_move(p: np.ndarray, q: np.ndarray, R: np.ndarray, covs: np.ndarray, bump_position_m: float) -> bool:
    """Do one frame's marker positions ``q`` (N, 3) against their means ``p`` (N, 3), m, show one
    rigid camera motion beyond noise and ``bump_position_m`` (m)? ``covs`` (N, 3, 3) are the
    observations' position covariances in the frame whose rotations are ``R`` (N or 1, 3, 3)."""
    motion = rigid_motion(p, q, R @ covs @ np.swapaxes(R, -1, -2) + 1e-8 * np.eye(3))
    if motion is None or not motion.is_move(bump_position_m, float(np.median(np.linalg.norm(p, axis=1)))):
        return False
    log.debug(
        "rigid motion %.1f mm %.2f deg (chi2 %.0f, %d markers)",
        1e3 * motion.shift_m,
        math.degrees(motion.angle_rad),
        motion.chi2,
        motion.inliers,
    )
    return True


def frame_moved(
    deltas: list[np.ndarray],
    before: list[np.ndarray],
    rotations: list[tuple[np.ndarray, np.ndarray]],
    obs_covs: list[np.ndarray],
    scales: list[float],
    margins: list[float],
    bump_position_m: float,
) -> tuple[bool, float]:
    """One frame's test (``Estimator._camera_is_still``): per marker its shift from where it was
    expected (``deltas``, (3,) m, camera frame; ``before``: the expected positions), the observation's
    and the expectation's rotations, the observation's position covariance (3, 3) in its marker
    frame, a scale on it (a young mean's own uncertainty) and a margin (m^2; a map prediction's).
    Moved: the median marker shift is beyond noise and ``bump_position_m``, or the shifts together
    are one rigid motion that is (``rigid_move``). Returns (moved, the median shift in m; NaN for
    no marker)."""
    if not deltas:
        return False, float("nan")
    D = np.array(deltas)
    # The marker-frame covariance into the camera frame, with the observation's rotation and with
    # the expected one: either may be a flip (a young mean can start on one), which points the long
    # (depth) axis astray; the frame that explains the shift better is kept.
    R = np.array(rotations)  # (N, 2, 3, 3)
    both = np.array(scales)[:, None, None, None] * (R @ np.array(obs_covs)[:, None] @ np.swapaxes(R, -1, -2))
    both += (np.array(margins)[:, None, None, None] + 1e-8) * np.eye(3)
    d2_both = mahalanobis_sq(D[:, None, :], both)
    nearer = np.argmin(d2_both, axis=1)
    d2 = d2_both[np.arange(len(D)), nearer]
    covs = both[np.arange(len(D)), nearer]
    shifts = np.linalg.norm(D, axis=1)
    moved = bool(np.median(d2) > MOVE_CHI2 and np.median(shifts) > bump_position_m)
    # The rigid fit explains at most the frame's whole chi-square (a least-squares projection):
    # below the move threshold in total, no fit can pass it.
    if not moved and float(d2.sum()) > RIGID_CHI2:
        P = np.array(before)
        moved = rigid_move(P, P + D, np.eye(3), covs, bump_position_m)
    return moved, float(np.median(shifts))


def any_frame_moved(
    s: ObservationRows, expected: np.ndarray, frames: int, screen: RigidScreen | None, bump_position_m: float
) -> tuple[bool, RigidScreen | None]:
    """``frame_moved`` for many frames of one camera at once (static rows ``s``, their pairs' means
    ``expected`` (N, 4, 4)): does any frame's median marker shift exceed noise, or the block's last
    frame (a move persists) show a rigid motion of the camera? ``screen``: the rigid screen of the
    camera's current view, returned renewed when the view changed."""
    if len(s.ids) == 0:
        return False, screen
    D = s.poses[:, :3, 3] - expected[:, :3, 3]
    shifts = np.linalg.norm(D, axis=1)
    # The last frame's rows by marker id: a detector lists the same markers in a different order
    # from frame to frame, and the screen belongs to the view (which markers), not to the order.
    last = np.flatnonzero(s.frame == s.frame.max())
    last = last[np.argsort(s.ids[last], kind="stable")]
    p, R, covs = expected[last, :3, 3], expected[last, :3, :3], s.covariances[last, :3, :3]
    if screen is None or not np.array_equal(screen.ids, s.ids[last]):
        screen = RigidScreen.of(s.ids[last], p, R @ covs @ R.transpose(0, 2, 1) + 1e-8 * np.eye(3))
    if (
        screen is not None
        and screen.chi2(D[last]) > RIGID_CHI2
        and rigid_move(p, p + D[last], R, covs, bump_position_m)
    ):
        return True, screen
    # A median above a threshold needs at least half of the frame's values above it: only frames
    # that pass this count can have moved, and only they get an exact median. The shift alone rules
    # most frames out before any covariance is solved.
    n_rows = np.bincount(s.frame, minlength=frames)
    far = shifts > bump_position_m
    if not np.any((n_rows > 0) & (2 * np.bincount(s.frame, weights=far, minlength=frames) >= n_rows)):
        return False, screen
    R = expected[:, :3, :3]
    covs = R @ s.covariances[:, :3, :3] @ R.transpose(0, 2, 1) + 1e-8 * np.eye(3)
    d2 = mahalanobis_sq(D, covs)
    high = (d2 > MOVE_CHI2) & far
    n_high = np.bincount(s.frame, weights=high, minlength=frames)
    for f in np.flatnonzero((n_rows > 0) & (2 * n_high >= n_rows)):
        rows = s.frame == f
        if np.median(d2[rows]) > MOVE_CHI2 and np.median(shifts[rows]) > bump_position_m:
            return True, screen
    return False, screen
