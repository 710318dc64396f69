"""BOP-format datasets (``cellsight.evaluation.bop``): written and read back, recognised from their files in
millimetres, scored, and refused with a clear error when malformed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellsight.errors import DatasetError
from cellsight.evaluation.bop import (
    ADDS_SHARE,
    BopDataset,
    BopInstance,
    BopWriter,
    adds_m,
    depth_of_organised,
    object_id,
    score,
)
from recognition.cloud import depth_to_cloud, read_coloured_cloud
from recognition.config import RecognitionConfig
from recognition.models import ModelDatabase
from recognition.pipeline import Recognizer
from schemas.geometry import invert_pose, make_pose, matrix_from_quat
from tests.core.test_recognition import PCL
from tests.helpers import assert_pose_close

WORKSPACE = ((-0.6, -0.4, 0.7), (0.6, 0.4, 1.3))  # the demo table's (benchmarks.recognition)


@pytest.fixture(scope="module")
def demo_dataset(tmp_path_factory: pytest.TempPathFactory):
    """The demo cell (its objects where the scenario puts them) rendered by two cameras and written
    as a BOP dataset: models in mm with their colours, depth in mm, the cameras' world poses given."""
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario().still()
    root = tmp_path_factory.mktemp("bop")
    w = BopWriter(root)
    ids = {o.id: i + 1 for i, o in enumerate(scenario.objects)}
    for o in scenario.objects:
        mesh = object_mesh(o).paint_uniform_color(o.color)
        w.add_model(ids[o.id], np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors))
    cell, frames = SimCell(scenario), []
    for image_id, cam in enumerate(("cam1", "cam3")):
        frame = cell.render(cam, 0.0, image_id)
        truth = [(ids[o.id], invert_pose(frame.world_T_camera) @ o.world_T_object(0.0), 1.0) for o in scenario.objects]
        w.add_frame(
            7,
            image_id,
            frame.depth_mm * 0.001,
            frame.info.K,
            truth,
            frame.rgb,
            depth_scale_mm=1.0,
            world_T_camera=frame.world_T_camera,
        )
        frames.append((frame, truth))
    return w.close(), frames, ids


def test_a_written_dataset_reads_back_in_metres(demo_dataset) -> None:
    root, frames, ids = demo_dataset
    ds = BopDataset.open(root)
    assert sorted(ds.models) == sorted(object_id(i) for i in ids.values()) and all(
        m.is_mesh for m in ds.models.values()
    )
    assert [(f.scene_id, f.image_id) for f in ds.frames] == [(7, 0), (7, 1)]
    info = json.loads((root / "models" / "models_info.json").read_text())
    assert info["2"]["diameter"] == pytest.approx(1000 * ds.models[object_id(2)].diameter_m)  # mm on disk, m read
    for f, (frame, truth) in zip(ds.frames, frames):
        cloud, rgb = f.load()
        expected = depth_to_cloud(frame.depth_mm, frame.info.K)
        np.testing.assert_array_equal(np.isnan(cloud), np.isnan(expected))
        np.testing.assert_allclose(cloud[np.isfinite(cloud)], expected[np.isfinite(expected)], atol=1e-6)
        np.testing.assert_array_equal(rgb, frame.rgb)
        assert_pose_close(f.world_T_camera, frame.world_T_camera, 1e-9, 1e-7, "camera's world pose")
        for inst, (oid, T, share) in zip(f.truth, truth):
            assert inst.object_id == object_id(oid) and inst.visible_share == share
            assert_pose_close(inst.camera_T_object, T, 1e-9, 1e-7, "annotated pose")


@pytest.mark.slow
def test_objects_are_recognised_from_their_model_files_in_millimetres(demo_dataset) -> None:
    """The database built from the dataset's PLY files (mm, scaled by 0.001, as `model build
    --mesh ID=FILE --scale 0.001`) finds every object in both frames within ADD-S 0.1 d, and
    nothing else."""
    from cellsight.model_build import build_database

    root, _, _ = demo_dataset
    ds = BopDataset.open(root)
    cfg = RecognitionConfig(workspace_min=WORKSPACE[0], workspace_max=WORKSPACE[1])
    db = build_database(cfg.descriptor, meshes={m.object_id: m.path for m in ds.models.values()}, scale=0.001)
    rec = Recognizer(db, cfg)
    for f in ds.frames:
        cloud, rgb = f.load()
        found = rec.recognize(cloud, world_T_camera=f.world_T_camera, rgb=rgb)
        s = score(
            f.truth,
            [(d.object_id, d.camera_T_object) for d in found],
            {o: m.points for o, m in db.models.items()},
            {o: m.diameter_m for o, m in ds.models.items()},
        )
        assert all(s.found) and s.false == [], (f.image_id, s)


