"""A cell configuration derived from a simulated scenario: what ``cellsight demo`` runs.

Anchors come from the scenario's anchor markers (their surveyed pose and sigma), marker sizes and
the dictionary from its markers, cameras from its cameras. Nothing else of the scenario (the
poses of static markers, camera motions) reaches the estimator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cellsight.config import CellConfig, CellSection
from drivers.config import CameraConfig, IntrinsicsConfig, MarkerConfig
from drivers.sim.scenario import Scenario, load_scenario
from estimator.config import AnchorConfig, EstimatorConfig
from recognition.config import ObjectMarkerConfig, RecognitionConfig
from schemas.geometry import quat_from_matrix
from schemas.spec import PoseSpec


def pose_spec(T: np.ndarray) -> PoseSpec:
    """A 4x4 pose as a config PoseSpec (position + quaternion)."""
    return PoseSpec(
        position=tuple(float(v) for v in T[:3, 3]), quaternion=tuple(float(v) for v in quat_from_matrix(T[:3, :3]))
    )


def anchors_of(scenario: Scenario) -> list[AnchorConfig]:
    out = []
    for mk in scenario.markers:
        if mk.role != "anchor":
            continue
        out.append(
            AnchorConfig(
                marker_id=mk.id,
                world_T_marker=pose_spec(mk.pose.matrix()),
                sigma_position_m=mk.sigma_position_m,
                sigma_rotation_deg=mk.sigma_rotation_deg,
            )
        )
    return out


def estimator_config_of(scenario: Scenario, **overrides) -> EstimatorConfig:
    return EstimatorConfig(
        anchors=anchors_of(scenario),
        object_markers=[mk.id for mk in scenario.markers if mk.role == "object"],
        known_markers=[mk.id for mk in scenario.markers],
        **overrides,
    )


def recognition_config_of(scenario: Scenario, base: RecognitionConfig) -> RecognitionConfig:
    """``base`` with the scenario's object markers and workspace (the scenario author's declarations)."""
    markers = []
    for mk in scenario.markers:
        if mk.role == "object" and mk.object is not None:
            markers.append(
                ObjectMarkerConfig(marker_id=mk.id, object_id=mk.object, object_T_marker=pose_spec(mk.pose.matrix()))
            )
    update: dict = {"object_markers": markers}
    if scenario.workspace is not None and base.workspace_min is None:
        update |= {"workspace_min": scenario.workspace[0], "workspace_max": scenario.workspace[1]}
    return base.model_copy(update=update)


def cell_config_of(scenario: Scenario, scenario_path: Path | None = None, base: CellConfig | None = None) -> CellConfig:
    """``base`` (transport, estimator tuning) with cameras, markers and anchors from the scenario."""
    base = base or CellConfig()
    cameras = []
    for c in scenario.cameras:
        i = c.camera_info()
        intr = IntrinsicsConfig(fx=i.K[0, 0], fy=i.K[1, 1], cx=i.K[0, 2], cy=i.K[1, 2], distortion=tuple(i.D.tolist()))
        cameras.append(
            CameraConfig(id=c.id, source="sim", width=c.width, height=c.height, rate_hz=c.rate_hz, intrinsics=intr)
        )
    markers = base.markers.model_copy(
        update={
            "dictionary": scenario.dictionary,
            "side_m": scenario.marker_side_m,
            "sides_m": {mk.id: scenario.side_of(mk) for mk in scenario.markers},
        }
    )
    tuning = base.estimator.model_dump(exclude={"anchors", "object_markers", "known_markers"})
    return base.model_copy(
        update={
            "cell": CellSection(name=base.cell.name, scenario=scenario_path, record=base.cell.record),
            "cameras": cameras,
            "markers": MarkerConfig.model_validate(markers.model_dump()),
            "estimator": estimator_config_of(scenario, **tuning),
            "recognition": recognition_config_of(scenario, base.recognition),
        }
    )


def demo_config(scenario_path: Path | None = None, base: CellConfig | None = None) -> CellConfig:
    return cell_config_of(load_scenario(scenario_path), scenario_path, base)


def complete(cfg: CellConfig) -> CellConfig:
    """A cell config with no cameras means "the simulated cell": fill it in from the scenario."""
    if cfg.cameras:
        return cfg
    return cell_config_of(load_scenario(cfg.cell.scenario), cfg.cell.scenario, cfg)
