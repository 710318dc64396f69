"""Composition root: CLI, configuration, process launcher, recorder and reports."""

__version__ = "0.1.0"
