"""Exception root of the ``drivers`` package."""


class DriverError(Exception):
    """Root of every error raised by ``drivers``."""


class NoDeviceError(DriverError):
    """The requested sensor could not be opened."""


class ScenarioError(DriverError, ValueError):
    """A scenario file is invalid; the message names the file and the field."""
