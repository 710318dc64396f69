"""Cell configuration: TOML round trip, environment overrides, errors that name the field."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from cellsight.config import CellConfig, load_config, parse_config, save_used
from cellsight.errors import ConfigError

EXAMPLE = """
[cell]
name = "lab"
[transport]
connect = ["tcp/127.0.0.1:7500"]
[[cameras]]
id = "cam1"
[[cameras]]
id = "cam2"
source = "openni2"
uri = "Dummy"
[markers]
side_m = 0.1
sides_m = { 3 = 0.2 }
[[estimator.anchors]]
marker_id = 0
world_T_marker = { position = [1.0, 0.0, 0.0], normal = [0.0, 0.0, 1.0] }
"""


def test_round_trip_through_the_saved_copy(tmp_path: Path) -> None:
    f = tmp_path / "cell.toml"
    f.write_text(EXAMPLE)
    cfg = load_config(f, environ={})
    saved = save_used(cfg, tmp_path / "run")
    assert load_config(saved, environ={}) == cfg
    assert cfg.markers.side_for(3) == 0.2 and cfg.markers.side_for(4) == 0.1
    assert cfg.estimator.anchors[0].world_T_marker.matrix()[2, 2] == pytest.approx(1.0)


def test_environment_overrides_nested_fields() -> None:
    cfg = parse_config(
        tomllib.loads(EXAMPLE), environ={"CELLSIGHT__TRANSPORT__MODE": "peer", "CELLSIGHT__ESTIMATOR__HUBER_K": "2.5"}
    )
    assert cfg.transport.mode == "peer" and cfg.estimator.huber_k == 2.5


def test_duplicate_camera_ids_are_rejected() -> None:
    with pytest.raises(ConfigError, match="duplicate camera ids"):
        parse_config({"cameras": [{"id": "a"}, {"id": "a"}]}, environ={})


def test_unknown_field_is_named() -> None:
    with pytest.raises(ConfigError, match=r"markers\.sidem"):
        parse_config({"markers": {"sidem": 1}}, environ={})


def test_two_orientations_for_one_pose_are_rejected() -> None:
    data = {"estimator": {"anchors": [{"marker_id": 1, "world_T_marker": {"rpy_deg": [0, 0, 0], "normal": [0, 0, 1]}}]}}
    with pytest.raises(ConfigError, match="one orientation"):
        parse_config(data, environ={})


def test_a_reorder_fill_that_would_reorder_every_update_is_rejected() -> None:
    with pytest.raises(ConfigError, match="reorder_fill 0.5 would re-order"):
        parse_config({"estimator": {"reorder_fill": 0.5}}, environ={})
    assert parse_config({"estimator": {"reorder_fill": 0}}, environ={}).estimator.reorder_fill == 0


def test_defaults_alone_are_valid() -> None:
    assert CellConfig().cell.name == "demo"


@pytest.mark.parametrize("value", [0.0, -0.1, float("nan"), float("inf")])
@pytest.mark.parametrize("where", ["side_m", "sides_m"])
def test_marker_sides_must_be_finite_and_positive(where: str, value: float) -> None:
    markers = {"side_m": value} if where == "side_m" else {"sides_m": {"3": value}}
    with pytest.raises(ConfigError, match=rf"markers\.{where}"):
        parse_config({"markers": markers}, environ={})


def test_no_setting_takes_infinity() -> None:
    """A NaN or an infinity means nothing in a cell: every model refuses them, naming the field."""
    for section, key in (("estimator", "huber_k"), ("estimator", "stale_after_s"), ("recognition", "min_fitness")):
        with pytest.raises(ConfigError, match=rf"{section}\.{key}: Input should be a finite number"):
            parse_config({section: {key: float("inf")}}, environ={})
