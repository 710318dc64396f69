"""Fused camera-marker pairs: every observation of one marker by one camera segment, as running sums.

A pair keeps the sums of its observations' positions, rotations (chosen IPPE branch and the other)
and covariances (``Pair.sums``, 57 numbers), so its mean and mean covariance cost O(1) to read and
a batch of frames folds in with one matrix product (``fold_rows``). Each observation picks the
IPPE branch nearer the pair's mean; one further than FLIP_GATE_RAD / POSITION_GATE_M is rejected,
and a majority of rejections restarts the pair. A young pair's mean is itself uncertain (its first
observation may be a flip): it keeps its observations' two rotations and re-decides their branches
against its mean a few times (``RESEAT_AT``) before it settles. The estimator (``estimator.graph``) turns a pair
into a factor: its mean, and its mean covariance over at most ``max_fused`` observations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from estimator.observation import Observation, ObservationRows
from schemas.geometry import covariance_in_frame, mahalanobis_sq, pose_difference

YOUNG_PAIR = 30  # observations before a pair's mean settles: until then its factor refreshes 10x as often
#: While young, a pair re-decides every observation's IPPE branch when its count reaches one of
#: these (``Pair._reseat``); from YOUNG_PAIR on, each new one is judged against the settled mean.
RESEAT_AT = (4, 8, 16, YOUNG_PAIR)
FLIP_GATE_RAD = math.radians(15.0)  # a candidate further than this from the pair mean is a flip
POSITION_GATE_M = 0.10  # and one further than this is an outlier (or a move, caught separately)
TRACE_GATE = 1.0 + 2.0 * math.cos(FLIP_GATE_RAD)  # trace(R_mean^T R) above this: within the flip gate


def project_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (chordal L2 mean of a sum of rotations); batched over leading axes."""
    U, _, Vt = np.linalg.svd(M)
    U[..., :, 2] *= np.sign(np.linalg.det(U @ Vt))[..., None]
    return U @ Vt


