"""Recognition against the Point Cloud Library's own data and reference values (data/pcl)."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from recognition.align import align_to_z, model_to_scene_rmse, roll_candidates, roll_histogram, rot_z
from recognition.cloud import (
    PointIndex,
    camera_rays,
    depth_to_cloud,
    estimate_normals,
    finite_points,
    image_window,
    radius_neighbours,
    read_cloud,
    read_coloured_cloud,
    smallest_eigenpair,
    voxel_downsample,
)
from recognition.config import DescriptorConfig, RecognitionConfig
from recognition.errors import CloudError, ModelError
from recognition.hypotheses import SceneCloud
from recognition.models import ModelDatabase, model_from_cloud, model_from_mesh
from recognition.pipeline import Recognizer
from recognition.segment import PointGraph, components, euclidean_clusters
from recognition.vfh import F_BINS, vfh
from schemas.codec import CameraInfo
from schemas.geometry import invert_pose, look_at_matrix, make_pose, rotation_angle
from tests.conftest import REAL_DATA
from tests.helpers import assert_pose_close

PCL = REAL_DATA / "pcl"
GRABBER_K = np.array([[525.0, 0, 320.0], [0, 525.0, 240.0], [0, 0, 1]])  # pclzf/*.xml


@pytest.fixture(scope="module")
def milk() -> np.ndarray:
    return read_cloud(PCL / "milk.pcd")


@pytest.fixture(scope="module")
def milk_pcl_normals() -> np.ndarray:
    return np.array(json.loads((PCL / "reference" / "milk_normals_pcl.json").read_text())["normals"])[:, :3]


def bun0() -> tuple[np.ndarray, np.ndarray]:
    pcd = o3d.t.io.read_point_cloud(str(PCL / "bun0.pcd"))
    return pcd.point.positions.numpy(), pcd.point.normals.numpy()


@pytest.mark.parametrize("frame", sorted(p.stem for p in (PCL / "grabber_sequences" / "pcd").glob("*.pcd")))
def test_depth_to_cloud_reproduces_pcl_grabber_exactly(frame: str) -> None:
    ref = read_cloud(PCL / "grabber_sequences" / "pcd" / f"{frame}.pcd", organised=True)
    depth = cv2.imread(str(PCL / "grabber_sequences" / "tiff" / f"{frame}_depth.tiff"), cv2.IMREAD_UNCHANGED)
    cloud = depth_to_cloud(depth, GRABBER_K, depth_scale=0.001)
    assert cloud.shape == ref.shape == (480, 640, 3)
    np.testing.assert_array_equal(np.isnan(cloud), np.isnan(ref))
    np.testing.assert_array_equal(cloud[~np.isnan(ref)], ref[~np.isnan(ref)])


def test_normals_agree_with_pcl_on_milk(milk: np.ndarray, milk_pcl_normals: np.ndarray) -> None:
    normals, _ = estimate_normals(milk, radius_m=0.02, viewpoint=(0, 0, 0))
    cos = np.clip(np.einsum("ij,ij->i", normals, milk_pcl_normals), -1, 1)  # signed: orientation counts too
    angle = np.degrees(np.arccos(cos))
    assert np.median(angle) < 1.0 and np.percentile(angle, 99) < 5.0, (np.median(angle), np.percentile(angle, 99))


def test_normals_are_nan_where_too_few_neighbours() -> None:
    pts = np.array([[0, 0, 1.0], [0.001, 0, 1.0], [5, 5, 5.0]] + [[x, y, 2.0] for x in (0, 0.01) for y in (0, 0.01)])
    normals, _ = estimate_normals(pts, radius_m=0.02)
    assert np.isnan(normals[:3]).all() and np.isfinite(normals[3:]).all()
    np.testing.assert_allclose(np.abs(normals[3:, 2]), 1.0, atol=1e-6)
    assert (normals[3:, 2] < 0).all(), "normals must face the viewpoint at the origin"


@pytest.mark.slow
def test_normals_from_a_wider_search_equal_their_own_search(milk: np.ndarray) -> None:
    """The recogniser searches once at the clustering tolerance and cuts down to the normal radius."""
    own, _ = estimate_normals(milk, radius_m=0.02)
    shared, _ = estimate_normals(milk, radius_m=0.02, neighbours=radius_neighbours(milk, 0.035))
    np.testing.assert_allclose(shared, own, atol=1e-5, equal_nan=True)
    with pytest.raises(CloudError, match="searched within"):
        estimate_normals(milk, radius_m=0.05, neighbours=radius_neighbours(milk, 0.035))


@pytest.mark.parametrize("tolerance", [0.01, 0.02, 0.035])
def test_euclidean_clusters_are_open3ds_single_linkage_components(milk: np.ndarray, tolerance: float) -> None:
    """Clusters from the union-find over the radius graph equal Open3D's DBSCAN with one point per
    core (the same components, independently computed), on the milk scene thinned to islands."""
    scene = read_cloud(PCL / "milk_cartoon_all_small_clorox.pcd")
    pts = scene[np.random.default_rng(0).random(len(scene)) < 0.05]
    ours = euclidean_clusters(pts, tolerance, 1, len(pts))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    labels = np.asarray(pcd.cluster_dbscan(tolerance, min_points=1))
    theirs = [np.flatnonzero(labels == k) for k in range(labels.max() + 1)]
    assert len(ours) > 10, "the thinned scene should fall apart into many islands"
    assert sorted(map(tuple, map(np.sort, ours))) == sorted(map(tuple, theirs))
    # A finer tolerance from the shared graph equals a search at that tolerance.
    graph = PointGraph.of(pts, 0.035)
    assert [c.tolist() for c in euclidean_clusters(pts, tolerance, 1, len(pts), graph)] == [c.tolist() for c in ours]


def test_components_of_a_path_in_scrambled_order() -> None:
    """Worst case for naive label propagation: a long chain, plus an isolated node; labels are the
    smallest node of each component."""
    rng = np.random.default_rng(1)
    order = rng.permutation(1000)
    i, j = order[:-1], order[1:]  # one path visiting every node, numbered at random
    labels = components(1001, i, j)
    assert (labels[:1000] == 0).all() and labels[1000] == 1000


def test_point_index_is_exact_nearest_and_radius_search(milk: np.ndarray) -> None:
    """The k-d tree ICP scoring shares answers as brute force does (nearest point and its squared
    distance) and as Open3D's radius search does (within r), for queries near and far from the points."""
    rng = np.random.default_rng(5)
    points = milk[rng.choice(len(milk), 800, replace=False)]
    query = np.concatenate([points + rng.normal(0, 0.01, points.shape), rng.uniform(-1, 2, (200, 3))]).astype(
        np.float32
    )
    index, sq_dist = PointIndex(points).nearest(query)
    all_sq = ((query[:, None, :] - points[None, :, :]) ** 2).sum(axis=2)
    np.testing.assert_allclose(sq_dist, all_sq.min(axis=1), rtol=1e-5, atol=1e-10)
    assert np.all(all_sq[np.arange(len(query)), index] <= all_sq.min(axis=1) * (1 + 1e-5) + 1e-10)
    search = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(points))
    search.fixed_radius_index(0.008)
    _, _, splits = search.fixed_radius_search(o3d.core.Tensor(query), 0.008)
    np.testing.assert_array_equal(PointIndex(points).within(query, 0.008), np.diff(splits.numpy()) > 0)
    assert not PointIndex(np.zeros((0, 3))).within(query, 1.0).any()


def test_closed_form_normals_match_lapack_on_random_neighbourhoods() -> None:
    """The closed-form smallest eigenpair against numpy's eigh, on flat, thin and round neighbourhoods."""
    rng = np.random.default_rng(3)
    scales = np.array([[1, 1, 1e-3], [1, 1e-2, 1e-3], [1, 0.9, 0.8]])
    x = rng.normal(size=(3000, 25, 3)) * np.repeat(scales, 1000, axis=0)[:, None, :]
    cov = np.einsum("nki,nkj->nij", x, x) / 25
    evals, evecs = np.linalg.eigh(cov)
    smallest, vec = smallest_eigenpair(cov)
    # Error bounded by rounding on the largest eigenvalue (~1 here), not on the smallest.
    np.testing.assert_allclose(smallest, evals[:, 0], rtol=0, atol=1e-10)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", vec, evecs[:, :, 0])), 0, 1)))
    assert angle[:2000].max() < 1e-3, "flat and thin neighbourhoods have a well-defined normal"
    assert np.median(angle[2000:]) < 1.0


REFERENCE = json.loads((PCL / "reference" / "vfh_pcl_1_13.json").read_text())
SETTINGS = {
    "default": {},
    "normalize_distance_and_size_component": {"normalize_distance": True, "size_component": True},
}


@pytest.mark.parametrize("setting", sorted(SETTINGS))
@pytest.mark.parametrize("cloud", ["bun0.pcd", "milk.pcd"])
def test_vfh_equals_pcl_bin_for_bin(cloud: str, setting: str, milk: np.ndarray, milk_pcl_normals: np.ndarray) -> None:
    points, normals = bun0() if cloud == "bun0.pcd" else (milk, milk_pcl_normals)
    ours = vfh(points, normals, (0, 0, 0), binning="pcl", **SETTINGS[setting])
    ref = np.array(REFERENCE[cloud][setting])
    assert ours.shape == ref.shape == (308,)
    worst = int(np.argmax(np.abs(ours - ref)))
    assert np.abs(ours - ref).max() <= 1e-3, f"bin {worst}: ours {ours[worst]}, PCL {ref[worst]}"


