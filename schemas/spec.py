"""How a pose is written in TOML files (scenarios, anchors): a position plus one orientation form.

    position = [1.0, 0.0, 0.8]     # metres
    rpy_deg = [0, 0, 90]           # roll-pitch-yaw (extrinsic x, y, z), or
    quaternion = [0, 0, 0, 1]      # (x, y, z, w), or
    look_at = [0, 0, 0]            # optical frame: z toward the point, y down (cameras), or
    normal = [0, 0, 1]             # marker frame: z out of the face, y toward ``up`` (markers)
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, model_validator

from schemas.codec import make_pose, matrix_from_quat

Vec3 = tuple[float, float, float]


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation Rz(yaw) Ry(pitch) Rx(roll), angles in radians."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def look_at_matrix(position: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Optical-frame rotation (x right, y down, z forward) of a camera at ``position`` facing ``target``."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight up or down: any right vector will do
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def normal_matrix(normal: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """Marker-frame rotation with z along ``normal`` and y toward ``up`` (default world z, else y)."""
    z = np.asarray(normal, float) / np.linalg.norm(normal)
    if up is None:
        up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = np.asarray(up, float) - np.dot(up, z) * z
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


class PoseSpec(BaseModel):
    """A pose in a config file; ``matrix()`` gives the 4x4 ``parent_T_child``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    position: Vec3 = (0.0, 0.0, 0.0)
    rpy_deg: Vec3 | None = None
    quaternion: tuple[float, float, float, float] | None = None
    look_at: Vec3 | None = None
    normal: Vec3 | None = None
    up: Vec3 | None = None

    @model_validator(mode="after")
    def _one_orientation(self) -> "PoseSpec":
        given = [n for n in ("rpy_deg", "quaternion", "look_at", "normal") if getattr(self, n) is not None]
        if len(given) > 1:
            raise ValueError(f"give one orientation, not {' and '.join(given)}")
        if not np.all(np.isfinite(self.position)):
            raise ValueError("position must be finite")
        if self.quaternion is not None and not 0.5 < np.linalg.norm(self.quaternion) < 2.0:
            raise ValueError("quaternion must be (close to) unit length")
        if self.normal is not None and np.linalg.norm(self.normal) < 1e-9:
            raise ValueError("normal must not be zero")
        if self.look_at is not None and np.linalg.norm(np.subtract(self.look_at, self.position)) < 1e-9:
            raise ValueError("look_at must differ from position")
        return self

    def matrix(self) -> np.ndarray:
        p = np.array(self.position, dtype=float)
        if self.rpy_deg is not None:
            R = rpy_matrix(*np.radians(self.rpy_deg))
        elif self.quaternion is not None:
            R = matrix_from_quat(self.quaternion)
        elif self.look_at is not None:
            R = look_at_matrix(p, np.array(self.look_at), np.array(self.up or (0.0, 0.0, 1.0)))
        elif self.normal is not None:
            R = normal_matrix(np.array(self.normal), None if self.up is None else np.array(self.up))
        else:
            R = np.eye(3)
        return make_pose(R, p)


def read_toml(path, error: type[Exception], what: str = "file") -> dict:
    """Parse a TOML file; raise ``error`` naming the file when it is missing or not TOML."""
    import tomllib
    from pathlib import Path

    path = Path(path)
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError as exc:
        raise error(f"{path}: no such {what}") from exc
    except IsADirectoryError as exc:
        raise error(f"{path}: a folder, not a {what}") from exc
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from exc
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise error(f"{path}: not valid TOML: {exc}") from exc


def format_validation_error(source: str, exc) -> str:
    """A pydantic ``ValidationError`` as lines naming the source, each field and what was wrong."""
    lines = [f"{source}: invalid configuration"]
    for err in exc.errors():
        field = ".".join(str(p) for p in err["loc"]) or "(top level)"
        got = err.get("input")
        got_s = "" if isinstance(got, dict) else f" (got {got!r})"
        lines.append(f"  {field}: {err['msg']}{got_s}")
    return "\n".join(lines)
