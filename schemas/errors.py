"""Exception root of the ``schemas`` package."""


class SchemaError(Exception):
    """Root of every error raised by ``schemas`` (bad keys, undecodable payloads, bad arrays).
    ``reason``: what receivers count a refusal by (``schemas.limits.REASONS``)."""

    reason = "malformed"


class KeyError_(SchemaError, ValueError):
    """A key expression or one of its parts (cell, camera id) is not valid."""


class DecodeError(SchemaError, ValueError):
    """A payload could not be decoded, or decoded into something inconsistent. ``reason`` is one of
    ``schemas.limits.REASONS``: what services count refusals by."""

    def __init__(self, message: str, reason: str = "malformed") -> None:
        super().__init__(message)
        self.reason = reason


class BusError(SchemaError, RuntimeError):
    """A zenoh session could not be opened or used."""
