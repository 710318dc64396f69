"""Assertion helpers with explicit tolerances, in the style of gtsam's own tests."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of R_a^T R_b in degrees (atan2 form: accurate for tiny angles, unlike arccos)."""
    Rd = R_a.T @ R_b
    s = np.linalg.norm([Rd[2, 1] - Rd[1, 2], Rd[0, 2] - Rd[2, 0], Rd[1, 0] - Rd[0, 1]]) / 2.0
    c = (np.trace(Rd) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def assert_pose_close(T_a: np.ndarray, T_b: np.ndarray, pos_tol_m: float, rot_tol_deg: float, what: str = "pose") -> None:
    """Fail unless the two 4x4 poses agree within the translation and rotation tolerances."""
    dp = float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]))
    dr = rotation_angle_deg(T_a[:3, :3], T_b[:3, :3])
    assert dp <= pos_tol_m and dr <= rot_tol_deg, (
        f"{what}: position off by {dp * 1000:.3f} mm (tol {pos_tol_m * 1000:.3f}), "
        f"rotation off by {dr:.4f} deg (tol {rot_tol_deg:.4f})"
    )


def wait_until(pred: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``pred`` every 20 ms until true; fail with ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
