"""Exception root of the ``estimator`` package."""


class EstimatorError(Exception):
    """Root of every error raised by ``estimator``."""


class StateFileError(EstimatorError):
    """A persisted state file is unreadable or inconsistent; it is set aside, never trusted."""