def pair_means(sums: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Exact mean poses (P, 4, 4) of pairs from their ``Pair.sums`` rows (P, 57) and counts (P,)."""
    means = np.tile(np.eye(4), (len(n), 1, 1))
    means[:, :3, :3] = project_rotation(sums[:, 3:12].reshape(-1, 3, 3))
    means[:, :3, 3] = sums[:, :3] / n[:, None]
    return means


@dataclass
class Pair:
    """Running mean of one camera-segment/marker relation, and the factor that carries it.

    Both IPPE branches are accumulated: every observation adds its candidate closest to the mean
    to the main branch and the other to the alternative branch. If the front-end's own choice
    landed in the alternative branch for most observations, the pair started on a flip and the
    branches swap; since each observation fed both, the swap is exact.
    """

    n: int = 0
    #: Sums in one row, laid out as ``FoldedRows.sums``, so a batch folds in with one add:
    #: position (3), chosen rotation (9), other branch's rotation (9), covariance (36, ROS order).
    sums: np.ndarray = field(default_factory=lambda: np.zeros(57), repr=False)
    primary_in_alt: int = 0  # observations whose chosen pose fell in the alternative branch
    rejected: int = 0
    slot: int | None = None  # iSAM2 factor index, None until the factor is in the graph
    refreshed_ns: int = 0
    dirty: bool = False
    factor_mean: np.ndarray | None = field(default=None, repr=False)  # camera_T_marker the factor holds
    factor_cov: np.ndarray | None = field(default=None, repr=False)  # its 6x6 covariance, ROS order
    factor_n_eff: int = 0  # observations it counts as independent
    _cached: np.ndarray | None = field(default=None, repr=False)
    _cached_n: int = field(default=0, repr=False)
    #: While young: each taken observation's rotations (front-end's choice, other branch), 3x3 each,
    #: and its covariance as the front-end gave it (in its choice's frame), 6x6.
    _young: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list, repr=False)

    @property
    def pos_sum(self) -> np.ndarray:
        return self.sums[:3]

    @property
    def rot_sum(self) -> np.ndarray:
        return self.sums[3:12].reshape(3, 3)

    @property
    def alt_rot_sum(self) -> np.ndarray:
        return self.sums[12:21].reshape(3, 3)

    @property
    def cov_sum(self) -> np.ndarray:
        return self.sums[21:].reshape(6, 6)

    def _swap_branches_if_flipped(self) -> None:
        """If most observations' own choice fell in the other branch, the pair started on a flip."""
        if self.n >= 3 and 2 * self.primary_in_alt > self.n:
            # The covariances were added in the frame of the branch taken: into the other one's
            # (every observation's branches sit within the flip gate of their means).
            self.cov_sum[:] = covariance_in_frame(
                self.cov_sum, project_rotation(self.rot_sum), project_rotation(self.alt_rot_sum)
            )
            self.sums[3:12], self.sums[12:21] = self.sums[12:21].copy(), self.sums[3:12].copy()
            self.primary_in_alt = self.n - self.primary_in_alt
            self._cached = None

    def mean(self, exact: bool = False) -> np.ndarray:
        """Mean pose (4x4; do not modify). The rotation is re-projected once the count has grown
        by an eighth since the last projection (the mean of many rotations barely moves; the SVD
        dominated the hot path), or always with ``exact`` (when a factor is built)."""
        if exact or self._cached is None or self.n - self._cached_n > self._cached_n // 8:
            T = np.eye(4)
            T[:3, :3] = project_rotation(self.rot_sum)
            self._cached, self._cached_n = T, self.n
        self._cached[:3, 3] = self.pos_sum / self.n
        return self._cached

    def holds(self, mean: np.ndarray, covariance: np.ndarray, max_fused: int) -> None:
        """Note the factor just built from this pair: its exact mean (4, 4), which is also the mean
        from now on, and covariance (6, 6, ROS order)."""
        self.factor_mean, self.factor_cov = mean, covariance
        self.factor_n_eff = min(self.n, max_fused)
        self._cached, self._cached_n = mean.copy(), self.n

    def factor_covariance(self, max_fused: int, rotation_floor_rad: float) -> np.ndarray:
        """The fused factor's covariance (6x6, ROS order, marker frame): the mean single-frame one
        over at most ``max_fused`` observations, plus the view's rotation bias on the diagonal."""
        cov = self.mean_covariance() / min(self.n, max_fused)
        cov[3:, 3:] += np.eye(3) * rotation_floor_rad**2
        return cov

    def factor_is_current(self, max_fused: int, sigmas: float, rotation_floor_rad: float = 0.0) -> bool:
        """Would rebuilding the factor change it by less than ``sigmas`` of its own sigma? (``factors_current``)"""
        return bool(factors_current([self], max_fused, sigmas, rotation_floor_rad)[0])

    def mean_covariance(self) -> np.ndarray:
        """Mean single-observation covariance (ROS order, marker frame)."""
        return self.cov_sum / self.n

    def _take(self, T: np.ndarray, other: np.ndarray | None, cov: np.ndarray, primary_in_alt: bool) -> None:
        """Add pose T (4x4) with its other branch; ``cov`` (6x6) is in the frame of the front-end's
        choice, which is ``other`` when ``primary_in_alt``: it is then turned into T's frame."""
        R, R_other = T[:3, :3], (other if other is not None else T)[:3, :3]
        self.n += 1
        self.pos_sum[:] += T[:3, 3]
        self.rot_sum[:] += R
        self.alt_rot_sum[:] += R_other
        self.cov_sum[:] += covariance_in_frame(cov, R_other, R) if primary_in_alt else cov
        self.primary_in_alt += int(primary_in_alt)
        self.dirty = True
        if self.n <= YOUNG_PAIR:
            self._young.append((R_other, R, cov) if primary_in_alt else (R, R_other, cov))
            if self.n in RESEAT_AT:
                self._reseat()
        self._swap_branches_if_flipped()

    def _reseat(self) -> None:
        """Re-decide every kept observation's branch against the mean, until the mean stops moving.

        The running choice judges each observation against the mean of those before it; if the
        first ones were flips, the mean starts between the branches and the flips it took stay in
        the sums (a bias of the flip angle over n that the majority rule never sees). Each observation
        goes to its branch nearer the mean, the mean is recomputed, repeated: the two branches are
        mirror images, so this settles on one of them, cleanly, and the majority rule then picks it.
        """
        if len(self._young) != self.n:  # only a pair that kept every observation can re-decide them
            return
        A = np.array([(R, R_other) for R, R_other, _ in self._young])  # (n, 2, 3, 3): front-end's choice, other branch
        C = np.array([cov for _, _, cov in self._young])  # (n, 6, 6), in the choice's frame
        M = project_rotation(self.rot_sum)
        pick: np.ndarray | None = None  # per observation: is its other branch the nearer one?
        for _ in range(4):
            tr = np.einsum("ij,nkij->nk", M, A)  # trace(M^T R) per branch: larger = nearer
            new_pick = tr[:, 1] > tr[:, 0]
            if pick is not None and np.array_equal(new_pick, pick):
                break
            pick = new_pick
            M = project_rotation(np.where(pick[:, None, None], A[:, 1], A[:, 0]).sum(axis=0))
        assert pick is not None
        idx = np.arange(len(A))
        self.rot_sum[:] = A[idx, pick.astype(int)].sum(axis=0)
        self.alt_rot_sum[:] = A[idx, 1 - pick.astype(int)].sum(axis=0)
        if pick.any():
            C[pick] = covariance_in_frame(C[pick], A[pick, 0], A[pick, 1])
        self.cov_sum[:] = C.sum(axis=0)
        self.primary_in_alt = int(pick.sum())
        self._cached = None
        if self.n >= YOUNG_PAIR:
            self._young = []  # settled: later observations are judged against its mean one by one

    def add(self, obs: Observation) -> bool:
        """Fold an observation in, choosing the IPPE branch consistent with the mean. False if rejected."""
        return self.add_pose(obs.camera_T_marker, obs.alternative, obs.covariance)

    def add_pose(self, T: np.ndarray, other: np.ndarray | None, cov: np.ndarray) -> bool:
        """``add`` of camera_T_marker T (4x4), its IPPE alternative and covariance (6x6, ROS order)."""
        if self.n == 0:
            self._take(T, other, cov, False)
            return True
        mean = self.mean()
        first, swapped = (T, other), False
        # trace(M^T R) falls as the angle between M and R grows: comparing traces (one product each)
        # decides nearer branch and flip gate exactly, without the angles themselves.
        M = mean[:3, :3]
        near = float(np.vdot(M, T[:3, :3]))
        if other is not None and (near_other := float(np.vdot(M, other[:3, :3]))) > near:
            T, other, swapped, near = other, T, True, near_other
        d = T[:3, 3] - mean[:3, 3]
        if near > TRACE_GATE and float(d @ d) < POSITION_GATE_M**2:
            self._take(T, other, cov, swapped)
            return True
        self.rejected += 1
        if self.rejected > self.n:  # the majority disagrees with the mean in position too: restart
            slot = self.slot
            self.__init__()
            self.slot = slot  # the factor in that slot is replaced on the next refresh, not left beside the new one
            self._take(*first, cov, False)
        return False

    def fold(self, rows: FoldedRows, j: int) -> None:
        """Add pair ``j``'s share of a batch judged against the means before it (see ``fold_rows``)."""
        k = int(rows.accepted[j])
        self.n += k
        self.sums += rows.sums[j]
        self.primary_in_alt += int(rows.swapped[j])
        self.rejected += int(rows.rejected[j])
        self.dirty = self.dirty or k > 0
        self._swap_branches_if_flipped()


def factors_current(pairs: list[Pair], max_fused: int, sigmas: float, rotation_floor_rad: float = 0.0) -> np.ndarray:
    """For each pair (P,): would rebuilding its factor change it by less than ``sigmas`` of its own sigma?

    True when the factor already counts ``max_fused`` observations (more do not tighten it), its
    covariance changed by under 10 % per axis, and the mean moved less than ``sigmas``
    (Mahalanobis, 6 dof, under the factor's covariance) since it was built. A settled static pair
    then stops costing solver updates: its mean's drift shrinks as 1/n. One batched test for all.
    """
    out = np.zeros(len(pairs), bool)
    full = [
        i
        for i, p in enumerate(pairs)
        if p.factor_mean is not None and p.factor_cov is not None and p.factor_n_eff >= max_fused
    ]
    if not full:
        return out
    sel = [pairs[i] for i in full]
    sums = np.stack([p.sums for p in sel])  # one row per pair: the means and covariances come from these
    n = np.array([p.n for p in sel], float)
    cov_diag = sums[:, COV_DIAGONAL] / (n * np.minimum(n, max_fused))[:, None]
    cov_diag[:, 3:] += rotation_floor_rad**2
    built = np.stack([p.factor_cov for p in sel])
    same_cov = np.abs(cov_diag / np.diagonal(built, axis1=1, axis2=2) - 1.0).max(axis=1) <= 0.1
    d = pose_difference(np.stack([p.factor_mean for p in sel]), pair_means(sums, n))
    out[full] = same_cov & (mahalanobis_sq(d, built) < sigmas**2)
    return out


#: Columns of ``Pair.sums`` holding the covariance sum's diagonal.
COV_DIAGONAL = 21 + 7 * np.arange(6)


@dataclass(frozen=True)
class FoldedRows:
    """Per-pair sums of a batch of observations: ``sums`` (P, 57) = position (3), chosen rotation
    (9), other branch's rotation (9), covariance (36, ROS order); counts (P,) of accepted, swapped
    (the other branch was nearer the mean) and rejected rows."""

    sums: np.ndarray
    accepted: np.ndarray
    swapped: np.ndarray
    rejected: np.ndarray


def fold_rows(expected: np.ndarray, row_pair: np.ndarray, n_pairs: int, a: ObservationRows) -> FoldedRows:
    """``Pair.add_pose`` for many rows of many pairs at once, each judged against its pair's mean
    ``expected[row]`` (N, 4, 4) from before the batch. For settled pairs the mean moves by a fraction
    of the noise over a batch, so the choices are those of one-by-one adding. One matrix product
    with the rows' pair membership gives every pair's sums: no Python loop over pairs or rows."""
    Rm = expected[:, :3, :3]
    tr_pose = np.einsum("nij,nij->n", Rm, a.poses[:, :3, :3])  # trace(R_mean^T R): larger = closer
    tr_alt = np.einsum("nij,nij->n", Rm, a.alternatives[:, :3, :3])
    swap = tr_alt > tr_pose
    chosen = np.where(swap[:, None, None], a.alternatives, a.poses)
    other = np.where(swap[:, None, None], a.poses, a.alternatives)
    ok = (np.maximum(tr_pose, tr_alt) > TRACE_GATE) & (
        np.linalg.norm(chosen[:, :3, 3] - expected[:, :3, 3], axis=1) < POSITION_GATE_M
    )
    covs = a.covariances
    if swap.any():  # given in the frame of the front-end's choice: into the taken branch's
        covs = covs.copy()
        covs[swap] = covariance_in_frame(covs[swap], a.poses[swap, :3, :3], a.alternatives[swap, :3, :3])
    n = len(row_pair)
    member = np.zeros((n_pairs, n))
    member[row_pair, np.arange(n)] = 1.0
    taken = member * ok
    stats = np.concatenate(
        [chosen[:, :3, 3], chosen[:, :3, :3].reshape(n, 9), other[:, :3, :3].reshape(n, 9), covs.reshape(n, 36)], axis=1
    )
    accepted = taken.sum(axis=1)
    return FoldedRows(taken @ stats, accepted, taken @ swap, member.sum(axis=1) - accepted)
