"""Joint estimation of camera and marker poses from marker observations (gtsam iSAM2)."""

from estimator.errors import EstimatorError

__all__ = ["EstimatorError"]
