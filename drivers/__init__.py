"""Sensor drivers: OpenNI2, the simulated cell and replay, each with the marker front-end."""

from drivers.errors import DriverError

__all__ = ["DriverError"]
