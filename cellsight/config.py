"""The cell configuration: nested pydantic models loaded from TOML with environment overrides.

    [cell]                 name, scenario
    [transport]            zenoh: mode, connect, listen, zenoh_config (TLS / ACL)
    [[cameras]]            one per sensor (drivers.config.CameraConfig)
    [markers]              marker front-end (drivers.config.MarkerConfig)
    [estimator]            solver and [[estimator.anchors]] (estimator.config)
    [ros2]                 ROS 2 (rmw_zenoh) view of the estimates for robots (schemas.ros2)

Environment overrides: ``CELLSIGHT__SECTION__FIELD=value`` (value parsed as JSON when it parses,
else taken as a string), e.g. ``CELLSIGHT__TRANSPORT__MODE=peer``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from cellsight.errors import ConfigError
from drivers.config import CameraConfig, MarkerConfig
from estimator.config import EstimatorConfig
from recognition.config import RecognitionConfig
from schemas.bus import TransportConfig
from schemas.keys import check_name
from schemas.limits import WireLimits
from schemas.ros2 import Ros2Config
from schemas.spec import format_validation_error, read_toml

ENV_PREFIX = "CELLSIGHT__"


class CellSection(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = "demo"
    scenario: Path | None = Field(default=None, description="simulated cell scenario (TOML); None: built-in demo")
    record: Path | None = Field(default=None, description="record every key to this MCAP file")
    role: Literal["cell", "edge"] = Field(
        default="cell",
        description="cell: the whole cell on this host; edge: this host's cameras beside a local router peered with `upstream`",
    )
    upstream: list[str] = Field(
        default_factory=list,
        description="edge: the cell router(s) this host's router connects to, e.g. tcp/10.0.3.2:7447",
    )
    router_config: Path | None = Field(
        default=None,
        description="edge: zenoh config of the router `cellsight run` starts here, e.g. the secure profile's "
        "edge_router.json5 (TLS both ways); its drivers then take transport.zenoh_config = driver.json5 and "
        'transport.connect = ["tls/127.0.0.1:7447"]. Unset: a plain TCP router on the loopback endpoint',
    )

    @model_validator(mode="after")
    def _edge_has_upstream(self) -> CellSection:
        if self.role == "edge" and not self.upstream:
            raise ValueError("an edge host needs [cell] upstream: the cell router(s) its router connects to")
        if self.router_config is not None and self.role != "edge":
            raise ValueError(
                '[cell] router_config is for edge hosts (role = "edge"); a cell host\'s secure router is '
                "started on its own: cellsight router --config ROUTER.json5"
            )
        return self


class CellConfig(BaseModel):
    """Everything one cell needs. ``CellConfig()`` alone is valid and means the simulated demo cell."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    cell: CellSection = Field(default_factory=CellSection)
    transport: TransportConfig = Field(default_factory=TransportConfig)
    cameras: list[CameraConfig] = Field(default_factory=list)
    markers: MarkerConfig = Field(default_factory=MarkerConfig)
    estimator: EstimatorConfig = Field(default_factory=EstimatorConfig)
    recognition: RecognitionConfig = Field(default_factory=RecognitionConfig)
    ros2: Ros2Config = Field(default_factory=Ros2Config)
    wire: WireLimits = Field(default_factory=WireLimits)

    @model_validator(mode="after")
    def _consistent(self) -> CellConfig:
        check_name(self.cell.name, "cell name")
        ids = [c.id for c in self.cameras]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"duplicate camera ids: {dupes}")
        anchors = [a.marker_id for a in self.estimator.anchors]
        if len(set(anchors)) != len(anchors):
            raise ValueError("an anchor marker id is listed twice")
        return self

    def to_toml(self) -> str:
        """The configuration as TOML (what ``save_used`` writes beside a run)."""
        return _to_toml(self.model_dump(mode="json", exclude_none=True))


def apply_env(data: dict[str, Any], environ: Mapping[str, str]) -> dict[str, Any]:
    """Overlay ``CELLSIGHT__A__B=value`` variables onto the nested dict ``data`` (returns a copy)."""
    out = json.loads(json.dumps(data, default=str))
    for name, raw in environ.items():
        if not name.startswith(ENV_PREFIX):
            continue
        path = [p.lower() for p in name[len(ENV_PREFIX) :].split("__") if p]
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"environment {name}: {part!r} is not a section")
        node[path[-1]] = value
    return out


def parse_config(
    data: dict[str, Any], source: str = "<config>", environ: Mapping[str, str] | None = None
) -> CellConfig:
    """Validate a dict (e.g. parsed TOML) with environment overrides; raise ``ConfigError``."""
    data = apply_env(data, os.environ if environ is None else environ)
    try:
        return CellConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, exc)) from exc


def load_config(path: Path | None, environ: Mapping[str, str] | None = None) -> CellConfig:
    """Load a cell config from TOML (None: defaults). Relative paths resolve against the file's folder."""
    if path is None:
        return parse_config({}, "<defaults>", environ)
    path = Path(path)
    cfg = parse_config(read_toml(path, ConfigError), str(path), environ)
    base = path.parent
    if cfg.cell.scenario is not None and not cfg.cell.scenario.is_absolute():
        cfg.cell.scenario = base / cfg.cell.scenario
    for cam in cfg.cameras:
        if cam.recording is not None and not cam.recording.is_absolute():
            cam.recording = base / cam.recording
    return cfg


def save_used(cfg: CellConfig, out_dir: Path) -> Path:
    """Write the configuration actually used to ``out_dir/config.toml``; return the path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / "config.toml"
    target.write_text(cfg.to_toml())
    return target


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _to_toml(data: dict[str, Any], prefix: str = "") -> str:
    """Minimal TOML writer for our config shape (tables, arrays of tables, scalars, lists)."""
    scalars, tables, arrays = [], [], []
    for k, v in data.items():
        if isinstance(v, dict) and not _is_map(k):
            tables.append((k, v))
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            arrays.append((k, v))
        else:
            scalars.append(f"{k} = {_toml_value(v)}")
    out = "\n".join(scalars) + ("\n" if scalars else "")
    for k, v in tables:
        name = f"{prefix}{k}"
        out += f"\n[{name}]\n" + _to_toml(v, name + ".")
    for k, items in arrays:
        name = f"{prefix}{k}"
        for item in items:
            out += f"\n[[{name}]]\n" + _to_toml(item, name + ".")
    return out


def _is_map(key: str) -> bool:
    """Fields that are free-form maps (written inline), not config sections."""
    return key in {"sides_m", "overrides"}
