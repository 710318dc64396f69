"""``cellsight model build``: a recognition model database from a scenario, meshes, point clouds or
recordings of an object on a marker board."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from drivers.sim.render import object_mesh
from drivers.sim.scenario import Scenario
from recognition.cloud import read_coloured_cloud
from recognition.config import BoardConfig, DescriptorConfig
from recognition.errors import ModelError
from recognition.models import (
    VIEW_DISTANCES_M,
    ModelDatabase,
    model_from_cloud,
    model_from_mesh,
    model_from_points,
    read_mesh,
)
from recognition.recording import model_from_recording

log = logging.getLogger(__name__)
#: Views rendered per object and distance: an icosahedron subdivided once.
VIEWS_PER_OBJECT = 42


def database_from_scenario(
    scenario: Scenario,
    params: DescriptorConfig,
    progress: Callable[[], None] | None = None,
    distances_m: Sequence[float] = VIEW_DISTANCES_M,
) -> ModelDatabase:
    """Every object of a scenario, rendered from its shape (box, cylinder, sphere or mesh file), in
    its colour."""
    db = ModelDatabase(params, {})
    for obj in scenario.objects:
        mesh = object_mesh(obj).paint_uniform_color(obj.color)
        db.add(model_from_mesh(obj.id, mesh, params, distances_m=distances_m, progress=progress))
    return db


def build_database(
    params: DescriptorConfig,
    *,
    scenario: Scenario | None = None,
    meshes: dict[str, Path] | None = None,
    clouds: dict[str, Path] | None = None,
    points: dict[str, Path] | None = None,
    recordings: dict[str, Path] | None = None,
    board: BoardConfig | None = None,
    distances_m: Sequence[float] = VIEW_DISTANCES_M,
    scale: float = 1.0,
    progress: Callable[[], None] | None = None,
) -> ModelDatabase:
    """One database from any mix of sources; object ids must be unique across them. Recordings
    (MCAP logs of the object on ``board``) need the board. ``scale``: metres per unit of the mesh,
    cloud and point files (0.001 for files in millimetres, as many model libraries ship them)."""
    if not scale > 0:
        raise ModelError(f"scale {scale:g}: metres per unit of the model files must be positive")
    db = database_from_scenario(scenario, params, progress, distances_m) if scenario else ModelDatabase(params, {})
    for oid, path in (meshes or {}).items():
        _check_new(db, oid)
        db.add(
            model_from_mesh(
                oid, read_mesh(path).scale(scale, np.zeros(3)), params, distances_m=distances_m, progress=progress
            )
        )
    for oid, path in (clouds or {}).items():
        _check_new(db, oid)
        pts, rgb = read_coloured_cloud(path)
        db.add(model_from_cloud(oid, pts * scale, params, colours=rgb, progress=progress))
    for oid, path in (points or {}).items():
        _check_new(db, oid)
        pts, rgb = read_coloured_cloud(path)
        db.add(model_from_points(oid, pts * scale, params, distances_m=distances_m, colours=rgb, progress=progress))
    if recordings and board is None:
        raise ModelError("a recording needs its marker board: give --board BOARD.toml")
    for oid, path in (recordings or {}).items():
        _check_new(db, oid)
        db.add(model_from_recording(oid, path, board, params, progress))
    return db


def load_board(path: Path) -> BoardConfig:
    """A board TOML ([[markers]] with marker_id and board_T_marker; optional object box); ModelError
    naming the file and field when it is wrong."""
    import tomllib

    from pydantic import ValidationError

    try:
        return BoardConfig.model_validate(tomllib.loads(path.read_text()))
    except OSError as exc:
        raise ModelError(f"board file {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"board file {path} is not valid TOML: {exc}") from None
    except ValidationError as exc:
        where = "; ".join(f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ModelError(f"board file {path}: {where}") from None


def _check_new(db: ModelDatabase, oid: str) -> None:
    if oid in db.models:
        raise ModelError(f"object id {oid!r} is given twice")


def models_for(cfg, models: Path | None = None) -> ModelDatabase:
    """The database a cell uses: ``models`` or ``[recognition] models`` if given, else built from the
    cell's scenario (a simulated cell's objects are known shapes). Raises ModelError otherwise."""
    from drivers.sim.scenario import load_scenario

    path = models or cfg.recognition.models
    if path is not None:
        return ModelDatabase.load(path)
    if any(c.source == "sim" for c in cfg.cameras):
        log.info("no model database given: building one from the scenario's objects (about 5 s)")
        return database_from_scenario(load_scenario(cfg.cell.scenario), cfg.recognition.descriptor)
    raise ModelError(
        "no model database: build one with `cellsight model build` and give it as --models or [recognition] models"
    )
