"""The simulated cell: scenario validation, determinism, geometry and the Kinect noise model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.errors import ScenarioError
from drivers.sim.render import SimCell, kinect_depth
from drivers.sim.scenario import CameraMotion, NoiseSpec, Scenario, apart, footprint, load_scenario
from drivers.sim.source import SimSource
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose, rotation_angle

MINIMAL = """
name = "mini"
[[markers]]
id = 0
role = "anchor"
pose = { position = [0.0, 0.0, 0.0005], normal = [0.0, 0.0, 1.0] }
[[cameras]]
id = "c"
pose = { position = [0.0, -1.0, 1.5], look_at = [0.0, 0.0, 0.0] }
"""


def test_demo_cell_meets_its_brief() -> None:
    s = load_scenario()
    roles = [m.role for m in s.markers]
    assert len(s.cameras) == 4 and roles.count("anchor") == 4 and roles.count("static") >= 12
    assert len(s.objects) == 3 and all(any(m.object == o.id for m in s.markers) for o in s.objects)
    kinds = {m.kind for c in s.cameras for m in c.motion}
    assert {"tilt", "bump"} <= kinds


def test_scenario_errors_name_the_field(tmp_path: Path) -> None:
    bad = tmp_path / "s.toml"
    bad.write_text(MINIMAL.replace('id = "c"', 'id = "c"\nrate_hz = -1'))
    with pytest.raises(ScenarioError, match=r"cameras\.0\.rate_hz"):
        load_scenario(bad)
    bad.write_text(MINIMAL + "[[markers]]\nid = 0\npose = { position = [1.0, 0.0, 0.0] }\n")
    with pytest.raises(ScenarioError, match="duplicate marker ids"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match="no such scenario"):
        load_scenario(tmp_path / "missing.toml")


def test_rendering_is_deterministic_and_frames_differ_by_noise(tmp_path: Path) -> None:
    f = tmp_path / "s.toml"
    f.write_text(MINIMAL)
    s = load_scenario(f)
    a, b = SimCell(s).render("c", 0.5, 3), SimCell(s).render("c", 0.5, 3)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
    c = SimCell(s).render("c", 0.5, 4)
    assert not np.array_equal(a.depth_mm, c.depth_mm)


def test_noise_free_depth_matches_geometry(tmp_path: Path) -> None:
    """Camera 1.5 m above a floor, looking straight down: noise-free depth is 1500 mm everywhere."""
    f = tmp_path / "s.toml"
    f.write_text(
        MINIMAL.replace("[0.0, -1.0, 1.5]", "[0.0, 0.0, 1.5]").replace(
            'name = "mini"', 'name = "mini"\nfloor_size = [5.0, 5.0]'
        )
        + "[noise]\nenabled = false\n"
    )
    frame = SimCell(load_scenario(f)).render("c", 0.0, 0)
    centre = frame.depth_mm[200:280, 280:360]
    assert np.all(np.abs(centre.astype(int) - 1500) <= 1)


@pytest.mark.parametrize("z", [1.0, 2.0, 3.0])
def test_kinect_noise_grows_with_z_squared(z: float) -> None:
    """Error statistics on a slanted surface (depth varies across pixels, as on real surfaces:
    a constant depth would quantise to one or two disparity levels)."""
    info = CameraInfo.kinect_v1()
    noise = NoiseSpec(grazing_cos=0.0, edge_jump_m=1.0)
    truth = np.linspace(0.95 * z, 1.05 * z, info.width * info.height).astype(np.float32)
    depth = kinect_depth(truth, np.ones_like(truth), info, noise, np.random.default_rng(0)).astype(float) / 1000
    err = (depth - truth.reshape(info.height, info.width))[2:-2, 2:-2]
    fb = info.K[0, 0] * noise.baseline_m
    step = z * z * noise.disparity_step_px / fb  # quantisation step in depth at z
    total = np.sqrt((0.0014 * z * z) ** 2 + step**2 / 12)  # Gaussian part + uniform quantisation
    assert abs(err.mean()) < 0.1 * total + 0.0005  # unbiased up to mm rounding
    assert 0.8 * total < err.std() < 1.25 * total


def test_flying_pixels_lie_between_the_surfaces_of_a_jump() -> None:
    """A step from 1.0 m to 2.0 m down the middle of the image: the Kinect returns nothing next to
    it; with flying pixels those pixels return a depth between the two surfaces (within the noise
    at 2 m), and every other pixel is the same."""
    info = CameraInfo.kinect_v1()
    z = (
        np.where(np.arange(info.width) < info.width // 2, 1.0, 2.0)[None, :]
        .repeat(info.height, axis=0)
        .astype(np.float32)
    )
    kinect, flying = (
        kinect_depth(z.reshape(-1), np.ones(z.size), info, NoiseSpec(flying_pixels=f), np.random.default_rng(3))
        for f in (False, True)
    )
    edge = kinect == 0
    assert edge[:, info.width // 2 - 1 : info.width // 2 + 1].all() and edge.sum() == 2 * info.height
    assert np.array_equal(kinect[~edge], flying[~edge])
    mixed = flying[edge].astype(float) / 1000
    assert np.all(mixed > 1.0 - 0.01) and np.all(mixed < 2.0 + 0.03) and np.ptp(mixed) > 0.5


def test_white_balance_and_registration_shift_the_colour() -> None:
    """The same frame with a warm white balance and colour 3 px off: red up and blue down by their
    gains, the image moved 3 px to the right, depth untouched."""
    s = load_scenario()
    warm = s.model_copy(
        update={"noise": s.noise.model_copy(update={"white_balance": (1.15, 1.0, 0.85), "rgb_shift_px": (3, 0)})}
    )
    a, b = (SimCell(x).render("cam1", 0.0, 0) for x in (s, warm))
    assert np.array_equal(a.depth_mm, b.depth_mm)
    inner = a.rgb[:, 40:-40].astype(float)
    moved = b.rgb[:, 43:-37].astype(float)
    unsaturated = np.all(inner < 200, axis=2)
    gains = [np.median(moved[..., c][unsaturated] / np.maximum(inner[..., c][unsaturated], 1.0)) for c in range(3)]
    assert np.allclose(gains, (1.15, 1.0, 0.85), atol=0.03)
    green_off = [
        np.abs(b.rgb[:, 40 + dx : b.rgb.shape[1] - 40 + dx, 1].astype(float) - inner[..., 1]).mean() for dx in (0, 3)
    ]
    assert green_off[1] < 0.7 * green_off[0]  # aligned only 3 px to the right


def test_saturation_pales_colour_towards_grey_and_keeps_its_hue() -> None:
    """At saturation 0.5 each bright pixel's rg-chromaticity lies half as far from grey (1/3, 1/3),
    in the same direction, within the 8-bit rounding and noise."""
    s = load_scenario()
    pale = s.model_copy(update={"noise": s.noise.model_copy(update={"saturation": 0.5, "rgb_sigma": 0.0})})
    clean = s.model_copy(update={"noise": s.noise.model_copy(update={"rgb_sigma": 0.0})})
    a, b = (SimCell(x).render("cam1", 0.0, 0).rgb.reshape(-1, 3).astype(float) for x in (clean, pale))
    bright = (a.sum(axis=1) > 150) & (np.abs(a - a.mean(axis=1, keepdims=True)).max(axis=1) > 40)
    chroma = [x[bright, :2] / x[bright].sum(axis=1, keepdims=True) - 1 / 3 for x in (a, b)]
    assert bright.sum() > 1000
    assert np.allclose(chroma[1], 0.5 * chroma[0], atol=0.01)


def test_true_marker_corners_project_onto_detections() -> None:
    """Ground truth and the renderer agree: true corners land on the detected ones (< 1.5 px)."""
    from drivers.config import MarkerConfig
    from drivers.markers import MarkerDetector, marker_object_points

    s = load_scenario()
    frame = SimCell(s).render("cam3", 1.0, 0)
    det = MarkerDetector(MarkerConfig(dictionary=s.dictionary, sides_m={m.id: s.side_of(m) for m in s.markers}))
    ids, corners = det.find(frame.rgb)
    assert len(ids) >= 8
    K = frame.info.K
    for i, c in zip(ids, corners):
        mk = next(m for m in s.markers if m.id == i)
        cam_T_m = invert_pose(frame.world_T_camera) @ s.world_T_marker(mk, 1.0)
        p = marker_object_points(s.side_of(mk)) @ cam_T_m[:3, :3].T + cam_T_m[:3, 3]
        uv = (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
        assert np.abs(uv - c).max() < 1.5, f"marker {i}"


def test_a_marker_close_to_the_camera_renders_and_its_corners_are_true() -> None:
    """A 20 cm marker 45 cm from the camera covers ~50k pixels (OpenCV's remap takes maps under
    32,767 rows): it renders, and its true corners land on the detected ones."""
    from drivers.config import MarkerConfig
    from drivers.markers import MarkerDetector, marker_object_points
    from drivers.sim.scenario import BoxSpec, CameraSpec, MarkerSpec
    from schemas.spec import PoseSpec

    s = Scenario(
        floor_size=(0.01, 0.01),
        noise={"enabled": False},
        boxes=[BoxSpec(size=(3, 0.02, 3), pose=PoseSpec(position=(0, 0.011, 1.0)))],
        markers=[MarkerSpec(id=5, side_m=0.2, pose=PoseSpec(position=(0, 0, 1.0), normal=(0, -1, 0), up=(0, 0, 1)))],
        cameras=[CameraSpec(id="c", pose=PoseSpec(position=(0.05, -0.45, 1.02), look_at=(0, 0, 1.0)))],
    )
    frame = SimCell(s).render("c", 0.0, 0)
    ids, corners = MarkerDetector(MarkerConfig(dictionary=s.dictionary, side_m=0.2)).find(frame.rgb)
    assert ids.tolist() == [5]
    cam_T_m = invert_pose(frame.world_T_camera) @ s.world_T_marker(s.markers[0], 0.0)
    p = marker_object_points(0.2) @ cam_T_m[:3, :3].T + cam_T_m[:3, 3]
    K = frame.info.K
    uv = (p[:, :2] / p[:, 2:]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    assert np.abs(uv - corners[0]).max() < 1.5


def test_bumped_camera_moves_by_the_scripted_amount() -> None:
    s = load_scenario()
    cam = s.camera("cam2")
    before, after = cam.world_T_camera(13.9), cam.world_T_camera(14.1)
    assert np.linalg.norm(after[:3, 3] - before[:3, 3]) == pytest.approx(0.03, abs=1e-9)
    R = before[:3, :3].T @ after[:3, :3]
    assert np.degrees(rotation_angle(np.eye(3), R)) == pytest.approx(2.0, abs=1e-6)


def test_unknown_camera_is_named() -> None:
    with pytest.raises(ScenarioError, match="no camera 'nope'"):
        Scenario().camera("nope")


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_mesh_objects_from_files_are_rendered(tmp_path: Path, suffix: str) -> None:
    """A 0.4 m cube from a mesh file, 1 m below a downward camera: its top face at 1.0 m depth."""
    import open3d as o3d

    cube = o3d.geometry.TriangleMesh.create_box(0.4, 0.4, 0.4).translate([-0.2, -0.2, 0.0])
    cube.compute_triangle_normals()  # STL needs them
    path = tmp_path / f"cube{suffix}"
    assert o3d.io.write_triangle_mesh(str(path), cube)
    scen = tmp_path / "s.toml"
    scen.write_text(
        'name = "mesh"\nfloor_size = [5.0, 5.0]\n[noise]\nenabled = false\n'
        f'[[objects]]\nid = "cube"\nshape = "mesh"\nmesh = "{path.name}"\npose = {{ position = [0.0, 0.0, 0.0] }}\n'
        '[[cameras]]\nid = "c"\npose = { position = [0.0, 0.0, 1.4], look_at = [0.0, 0.0, 0.0] }\n'
    )
    frame = SimCell(load_scenario(scen)).render("c", 0.0, 0)
    centre = frame.depth_mm[230:250, 310:330].astype(int)
    assert np.all(np.abs(centre - 1000) <= 1), "the cube's top face is not at 1.0 m"
    assert abs(int(frame.depth_mm[20, 20]) - 1400) <= 1  # the corner sees the floor (optical depth 1.4 m)


def test_missing_mesh_file_is_named(tmp_path: Path) -> None:
    scen = tmp_path / "s.toml"
    scen.write_text(
        '[[objects]]\nid = "x"\nshape = "mesh"\nmesh = "nope.ply"\n[[cameras]]\nid = "c"\npose = { position = [0.0, 0.0, 1.4], look_at = [0.0, 0.0, 0.0] }\n'
    )
    with pytest.raises(ScenarioError, match="nope.ply"):
        load_scenario(scen)


def test_prerendered_frames_loop_with_live_stamps() -> None:
    """``prerender``: the first frames rendered once and played again, stamped as new frames."""
    source = SimSource(load_scenario(), "cam1", epoch_ns=0, realtime=False, prerender=2)
    frames = [source.read() for _ in range(5)]
    assert [f.stamp_ns for f in frames] == [round(i * 1e9 / 30) for i in range(5)]
    np.testing.assert_array_equal(frames[2].rgb, frames[0].rgb)
    np.testing.assert_array_equal(frames[3].depth_mm, frames[1].depth_mm)
    assert not np.array_equal(frames[0].depth_mm, frames[1].depth_mm)  # two renders: their own noise


def test_prerendered_truth_is_the_looped_frames_with_live_stamps() -> None:
    """A camera sliding 1 m a second, two frames prerendered: each frame's truth is the pose its
    looped image was rendered at, stamped like the frame."""
    scenario = load_scenario()
    cam = scenario.cameras[0].model_copy(
        update={"motion": [CameraMotion(kind="slide", offset=(1.0, 0.0, 0.0), end_s=10.0)]}
    )
    scenario = scenario.model_copy(update={"cameras": [cam]})
    looped = SimSource(scenario, cam.id, epoch_ns=0, realtime=False, prerender=2)
    for k in range(6):
        frame = looped.read()
        cams, markers, _ = looped.truth(looped.t_s)
        assert cams[0].stamp_ns == frame.stamp_ns and {p.stamp_ns for p in markers} == {frame.stamp_ns}
        shown_x = scenario.cameras[0].world_T_camera((k % 2) / 30)[0, 3]
        assert abs(cams[0].T[0, 3] - shown_x) < 1e-12, (k, cams[0].T[0, 3], shown_x)


@pytest.mark.slow
def test_footprints_said_apart_are_apart_and_overlapping_ones_never() -> None:
    """``apart`` against the distance between the objects' true outlines on the table (a box's
    rectangle, the can's circle, sampled every millimetre), for random placements of the demo objects."""
    objects = load_scenario().objects
    rng = np.random.default_rng(4)

    def outline(obj, xy: np.ndarray, yaw: float) -> np.ndarray:  # (N, 2) on the true edge
        if obj.shape == "box":
            hx, hy = 0.5 * obj.size[0], 0.5 * obj.size[1]
            tx, ty = np.arange(-hx, hx, 0.001)[:, None], np.arange(-hy, hy, 0.001)[:, None]
            edge = np.concatenate(
                [np.hstack([tx, np.full_like(tx, s_ * hy)]) for s_ in (-1, 1)]
                + [np.hstack([np.full_like(ty, s_ * hx), ty]) for s_ in (-1, 1)]
            )
        else:
            a = np.arange(0, 2 * np.pi, 0.001 / obj.size[0])
            edge = obj.size[0] * np.column_stack([np.cos(a), np.sin(a)])
        c, s_ = np.cos(yaw), np.sin(yaw)
        return edge @ np.array([[c, s_], [-s_, c]]) + xy

    def inside(obj, xy: np.ndarray, yaw: float, p: np.ndarray) -> bool:  # p (2,) within the true outline
        c, s_ = np.cos(yaw), np.sin(yaw)
        local = np.array([[c, -s_], [s_, c]]) @ (p - xy)
        return (
            bool(np.all(np.abs(local) <= 0.5 * np.array(obj.size[:2])))
            if obj.shape == "box"
            else bool(np.linalg.norm(local) <= obj.size[0])
        )

    said_apart = overlapping = 0
    for _ in range(100):
        a, b = (objects[k] for k in rng.choice(len(objects), 2, replace=False))
        (xa, xb), (ya, yb) = rng.uniform(-0.25, 0.25, (2, 2)), rng.uniform(0, 2 * np.pi, 2)
        ea, eb = outline(a, xa, ya), outline(b, xb, yb)
        gap = np.sqrt(((ea[:, None] - eb[None]) ** 2).sum(-1).min())
        if (
            inside(a, xa, ya, xb) or inside(b, xb, yb, xa) or gap < 0.0015
        ):  # convex: edges cross, or one holds the other
            overlapping += 1
            assert not apart(footprint(a, xa, ya), footprint(b, xb, yb), 0.0)
        elif apart(footprint(a, xa, ya), footprint(b, xb, yb), 0.015):
            said_apart += 1
            assert gap >= 0.015 - 0.001, f"said 1.5 cm apart, {1e3 * gap:.1f} mm"  # the samples' spacing
    assert said_apart >= 15 and overlapping >= 15  # both cases were tried