def test_vfh_pcl17_binning_spreads_f2_f3_and_keeps_the_rest(milk: np.ndarray, milk_pcl_normals: np.ndarray) -> None:
    new = vfh(milk, milk_pcl_normals, binning="pcl")
    old = vfh(milk, milk_pcl_normals, binning="pcl17")
    f2_new, f2_old = new[F_BINS : 2 * F_BINS], old[F_BINS : 2 * F_BINS]
    # PCL >= 1.10.1 maps f2 in [-1, 1] through (f + pi) / 2 pi: only bins 15..29 can fill.
    assert f2_new[:15].sum() == 0 and f2_new[30:].sum() == 0
    assert f2_old[:15].sum() + f2_old[30:].sum() > 0
    np.testing.assert_allclose(f2_old.sum(), f2_new.sum(), rtol=1e-4)  # same points, other bins (float32 sums)
    np.testing.assert_array_equal(old[:F_BINS], new[:F_BINS])  # f1 binned alike in both
    np.testing.assert_array_equal(old[3 * F_BINS :], new[3 * F_BINS :])


def test_vfh_leaves_out_points_with_non_finite_normals(milk: np.ndarray, milk_pcl_normals: np.ndarray) -> None:
    pts = np.vstack([milk, [[0.1, 0.1, 0.8], [0.2, 0.1, 0.8]]])
    normals = np.vstack([milk_pcl_normals, [[np.nan, 0, 0], [np.inf, 0, 1]]])
    np.testing.assert_array_equal(vfh(pts, normals), vfh(milk, milk_pcl_normals))


@pytest.mark.parametrize("bad", ["shape", "few", "binning"])
def test_vfh_bad_input_is_a_clear_error(bad: str) -> None:
    p = np.random.default_rng(0).normal(size=(50, 3))
    args = {"shape": (p, p[:10]), "few": (p[:1], p[:1]), "binning": (p, p)}[bad]
    with pytest.raises(CloudError):
        vfh(*args, binning="pcl15" if bad == "binning" else "pcl")


def test_roll_histogram_recovers_a_known_roll(milk: np.ndarray, milk_pcl_normals: np.ndarray) -> None:
    """Turn the milk view about its centroid's line of sight; the roll alignment must find the angle."""
    A = align_to_z(milk.mean(axis=0))
    for roll_deg in (17.0, 95.0, -140.0):
        R = A.T @ rot_z(np.radians(roll_deg)) @ A  # rotation about the centroid ray, through the origin
        h0 = roll_histogram(milk, milk_pcl_normals)
        h1 = roll_histogram(milk @ R.T, milk_pcl_normals @ R.T)
        found = np.degrees(roll_candidates(h1, h0, peaks=1)[0])
        err = (found - roll_deg + 180) % 360 - 180
        assert abs(err) < 4.0, f"roll {roll_deg} deg recovered as {found:.1f} deg"


@pytest.mark.slow
def test_recognizes_the_milk_carton_in_pcls_real_scene(milk: np.ndarray) -> None:
    """PCL's acceptance on its own data: model-to-scene RMSE under 1 cm, true pose the identity."""
    cfg = RecognitionConfig()
    db = ModelDatabase(cfg.descriptor, {})
    db.add(model_from_cloud("milk", milk, cfg.descriptor))
    scene = read_cloud(PCL / "milk_cartoon_all_small_clorox.pcd", organised=True)
    detections = Recognizer(db, cfg).recognize(scene)
    assert [d.object_id for d in detections] == ["milk"]
    pose = detections[0].camera_T_object
    rmse = model_to_scene_rmse(milk, pose, read_cloud(PCL / "milk_cartoon_all_small_clorox.pcd"))
    assert rmse < 0.01, f"model-to-scene RMSE {rmse * 1000:.1f} mm"
    assert_pose_close(pose, np.eye(4), pos_tol_m=0.01, rot_tol_deg=2.0, what="milk carton")


@pytest.mark.slow
def test_model_database_round_trips_and_refuses_damage(tmp_path: Path, milk: np.ndarray) -> None:
    params = DescriptorConfig()
    db = ModelDatabase(params, {})
    db.add(model_from_cloud("milk", milk, params, subdivisions=0))
    box = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.05).paint_uniform_color([0.8, 0.2, 0.15])
    db.add(model_from_mesh("box", box, params, subdivisions=0, distances_m=(1.5,)))
    loaded = ModelDatabase.load(db.save(tmp_path / "db"))
    assert sorted(loaded.models) == ["box", "milk"]
    for oid in db.models:
        np.testing.assert_array_equal(loaded.models[oid].views.vfh, db.models[oid].views.vfh)
        np.testing.assert_allclose(loaded.models[oid].points, db.models[oid].points, atol=1e-6)
    # The mesh's colour is the model's, kept to 8 bits; a cloud without colour gives none.
    colours = loaded.models["box"].colours
    assert colours.shape == loaded.models["box"].points.shape and loaded.models["milk"].colours is None
    np.testing.assert_allclose(colours, np.broadcast_to([0.8, 0.2, 0.15], colours.shape), atol=0.5 / 255)
    assert len(loaded.models["box"].views) == 12  # an icosahedron's vertices, each sees the box
    with pytest.raises(ModelError, match="rebuild"):
        Recognizer(loaded, RecognitionConfig(descriptor=DescriptorConfig(voxel_m=params.voxel_m * 2)))
    np.savez(tmp_path / "db" / "box" / "views.npz", vfh=np.zeros((2, 5)))
    with pytest.raises(ModelError, match="views.npz"):
        ModelDatabase.load(tmp_path / "db")
    with pytest.raises(ModelError, match="no database.json"):
        ModelDatabase.load(tmp_path)


@pytest.mark.slow
def test_rays_cast_only_in_the_objects_window_render_the_same_depth() -> None:
    """Model views cast rays only where the object's bounding box projects: the depth image is the
    full image's, pixel for pixel, from views near and far, and a box reaching behind the camera
    falls back to the whole image."""
    mesh = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    corners = np.asarray(mesh.get_axis_aligned_bounding_box().get_box_points())
    info = CameraInfo.kinect_v1()
    for eye in ([0.8, -0.6, 0.5], [0.15, 0.1, 0.9], [2.5, 1.0, -1.0]):
        object_T_view = make_pose(
            look_at_matrix(np.array(eye), np.array([0.15, 0.1, 0.05]), np.array([0.0, 0.0, 1.0])), eye
        )
        view_T_object = invert_pose(object_T_view)
        full = scene.cast_rays(o3d.core.Tensor(camera_rays(info.K, info.width, info.height, object_T_view)))[
            "t_hit"
        ].numpy()
        full = full.reshape(info.height, info.width)
        u0, v0, u1, v1 = image_window(
            info.K, info.width, info.height, corners @ view_T_object[:3, :3].T + view_T_object[:3, 3]
        )
        assert (u1 - u0) * (v1 - v0) < info.width * info.height  # a window, not the image
        part = scene.cast_rays(
            o3d.core.Tensor(camera_rays(info.K, info.width, info.height, object_T_view, (u0, v0, u1, v1)))
        )
        inside = np.full_like(full, np.inf)
        inside[v0:v1, u0:u1] = part["t_hit"].numpy().reshape(v1 - v0, u1 - u0)
        assert np.isfinite(full).sum() > 100 and np.array_equal(inside, full), eye
    assert image_window(info.K, info.width, info.height, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -0.1]])) == (
        0,
        0,
        info.width,
        info.height,
    )


def test_a_mesh_gives_the_same_model_every_time() -> None:
    """Surface sampling is random: unseeded, two builds of one database would recognise differently."""
    box = o3d.geometry.TriangleMesh.create_box(0.2, 0.1, 0.05)
    a, b = (model_from_mesh("box", box, DescriptorConfig(), subdivisions=0) for _ in range(2))
    np.testing.assert_array_equal(a.points, b.points)


@pytest.mark.slow
def test_coloured_model_files_give_coloured_models(tmp_path: Path) -> None:
    """A crate's surface points in its colour, as a PLY (``--points``) and as a PCD (``--cloud``):
    both models carry the colour (to 8 bits), which verification judges; PCL's real Kinect scenes
    load with one colour per point, in the cloud's layout."""
    from cellsight.model_build import build_database

    box = o3d.geometry.TriangleMesh.create_box(0.24, 0.18, 0.14)
    o3d.utility.random.seed(1)
    surface = box.sample_points_uniformly(20000).paint_uniform_color([0.2, 0.45, 0.7])
    o3d.io.write_point_cloud(str(tmp_path / "crate.ply"), surface)
    o3d.io.write_point_cloud(str(tmp_path / "crate.pcd"), surface)
    db = build_database(DescriptorConfig(), points={"a": tmp_path / "crate.ply"}, clouds={"b": tmp_path / "crate.pcd"})
    for model in db.models.values():
        assert model.colours.shape == model.points.shape
        np.testing.assert_allclose(
            model.colours, np.broadcast_to([0.2, 0.45, 0.7], model.colours.shape), atol=0.6 / 255
        )
    points, rgb = read_coloured_cloud(PCL / "milk_cartoon_all_small_clorox.pcd", organised=True)
    assert points.shape == rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8 and rgb.std() > 10
    assert read_coloured_cloud(PCL / "milk.pcd")[1] is None


@pytest.mark.slow
def test_a_model_from_surface_points_finds_the_demo_crate(tmp_path: Path) -> None:
    """``model build --points``: the crate's whole surface as an .xyz file of points (as model
    libraries ship them), its views by hidden-point removal; the rendered demo frame's crate is
    found where it stands (2 cm: the mesh-built model's bound in the end-to-end demo test)."""
    from cellsight.model_build import build_database
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario()
    crate = next(o for o in scenario.objects if o.id == "crate")
    o3d.utility.random.seed(1)
    surface = np.asarray(object_mesh(crate).sample_points_uniformly(20000).points)
    np.savetxt(tmp_path / "crate.xyz", surface)
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    db = build_database(cfg.descriptor, points={"crate": tmp_path / "crate.xyz"}, distances_m=(2.0,))
    model = db.models["crate"]
    assert model.source == "points" and len(model.views) >= 20
    outward = np.einsum("ij,ij->i", model.normals, model.points - model.points.mean(axis=0)) > 0
    assert outward.mean() > 0.95  # verification's front-facing test needs them outward
    frame = SimCell(scenario).render("cam1", 0.0, 0)
    found = {
        d.object_id: d
        for d in Recognizer(db, cfg).recognize(
            depth_to_cloud(frame.depth_mm, frame.info.K), world_T_camera=frame.world_T_camera
        )
    }
    truth = invert_pose(frame.world_T_camera) @ crate.world_T_object(0.0)
    assert "crate" in found
    assert np.linalg.norm(found["crate"].camera_T_object[:3, 3] - truth[:3, 3]) < 0.02


