"""How well factors fit against their covariances (``estimator.variance``): known answers."""

from __future__ import annotations

import numpy as np
import pytest

from cellsight.evaluation.synthetic import perturb
from estimator.variance import Fit, chi2_quantile, inflation, pose_fit
from schemas.geometry import make_pose, rpy_matrix


@pytest.mark.parametrize(
    "dof, z, table",
    [
        (3, 1.6449, 7.815),
        (10, 1.6449, 18.307),
        (10, -1.6449, 3.940),
        (30, -1.6449, 18.493),
        (100, 1.6449, 124.342),
        (100, -1.6449, 77.929),
    ],
)
def test_chi2_quantiles_match_the_table(dof: int, z: float, table: float) -> None:
    assert chi2_quantile(dof, z) == pytest.approx(table, rel=0.01)


def test_poses_drawn_from_their_covariance_fit_with_factor_one() -> None:
    """2,000 poses each moved by a draw of its own covariance (different per pose, rotation and
    translation correlated) against their true poses: the variance factor is 1 within its sampling
    error (sd sqrt(2 / 12,000) ~ 0.013); claiming four times the covariance reads a quarter."""
    rng = np.random.default_rng(3)
    n = 2000
    truth = np.stack([make_pose(rpy_matrix(*rng.uniform(-1, 1, 3)), rng.uniform(-2, 2, 3)) for _ in range(n)])
    A = rng.normal(size=(n, 6, 6)) * np.array([0.002] * 3 + [0.01] * 3)[:, None]
    covs = A @ np.swapaxes(A, 1, 2) + np.eye(6) * 1e-7
    measured = perturb(truth, covs, rng)
    fit = pose_fit(measured, truth, covs, variables=0)
    assert fit.dof == 6 * n
    assert fit.factor == pytest.approx(1.0, abs=0.05)
    assert pose_fit(measured, truth, 4 * covs, variables=0).factor == pytest.approx(0.25, abs=0.0125)
    assert fit.lower() < fit.factor < fit.upper()
    assert pose_fit(measured, truth, covs, variables=n // 2).dof == 3 * n  # each variable takes 6 rows' redundancy


def test_frames_are_weighed_down_by_how_much_better_the_static_pairs_fit_never_up() -> None:
    static_good = Fit(chi2=2.0, dof=144)  # 0.014 of what the pairs claim
    frames = Fit(chi2=0.9 * 1230, dof=1230)
    ratio = frames.factor / static_good.factor
    assert 0.25 * ratio < inflation(static_good, frames) < ratio  # the bounds take the uncertain side
    assert inflation(Fit(chi2=144.0, dof=144), frames) == 1.0  # pairs fit as claimed: the frames' own covariances
    assert inflation(Fit(chi2=1440.0, dof=144), frames) == 1.0  # pairs fit worse than frames: never weighed up
    assert inflation(Fit(), frames) == 1.0 and inflation(static_good, Fit()) == 1.0  # nothing to judge by
    few = Fit(chi2=2.0 * 6 / 144, dof=6)  # the same fit on 6 dof: the bound allows far more
    assert inflation(few, frames) < inflation(static_good, frames)
