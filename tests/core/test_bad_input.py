"""Damaged files at the entry points that read them: each gives the package's own error naming the
file, or a valid result, and never another exception or a crash.

Mutations are truncations, overwritten bytes and inserted bytes of real files (the demo cell's
scenario and config, PCL's clouds, a saved state file).
"""

from __future__ import annotations

import functools
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from cellsight.config import CellConfig, load_config
from cellsight.errors import ConfigError
from cellsight.model_build import build_database
from cellsight.scene_files import load_scene
from drivers.errors import ScenarioError
from drivers.sim.scenario import DEMO_CELL, Scenario, load_scenario
from estimator.errors import StateFileError
from estimator.state import SavedMarker, load_state, save_state
from recognition.cloud import read_cloud, read_coloured_cloud
from recognition.config import DescriptorConfig
from recognition.errors import CloudError, ModelError
from recognition.models import model_from_cloud, model_from_mesh, model_from_points, read_mesh
from tests.conftest import REAL_DATA
from tests.core.test_config import EXAMPLE

PCL = REAL_DATA / "pcl"
HERE = Path(__file__).resolve().parent


@st.composite
def damaged(draw: st.DrawFn, original: bytes) -> bytes:
    """original truncated, with bytes overwritten, or with bytes inserted."""
    b = bytearray(original)
    kind = draw(st.sampled_from(["truncate", "overwrite", "insert"]))
    if kind == "truncate":
        return bytes(b[: draw(st.integers(0, len(b) - 1))])
    if kind == "overwrite":
        for _ in range(draw(st.integers(1, 8))):
            b[draw(st.integers(0, len(b) - 1))] = draw(st.integers(0, 255))
        return bytes(b)
    at = draw(st.integers(0, len(b)))
    return bytes(b[:at] + draw(st.binary(min_size=1, max_size=16)) + b[at:])


FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.mark.parametrize(
    ("original", "load", "error", "kind"),
    [
        (EXAMPLE.encode(), lambda p: load_config(p, environ={}), ConfigError, CellConfig),
        (DEMO_CELL.read_bytes(), load_scenario, ScenarioError, Scenario),
    ],
    ids=["config", "scenario"],
)
@FUZZ
@given(data=st.data())
def test_a_damaged_toml_file_is_its_package_error_naming_the_file(
    tmp_path: Path, original: bytes, load, error: type[Exception], kind: type, data: st.DataObject
) -> None:
    path = tmp_path / "cell.toml"
    path.write_bytes(data.draw(damaged(original)))
    try:
        assert isinstance(load(path), kind)
    except error as exc:
        assert str(path) in str(exc)


STATE = {3: SavedMarker(np.eye(4), np.eye(6) * 1e-4), 7: SavedMarker(np.eye(4), np.eye(6))}