@dataclass
class Layout:
    """The demo objects placed on the table and one camera's rendered frame of them."""

    recognizer: Recognizer
    config: RecognitionConfig
    cloud: np.ndarray  # (H, W, 3) camera frame
    world_T_camera: np.ndarray
    truth: dict[str, np.ndarray]  # object -> camera_T_object
    scene: SceneCloud

    def surface_points(self, oid: str) -> np.ndarray:
        """Indices of the prepared scene's points within 1 cm of the object's posed model."""
        T = self.truth[oid]
        surface = o3d.geometry.PointCloud(
            o3d.utility.Vector3dVector(self.recognizer.db.models[oid].points @ T[:3, :3].T + T[:3, 3])
        )
        scene = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.scene.points.astype(np.float64)))
        return np.flatnonzero(np.asarray(scene.compute_point_cloud_distance(surface)) < 0.01)


def static_demo(where: dict[str, tuple[float, float, float]]):
    """The demo cell's scenario with each object standing still at ``where`` (x, y in m on the
    table, yaw in deg), and a recogniser of its objects with the benchmark's workspace."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.scenario import apart, footprint, load_scenario
    from schemas.spec import PoseSpec

    scenario = load_scenario()
    outlines = [footprint(o, np.array(where[o.id][:2]), np.radians(where[o.id][2])) for o in scenario.objects]
    assert all(apart(a, b, 0.0) for i, a in enumerate(outlines) for b in outlines[i + 1 :]), (
        "objects that interpenetrate are no scene"
    )
    objects = [
        o.still().model_copy(
            update={
                "pose": PoseSpec(position=(where[o.id][0], where[o.id][1], 0.75), rpy_deg=(0.0, 0.0, where[o.id][2]))
            }
        )
        for o in scenario.objects
    ]
    scenario = scenario.model_copy(update={"objects": objects})
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    return scenario, Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg)


def demo_layout(where: dict[str, tuple[float, float, float]], camera: str, seed: int) -> Layout:
    """The demo cell with each object at ``where`` (``static_demo``), rendered by ``camera`` with
    noise seed ``seed``; recognised with the benchmark's workspace."""
    from drivers.sim.render import SimCell

    scenario, recognizer = static_demo(where)
    frame = SimCell(scenario).render(camera, 0.0, seed)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    truth = {o.id: invert_pose(frame.world_T_camera) @ o.world_T_object(0.0) for o in scenario.objects}
    return Layout(
        recognizer,
        recognizer.config,
        cloud,
        frame.world_T_camera,
        truth,
        recognizer.prepare(cloud, frame.world_T_camera),
    )


@pytest.mark.slow
def test_objects_standing_together_are_found_in_their_merged_cluster() -> None:
    """The demo objects about 1 cm apart on the table: from cam3 they form one cluster (no descriptor of
    it is any object's) and the crate is partly hidden. Each is stood on the table at pieces of the
    cluster, verified, and found within 2 cm of where it stands."""
    lay = demo_layout({"crate": (0.0, 0.0, 0.0), "can": (0.19, 0.03, 0.0), "tote": (-0.05, 0.25, 90.0)}, "cam3", 0)
    cfg = lay.config
    clusters = euclidean_clusters(
        lay.scene.points, cfg.cluster_tolerance_m, cfg.cluster_min_points, cfg.cluster_max_points, lay.scene.graph
    )
    owner = {}  # object -> the clusters holding points of its surface
    for oid in lay.truth:
        on = lay.surface_points(oid)
        owner[oid] = {k for k, idx in enumerate(clusters) if np.isin(idx, on).sum() >= cfg.cluster_min_points}
    assert owner["crate"] == owner["can"] == owner["tote"] and len(owner["crate"]) == 1  # one cluster holds all three
    found = {d.object_id: d for d in lay.recognizer.recognize(lay.cloud, world_T_camera=lay.world_T_camera)}
    assert set(found) == set(lay.truth)
    for oid, det in found.items():
        assert np.linalg.norm(det.camera_T_object[:3, 3] - lay.truth[oid][:3, 3]) < 0.02, oid


@pytest.mark.slow
def test_a_pose_hint_adds_a_candidate_and_never_hides_an_object() -> None:
    """The standing-together layout above (one cluster holds all three objects): a hint (``Prior``,
    as a marker fixed on an object gives) at an object's true pose leaves every object found where
    it stands, and one at the wrong object (the crate hinted where the tote stands) is no crate
    there and no lost tote. The hint's cluster is matched as any other and the joint resolution
    chooses: a hint that explains part of a cluster must not keep its neighbours, or the object
    itself when its hinted fit fails, from being looked for."""
    from recognition.pipeline import Prior

    lay = demo_layout({"crate": (0.0, 0.0, 0.0), "can": (0.19, 0.03, 0.0), "tote": (-0.05, 0.25, 90.0)}, "cam3", 0)

    def found(priors: list[Prior]) -> dict[str, np.ndarray]:  # object id -> camera_T_object
        dets = lay.recognizer.recognize(lay.cloud, priors, world_T_camera=lay.world_T_camera)
        return {d.object_id: d.camera_T_object for d in dets}

    hints = {"none": [], "wrong": [Prior("crate", lay.truth["tote"])]} | {
        oid: [Prior(oid, T)] for oid, T in lay.truth.items()
    }
    for name, priors in hints.items():
        poses = found(priors)
        assert set(poses) == set(lay.truth), f"hint {name}: found {sorted(poses)}"
        for oid, T in poses.items():
            assert np.linalg.norm(T[:3, 3] - lay.truth[oid][:3, 3]) < 0.02, f"hint {name}: {oid}"


@pytest.mark.slow
@pytest.mark.parametrize(
    ("where", "camera", "seed"),
    [
        (
            {"crate": (-0.1219, -0.0885, 4.51), "can": (0.1344, -0.1252, 92.21), "tote": (0.1608, 0.1228, 282.83)},
            "cam4",
            3,
        ),
        (
            {"crate": (-0.149, -0.1064, 149.39), "can": (0.1284, -0.1112, 146.07), "tote": (0.1984, 0.0747, 169.12)},
            "cam4",
            5,
        ),
    ],
)
def test_a_small_object_half_hidden_among_larger_ones_is_found_in_its_fragments(
    where: dict, camera: str, seed: int
) -> None:
    """Two layouts of the recognition benchmark (layout seeds 7 and 11, trials 3 and 5; no two
    objects closer than 1.5 cm): crate, tote and can form one cluster, the can partly hidden. Split at a finer tolerance, crate and tote come apart, but
    the can's visible surface falls into fragments (crumbs of the big cluster, small parts): no
    part holds half of it. Together they go to the pieces path: the can is found, and every object
    reported is where it stands within the benchmark's ADD-S bound (a tenth of its diameter; the
    can is round, so its origin's offset says little)."""
    from recognition.segment import split_oversized

    lay = demo_layout(where, camera, seed)
    cfg, scene = lay.config, lay.scene
    on_can = lay.surface_points("can")
    clusters = euclidean_clusters(
        scene.points, cfg.cluster_tolerance_m, cfg.cluster_min_points, cfg.cluster_max_points, scene.graph
    )
    parts, shed = split_oversized(
        scene.points,
        clusters,
        1.2 * lay.recognizer._largest,
        cfg.cluster_tolerance_m,
        1.5 * cfg.descriptor.voxel_m,
        cfg.cluster_min_points,
        scene.graph,
    )
    assert len(on_can) >= 100, "the can must be partly visible for this test"
    assert max(np.isin(idx, on_can).sum() for idx in parts) < 0.5 * len(on_can), "a part holds most of the can"
    assert sum(np.isin(idx, on_can).sum() for idx in shed) > 0, "the split shed none of the can"
    found = {d.object_id: d for d in lay.recognizer.recognize(lay.cloud, world_T_camera=lay.world_T_camera)}
    assert "can" in found
    for oid, det in found.items():
        model = lay.recognizer.db.models[oid]
        posed = [
            o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.points @ P[:3, :3].T + P[:3, 3]))
            for P in (det.camera_T_object, lay.truth[oid])
        ]
        adds = float(np.mean(np.asarray(posed[0].compute_point_cloud_distance(posed[1]))))
        assert adds < 0.1 * model.diameter_m, f"{oid}: ADD-S {1e3 * adds:.1f} mm"


#: Layouts of the recognition benchmark (layout seed 7, trials 10 and 9) where the code before the
#: turned starts found the tote ~90 deg turned: (where, camera, noise seed).
TOTE_TURNED = [
    ({"crate": (0.0654, 0.1829, 17.58), "can": (0.0777, -0.0731, 230.8), "tote": (0.3944, -0.241, 62.36)}, "cam3", 10),
    ({"crate": (0.0242, -0.124, 174.22), "can": (0.1875, 0.0938, 84.78), "tote": (-0.1599, 0.1196, 225.36)}, "cam1", 9),
]


