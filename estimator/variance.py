"""How well a group of factors fits the solution, against what its covariances claim (pure).

A group's squared Mahalanobis residuals sum to ``chi2`` over its redundancy ``dof``; ``chi2 / dof``
is its a-posteriori variance factor (Helmert's variance components; Foerstner 1979): 1 where the
covariances are the errors' own, under 1 where they overstate them. Two groups that fit
differently are weighted wrongly against each other, even if each is right on its own terms.

The daemon's static pairs fuse many frames, and the view rotation floor in their covariance
allows for a bias no averaging removes. A moving camera's frame is one view with its own noise.
Where the views carry less bias than the floor allows, the pairs fit far better than they claim
while single frames fit as theirs do, and a frame then pulls the cameras by more than it knows
(``benchmarks.estimator_accuracy``: bias-free synthetic frames, pairs 0.01-0.02, frames ~0.9; the
rendered demo 0.13-0.17 and 0.06; frames with the model's own biases both ~1.2). ``inflation``
scales the frames' covariances by the ratio, never below their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.geometry import mahalanobis_sq, pose_difference

Z_95 = 1.6449  # one-sided 95 % of the standard normal


def chi2_quantile(dof: int, z: float) -> float:
    """The chi-square quantile of ``dof`` degrees of freedom at the standard normal's ``z``
    (Wilson-Hilferty: within 1 % for dof >= 3)."""
    c = 2.0 / (9.0 * dof)
    return dof * max(1.0 - c + z * math.sqrt(c), 0.0) ** 3


@dataclass(frozen=True)
class Fit:
    """Sum of squared Mahalanobis residuals ``chi2`` of a group of factors and its redundancy ``dof``."""

    chi2: float = 0.0
    dof: int = 0

    def __add__(self, other: Fit) -> Fit:
        return Fit(self.chi2 + other.chi2, self.dof + other.dof)

    @property
    def factor(self) -> float:
        """The variance factor chi2 / dof (nan without redundancy)."""
        return self.chi2 / self.dof if self.dof > 0 else math.nan

    def upper(self) -> float:
        """One-sided 95 % upper bound of the variance factor (inf without redundancy)."""
        return self.chi2 / chi2_quantile(self.dof, -Z_95) if self.dof > 0 else math.inf

    def lower(self) -> float:
        """One-sided 95 % lower bound of the variance factor (0 without redundancy)."""
        return self.chi2 / chi2_quantile(self.dof, Z_95) if self.dof > 0 else 0.0


def pose_fit(measured: np.ndarray, predicted: np.ndarray, covariances: np.ndarray, variables: int) -> Fit:
    """Fit of pose factors: ``measured`` and ``predicted`` (N, 4, 4) poses with ``covariances``
    (N, 6, 6; ROS order, in the measured pose's frame), tying ``variables`` 6-dof poses between them."""
    if not len(measured):
        return Fit()
    d2 = mahalanobis_sq(
        pose_difference(np.asarray(measured, np.float64), np.asarray(predicted, np.float64)), covariances
    )
    return Fit(float(d2.sum()), 6 * (len(measured) - variables))


def inflation(static: Fit, frames: Fit) -> float:
    """The factor on a moving camera's frames' covariances against the static pairs: the lower bound
    of how the frames fit over the upper bound of how the pairs do, and at least 1 (single frames
    are never taken for better than their own covariances say)."""
    if static.dof <= 0 or frames.dof <= 0:
        return 1.0
    return max(1.0, frames.lower() / static.upper())