@functools.cache
def _state_file() -> bytes:
    """One saved state (it holds its save time, so every example must damage the same one)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "state.json"
        save_state(path, STATE, "lab")
        return path.read_bytes()


@FUZZ
@given(st.data())
def test_a_damaged_state_file_is_a_state_file_error_or_the_same_state(tmp_path: Path, data: st.DataObject) -> None:
    """The checksum catches every change to the content; a change JSON ignores (whitespace between
    tokens) loads the same state. Never a different state: the estimator would trust it."""
    path = tmp_path / "state.json"
    path.write_bytes(data.draw(damaged(_state_file())))
    try:
        loaded = load_state(path, "lab")
    except StateFileError as exc:
        assert str(path) in str(exc)
        return
    assert set(loaded) == set(STATE)
    for k, saved in STATE.items():
        np.testing.assert_array_equal(loaded[k].T, saved.T)
        np.testing.assert_array_equal(loaded[k].covariance, saved.covariance)


@pytest.mark.parametrize(
    ("edit", "why"),
    [
        (("normal_x", "foo"), "only"),  # Open3D dies of SIGSEGV on normal_y without normal_x
        (("FIELDS x y z", "FIELDS x y z w"), "one entry per field"),
        (("WIDTH 397", "WIDTH 3x97"), "non-negative integers"),
        (("POINTS 397", "POINTS 398"), "POINTS 398"),
        (("DATA ascii", "DATA zip"), "DATA"),
        (("FIELDS x y z", "FIELDS a y z"), "lack x"),
    ],
)
def test_a_damaged_pcd_header_is_named(tmp_path: Path, edit: tuple[str, str], why: str) -> None:
    path = tmp_path / "bun0.pcd"
    path.write_text((PCL / "bun0.pcd").read_text().replace(*edit, 1))
    with pytest.raises(CloudError, match=why):
        read_cloud(path)


FUZZ_CLOUDS = """
import sys
from pathlib import Path
import cv2
import numpy as np
from recognition.cloud import read_cloud, read_coloured_cloud
from recognition.errors import CloudError, ModelError
from recognition.models import read_mesh
src, out = Path(sys.argv[1]), Path(sys.argv[2])
original, rng = src.read_bytes(), np.random.default_rng(int(sys.argv[3]))
for k in range(int(sys.argv[4])):
    b = bytearray(original)
    if k % 3 == 0:
        b = b[: rng.integers(0, len(b))]
    elif k % 3 == 1:
        for _ in range(rng.integers(1, 20)):
            b[rng.integers(0, len(b))] = rng.integers(0, 256)
    else:  # inserted in or near the header, where the reader decides what to do
        at = rng.integers(0, min(len(b), 400))
        b[at:at] = rng.integers(0, 256, rng.integers(1, 30)).astype(np.uint8).tobytes()
    out.write_bytes(bytes(b))
    try:
        pts = read_cloud(out, organised=bool(k % 2))
        assert pts.dtype == np.float32 and pts.shape[-1] == 3
    except CloudError as exc:
        assert str(out) in str(exc)
