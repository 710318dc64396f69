"""``cellsight model build``: a recognition model database from a scenario, meshes or point clouds."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from drivers.sim.render import object_mesh
from drivers.sim.scenario import Scenario
from recognition.cloud import read_cloud
from recognition.config import DescriptorConfig
from recognition.errors import ModelError
from recognition.models import ModelDatabase, model_from_cloud, model_from_mesh, read_mesh

log = logging.getLogger(__name__)
#: Views rendered per object: an icosahedron subdivided once.
VIEWS_PER_OBJECT = 42


def database_from_scenario(
    scenario: Scenario, params: DescriptorConfig, progress: Callable[[], None] | None = None, distance_m: float = 2.0
) -> ModelDatabase:
    """Every object of a scenario, rendered from its shape (box, cylinder, sphere or mesh file)."""
    db = ModelDatabase(params, {})
    for obj in scenario.objects:
        db.add(model_from_mesh(obj.id, object_mesh(obj), params, distance_m=distance_m, progress=progress))
    return db


def build_database(
    params: DescriptorConfig,
    *,
    scenario: Scenario | None = None,
    meshes: dict[str, Path] | None = None,
    clouds: dict[str, Path] | None = None,
    distance_m: float = 2.0,
    progress: Callable[[], None] | None = None,
) -> ModelDatabase:
    """One database from any mix of sources; object ids must be unique across them."""
    db = database_from_scenario(scenario, params, progress, distance_m) if scenario else ModelDatabase(params, {})
    for oid, path in (meshes or {}).items():
        _check_new(db, oid)
        db.add(model_from_mesh(oid, read_mesh(path), params, distance_m=distance_m, progress=progress))
    for oid, path in (clouds or {}).items():
        _check_new(db, oid)
        db.add(model_from_cloud(oid, read_cloud(path), params, progress=progress))
    return db


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
    raise ModelError("no model database: build one with `cellsight model build` and give it as --models or "
                     "[recognition] models")