def test_scoring_matches_each_instance_once_and_calls_the_rest_false() -> None:
    """ADD-S of a known offset (a tube moved sideways by delta: each point's distance to the moved
    circle is delta |cos theta|, 2 delta / pi on average); a cylinder turned about its axis is its own
    pose; a pose 0.2 d off, a second detection of one instance and an object not annotated are false."""
    rng = np.random.default_rng(0)
    angle = rng.uniform(0, 2 * np.pi, 4000)
    height = rng.uniform(0, 0.2, 4000)
    cylinder = np.c_[0.03 * np.cos(angle), 0.03 * np.sin(angle), height]  # a can's side, m
    T = make_pose(np.eye(3), (0.1, 0.0, 1.0))
    assert adds_m(cylinder, make_pose(np.eye(3), (0.11, 0.0, 1.0)), T) == pytest.approx(0.02 / np.pi, rel=0.1)
    turned = T @ make_pose(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), (0, 0, 0))
    assert adds_m(cylinder, turned, T) < 0.003  # the nearest-neighbour spacing of 4000 points
    d = 0.2
    truth = (BopInstance("can", T, 1.0),)
    far = make_pose(np.eye(3), (0.1 + 2 * ADDS_SHARE * d, 0.0, 1.0))
    s = score(
        truth,
        [("can", far), ("can", turned), ("can", T), ("box", T)],
        {"can": cylinder, "box": cylinder},
        {"can": d, "box": d},
    )
    assert s.found == [True] and s.false == ["can", "can", "box"]


def test_a_real_kinect_frame_repacked_as_a_depth_image_gives_its_cloud_back(tmp_path: Path) -> None:
    """PCL's real organised frame to depth + intrinsics (fx = fy = 525, the principal point fitted),
    written at 0.2 mm a unit and read back: every point within the 0.1 mm of that quantisation and
    0.5 % of its range (the fitted principal point)."""
    cloud, rgb = read_coloured_cloud(PCL / "office1.pcd", organised=True)
    depth, K = depth_of_organised(cloud, 525.0)
    w = BopWriter(tmp_path)
    w.add_model(1, np.random.default_rng(0).uniform(-0.05, 0.05, (500, 3)))
    w.add_frame(1, 0, depth, K, [], rgb)
    frame = BopDataset.open(w.close()).frames[0]
    back, colours = frame.load()
    ok = np.isfinite(cloud[..., 2])
    np.testing.assert_array_equal(np.isfinite(back[..., 2]), ok)
    np.testing.assert_allclose(back[..., 2][ok], cloud[..., 2][ok], atol=1e-4)
    assert np.max(np.linalg.norm(back[ok] - cloud[ok], axis=1) / cloud[..., 2][ok]) < 0.005
    np.testing.assert_array_equal(colours, rgb)
    assert frame.truth == () and frame.world_T_camera is None