"""


@pytest.mark.slow
@pytest.mark.parametrize("cloud", ["bun0.pcd", "milk.pcd"])  # ascii with normals; binary_compressed
def test_damaged_clouds_are_cloud_errors_never_a_crash(tmp_path: Path, cloud: str) -> None:
    """In a child process: before the header checks, Open3D's reader killed the process (SIGSEGV)."""
    out = tmp_path / f"damaged{Path(cloud).suffix}"
    run = subprocess.run(
        [sys.executable, "-c", FUZZ_CLOUDS, str(PCL / cloud), str(out), "3", "300"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=HERE.parents[1],
    )
    assert run.returncode == 0, f"exit {run.returncode}: {run.stderr[-2000:]}"


def _box_mesh_file(path: Path) -> bytes:
    """A 10 x 20 x 30 cm box with vertex normals, written by Open3D (binary PLY, STL or OBJ by suffix)."""
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    box.compute_vertex_normals()
    o3d.io.write_triangle_mesh(str(path), box)
    return path.read_bytes()


@pytest.mark.slow
def test_a_mesh_that_kills_open3d_is_a_model_error(tmp_path: Path) -> None:
    """Four bytes inserted into the face list of a binary PLY: Open3D's reader dies of SIGSEGV on
    this file when called in the test process (found by fuzzing); read_mesh reads in a child."""
    data = _box_mesh_file(tmp_path / "box.ply")
    at = data.index(b"end_header\n") + len(b"end_header\n") + 431
    bad = tmp_path / "damaged.ply"
    bad.write_bytes(data[:at] + bytes.fromhex("5b99dd50") + data[at:])
    with pytest.raises(ModelError, match="damaged.ply"):
        read_mesh(bad)
    mesh = read_mesh(tmp_path / "box.ply")  # the intact file still reads, whole
    assert len(mesh.triangles) == 12 and np.allclose(mesh.get_max_bound(), [0.1, 0.2, 0.3])


def test_a_model_in_millimetres_is_named_as_such() -> None:
    """A 10 x 20 x 30 cm box given in millimetres (as model libraries also ship them) or in metres:
    the first is an error naming the unit, from each model source; the second builds."""
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    points = np.asarray(box.sample_points_uniformly(3000).points)
    params = DescriptorConfig()
    for build in (
        lambda k: model_from_points("box", points * k, params),
        lambda k: model_from_cloud("box", points * k, params),
        lambda k: model_from_mesh("box", o3d.geometry.TriangleMesh(box).scale(k, np.zeros(3)), params),
    ):
        with pytest.raises(ModelError, match=r"'box' is 37[0-9.]+ across.*millimetres\? scale it by 0.001"):
            build(1000.0)
    assert len(model_from_points("box", points, params).views) > 0


def test_a_scene_in_millimetres_is_named_as_such(tmp_path: Path) -> None:
    """PCL's real milk scene written in millimetres: ``cellsight recognize`` says so instead of
    finding nothing; in metres (as PCL ships it) it loads."""
    scene = PCL / "milk_cartoon_all_small_clorox.pcd"
    cloud, _ = load_scene(scene)
    pts = cloud.reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    o3d.io.write_point_cloud(
        str(tmp_path / "mm.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts * 1000.0))
    )
    with pytest.raises(
        CloudError, match=r"mm.ply: its points lie [0-9.]+ from the camera.*millimetres\? give --scale 0.001"
    ):
        load_scene(tmp_path / "mm.ply")
    scaled, _ = load_scene(tmp_path / "mm.ply", scale=0.001)  # what the error says to do
    np.testing.assert_allclose(scaled, pts, atol=1e-6)
    with pytest.raises(CloudError, match="scale -1"):
        load_scene(scene, scale=-1.0)


def test_a_depth_image_takes_its_colour_from_the_registered_colour_image(tmp_path: Path) -> None:
    """PCL's grabber frames as TIFF depth + RGB (``cellsight recognize --scene D --rgb C``) give the
    colours PCL's grabber put in the PCD it built from them; a colour image of another size, or
    colour given to a cloud that has its own, is an error naming both."""
    tiff = PCL / "grabber_sequences" / "tiff"
    frame = "frame_20121214T142255.814212"
    cloud, rgb = load_scene(
        tiff / f"{frame}_depth.tiff", fx=525.0, fy=525.0, cx=320.0, cy=240.0, rgb=tiff / f"{frame}_rgb.tiff"
    )
    pcl_points, pcl_rgb = read_coloured_cloud(PCL / "grabber_sequences" / "pcd" / f"{frame}.pcd", organised=True)
    finite = np.all(np.isfinite(pcl_points), axis=2)
    assert finite.mean() > 0.5 and rgb.shape == pcl_rgb.shape
    np.testing.assert_array_equal(rgb[finite], pcl_rgb[finite])
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((240, 320, 3), np.uint8))
    with pytest.raises(CloudError, match=r"small.png is 320x240 but the depth image .* is 640x480"):
        load_scene(tiff / f"{frame}_depth.tiff", rgb=small)
    with pytest.raises(CloudError, match="carries its own colours"):
        load_scene(PCL / "milk_cartoon_all_small_clorox.pcd", rgb=small)


@pytest.mark.slow
def test_model_files_in_millimetres_build_with_their_scale(tmp_path: Path) -> None:
    """The millimetre box of the test above, as a points file and a mesh file: with ``scale`` 0.001
    (``cellsight model build --scale``) each builds the model the metre files build."""
    box = o3d.geometry.TriangleMesh.create_box(0.1, 0.2, 0.3)
    o3d.io.write_triangle_mesh(str(tmp_path / "m.ply"), box)
    o3d.io.write_triangle_mesh(str(tmp_path / "mm.ply"), o3d.geometry.TriangleMesh(box).scale(1000.0, np.zeros(3)))
    pts = np.asarray(box.sample_points_uniformly(3000).points)
    np.savetxt(tmp_path / "m.xyz", pts)
    np.savetxt(tmp_path / "mm.xyz", pts * 1000.0)
    params = DescriptorConfig()
    for kind in ("meshes", "points"):
        suffix = ".ply" if kind == "meshes" else ".xyz"
        metre = build_database(params, **{kind: {"box": tmp_path / f"m{suffix}"}}).models["box"]
        with pytest.raises(ModelError, match="millimetres"):
            build_database(params, **{kind: {"box": tmp_path / f"mm{suffix}"}})
        milli = build_database(params, **{kind: {"box": tmp_path / f"mm{suffix}"}}, scale=0.001).models["box"]
        assert milli.diameter_m == pytest.approx(metre.diameter_m, rel=1e-6), kind
        assert metre.diameter_m == pytest.approx(np.sqrt(0.14), rel=0.05), kind  # the box's diagonal
        assert len(milli.views) == len(metre.views)


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
@pytest.mark.slow
def test_a_damaged_mesh_is_a_model_error_or_a_valid_mesh(tmp_path: Path, suffix: str, data: st.DataObject) -> None:
    """Every read runs in a child forked from read_mesh's fork server (milliseconds each)."""
    path = tmp_path / f"mesh{suffix}"
    path.write_bytes(data.draw(damaged(_box_mesh_file(tmp_path / f"box{suffix}"))))
    try:
        mesh = read_mesh(path)
    except ModelError as exc:
        assert str(path) in str(exc)
        return
    triangles = np.asarray(mesh.triangles)
    assert len(triangles) > 0 and triangles.min() >= 0 and triangles.max() < len(mesh.vertices)


#: Offline commands with every argument a placeholder: P a path, N a number, S a word.
CLI_TEMPLATES = [
    ["config", "check", "P"],
    ["config", "show", "P"],
    ["markers", "detect", "P", "--size", "N", "--dict", "S", "--camera-info", "P", "--depth", "P", "--json"],
    ["recognize", "--models", "P", "--scene", "P", "--fx", "N", "--cy", "N", "--rgb", "P", "--picture", "P"],
    ["model", "build", "--out", "OUT", "--cloud", "S=P", "--mesh", "S=P", "--distance", "N"],
    ["resolve", "P", "--out", "OUT"],
    ["compare", "P", "P"],
]


@pytest.fixture(scope="module")
def junk_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, ...]:
    """Paths a confused user might pass: missing, a folder, empty and garbage files of each kind."""
    where = tmp_path_factory.mktemp("cli-fuzz")
    paths = [where / "missing.toml", where, where / ""]
    for name, data in [
        ("empty.toml", b""),
        ("junk.toml", b"[cell\nname = 3"),
        ("junk.mcap", b"\x89MCAP0\r\n" + bytes(100)),
        ("junk.pcd", b"# .PCD\nFIELDS x\n"),
        ("junk.png", b"\x89PNG\r\n\x1a\n garbage"),
        ("junk.yml", b"%YAML:1.0\nfoo: ["),
    ]:
        (where / name).write_bytes(data)
        paths.append(where / name)
    return tuple(str(p) for p in paths)


NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(str),
    st.integers(-(10**12), 10**12).map(str),
    st.text(max_size=6),
)


@pytest.mark.slow
@settings(
    max_examples=100, deadline=None, phases=[Phase.explicit, Phase.reuse, Phase.generate]
)  # the message names the args: no shrinking
@given(data=st.data())
def test_cli_arguments_give_an_exit_code_never_a_traceback(junk_files: tuple[str, ...], data: st.DataObject) -> None:
    """Any mix of junk arguments to the offline commands ends in a clean exit 0, 1 or 2."""
    from typer.testing import CliRunner

    from cellsight.cli import app

    args = []
    for token in data.draw(st.sampled_from(CLI_TEMPLATES)):
        if data.draw(st.integers(0, 9)) == 0:
            continue  # a missing argument or option value
        word = data.draw(st.text(st.characters(codec="ascii", categories=["L", "N", "P"]), min_size=0, max_size=8))
        path = data.draw(st.sampled_from(junk_files))
        args.append(
            token.replace("S=P", f"{word}={path}").replace("OUT", f"{junk_files[1]}/out").replace("P", path)
            if token in ("P", "S=P", "OUT")
            else data.draw(NUMBERS)
            if token == "N"
            else word
            if token == "S"
            else token
        )
    result = CliRunner().invoke(app, args, catch_exceptions=True)
    assert result.exception is None or isinstance(result.exception, SystemExit), f"{args}: {result.exception!r}"
    assert result.exit_code in (0, 1, 2), f"{args}: exit {result.exit_code}\n{result.output[-1000:]}"