@pytest.mark.slow
@pytest.mark.parametrize(("where", "camera", "seed"), TOTE_TURNED)
def test_a_box_is_found_at_its_yaw_not_turned_a_quarter(where: dict, camera: str, seed: int) -> None:
    """Two layouts of the recognition benchmark (layout seed 7, trials 10 and 9), the tote in full
    view 2.2-2.3 m away: none of its descriptor's starts was near its yaw, and it was found turned by
    ~90 deg, overhanging its footprint by 4 cm (yet within ADD-S's 0.1 d). Turned starts find it
    where it stands (2 cm, 10 deg; a box looks the same turned by a half turn)."""
    lay = demo_layout(where, camera, seed)
    found = {d.object_id: d for d in lay.recognizer.recognize(lay.cloud, world_T_camera=lay.world_T_camera)}
    assert "tote" in found
    T, truth = found["tote"].camera_T_object, lay.truth["tote"]
    turn = np.degrees(rotation_angle(T[:3, :3], truth[:3, :3]))
    assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 0.02 and min(turn, 180.0 - turn) < 10.0, f"{turn:.1f} deg"


@pytest.mark.slow
def test_verification_keeps_the_box_where_it_stands_and_turns_it_down_a_quarter_turned() -> None:
    """The first layout above: the tote posed where it stands agrees with the frame (visible fitness
    well over min_visible_fitness); turned a quarter about its upright axis through its centre, it
    overhangs its footprint, the sensor sees the table through that part, and it falls below."""
    from recognition.verify import DepthView, verdict

    lay = demo_layout(*TOTE_TURNED[0])
    model, cfg = lay.recognizer.db.models["tote"], lay.config
    view = DepthView.of(lay.cloud)
    centre = 0.5 * (model.points.min(axis=0) + model.points.max(axis=0))
    quarter = make_pose(rot_z(np.pi / 2), centre - rot_z(np.pi / 2) @ centre)  # about the object's z through its centre
    fitness = {
        name: verdict(view, model.points, model.normals, T, cfg.icp_distance_m, cfg.plane_noise_per_m2).fitness
        for name, T in (("standing", lay.truth["tote"]), ("turned", lay.truth["tote"] @ quarter))
    }
    assert fitness["standing"] >= 0.94 and fitness["turned"] < cfg.min_visible_fitness, fitness


@pytest.mark.slow
def test_an_object_rests_on_the_table_or_on_an_object_found_under_it() -> None:
    """Nothing in a cell hovers. The tote stacked on the crate is found with it (it rests on the
    found crate); the same tote pose with nothing found under it, 14 cm above the table, is
    rejected; lowered onto the table it rests."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario
    from recognition.hypotheses import Detection
    from recognition.pipeline import support_plane
    from schemas.spec import PoseSpec

    scenario = load_scenario()
    where = {
        "crate": (0.0, 0.0, 0.75, 0.0),
        "can": (0.25, 0.2, 0.75, 0.0),
        "tote": (0.02, 0.01, 0.89, 20.0),
    }  # x, y, z (m), yaw (deg)
    objects = [
        o.still().model_copy(update={"pose": PoseSpec(position=where[o.id][:3], rpy_deg=(0.0, 0.0, where[o.id][3]))})
        for o in scenario.objects
    ]
    scenario = scenario.model_copy(update={"objects": objects})
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    recognizer = Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg)
    frame = SimCell(scenario).render("cam4", 0.0, 0)  # sees the crate's sides under the tote
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    truth = {o.id: invert_pose(frame.world_T_camera) @ o.world_T_object(0.0) for o in objects}
    found = {d.object_id: d for d in recognizer.recognize(cloud, world_T_camera=frame.world_T_camera)}
    assert set(found) == set(truth)
    for oid, det in found.items():
        assert np.linalg.norm(det.camera_T_object[:3, 3] - truth[oid][:3, 3]) < 0.02, oid
    support = support_plane(recognizer.prepare(cloud, frame.world_T_camera).planes, frame.world_T_camera[2, :3])
    assert support is not None

    def posed(oid: str, world_T_object: np.ndarray) -> Detection:
        return Detection(oid, invert_pose(frame.world_T_camera) @ world_T_object, 1.0, 1.0, 0.0, 1000)

    world_T = {o.id: o.world_T_object(0.0) for o in objects}
    tote_up, crate = posed("tote", world_T["tote"]), posed("crate", world_T["crate"])
    assert recognizer.resolver.rests(tote_up, [crate], support)
    assert not recognizer.resolver.rests(tote_up, [], support)
    assert not recognizer.resolver.rests(tote_up, [posed("can", world_T["can"])], support)  # not under it
    down = world_T["tote"] @ make_pose(t=(0.0, 0.0, -0.14))
    assert recognizer.resolver.rests(posed("tote", down), [], support)


@pytest.mark.slow
def test_a_detection_another_camera_sees_through_is_held_back() -> None:
    """The demo cell's four cameras on one layout. What cam2 finds, no other camera contradicts.
    The same objects 20 cm up, over where they stand (a pose no surface there supports): the
    other cameras see the objects and the table behind where they would be, so none is reported; frames older than the age limit judge nothing. A wrong pose outvoting a right one
    (cam2's lifted crate against cam3's true one) is held back and the right one reported."""
    from drivers.sim.render import SimCell
    from recognition.fusion import CameraView, WorldDetection, cross_checked
    from recognition.verify import DepthView

    scenario, recognizer = static_demo(
        {"crate": (-0.15, -0.05, 10.0), "can": (0.18, -0.12, 0.0), "tote": (0.12, 0.2, 80.0)}
    )
    cell = SimCell(scenario)
    frames = {cam.id: cell.render(cam.id, 0.0, 1) for cam in scenario.cameras}
    views = [
        CameraView(c, 0, DepthView.of(depth_to_cloud(f.depth_mm, f.info.K)), f.world_T_camera)
        for c, f in frames.items()
    ]
    f2 = frames["cam2"]
    found = recognizer.recognize(depth_to_cloud(f2.depth_mm, f2.info.K), world_T_camera=f2.world_T_camera)
    assert len(found) >= 2, f"cam2 found {[d.object_id for d in found]}"

    def world(dets, lift: float = 0.0, camera: str = "cam2") -> list[WorldDetection]:
        up = make_pose(t=(0.0, 0.0, lift))
        return [
            WorldDetection(
                camera, 0, up @ frames[camera].world_T_camera @ d.camera_T_object, d, frames[camera].world_T_camera
            )
            for d in dets
        ]

    objects, held = cross_checked(world(found), views, recognizer.seen_through, 10**9)
    assert held == [] and sorted(o.object_id for o in objects) == sorted(d.object_id for d in found)
    objects, held = cross_checked(world(found, 0.2), views, recognizer.seen_through, 10**9)
    assert objects == [] and sorted(h.object_id for h in held) == sorted(d.object_id for d in found)
    assert all(h.camera_id != "cam2" and h.detected_by == ["cam2"] for h in held)
    stale = [replace(v, stamp_ns=3 * 10**9) for v in views]
    assert len(cross_checked(world(found, 0.2), stale, recognizer.seen_through, 2 * 10**9)[0]) == len(found)
    # cam3's crate where it stands, but scored below cam2's lifted one: fused alone, the lifted one wins.
    truth = next(o for o in scenario.objects if o.id == "crate").world_T_object(0.0)
    lifted = next(d for d in world(found, 0.2) if d.detection.object_id == "crate")
    right = WorldDetection(
        "cam3", 0, truth, replace(lifted.detection, rmse_m=2 * lifted.detection.rmse_m), frames["cam3"].world_T_camera
    )
    objects, held = cross_checked([lifted, right], views, recognizer.seen_through, 10**9)
    assert [h.detected_by for h in held] == [["cam2"]]
    assert [o.camera_ids for o in objects] == [["cam3"]]
    np.testing.assert_allclose(objects[0].world_T_object, truth)


def test_standing_starts_put_the_base_on_the_support_below_the_piece() -> None:
    """Every start stands the object upright on the plane (its +z the plane's normal, the centre of
    its lowest points on the plane), under the piece's centroid or half its width further from the
    camera, at 12 different yaws."""
    from recognition.hypotheses import YAW_STEP_DEG, standing_starts

    rng = np.random.default_rng(3)
    model = rng.uniform([-0.12, -0.09, 0.0], [0.12, 0.09, 0.14], (500, 3))  # a crate-sized box's points
    n = np.array([0.0, -0.8, -0.6])  # a table seen from above at 37 deg, normal towards the camera
    support = np.append(n, 1.5)  # 1.5 m from the camera
    near = np.array([0.1, 0.2, 1.8])
    starts = standing_starts(model, near, support)
    assert starts.shape == (2 * 360 // YAW_STEP_DEG, 4, 4)
    lo, hi = model.min(axis=0), model.max(axis=0)
    base = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    feet = starts[:, :3, :3] @ base + starts[:, :3, 3]
    assert np.allclose(starts[:, :3, 2], n) and np.allclose(feet @ n + 1.5, 0.0)
    assert np.allclose(np.einsum("sij,sjk->sik", starts[:, :3, :3].transpose(0, 2, 1), starts[:, :3, :3]), np.eye(3))
    below = near - (near @ n + 1.5) * n
    back = np.linalg.norm(feet - below, axis=1)
    assert np.allclose(back[:12], 0.0) and np.allclose(back[12:], 0.5 * (hi[1] - lo[1]))
    x0, x = starts[0, :3, 0], starts[:12, :3, 0]
    yaw = np.degrees(np.arctan2(np.cross(x0, x) @ n, x @ x0)) % 360  # about the normal, from the first
    assert np.allclose(np.sort(yaw), np.arange(0, 360, YAW_STEP_DEG))


def test_the_display_cloud_covers_what_the_full_cloud_does() -> None:
    """The worker's share of the fused world cloud from a pixel grid: within one 3 cm voxel of 96 %
    of the full frame's voxel points (a grid of every 3rd pixel: 94 %), none off them."""
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario
    from recognition.fusion import display_cloud

    frame = SimCell(load_scenario()).render("cam1", 0.0, 0)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    pts = finite_points(cloud)
    full = voxel_downsample(pts[pts[:, 2] <= 3.5], 0.03)
    shown = display_cloud(cloud, frame.info.K[0, 0], 0.03, 3.5)
    assert len(shown) < len(full)
    covered = PointIndex(shown).nearest(full)[1] <= 0.03**2
    assert covered.mean() >= 0.96, covered.mean()
    assert np.all(PointIndex(full).nearest(shown)[1] <= 0.03**2)