def _minimal(root: Path) -> Path:
    w = BopWriter(root)
    w.add_model(1, np.random.default_rng(0).uniform(-0.05, 0.05, (500, 3)))
    w.add_frame(
        1,
        0,
        np.full((48, 64), 1.0),
        np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]),
        [(1, make_pose(np.eye(3), (0, 0, 1)), None)],
    )
    return w.close()


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda r: (r / "models" / "models_info.json").unlink(), "models_info.json is missing"),
        (lambda r: (r / "models" / "obj_000001.ply").unlink(), "obj_000001.ply is missing"),
        (lambda r: (r / "test").rename(r / "val"), "no split 'test' (folders: val)"),
        (lambda r: (r / "test" / "000001" / "scene_camera.json").write_text("{"), "scene_camera.json: not JSON"),
        (
            lambda r: (r / "test" / "000001" / "scene_gt.json").write_text(
                '{"0": [{"obj_id": 2, "cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,0]}]}'
            ),
            "obj_id 2 has no model",
        ),
        (
            lambda r: (r / "test" / "000001" / "scene_gt.json").write_text(
                '{"0": [{"obj_id": 1, "cam_R_m2c": [2,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,0]}]}'
            ),
            "cam_R_m2c is no rotation",
        ),
        (
            lambda r: (r / "test" / "000001" / "scene_camera.json").write_text('{"0": {"depth_scale": 1}}'),
            "cam_K must be 9 numbers",
        ),
        (lambda r: (r / "test" / "000001" / "depth" / "000000.png").unlink(), "no image 000000"),
        (
            lambda r: (r / "test" / "000001" / "scene_camera.json").write_text(
                '{"0": {"cam_K": [1,0,0,0,1,0,0,0,1], "depth_scale": 0}}'
            ),
            "depth_scale 0 must be positive",
        ),
        (lambda r: (r / "test" / "000001" / "scene_camera.json").write_text('{"first": {}}'), "keys must be image ids"),
    ],
)
def test_a_malformed_dataset_is_refused_naming_what_is_wrong(tmp_path: Path, damage, message: str) -> None:
    root = _minimal(tmp_path)
    assert len(BopDataset.open(root).frames) == 1
    damage(root)
    with pytest.raises(DatasetError, match=message.replace("(", r"\(").replace(")", r"\)")):
        BopDataset.open(root)


def test_the_models_are_read_from_the_first_model_folder_a_dataset_has_or_the_one_named(tmp_path: Path) -> None:
    """T-LESS ships its models as ``models_cad/`` and ``models_reconst/``, every BOP dataset also
    ``models_eval/``: the first present is taken (``MODEL_FOLDERS``) unless one is named, and a
    dataset with none, or without the one named, is refused with the folders it has."""
    root = _minimal(tmp_path)
    (root / "models").rename(root / "models_cad")
    (root / "models_eval").mkdir()
    for f in (root / "models_cad").iterdir():
        (root / "models_eval" / f.name).write_bytes(f.read_bytes())
    assert BopDataset.open(root).models["obj_000001"].path.parent.name == "models_cad"
    assert BopDataset.open(root, models_dir="models_eval").models["obj_000001"].path.parent.name == "models_eval"
    with pytest.raises(DatasetError, match="no model folder 'models_x' \\(folders: models_cad, models_eval, test\\)"):
        BopDataset.open(root, models_dir="models_x")
    (root / "models_cad").rename(root / "meshes")
    (root / "models_eval").rename(root / "eval")
    with pytest.raises(DatasetError, match="none of the model folders .* \\(folders: eval, meshes, test\\)"):
        BopDataset.open(root)


@pytest.mark.parametrize("listing", ["test_targets_bop19.json", "test_targets_bop24.json"])
def test_only_the_images_a_dataset_lists_as_targets_are_read(tmp_path: Path, listing: str) -> None:
    """BOP's challenges evaluate on the images a targets file lists (2019's for the classic datasets,
    2024's for the newer): where one is there, only those frames are read; without it, all."""
    w = BopWriter(tmp_path / "ds")
    w.add_model(1, np.random.default_rng(0).uniform(-0.05, 0.05, (500, 3)))
    K = np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    for image_id in (0, 1, 2):
        w.add_frame(1, image_id, np.full((48, 64), 1.0), K, [(1, make_pose(np.eye(3), (0, 0, 1)), None)])
    root = w.close()
    assert [f.image_id for f in BopDataset.open(root).frames] == [0, 1, 2]
    (root / listing).write_text(json.dumps([{"scene_id": 1, "im_id": 2, "obj_id": 1, "inst_count": 1}]))
    assert [f.image_id for f in BopDataset.open(root).frames] == [2]
    assert [f.image_id for f in BopDataset.open(root, split="test").frames] == [2]
    (root / listing).write_text(json.dumps([{"scene": 1}]))
    with pytest.raises(DatasetError, match=f"{listing}: expected a list of objects with scene_id and im_id"):
        BopDataset.open(root)