@functools.cache
def _bus_payloads() -> dict[str, tuple[type, bytes]]:
    """One valid payload of each message the services subscribe to, by name."""
    from cellsight.evaluation.synthetic import observations_msg
    from estimator.observation import Observation
    from schemas import codec

    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 2.0)
    obs = [Observation("cam1", 5, i, T, np.eye(6) * 1e-4, T) for i in (1, 2)]
    msgs = [
        observations_msg("cam1", 5, obs),
        codec.image_to_msg(np.arange(48, dtype=np.uint16).reshape(6, 8), 5, "cam1", "16UC1"),
        codec.CameraInfo.kinect_v1().to_msg(5, "cam1"),
        codec.poses_to_msg(5, [codec.StampedPose("world", "cam1", 5, T, np.eye(6))]),
        codec.transforms_to_msg(5, [("world", "cam1", T)]),
    ]
    return {type(x).__name__: (type(x), x.SerializeToString()) for x in msgs}


@FUZZ
@given(data=st.data())
def test_a_damaged_bus_payload_is_a_decode_error_or_a_valid_message(data: st.DataObject) -> None:
    """What every subscription does with a payload before a service sees it."""
    from schemas import codec
    from schemas.errors import DecodeError

    name = data.draw(st.sampled_from(sorted(_bus_payloads())))
    msg_type, payload = _bus_payloads()[name]
    try:
        msg = codec.decode(data.draw(damaged(payload)), msg_type)
    except DecodeError as exc:
        assert str(exc), name  # says what was wrong
        return
    if name == "MarkerObservations":  # what the estimator takes from it is finite, with real covariances
        arrays = codec.marker_arrays(msg)
        assert np.all(np.isfinite(arrays.poses)) and np.all(np.isfinite(arrays.covariances))
        assert np.all(np.linalg.eigvalsh(arrays.covariances) > 0)


@functools.cache
def _small_log() -> bytes:
    """A log of 60 driver statuses, frames 0-59, in 1 KiB chunks (many chunks to damage), as bytes."""
    from schemas import keys
    from schemas import messages as m
    from schemas.log import LogWriter

    with tempfile.TemporaryDirectory(prefix="log-fuzz-") as where:
        path = Path(where) / "small.mcap"
        writer = LogWriter(path, chunk_size=1024, metadata={"config": "x"})
        for i in range(60):
            writer.write(keys.status("fz", "cam1"), m.DriverStatus(camera_id="cam1", stamp_ns=1 + i, frames=i), 1 + i)
        writer.close()
        return path.read_bytes()


@FUZZ
@given(data=st.data())
def test_a_damaged_log_reads_up_to_the_damage_and_reports_it(tmp_path: Path, data: st.DataObject) -> None:
    from schemas.log import ReadReport, read_log

    path = tmp_path / "damaged.mcap"
    path.write_bytes(data.draw(damaged(_small_log())))
    report = ReadReport()
    frames = [x.msg.frames for x in read_log(path, None, report)]
    # Nothing invented or reordered. (Not "every loss reported": MCAP readers skip records of an
    # unknown opcode by design, and a damaged opcode byte makes a whole chunk one.)
    assert set(frames) <= set(range(60)) and frames == sorted(set(frames))
    cut_short = len(path.read_bytes()) < len(_small_log()) and _small_log().startswith(path.read_bytes())
    if cut_short and len(frames) < 60:  # a truncated log lost messages: the report must say so
        assert report.stopped_early