def test_a_look_alike_of_another_colour_is_not_the_model(demo_models: dict) -> None:
    """The demo cell with its red can painted grey: the same depth, so without colour the grey can
    is still a `can`; with the frame's colour, the red model is turned down on it and still found
    on the red one. The crate and the tote keep their colours and are found either way."""
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    red = load_scenario()
    grey = red.model_copy(
        update={
            "objects": [o.model_copy(update={"color": (0.5, 0.5, 0.5)}) if o.id == "can" else o for o in red.objects]
        }
    )
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    recognizer = Recognizer(ModelDatabase(cfg.descriptor, dict(demo_models)), cfg)
    found = {}
    for name, scenario in (("red", red), ("grey", grey)):
        frame = SimCell(scenario).render("cam2", 0.0, 0)
        cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
        for colour in (True, False):
            dets = recognizer.recognize(cloud, world_T_camera=frame.world_T_camera, rgb=frame.rgb if colour else None)
            found[name, colour] = {d.object_id: frame.world_T_camera @ d.camera_T_object for d in dets}
    can = next(o for o in red.objects if o.id == "can").world_T_object(0.0)
    for key in (("red", True), ("red", False), ("grey", False)):
        assert np.linalg.norm(found[key]["can"][:3, 3] - can[:3, 3]) < 0.02, key
    assert "can" not in found["grey", True]
    assert {"crate", "tote"} <= set(found["grey", True]) and {"crate", "tote"} <= set(found["red", True])


def test_floor_and_walls_go_as_planes_and_an_object_face_stays() -> None:
    """remove_planes on a synthetic room seen from the side, sampled as the pipeline's 1 cm voxels
    are: a floor (most of the points), a strip of wall (4.5 %) and a 35 cm box on the floor whose
    faces are planes of 1.8 %. With the largest object's diameter (0.6 m) as the width a further
    plane must exceed, the wall goes and the box stays whole; on a share of the scene alone (the
    rule without it) the wall stays."""
    from recognition.segment import remove_planes

    def grid(a: np.ndarray, b: np.ndarray, step: float) -> np.ndarray:
        return np.stack(np.meshgrid(np.arange(*a, step), np.arange(*b, step)), -1).reshape(-1, 2)

    floor = grid((-1.5, 1.5), (2.5, 4.5), 0.01)
    floor = np.c_[floor[:, 0], np.full(len(floor), 1.0), floor[:, 1]]  # camera y down: the floor 1 m below
    wall = grid((-1.5, 1.5), (-0.1, 0.0), 0.01)
    wall = np.c_[wall, np.full(len(wall), 4.5)]  # the wall's visible strip, facing the camera
    face = grid((-0.175, 0.175), (0.65, 1.0), 0.01)
    box = np.vstack(
        [
            np.c_[face, np.full(len(face), 3.0)],  # front, top and side of a 35 cm box
            np.c_[face[:, 0], np.full(len(face), 0.65), face[:, 1] + 2.35],
            np.c_[np.full(len(face), 0.175), face[:, 1], face[:, 0] + 3.175],
        ]
    )
    points = np.vstack([floor, wall, box]).astype(np.float32)
    n_room = len(floor) + len(wall)
    assert 0.01 < len(face) / len(points) < len(wall) / len(points) < 0.1
    keep, planes = remove_planes(points, 0.012, 4, 0.1, min_extent_m=0.6)  # the box's diameter
    assert len(planes) == 2 and abs(planes[0][1]) > 0.99 and abs(planes[1][2]) > 0.99  # the floor, then the wall
    assert not keep[:n_room].any()
    assert keep[n_room:].mean() > 0.95  # the box's points on the floor's band (its bottom row) go with it
    keep_old, planes_old = remove_planes(points, 0.012, 4, 0.1)
    assert len(planes_old) == 1 and keep_old[len(floor) : n_room].all()


def test_a_model_captured_as_a_cloud_is_found_by_a_localized_camera() -> None:
    """`model build --cloud`: the model's frame is the capturing camera's (cam1's, looking down at
    the table), not one whose +z is up. The upright test of a localized camera must not apply to
    it: cam1's next frame, with its world pose, finds the crate where it was captured (2 cm). (Seen
    from another side, one captured view is another object: cam2 and cam3 place it 9-10 cm off.)"""
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario()
    crate = next(o for o in scenario.objects if o.id == "crate").still()
    scenario = scenario.model_copy(
        update={"objects": [crate], "markers": [m for m in scenario.markers if m.object in (None, "crate")]}
    )
    cell = SimCell(scenario)
    cam1, later = cell.render("cam1", 0.0, 0), cell.render("cam1", 0.0, 1)
    cam1_T_crate = invert_pose(cam1.world_T_camera) @ crate.world_T_object(0.0)
    pts = finite_points(depth_to_cloud(cam1.depth_mm, cam1.info.K))
    local = (pts - cam1_T_crate[:3, 3]) @ cam1_T_crate[:3, :3]  # crate frame: base centre, z up
    half = np.array(crate.size[:2]) / 2 + 0.01
    captured = pts[
        np.all(np.abs(local[:, :2]) < half, axis=1) & (local[:, 2] > 0.01) & (local[:, 2] < crate.size[2] + 0.01)
    ]
    assert abs(cam1.world_T_camera[:3, 2] @ [0, 0, 1]) < 0.9  # cam1's +z, the model's, is far from up
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    assert cfg.upright
    db = ModelDatabase(cfg.descriptor, {})
    db.add(model_from_cloud("crate", captured, cfg.descriptor))
    found = Recognizer(db, cfg).recognize(
        depth_to_cloud(later.depth_mm, later.info.K), world_T_camera=later.world_T_camera
    )
    assert [d.object_id for d in found] == ["crate"]
    centre = db.models["crate"].points.mean(axis=0)  # the model's frame is cam1's: its points ~2 m from the origin
    est = found[0].camera_T_object
    assert np.linalg.norm(est[:3, :3] @ centre + est[:3, 3] - centre) < 0.02


def test_the_support_is_the_level_plane_nearest_the_camera() -> None:
    """A room seen from 2 m up: the floor (removed first), a wall, the table top 0.75 m above the
    floor. The objects stand on the table: the level plane nearest the camera, not the first."""
    from recognition.pipeline import support_plane

    up = np.array([0.0, -1.0, 0.0])  # camera y points down
    floor, wall, table = [0.0, -1.0, 0.0, 2.0], [0.0, 0.0, -1.0, 4.0], [0.0, -1.0, 0.0, 1.25]
    np.testing.assert_allclose(support_plane(np.array([floor, wall, table]), up), table)
    np.testing.assert_allclose(support_plane(np.array([wall, floor]), up), floor)
    assert support_plane(np.array([wall]), up) is None and support_plane(np.array([floor]), None) is None


@pytest.mark.parametrize("stance", ["level_support", "stand_on_level"])
@pytest.mark.slow
def test_a_frame_without_a_pose_finds_what_stands_on_the_table(stance: str) -> None:
    """cam2's demo frame recognised in its own frame, no pose, the room in view: with the plane
    nearest the image's up declared level (`level_support`), or objects tried both free and standing
    on it (`stand_on_level`, the default), every object is found within 2 cm of where it stands
    (tried only free, the crate is not)."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario().still()
    cfg = RecognitionConfig(level_support=stance == "level_support", stand_on_level=stance == "stand_on_level")
    frame = SimCell(scenario).render("cam2", 0.0, 0)
    found = {
        d.object_id: d
        for d in Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg).recognize(
            depth_to_cloud(frame.depth_mm, frame.info.K), rgb=frame.rgb
        )
    }
    assert sorted(found) == sorted(o.id for o in scenario.objects)
    for o in scenario.objects:
        truth = invert_pose(frame.world_T_camera) @ o.world_T_object(0.0)
        assert np.linalg.norm(found[o.id].camera_T_object[:3, 3] - truth[:3, 3]) < 0.02, o.id


@pytest.mark.parametrize("cam", ["cam1", "cam2"])
@pytest.mark.slow
def test_without_a_pose_an_object_in_the_air_is_not_reported(cam: str) -> None:
    """The demo frame with the can lifted 15 cm off the table (as a piece of something else would
    hang there: a can fitted to a leg in a room), recognised in the camera frame, no pose: the level
    plane stands in for the support, and a fit that floats above it with nothing found under it is
    not reported, free or standing. The crate and the tote, on the table, are."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario().still()
    objects = []
    for o in scenario.objects:
        if o.id == "can":
            x, y, z = o.pose.position
            o = o.model_copy(update={"pose": o.pose.model_copy(update={"position": (x, y, z + 0.15)})})
        objects.append(o)
    lifted = scenario.model_copy(update={"objects": objects})
    cfg = RecognitionConfig()
    frame = SimCell(lifted).render(cam, 0.0, 0)
    found = Recognizer(database_from_scenario(lifted, cfg.descriptor), cfg).recognize(
        depth_to_cloud(frame.depth_mm, frame.info.K), rgb=frame.rgb
    )
    assert sorted(d.object_id for d in found) == ["crate", "tote"]