@pytest.mark.slow
def test_the_benchmark_names_what_is_wrong_with_a_dataset_and_exits_2(tmp_path: Path) -> None:
    """``python -m benchmarks.bop --dataset DIR`` on a folder that is no dataset: the reason on
    stderr and exit code 2, not a traceback."""
    root = _minimal(tmp_path)
    (root / "models").rename(root / "meshes")
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.bop", "--dataset", str(root)],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[2],
        timeout=120,
    )
    assert run.returncode == 2, run.stderr
    assert "none of the model folders" in run.stderr and "Traceback" not in run.stderr


@pytest.mark.slow
def test_recognize_standing_finds_what_stands_on_the_table_in_a_dataset_frame(demo_dataset, tmp_path: Path) -> None:
    """`cellsight model build --mesh ID=PLY --scale 0.001` from the dataset's models, then `cellsight
    recognize` on cam1's depth and colour PNGs with its intrinsics, no pose: every object is found
    (ADD-S under 0.1 d), tried standing on the floor-or-table plane by default and declared to
    stand there with `--standing`."""
    from typer.testing import CliRunner

    from cellsight.cli import app

    root, frames, _ = demo_dataset
    ds = BopDataset.open(root)
    db = tmp_path / "db"
    meshes = [a for m in ds.models.values() for a in ("--mesh", f"{m.object_id}={m.path}")]
    assert CliRunner().invoke(app, ["model", "build", "--out", str(db), *meshes, "--scale", "0.001"]).exit_code == 0
    frame = ds.frames[0]
    K = frame.K
    args = [
        "recognize",
        "--models",
        str(db),
        "--scene",
        str(frame.depth_path),
        "--rgb",
        str(frame.rgb_path),
        "--fx",
        str(K[0, 0]),
        "--fy",
        str(K[1, 1]),
        "--cx",
        str(K[0, 2]),
        "--cy",
        str(K[1, 2]),
        "--json",
    ]
    truth = {i.object_id: i.camera_T_object for i in frame.truth}
    models = ModelDatabase.load(db).models
    results = {}
    for standing in (False, True):
        result = CliRunner().invoke(app, args + (["--standing"] if standing else []))
        found = json.loads(result.stdout)["detections"]
        for d in found:
            T = make_pose(matrix_from_quat(d["quaternion_xyzw"]), d["position_m"])  # rounded to 0.1 mm, 1e-5
            oid = d["object_id"]
            assert adds_m(models[oid].points, T, truth[oid]) < ADDS_SHARE * ds.models[oid].diameter_m, (standing, d)
        results[standing] = sorted(d["object_id"] for d in found)
    assert results[True] == results[False] == sorted(truth)


@pytest.mark.slow
def test_a_world_pose_whose_z_is_not_up_is_set_aside(demo_dataset) -> None:
    """cam1's frame with its world pose, and with the same pose in a world turned a quarter about x
    (a marker board's frame on a wall: its z lies along the table). Recognition given the turned
    pose stands every object on a horizontal axis and finds none; ``level_world_pose`` keeps the true
    pose (the table is level in it) and sets the turned one aside, and without it every object is
    found (ADD-S under 0.1 d)."""
    from cellsight.evaluation.bop import level_world_pose
    from cellsight.model_build import build_database

    root, _, _ = demo_dataset
    ds = BopDataset.open(root)
    cfg = RecognitionConfig()
    db = build_database(cfg.descriptor, meshes={m.object_id: m.path for m in ds.models.values()}, scale=0.001)
    rec = Recognizer(db, cfg)
    frame = ds.frames[0]
    cloud, rgb = frame.load()
    turned = make_pose(matrix_from_quat([np.sin(np.pi / 4), 0.0, 0.0, np.cos(np.pi / 4)])) @ frame.world_T_camera
    assert rec.recognize(cloud, world_T_camera=turned, rgb=rgb) == []
    assert level_world_pose(rec, cloud, frame.world_T_camera) is frame.world_T_camera
    assert level_world_pose(rec, cloud, turned) is None
    found = rec.recognize(cloud, world_T_camera=level_world_pose(rec, cloud, turned), rgb=rgb)
    s = score(
        frame.truth,
        [(d.object_id, d.camera_T_object) for d in found],
        {o: m.points for o, m in db.models.items()},
        {o: m.diameter_m for o, m in ds.models.items()},
    )
    assert all(s.found) and s.false == [], s
