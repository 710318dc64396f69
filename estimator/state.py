"""Persisting the map between daemon runs: atomic writes, checksummed, never trusted when corrupt."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimator.errors import StateFileError

log = logging.getLogger(__name__)
VERSION = 1


@dataclass(frozen=True)
class SavedMarker:
    """world_T_marker (4x4) and its 6x6 covariance (ROS order, body frame)."""

    T: np.ndarray
    covariance: np.ndarray


def save_state(path: Path, markers: dict[int, SavedMarker], cell: str) -> None:
    """Write atomically: a temporary file, fsync, rename. A crash leaves the old file or the new one."""
    body = {
        "version": VERSION,
        "cell": cell,
        "saved_unix_s": time.time(),
        "markers": {
            str(k): {"T": v.T.tolist(), "covariance": v.covariance.tolist()} for k, v in sorted(markers.items())
        },
    }
    text = json.dumps(body, sort_keys=True)
    payload = json.dumps({"sha256": hashlib.sha256(text.encode()).hexdigest(), "body": body}, sort_keys=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        with open(tmp, "w") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # on a full disk, a half-written copy would hold the space the next try needs
        raise


def load_state(path: Path, cell: str) -> dict[int, SavedMarker]:
    """Read a state file; raise ``StateFileError`` saying what is wrong with it."""
    try:
        outer = json.loads(path.read_text())
        body = outer["body"]
        text = json.dumps(body, sort_keys=True)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise StateFileError(f"{path}: unreadable state file ({exc})") from exc
    if hashlib.sha256(text.encode()).hexdigest() != outer.get("sha256"):
        raise StateFileError(f"{path}: checksum mismatch (truncated or edited)")
    if body.get("version") != VERSION or body.get("cell") != cell:
        raise StateFileError(
            f"{path}: state of cell {body.get('cell')!r} version {body.get('version')}, expected cell {cell!r} version {VERSION}"
        )
    out = {}
    for k, v in body["markers"].items():
        T, cov = np.array(v["T"], float), np.array(v["covariance"], float)
        if T.shape != (4, 4) or cov.shape != (6, 6) or not (np.all(np.isfinite(T)) and np.all(np.isfinite(cov))):
            raise StateFileError(f"{path}: marker {k} has a malformed pose or covariance")
        out[int(k)] = SavedMarker(T, cov)
    return out


def set_aside(path: Path) -> Path:
    """Move a bad state file out of the way (kept for inspection); return where it went."""
    target = path.with_name(f"{path.name}.corrupt-{int(time.time())}")
    os.replace(path, target)
    return target