@pytest.mark.parametrize("cam", ["cam1", "cam3"])
@pytest.mark.slow
def test_a_can_found_without_a_pose_is_reported_standing_up(cam: str) -> None:
    """The demo frame on depth alone, no pose: the can's visible top and side fit it upside down as
    well as upright, and the free search ranked the upside-down fit first here by under 1 % (its
    origin, the can's base, then 20 cm up at its top). Between near-equal fits the one resting on
    the table goes first: the can's +z within 10 deg of the true one, its origin within 2 cm."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario().still()
    cfg = RecognitionConfig()
    frame = SimCell(scenario).render(cam, 0.0, 0)
    found = {
        d.object_id: d
        for d in Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg).recognize(
            depth_to_cloud(frame.depth_mm, frame.info.K)
        )
    }
    truth = invert_pose(frame.world_T_camera) @ next(o for o in scenario.objects if o.id == "can").world_T_object(0.0)
    assert "can" in found, sorted(found)
    can = found["can"].camera_T_object
    assert can[:3, 2] @ truth[:3, 2] > np.cos(np.radians(10.0)), "the can is reported upside down"
    assert np.linalg.norm(can[:3, 3] - truth[:3, 3]) < 0.02


@pytest.mark.slow
def test_a_free_fit_found_upside_down_is_reported_upright_when_the_frame_holds_it_so() -> None:
    """The demo frame from cam3: the can's true pose turned upside down about its centre, as a free
    candidate (no stance), beside the crate resting on the table (which gives the frame's up). A can
    fits its frame upside down as well: the upright reading is judged first and reported; the
    upside-down one would pass verification too."""
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario
    from recognition.hypotheses import Candidate, Detection, Stance
    from recognition.pipeline import support_plane
    from recognition.verify import DepthView

    scenario = load_scenario().still()
    cfg = RecognitionConfig()
    frame = SimCell(scenario).render("cam3", 0.0, 0)
    recognizer = Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    camera_T_world = invert_pose(frame.world_T_camera)
    truth = {o.id: camera_T_world @ o.world_T_object(0.0) for o in scenario.objects}
    up = camera_T_world[:3, 2]
    scene = recognizer.prepare(cloud, None)
    centre = recognizer.db.models["can"].points.mean(axis=0)
    half_turn = np.diag([1.0, -1.0, -1.0])  # about the can's x axis
    flipped = truth["can"] @ make_pose(half_turn, centre - half_turn @ centre)
    free = Candidate(0, None, Detection("can", flipped, 1.0, 1.0, 0.0, 1000), Stance(None, None))
    crate = Candidate(
        1, None, Detection("crate", truth["crate"], 1.0, 1.0, 0.0, 1000), Stance(up, support_plane(scene.planes, up))
    )
    found = {d.object_id: d for d in recognizer.resolver.resolve([free, crate], DepthView.of(cloud), scene, [])}
    assert set(found) == {"can", "crate"}
    can = found["can"].camera_T_object
    assert can[:3, 2] @ truth["can"][:3, 2] > np.cos(np.radians(10.0)), "the can is reported upside down"
    assert np.linalg.norm(can[:3, 3] - truth["can"][:3, 3]) < 0.02


def test_a_can_looks_the_same_turned_about_its_axis_and_a_mug_or_a_box_does_not(
    demo_models: dict, tmp_path: Path
) -> None:
    """Which objects the resolution tries turned about their upright axis (``round_about_z``, at
    the models' 1 cm voxel): the demo can and the cone are round; the mug (its handle), the tote
    and the crate (a box turned by 30 deg) are not."""
    from drivers.sim.render import object_mesh
    from drivers.sim.shapes import shapes
    from recognition.hypotheses import round_about_z

    voxel = RecognitionConfig().descriptor.voxel_m
    models = {oid: m.points for oid, m in demo_models.items()}
    models |= {
        o.id: model_from_mesh(o.id, object_mesh(o), DescriptorConfig()).points
        for o in shapes(tmp_path)
        if o.id in ("mug", "cone")
    }
    assert {oid for oid, points in models.items() if round_about_z(points, voxel)} == {"can", "cone"}


def test_a_mug_whose_handle_the_frame_hides_is_taken_turned_to_hide_it(tmp_path: Path) -> None:
    """The mug (``drivers.sim.shapes``: a can and a ring handle) alone on the table 1 m from cam3, its
    handle behind its body. A standing candidate with the handle turned a quarter to the side, where
    the sensor sees the table past the body, is turned down as it stands (visible fitness under
    ``min_visible_fitness``); the resolution judges it turned about its upright axis, each turn
    fitted to the frame's depth, and takes the one the sensor sees through least, its red judged:
    the handle back behind the body (within 30 deg of the true one), ADD-S under 0.1 d."""
    from cellsight.evaluation.bop import adds_m
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario
    from drivers.sim.shapes import shapes
    from recognition.hypotheses import Candidate, Detection, Stance
    from recognition.pipeline import support_plane
    from recognition.verify import DepthView, verdict
    from schemas.spec import PoseSpec

    base = load_scenario()
    camera = next(c for c in base.cameras if c.id == "cam3").moved_in(0.8, 1.25, (0.0, 0.0, 0.8))
    at = np.array([0.05, -0.05])
    away = at - np.array(camera.pose.position[:2])  # the handle (the mug's +x) points away from the camera
    mug = next(o for o in shapes(tmp_path) if o.id == "mug").still()
    mug = mug.model_copy(
        update={
            "pose": PoseSpec(position=(*at, 0.75), rpy_deg=(0.0, 0.0, float(np.degrees(np.arctan2(away[1], away[0])))))
        }
    )
    scenario = base.model_copy(
        update={"objects": [mug], "cameras": [camera], "markers": [m for m in base.markers if m.object is None]}
    )
    cfg = RecognitionConfig()
    model = model_from_mesh("mug", object_mesh(mug).paint_uniform_color(mug.color), cfg.descriptor)
    recognizer = Recognizer(ModelDatabase(cfg.descriptor, {"mug": model}), cfg)
    frame = SimCell(scenario).render(camera.id, 0.0, 0)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    camera_T_world = invert_pose(frame.world_T_camera)
    truth, up = camera_T_world @ mug.world_T_object(0.0), camera_T_world[:3, 2]
    quarter = rot_z(np.radians(90.0))
    sideways = truth @ make_pose(quarter, model.centre - quarter @ model.centre)
    view = DepthView.of(cloud, frame.rgb)
    as_it_stands = verdict(
        view,
        model.points,
        model.normals,
        sideways,
        cfg.icp_distance_m,
        cfg.plane_noise_per_m2,
        spacing_m=cfg.descriptor.voxel_m,
    )
    assert as_it_stands.fitness < cfg.min_visible_fitness and as_it_stands.violations > 0
    scene = recognizer.prepare(cloud, None)
    candidate = Candidate(
        0, None, Detection("mug", sideways, 1.0, 1.0, 0.0, 1000), Stance(up, support_plane(scene.planes, up))
    )
    found = recognizer.resolver.resolve([candidate], view, scene, [])
    assert [d.object_id for d in found] == ["mug"] and found[0].needs_colour
    handle, true_handle = found[0].camera_T_object[:3, 0], truth[:3, 0]
    assert handle @ true_handle > np.cos(np.radians(30.0)), "the handle is not behind the body"
    assert adds_m(model.points, found[0].camera_T_object, truth) < 0.1 * model.diameter_m


@pytest.mark.slow
def test_a_curved_object_open3ds_steps_run_off_is_found_by_damped_ones_and_its_colour(tmp_path: Path) -> None:
    """The duck (``drivers.sim.shapes``: two spheres and a beak, 15 cm) alone on the table, seen
    from cam3 ~2 m away: Open3D's steps lose it (nothing they screen passes). The start with the
    most overlap is screened again with damped steps, and with the frame's colour judged on it the
    duck is found within ADD-S 0.1 d (of the four shapes' database)."""
    from cellsight.evaluation.bop import adds_m
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario
    from drivers.sim.shapes import shapes
    from schemas.spec import PoseSpec

    objects = shapes(tmp_path)
    duck = next(o for o in objects if o.id == "duck")
    duck = duck.still().model_copy(update={"pose": PoseSpec(position=(0.218, 0.095, 0.75), rpy_deg=(0.0, 0.0, 1.0))})
    base = load_scenario()
    scenario = base.model_copy(update={"objects": [duck], "markers": [m for m in base.markers if m.object is None]})
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    meshes = {o.id: object_mesh(o).paint_uniform_color(o.color) for o in objects}
    db = ModelDatabase(
        cfg.descriptor, {oid: model_from_mesh(oid, mesh, cfg.descriptor) for oid, mesh in meshes.items()}
    )
    model = db.models["duck"]
    recognizer = Recognizer(db, cfg)
    frame = SimCell(scenario).render("cam3", 0.0, 3)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    truth = invert_pose(frame.world_T_camera) @ duck.world_T_object(0.0)
    found = recognizer.recognize(cloud, world_T_camera=frame.world_T_camera, rgb=frame.rgb)
    assert [d.object_id for d in found] == ["duck"] and found[0].needs_colour
    assert adds_m(model.points, found[0].camera_T_object, truth) < 0.1 * model.diameter_m


@pytest.mark.slow
def test_on_depth_alone_a_shape_another_fits_as_well_is_not_reported_as_that_other(tmp_path: Path) -> None:
    """The duck (``drivers.sim.shapes``) alone on the table, seen from cam1 ~2 m away without
    colour, the four shapes in the database: at that range the cone's fit, ranked first, verifies
    on the duck's pixels too. Of two objects that verification accepts on the same pixels, one is
    taken only if it explains half as many again: the duck, or nothing, never the cone."""
    from cellsight.evaluation.bop import adds_m
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario
    from drivers.sim.shapes import shapes
    from schemas.spec import PoseSpec

    objects = shapes(tmp_path)
    duck = next(o for o in objects if o.id == "duck")
    duck = duck.still().model_copy(update={"pose": PoseSpec(position=(-0.162, 0.109, 0.75), rpy_deg=(0.0, 0.0, 195.0))})
    base = load_scenario()
    scenario = base.model_copy(update={"objects": [duck], "markers": [m for m in base.markers if m.object is None]})
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    meshes = {o.id: object_mesh(o).paint_uniform_color(o.color) for o in objects}
    db = ModelDatabase(
        cfg.descriptor, {oid: model_from_mesh(oid, mesh, cfg.descriptor) for oid, mesh in meshes.items()}
    )
    frame = SimCell(scenario).render("cam1", 0.0, 5)
    truth = invert_pose(frame.world_T_camera) @ duck.world_T_object(0.0)
    found = Recognizer(db, cfg).recognize(
        depth_to_cloud(frame.depth_mm, frame.info.K), world_T_camera=frame.world_T_camera
    )
    assert [d.object_id for d in found] in ([], ["duck"])
    for d in found:
        assert adds_m(db.models["duck"].points, d.camera_T_object, truth) < 0.1 * db.models["duck"].diameter_m


def found_packed(
    where: dict[str, tuple[float, float, float]],
    unknown: list[tuple[str, tuple, float, float, float]],
    camera: str,
    seed: int,
    object_id: str,
) -> tuple[bool, float]:
    """The demo objects at ``where`` (x, y m, yaw deg on the table) among objects no database holds
    (shape, size m, x, y, yaw: grey boxes, grey-green cylinders, as ``benchmarks.recognition``'s
    distractors), rendered from ``camera`` with noise ``seed`` and recognised with colour: whether
    ``object_id`` was found, and its ADD-S over its diameter (inf if not)."""
    from cellsight.evaluation.bop import adds_m
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import ObjectSpec, load_scenario
    from schemas.spec import PoseSpec

    base = load_scenario().still()
    objects = [
        o.model_copy(update={"pose": PoseSpec(position=(*where[o.id][:2], 0.75), rpy_deg=(0.0, 0.0, where[o.id][2]))})
        for o in base.objects
    ]
    for i, (shape, size, x, y, yaw) in enumerate(unknown):
        pose = PoseSpec(position=(x, y, 0.75), rpy_deg=(0.0, 0.0, yaw))
        grey = (0.5, 0.5, 0.5) if shape == "box" else (0.4, 0.5, 0.4)
        objects.append(ObjectSpec(id=f"unknown{i}", shape=shape, size=size, color=grey, pose=pose))
    scenario = base.model_copy(update={"objects": objects, "markers": [m for m in base.markers if m.object is None]})
    cfg = RecognitionConfig(workspace_min=(-0.6, -0.4, 0.7), workspace_max=(0.6, 0.4, 1.3))
    recognizer = Recognizer(database_from_scenario(base, cfg.descriptor), cfg)
    frame = SimCell(scenario).render(camera, 0.0, seed)
    obj = next(o for o in objects if o.id == object_id)
    truth = invert_pose(frame.world_T_camera) @ obj.world_T_object(0.0)
    model = recognizer.db.models[object_id]
    found = {
        d.object_id: d
        for d in recognizer.recognize(
            depth_to_cloud(frame.depth_mm, frame.info.K), world_T_camera=frame.world_T_camera, rgb=frame.rgb
        )
    }
    if object_id not in found:
        return False, np.inf
    return True, adds_m(model.points, found[object_id].camera_T_object, truth) / model.diameter_m


@pytest.mark.slow
def test_an_object_partly_hidden_by_one_no_database_holds_is_found_with_its_colour() -> None:
    """The demo objects packed on the table with four grey boxes no database holds, seen from cam3:
    a 29 cm box stands between the camera and the can and hides most of its visible surface.
    What a cluster apart from the surface a hypothesis explains hides in front of it is no evidence
    against it once its colour is judged: the can is found within ADD-S 0.1 d."""
    where = {"crate": (-0.078, 0.116, 352.8), "can": (0.064, -0.151, 240.8), "tote": (0.275, 0.188, 24.5)}
    unknown = [
        ("box", (0.05, 0.068, 0.288), 0.192, -0.053, 65.3),
        ("box", (0.089, 0.114, 0.246), 0.314, -0.124, 47.3),
        ("box", (0.095, 0.058, 0.21), -0.268, -0.18, 347.8),
        ("box", (0.111, 0.111, 0.257), -0.279, 0.149, 170.5),
    ]
    found, error = found_packed(where, unknown, "cam3", 4, "can")
    assert found and error < 0.1, (found, error)


@pytest.mark.slow
def test_a_small_object_merged_with_a_larger_one_is_tried_where_its_colour_shows() -> None:
    """The demo objects packed with four grey boxes no database holds, seen from cam3: the can
    shares its cluster with a box beside it (half the cluster), its descriptor no object's, and
    the pieces path's balls around seeds spread over the cluster centre on neither. Where the
    cluster shows the can's red, a colour no grey surface has, a piece is tried on its own
    (``Matcher._colour_seeds``): the can is found within ADD-S 0.1 d (missed without)."""
    where = {"crate": (-0.139, -0.042, 106.5), "can": (0.163, 0.114, 178.4), "tote": (0.275, -0.167, 6.0)}
    unknown = [
        ("box", (0.088, 0.075, 0.189), -0.234, 0.165, 156.2),
        ("box", (0.1, 0.103, 0.177), -0.309, -0.102, 186.6),
        ("box", (0.098, 0.059, 0.231), 0.301, 0.194, 250.9),
        ("box", (0.099, 0.094, 0.176), 0.022, 0.083, 59.7),
    ]
    found, error = found_packed(where, unknown, "cam3", 3, "can")
    assert found and error < 0.1, (found, error)


@pytest.mark.slow
def test_an_object_packed_among_others_no_database_holds_is_found_refitted_to_the_depth() -> None:
    """The demo objects packed on the table with two grey boxes and two cylinders no database
    holds, seen from cam2: the tote, half hidden, shares its cluster with its neighbours and the fit
    to it ends a few cm off, which verification refuses. Refitted to the frame's depth on each model
    point's own ray, its colour judged, the tote is found within ADD-S 0.1 d."""
    where = {"crate": (0.235, 0.025, 347.3), "can": (-0.314, -0.063, 276.9), "tote": (-0.069, -0.056, 258.8)}
    unknown = [
        ("cylinder", (0.037, 0.037, 0.24), -0.266, 0.144, 315.5),
        ("box", (0.069, 0.099, 0.175), 0.241, -0.143, 225.0),
        ("box", (0.104, 0.085, 0.261), 0.095, -0.177, 88.0),
        ("cylinder", (0.035, 0.035, 0.2), 0.058, 0.158, 252.4),
    ]
    found, error = found_packed(where, unknown, "cam2", 2, "tote")
    assert found and error < 0.1, (found, error)


@pytest.mark.slow
def test_a_can_whose_colour_vouches_for_it_stands_beside_an_unknown_box_in_its_cluster() -> None:
    """The demo objects packed with four objects no database holds, seen from cam2: the red can,
    in full view, shares its cluster with a grey box beside it and explains half of it. The rule
    for a match alone in its cluster (a shape fitting a piece of a larger surface) would refuse it;
    its colour, one no grey surface has, vouches for it, and it is found within ADD-S 0.1 d."""
    where = {"crate": (0.115, 0.152, 171.4), "can": (0.263, -0.1, 96.1), "tote": (-0.272, 0.091, 300.4)}
    unknown = [
        ("cylinder", (0.044, 0.044, 0.223), -0.257, -0.181, 292.2),
        ("box", (0.118, 0.057, 0.239), 0.114, -0.065, 337.5),
        ("cylinder", (0.06, 0.06, 0.292), 0.014, -0.174, 43.1),
        ("box", (0.081, 0.075, 0.151), -0.109, -0.143, 229.5),
    ]
    found, error = found_packed(where, unknown, "cam2", 2, "can")
    assert found and error < 0.1, (found, error)


def test_with_free_with_pose_an_object_not_standing_on_its_base_is_found_in_a_posed_frame(tmp_path: Path) -> None:
    """The cone (``drivers.sim.shapes``) lying on its side, its model's +z level, seen by a camera
    whose world pose is known, as a dataset's frame may be: the cell's reading (every object stands
    on its +z) finds nothing; with ``free_with_pose`` it is also tried any way up, resting on the
    table, and found within ADD-S 0.1 d."""
    from cellsight.evaluation.bop import adds_m
    from drivers.sim.render import SimCell, object_mesh
    from drivers.sim.scenario import load_scenario
    from drivers.sim.shapes import shapes
    from schemas.spec import PoseSpec

    cone = next(o for o in shapes(tmp_path) if o.id == "cone")
    lying = PoseSpec(position=(0.05, 0.02, 0.75 + 0.045), rpy_deg=(90.0, 0.0, 30.0))  # on its side: 4.5 cm base radius
    cone = cone.still().model_copy(update={"pose": lying})
    base = load_scenario()
    close = [c.moved_in(0.8, 1.25, (0.0, 0.0, 0.8)) for c in base.cameras]
    scenario = base.model_copy(
        update={"objects": [cone], "markers": [m for m in base.markers if m.object is None], "cameras": close}
    )
    cfg = RecognitionConfig()
    model = model_from_mesh("cone", object_mesh(cone).paint_uniform_color(cone.color), cfg.descriptor)
    frame = SimCell(scenario).render("cam1", 0.0, 1)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    truth = invert_pose(frame.world_T_camera) @ cone.world_T_object(0.0)
    found = {}
    for free in (False, True):
        options = cfg.model_copy(update={"free_with_pose": free})
        recognizer = Recognizer(ModelDatabase(cfg.descriptor, {"cone": model}), options)
        found[free] = recognizer.recognize(cloud, world_T_camera=frame.world_T_camera, rgb=frame.rgb)
    assert found[False] == []
    assert [d.object_id for d in found[True]] == ["cone"]
    assert adds_m(model.points, found[True][0].camera_T_object, truth) < 0.1 * model.diameter_m


def test_a_fit_only_damped_steps_reached_is_taken_only_with_its_colour_judged(demo_models: dict) -> None:
    """The demo frame from cam3, the crate at its true pose as a candidate that only damped steps
    reached (``Detection.needs_colour``): taken when the frame's colour is judged on it, not on
    depth alone, where the same candidate otherwise is."""
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario
    from recognition.hypotheses import Candidate, Detection, Stance
    from recognition.pipeline import support_plane
    from recognition.verify import DepthView

    scenario = load_scenario().still()
    cfg = RecognitionConfig()
    frame = SimCell(scenario).render("cam3", 0.0, 0)
    recognizer = Recognizer(ModelDatabase(cfg.descriptor, dict(demo_models)), cfg)
    cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
    camera_T_world = invert_pose(frame.world_T_camera)
    crate = next(o for o in scenario.objects if o.id == "crate")
    scene = recognizer.prepare(cloud, None)
    up = camera_T_world[:3, 2]
    stance = Stance(up, support_plane(scene.planes, up))

    def taken(needs_colour: bool, view: DepthView) -> bool:
        pose = camera_T_world @ crate.world_T_object(0.0)
        det = Detection("crate", pose, 1.0, 1.0, 0.0, 1000, needs_colour=needs_colour)
        return bool(recognizer.resolver.resolve([Candidate(0, None, det, stance)], view, scene, []))

    assert taken(True, DepthView.of(cloud, frame.rgb))
    assert taken(False, DepthView.of(cloud)) and not taken(True, DepthView.of(cloud))


@pytest.mark.parametrize("cam, object_id", [("cam1", "tote"), ("cam3", "crate")])
@pytest.mark.slow
def test_an_object_cut_in_half_by_the_frame_border_is_found(cam: str, object_id: str) -> None:
    """The demo frame cut at the object's centre column, the left part kept: half of the object's
    facing surface lies beyond the border, where no camera could see it. Looked for only inside the
    image, the half in it is enough (counted over the whole object, it explained too little)."""
    from cellsight.evaluation.bop import ADDS_SHARE, adds_m
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario().still()
    cfg = RecognitionConfig()
    recognizer = Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg)
    frame = SimCell(scenario).render(cam, 0.0, 0)
    obj = next(o for o in scenario.objects if o.id == object_id)
    truth = invert_pose(frame.world_T_camera) @ obj.world_T_object(0.0)
    model = recognizer.db.models[object_id]
    centre = truth[:3, :3] @ model.points.mean(axis=0) + truth[:3, 3]
    cut = int(frame.info.K[0, 0] * centre[0] / centre[2] + frame.info.K[0, 2])
    assert 0 < cut < frame.depth_mm.shape[1]
    depth, rgb = np.ascontiguousarray(frame.depth_mm[:, :cut]), np.ascontiguousarray(frame.rgb[:, :cut])
    found = {
        d.object_id: d
        for d in recognizer.recognize(depth_to_cloud(depth, frame.info.K), world_T_camera=frame.world_T_camera, rgb=rgb)
    }
    assert object_id in found, sorted(found)
    assert adds_m(model.points, found[object_id].camera_T_object, truth) < ADDS_SHARE * model.diameter_m


@pytest.mark.parametrize("cam_id", ["cam2", "cam4"])
@pytest.mark.slow
def test_objects_lying_on_their_side_are_found_in_a_close_frame_without_a_pose(cam_id: str) -> None:
    """The demo's objects each laid on a side (a quarter turn about its x axis), seen from 0.8 m in
    the camera's own frame with colour: tried lying on the level plane on each side
    (`rest_on_sides`), every one is found within ADD-S 0.1 d (tried only free and standing, cam2's
    tote and cam4's can were not)."""
    from cellsight.evaluation.bop import ADDS_SHARE, adds_m
    from cellsight.model_build import database_from_scenario
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    scenario = load_scenario()
    places = {"crate": (-0.2, 0.05, 0.0), "can": (0.05, -0.1, 90.0), "tote": (0.25, 0.1, 20.0)}  # x, y (m), yaw (deg)
    objects = [o.laid_on_side(places[o.id][:2], places[o.id][2], 0.75) for o in scenario.objects]
    close = next(c for c in scenario.cameras if c.id == cam_id).moved_in(0.8, 1.25, (0.0, 0.0, 0.8))
    scenario = scenario.model_copy(update={"objects": objects, "cameras": [close]})
    cfg = RecognitionConfig()
    recognizer = Recognizer(database_from_scenario(scenario, cfg.descriptor), cfg)
    frame = SimCell(scenario).render(close.id, 0.0, 0)
    found = {d.object_id: d for d in recognizer.recognize(depth_to_cloud(frame.depth_mm, frame.info.K), rgb=frame.rgb)}
    for o in objects:
        truth = invert_pose(frame.world_T_camera) @ o.world_T_object(0.0)
        model = recognizer.db.models[o.id]
        assert o.id in found, sorted(found)
        assert adds_m(model.points, found[o.id].camera_T_object, truth) < ADDS_SHARE * model.diameter_m, o.id


def test_sides_alike_are_tried_once() -> None:
    """A can lain on any of its four sides shows one shape, a box two (on +-x, on +-y), and a box
    with a block on one end of its +x face four: only the first side of each kind is tried.
    Surfaces sampled at 5 mm, the model's 1 cm voxel judging them."""
    from recognition.hypotheses import ALIKE_VOXELS, RESTS, distinct_rests

    def surface(mesh: o3d.geometry.TriangleMesh) -> np.ndarray:
        o3d.utility.random.seed(0)
        return np.asarray(mesh.sample_points_uniformly(20000).voxel_down_sample(0.005).points)

    can = o3d.geometry.TriangleMesh.create_cylinder(0.06, 0.2, resolution=60)
    box = o3d.geometry.TriangleMesh.create_box(0.24, 0.18, 0.14).translate((-0.12, -0.09, 0.0))
    block = o3d.geometry.TriangleMesh.create_box(0.04, 0.06, 0.05).translate((0.12, 0.0, 0.0))
    tol = ALIKE_VOXELS * RecognitionConfig().descriptor.voxel_m  # as the matcher judges them
    assert len(distinct_rests(surface(can), tol)) == 1
    kinds = distinct_rests(surface(box), tol)
    assert len(kinds) == 2 and np.array_equal(kinds[0], RESTS[0]) and np.array_equal(kinds[1], RESTS[2])
    assert len(distinct_rests(surface(box + block), tol)) == 4


@pytest.mark.slow
def test_a_recognition_picture_draws_the_found_object_where_the_scene_shows_it(
    tmp_path: Path, milk: np.ndarray
) -> None:
    """``cellsight recognize --picture`` on PCL's real milk scene: what it draws over the scene's colour
    covers the carton's true silhouette (the model was cut from the scene: its pose is the identity)
    and little else (the label above it); an annotated pose alone is outlined in white round it; a
    scene where nothing is found comes back as its colour alone; a picture file of another kind is
    refused before recognition runs."""
    from typer.testing import CliRunner

    from cellsight.cli import app
    from cellsight.evaluation.pictures import draw_recognition
    from recognition.verify import VIRTUAL_K, VIRTUAL_SIZE

    db = tmp_path / "db"
    assert (
        CliRunner().invoke(app, ["model", "build", "--out", str(db), "--cloud", f"milk={PCL / 'milk.pcd'}"]).exit_code
        == 0
    )
    scene = PCL / "milk_cartoon_all_small_clorox.pcd"
    picture = tmp_path / "found.png"
    result = CliRunner().invoke(
        app, ["recognize", "--models", str(db), "--scene", str(scene), "--picture", str(picture), "--json"]
    )
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["picture"] == str(picture)
    cloud, rgb = read_coloured_cloud(scene, organised=True)
    drawn = np.any(cv2.imread(str(picture)) != rgb[..., ::-1], axis=2)
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])  # the scene's (data README)
    uv = np.round(milk @ K.T / milk[:, 2:]).astype(int)[:, :2]
    truth = np.zeros(drawn.shape, np.uint8)
    truth[uv[:, 1], uv[:, 0]] = 1
    truth = cv2.morphologyEx(truth, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)) > 0
    near_truth = cv2.dilate(truth.astype(np.uint8), np.ones((11, 11), np.uint8)) > 0
    assert (drawn & truth).sum() >= 0.9 * truth.sum()
    label = 100 * 25  # the id and fitness on their box, px
    assert (drawn & ~near_truth).sum() <= label, (drawn & ~near_truth).sum()
    models = ModelDatabase.load(db)
    outlined = draw_recognition(cloud, rgb, [], models, truth=[("milk", np.eye(4))])
    changed = np.any(outlined != rgb[..., ::-1], axis=2)
    assert np.all(outlined[changed] == 255) and changed.sum() > 300  # one white line round the carton
    deep_inside = cv2.erode(truth.astype(np.uint8), np.ones((11, 11), np.uint8)) > 0
    assert (changed & near_truth & ~deep_inside).sum() >= 0.95 * changed.sum()
    # The same scene as a list of points: drawn as verification's virtual camera sees it.
    points, colours = cloud.reshape(-1, 3), rgb.reshape(-1, 3)
    listed = draw_recognition(points, colours, [], models, truth=[("milk", np.eye(4))])
    drawn_on = np.argwhere(np.any(listed != draw_recognition(points, colours, [], models), axis=2))[:, ::-1]  # (u, v)
    v_uv = np.round(milk @ VIRTUAL_K.T / milk[:, 2:]).astype(int)[:, :2]
    assert listed.shape == (*VIRTUAL_SIZE, 3) and len(drawn_on) > 100
    assert np.all((drawn_on >= v_uv.min(axis=0) - 8) & (drawn_on <= v_uv.max(axis=0) + 8))
    empty = tmp_path / "nothing.png"
    office = PCL / "office1.pcd"
    result = CliRunner().invoke(
        app, ["recognize", "--models", str(db), "--scene", str(office), "--picture", str(empty)]
    )
    assert result.exit_code == 1  # nothing found
    _, office_rgb = read_coloured_cloud(office, organised=True)
    np.testing.assert_array_equal(cv2.imread(str(empty)), office_rgb[..., ::-1])
    result = CliRunner().invoke(
        app, ["recognize", "--models", str(db), "--scene", str(scene), "--picture", str(tmp_path / "p.txt")]
    )
    assert result.exit_code == 1 and "p.txt: give a file ending in .png or .jpg" in " ".join(result.output.split())
