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

from schemas.geometry import look_at_matrix, make_pose, matrix_from_quat, normal_matrix, rpy_matrix

Vec3 = tuple[float, float, float]


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
    def _one_orientation(self) -> PoseSpec:
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
