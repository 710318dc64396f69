"""gtsam keys of the estimator's variables, one letter per kind."""

from __future__ import annotations

import gtsam


def camera_symbol(index: int) -> int:
    """A camera's static segment (``Estimator.camera_index`` numbers them)."""
    return gtsam.symbol("c", index)


def marker_symbol(marker_id: int) -> int:
    return gtsam.symbol("m", marker_id)


def keyframe_symbol(index: int) -> int:
    """A moving camera's frame solved as a pose of its own (offline only, ``estimator.keyframes``)."""
    return gtsam.symbol("k", index)


def object_symbol(index: int) -> int:
    """An object marker at one instant seen by several cameras (``estimator.links``)."""
    return gtsam.symbol("o", index)
