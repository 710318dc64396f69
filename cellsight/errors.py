"""Exception root of the ``cellsight`` composition package."""


class CellsightError(Exception):
    """Root of errors raised by the composition root (config, launcher, recorder)."""


class ConfigError(CellsightError, ValueError):
    """A configuration file is invalid. The message names the file, the field and what was expected."""


class RunError(CellsightError):
    """A cell, its router or a recording could not run (the message says which and why)."""


class DatasetError(CellsightError, ValueError):
    """An annotated dataset (BOP format) is incomplete or malformed: the message names the file and the field."""
