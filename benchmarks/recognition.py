"""Object recognition on the simulated cell: ADD-S recall and BOP's MSSD, unoccluded and partly occluded.

Each trial places the demo cell's objects (crate, can, tote) at random non-overlapping positions and
yaws on the table (every other trial crowded together, so that they hide one another) and renders every camera (Kinect noise model). Each (camera, object) pair is
classed by the share of the object's own silhouette that is visible: unoccluded >= 95 %, partly
occluded 40-95 %, and below 40 % not scored. The recogniser gets the camera's true world pose (the
estimator's job, measured elsewhere) for the workspace crop and the upright test.

Scores: ADD-S (mean distance to the closest model point) correct below 0.1 x diameter; MSSD (BOP:
max surface distance, minimised over the shape's symmetries) averaged over BOP's thresholds 0.05 ..
0.5 x diameter (AR_MSSD). A missed object scores as wrong. The same frames are run with PCL 1.7's
VFH binning (the paper's) as the reference.

Real scenes: the demo objects and PCL's milk.pcd (as ``cellsight model build --demo --cloud
milk=...``) against every real scene in ``data/pcl/`` (Kinect frames, one stereo pair):
the milk found in its scene (true pose the identity) with its model-to-scene RMSE, and every other
detection counted false (``false_positives_real_scenes``; none of the other scenes holds any of the
objects).

Baseline: point-pair-feature voting (Drost et al. 2010, ``benchmarks.ppf``) on the same frames,
after the same preparation (range, workspace, voxels, planes off, normals): each model's three
best-voted pose clusters refined by the same ICP, the best-fitting one reported, scored the same
way (``ppf_*``). Its time per frame includes the preparation, as ours does.

False detections in the simulated cell: any detection whose ADD-S is 0.1 x diameter or more from
the object's true pose, per rendered frame (``false_positives_per_frame_sim``).

Fused cameras (``adds_recall_fused``): what the recognition worker publishes, each camera's
detections put in world by its pose, fused, and held back where another camera's frame saw
through them (``recognition.fusion.cross_checked``), scored for every object partly occluded in
at least one camera of its trial; a fused object that is wrong counts in
``false_positives_per_trial_fused``, a right one held back in ``fused_held_back_right``. The
fused objects are then each fitted to every camera's points around it, as the worker does with
``[recognition] refine_in_cloud`` (``recognition.fusion.refined_in_cloud``): ``fused_position_error_mm_*`` against
``..._unrefined`` (the fused detections before the fit), over every fused object. What the
check catches: every correct detection moved 20 cm (up, or sideways along either table axis) and
judged by the trial's other cameras, the share held back (``cross_view_caught_moved``). In the
demo cell every object is unoccluded in some camera of its trial, so the same fusion is also run
for every pair of cameras alone, scored for the objects partly occluded in both
(``adds_recall_fused_pairs``; wrong objects any pair publishes in ``false_positives_fused_pairs``).
Recognition in the cameras' points together (``recognition.fusion.found_in_cloud``): every camera's
workspace points put in one camera's frame and recognised there, verified by that camera's frame,
for every object at least 40 % visible in some camera (``adds_recall_fused_cloud``, wrong ones in
``false_detections_fused_cloud``, before any cross-check); the worker searches so only for objects
no camera found, and what that adds to the published objects is ``fused_cloud_added`` (and in the
fused and distractor figures).

Distractors (``false_positives_per_trial_distractors``): the cell with one of its objects taken away
(each in turn) and four objects that are in no database put on the table with the others: boxes of
5-12 cm x 5-12 cm x 12-30 cm and cylinders of 3-6 cm radius and 12-30 cm height, every one of them
shaped like the database's can or crate or like neither. A published object that is not on the
table, and so is one of the objects on it published away from its true pose (ADD-S 0.1 x diameter
or more); ``false_detections_per_frame_distractors`` counts them per camera before fusion. A real
cell holds many things besides its models: some of these the sensor's depth alone cannot tell apart
from a model (a can of 12 cm fits a 6 x 12 cm box within the depth noise at 2 m). The distractors
are grey; the same frames are run without colour too (``..._depth_only``).

Clutter (``adds_recall_partly_occluded_clutter``, ``..._unoccluded_clutter``): all three objects
packed with 1.5 cm gaps among four such objects over 0.7 of the table (24 layouts; 2 with
``--quick``), every camera with colour, scored per camera as the main pass; wrong or absent
objects reported in ``false_detections_per_frame_clutter``. What hides an object there is mostly
something no database holds, as on a real table.

A rougher sensor (``adds_recall_unoccluded_rough``, ``..._partly_occluded_rough``,
``false_detections_per_frame_rough``): random layouts (12; 2 with ``--quick``) rendered twice, as
the cell's Kinects give them and by a sensor with what the simulated Kinect lacks and real ones
show: mixed depths at the depth jumps where the Kinect returns none (flying pixels, as a
time-of-flight camera gives), a white balance off (red x 1.15 and blue x 0.85 in every other layout,
the other way round in the rest), colours washed out to 0.7 of their saturation and registered 3 px
off the depth (``NoiseSpec``); both scored per camera as the main pass, the first as
``..._as_rendered`` beside it (the same frames: the difference is the sensor's).

Latency: one 640x480 frame of the demo cell (3 objects) from depth image to detections
(``depth_to_cloud`` + ``Recognizer.recognize``), on one core: the process is pinned to one CPU and
its OpenMP / BLAS pools to one thread before they start.

``--quick`` (within a minute): 2 trials of the main pass, of the distractors, of the clutter and of
the rougher sensor, the baseline on every other frame (``ppf_frames``).
"""

from __future__ import annotations

import os

# One core, pinned before numpy and Open3D start their thread pools (threads inherit the mask, and
# Open3D's parallel reductions are then also repeatable run to run).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import itertools  # noqa: E402
import re  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

from benchmarks import ppf  # noqa: E402
from benchmarks.common import PCL_DATA, main  # noqa: E402
from cellsight.evaluation.bop import adds_m  # noqa: E402
from cellsight.model_build import database_from_scenario  # noqa: E402
from drivers.sim.render import SimCell, SimFrame, object_mesh  # noqa: E402
from drivers.sim.scenario import ObjectSpec, Scenario, apart, footprint, load_scenario  # noqa: E402
from recognition.align import Surface, model_to_scene_rmse, refine_icp, rot_z  # noqa: E402
from recognition.cloud import (  # noqa: E402
    camera_rays,
    depth_to_cloud,
    finite_points,
    read_cloud,
    read_coloured_cloud,
    voxel_downsample,
)
from recognition.config import DescriptorConfig, RecognitionConfig  # noqa: E402
from recognition.fusion import (  # noqa: E402
    REFINE_VOXEL_M,
    CameraPoints,
    CameraView,
    FusedObject,
    WorldDetection,
    cross_checked,
    found_in_cloud,
    refined_in_cloud,
)
from recognition.models import model_from_cloud  # noqa: E402
from recognition.pipeline import Recognizer  # noqa: E402
from recognition.verify import DepthView  # noqa: E402
from schemas.geometry import invert_pose, make_pose  # noqa: E402
from schemas.spec import PoseSpec  # noqa: E402

TABLE_HALF = (0.45, 0.28)  # where object centres may go on the demo table, m
WORKSPACE = ((-0.6, -0.4, 0.7), (0.6, 0.4, 1.3))
UNOCCLUDED, SCORED = 0.95, 0.40
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)


@dataclass
class PpfBaseline:
    """Drost et al.'s voting, then ICP: each model's best pose in a frame (camera_T_object)."""

    rec: Recognizer
    trained: dict[str, ppf.PpfModel]

    @classmethod
    def of(cls, rec: Recognizer) -> PpfBaseline:
        return cls(rec, {oid: ppf.train(m.points, m.normals, m.diameter_m) for oid, m in rec.db.models.items()})

    def __call__(
        self, cloud: np.ndarray, world_T_camera: np.ndarray | None, objects: set[str] | None = None
    ) -> dict[str, np.ndarray]:
        """Each model's (or only ``objects``') best pose in the frame."""
        scene = self.rec.prepare(cloud, world_T_camera)
        if len(scene.points) == 0:
            return {}
        target = Surface.of(scene.points, scene.normals)
        c, out = self.rec.config, {}
        for oid, trained in self.trained.items():
            if objects is not None and oid not in objects:
                continue
            model = self.rec.db.models[oid]
            refined = [
                refine_icp(
                    model.points,
                    model.normals,
                    target,
                    h.camera_T_object,
                    c.icp_distance_m,
                    c.icp_iterations,
                    max_shift_m=model.diameter_m,
                )
                for h in ppf.match(trained, scene.points, scene.normals)
            ]
            refined = [r for r in refined if r.fitness > 0]
            if refined:
                out[oid] = max(refined, key=lambda r: (r.fitness, -r.rmse_m)).camera_T_object
        return out


@dataclass
class Shape:
    """An object's evaluation geometry: surface samples (N, 3), diameter (m), symmetries (S, 4, 4)."""

    points: np.ndarray
    diameter_m: float
    symmetries: np.ndarray


def shape_of(obj: ObjectSpec) -> Shape:
    mesh = object_mesh(obj)
    pts = np.asarray(mesh.sample_points_uniformly(3000).points)
    v = np.asarray(mesh.vertices)
    diameter = float(np.max(np.linalg.norm(v[:, None] - v[None], axis=-1)))
    centre = np.array([0.0, 0.0, obj.size[2] / 2 if obj.shape != "sphere" else obj.size[0]])
    flips = [np.eye(3), np.diag([1.0, -1, -1])]
    if obj.shape == "box":
        turns = [np.eye(3), np.diag([-1.0, -1, 1])]
    else:  # cylinder (sphere scored as one too): any turn about the axis
        turns = [rot_z(a) for a in np.radians(np.arange(0, 360, 2))]
    syms = []
    for F in flips:
        for Rz in turns:
            R = Rz @ F
            syms.append(make_pose(R, centre - R @ centre))
    return Shape(pts, diameter, np.stack(syms))


def adds(shape: Shape, est: np.ndarray, gt: np.ndarray) -> float:
    """ADD-S (m) of an estimated pose against the true one (``cellsight.evaluation.bop.adds_m``)."""
    return adds_m(shape.points, est, gt)


def mssd(shape: Shape, est: np.ndarray, gt: np.ndarray) -> float:
    x_est = shape.points @ est[:3, :3].T + est[:3, 3]
    gts = gt[None] @ shape.symmetries  # (S, 4, 4)
    x_gt = np.einsum("sij,nj->sni", gts[:, :3, :3], shape.points) + gts[:, None, :3, 3]
    return float(np.min(np.max(np.linalg.norm(x_gt - x_est[None], axis=-1), axis=1)))


def random_layout(s: Scenario, rng: np.random.Generator, tight: bool, within: float | None = None) -> Scenario:
    """The scenario with its objects at random table positions and yaws, all static, no two closer
    than a gap (their outlines on the table, ``footprint``): objects that interpenetrate are no
    scene a sensor can see.

    tight: crowded into the middle of the table with 1.5 cm gaps (so that they hide one another),
    instead of spread with 5 cm gaps. within: the share of the table's half-extents their centres
    stay within (default 0.45 tight, 1 spread).
    """
    share = within if within is not None else 0.45 if tight else 1.0
    half, gap = np.array(TABLE_HALF) * share, (0.015 if tight else 0.05)
    for _ in range(200):  # a layout whose last object found no room starts again
        outlines: list[np.ndarray] = []
        objects = []
        for obj in s.objects:
            for _ in range(200):
                xy, yaw = rng.uniform(-half, half), float(rng.uniform(0, 2 * np.pi))
                outline = footprint(obj, xy, yaw)
                if all(apart(outline, other, gap) for other in outlines):
                    break
            else:
                break
            outlines.append(outline)
            pose = PoseSpec(position=(float(xy[0]), float(xy[1]), 0.75), rpy_deg=(0.0, 0.0, float(np.degrees(yaw))))
            objects.append(obj.still().model_copy(update={"pose": pose}))
        if len(objects) == len(s.objects):
            return s.model_copy(update={"objects": objects})
    raise RuntimeError(f"no layout of {len(s.objects)} objects {gap} m apart within +-{half} m")


def visibility_class(visible: float) -> str | None:
    """An object's scoring class by the visible share of its silhouette: "unoccluded",
    "partly_occluded", or None (too hidden to score)."""
    return None if visible < SCORED else "unoccluded" if visible >= UNOCCLUDED else "partly_occluded"


def visible_share(cell: SimCell, s: Scenario, cam_id: str, obj: ObjectSpec) -> float:
    """Share of the object's own silhouette (self-occlusion included) that the full scene shows."""
    layer, info, world_T_camera = cell.clean(cam_id, 0.0)
    alone = o3d.t.geometry.RaycastingScene()
    alone.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(object_mesh(obj).transform(obj.world_T_object(0.0))))
    z = alone.cast_rays(o3d.core.Tensor(camera_rays(info.K, info.width, info.height, world_T_camera)))["t_hit"].numpy()
    mine = np.isfinite(z)
    if not mine.any():
        return 0.0
    return float(np.mean(np.abs(layer.z.reshape(-1)[mine] - z[mine]) < 0.002))


#: PCL's real scenes (Kinect frames, one stereo): the one the milk carton is in, and ones holding none of the objects.
MILK_SCENE = "milk_cartoon_all_small_clorox.pcd"
EMPTY_SCENES = (
    "office1.pcd",
    "five_people.pcd",
    "sac_plane_test.pcd",
    "table_scene_mug_stereo_textured.pcd",
    *(f"grabber_sequences/pcd/{p.name}" for p in sorted((PCL_DATA / "grabber_sequences" / "pcd").glob("*.pcd"))),
)


def scene_key(name: str) -> str:
    """The figure's name for a scene's false detections: ``false_positives_office1``,
    ``false_positives_frame_20121214T142255_814212``."""
    return "false_positives_" + re.sub(r"\W", "_", Path(name).stem)


def real_scenes() -> dict[str, float]:
    """The demo objects + PCL's milk carton against PCL's real scenes: the milk found in its scene,
    its model-to-scene RMSE, and every other detection (false)."""
    milk = read_cloud(PCL_DATA / "milk.pcd")
    cfg = RecognitionConfig()
    db = database_from_scenario(load_scenario(), cfg.descriptor)
    db.add(model_from_cloud("milk", milk, cfg.descriptor))
    rec = Recognizer(db, cfg)
    scene, rgb = read_coloured_cloud(PCL_DATA / MILK_SCENE, organised=True)
    found = rec.recognize(scene, rgb=rgb)
    hits = [d for d in found if d.object_id == "milk"]
    rmse = model_to_scene_rmse(milk, hits[0].camera_T_object, finite_points(scene)) if hits else float("inf")
    out = {"milk_found": float(bool(hits)), "milk_rmse_m": rmse, "false_positives_real": float(len(found) - len(hits))}
    for name in EMPTY_SCENES:
        cloud, rgb = read_coloured_cloud(PCL_DATA / name, organised=True)
        out[scene_key(name)] = float(len(rec.recognize(cloud, rgb=rgb)))
    out["false_positives_real_scenes"] = out["false_positives_real"] + sum(out[scene_key(n)] for n in EMPTY_SCENES)
    return out


def searched(
    rec: Recognizer, published: list[FusedObject], views: list[CameraView], points: list[CameraPoints]
) -> list[FusedObject]:
    """What the worker adds with ``search_fused_cloud``: the objects no camera found, recognised in
    all the cameras' points together seen from each camera in turn (the worker takes one a period),
    then cross-checked by the other cameras' frames."""
    missing = set(rec.db.models) - {o.object_id for o in published}
    added: list[WorldDetection] = []
    for cv in views:
        added += found_in_cloud(
            missing - {a.detection.object_id for a in added},
            cv,
            points,
            lambda cloud, W, view: rec.recognize(cloud, world_T_camera=W, view=view),
        )
    return cross_checked(added, views, rec.seen_through, 10**9)[0]


def distractor(rng: np.random.Generator, i: int) -> ObjectSpec:
    """An object of no database: a box or a cylinder of a random size (see the module docstring)."""
    if rng.random() < 0.5:
        return ObjectSpec(
            id=f"distractor{i}",
            shape="box",
            size=tuple(rng.uniform([0.05, 0.05, 0.12], [0.12, 0.12, 0.30])),
            color=(0.5, 0.5, 0.5),
        )
    r = float(rng.uniform(0.03, 0.06))
    return ObjectSpec(
        id=f"distractor{i}", shape="cylinder", size=(r, r, float(rng.uniform(0.12, 0.30))), color=(0.4, 0.5, 0.4)
    )


def distractors(rec: Recognizer, trials: int, colour: bool) -> dict[str, float]:
    """Published and per-camera false detections among objects of no database (module docstring),
    with the frames' colour or depth only."""
    base, rng = load_scenario(), np.random.default_rng(11)
    shapes = {o.id: shape_of(o) for o in base.objects}
    published, per_camera, frames = 0, 0, 0
    for trial in range(trials):
        absent = base.objects[trial % len(base.objects)].id
        s = base.model_copy(
            update={
                "objects": [o for o in base.objects if o.id != absent] + [distractor(rng, i) for i in range(4)],
                "markers": [mk for mk in base.markers if mk.object != absent],
            }
        )
        s = random_layout(s, rng, tight=False)
        cell = SimCell(s)
        truth = {o.id: o.world_T_object(0.0) for o in s.objects if o.id in shapes}

        def false(oid: str, world_T_object: np.ndarray) -> bool:
            return oid not in truth or adds(shapes[oid], world_T_object, truth[oid]) >= 0.1 * shapes[oid].diameter_m

        found, views, points = [], [], []
        for cam in s.cameras:
            frame = cell.render(cam.id, 0.0, trial)
            cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
            view = DepthView.of(cloud, frame.rgb if colour else None)
            views.append(CameraView(cam.id, 0, view, frame.world_T_camera))
            points.append(
                CameraPoints(
                    cam.id,
                    0,
                    voxel_downsample(rec.workspace_points(cloud, frame.world_T_camera), REFINE_VOXEL_M),
                    frame.world_T_camera,
                )
            )
            for det in rec.recognize(cloud, world_T_camera=frame.world_T_camera, view=view):
                found.append(
                    WorldDetection(cam.id, 0, frame.world_T_camera @ det.camera_T_object, det, frame.world_T_camera)
                )
                per_camera += false(det.object_id, found[-1].world_T_object)
            frames += 1
        objects = cross_checked(found, views, rec.seen_through, 10**9)[0]
        objects += searched(rec, objects, views, points)  # the absent object is always searched for
        published += sum(false(f.object_id, f.world_T_object) for f in objects)
    suffix = "" if colour else "_depth_only"
    return {
        f"false_positives_per_trial_distractors{suffix}": published / trials,
        f"false_detections_per_frame_distractors{suffix}": per_camera / frames,
    }


def clutter(rec: Recognizer, trials: int) -> dict[str, float]:
    """The demo objects packed with 1.5 cm gaps among four objects of no database (``distractor``)
    over 0.7 of the table, every camera with colour: per camera, ADD-S recall of the objects
    unoccluded and partly occluded (as the main pass classes them), and false detections a frame."""
    base, rng = load_scenario(), np.random.default_rng(3)
    shapes = {o.id: shape_of(o) for o in base.objects}
    rows: list[tuple[str, bool]] = []
    false, frames = 0, 0
    for trial in range(trials):
        s = base.model_copy(
            update={
                "objects": list(base.objects) + [distractor(rng, i) for i in range(4)],
                "markers": [mk for mk in base.markers if mk.object is None],
            }
        )
        s = random_layout(s, rng, tight=True, within=0.7)
        cell = SimCell(s)
        truth = {o.id: o.world_T_object(0.0) for o in s.objects if o.id in shapes}
        for cam in s.cameras:
            right, wrong = _judged_frame(rec, cell.render(cam.id, 0.0, trial), shapes, truth)
            false += wrong
            frames += 1
            for o in s.objects:
                if o.id in shapes and (cls := visibility_class(visible_share(cell, s, cam.id, o))) is not None:
                    rows.append((cls, o.id in right))
    return {"false_detections_per_frame_clutter": false / frames, **_recall_by_class(rows, "clutter")}


def _judged_frame(rec: Recognizer, frame: SimFrame, shapes: dict, truth: dict[str, np.ndarray]) -> tuple[set[str], int]:
    """One frame recognised with its camera's pose and colour: the objects found within ADD-S 0.1 d
    of their world pose in ``truth`` (object id -> (4, 4)), and how many were found away from it."""
    found = {
        d.object_id: frame.world_T_camera @ d.camera_T_object
        for d in rec.recognize(
            depth_to_cloud(frame.depth_mm, frame.info.K), world_T_camera=frame.world_T_camera, rgb=frame.rgb
        )
    }
    right = {oid for oid, T in found.items() if adds(shapes[oid], T, truth[oid]) < 0.1 * shapes[oid].diameter_m}
    return right, len(found) - len(right)


def _recall_by_class(rows: list[tuple[str, bool]], suffix: str) -> dict[str, float]:
    """``adds_recall_{class}_{suffix}`` and ``views_{class}_{suffix}`` of scored views (class, found right)."""
    out = {}
    for cls in ("unoccluded", "partly_occluded"):
        hits = [hit for c, hit in rows if c == cls]
        out[f"adds_recall_{cls}_{suffix}"] = float(np.mean(hits)) if hits else float("nan")
        out[f"views_{cls}_{suffix}"] = float(len(hits))
    return out


#: What the simulated Kinect lacks and real sensors show (module docstring: a rougher sensor).
ROUGH_SENSOR = {"flying_pixels": True, "saturation": 0.7, "rgb_shift_px": (3, 0)}
#: Its white balance, layout by layout in turn: warm, then cool light.
ROUGH_WHITE_BALANCE = ((1.15, 1.0, 0.85), (0.85, 1.0, 1.15))


def rough(s: Scenario, layout: int) -> Scenario:
    """The scenario as the rougher sensor renders it (``ROUGH_SENSOR``), with the white balance of
    its layout's turn (``ROUGH_WHITE_BALANCE``)."""
    update = ROUGH_SENSOR | {"white_balance": ROUGH_WHITE_BALANCE[layout % len(ROUGH_WHITE_BALANCE)]}
    return s.model_copy(update={"noise": s.noise.model_copy(update=update)})


def rough_sensor(rec: Recognizer, trials: int) -> dict[str, float]:
    """Recall and false detections on random layouts as the simulated Kinect renders them and as a
    rougher sensor does (``ROUGH_SENSOR``, ``ROUGH_WHITE_BALANCE``), the same layouts and cameras."""
    base = load_scenario()
    shapes = {o.id: shape_of(o) for o in base.objects}
    rng = np.random.default_rng(13)
    rows: dict[str, list[tuple[str, bool]]] = {"as_rendered": [], "rough": []}  # (class, right) per scored view
    false = {"as_rendered": 0, "rough": 0}
    frames = 0
    for trial in range(trials):
        s = random_layout(base, rng, tight=trial % 2 == 1)
        cells = {"as_rendered": SimCell(s), "rough": SimCell(rough(s, trial))}
        truth = {o.id: o.world_T_object(0.0) for o in s.objects}
        for cam in s.cameras:
            classes = {
                o.id: cls
                for o in s.objects
                if (cls := visibility_class(visible_share(cells["as_rendered"], s, cam.id, o))) is not None
            }
            frames += 1
            for sensor, cell in cells.items():
                right, wrong = _judged_frame(rec, cell.render(cam.id, 0.0, trial), shapes, truth)
                false[sensor] += wrong
                rows[sensor] += [(cls, oid in right) for oid, cls in classes.items()]
    out = {}
    for sensor, hits in rows.items():
        out[f"false_detections_per_frame_{sensor}"] = false[sensor] / frames
        out |= _recall_by_class(hits, sensor)
    return out


def run(quick: bool) -> dict[str, float]:
    base = load_scenario()
    shapes = {o.id: shape_of(o) for o in base.objects}
    recognisers = {}
    for binning in ("pcl", "pcl17"):
        cfg = RecognitionConfig(
            descriptor=DescriptorConfig(binning=binning), workspace_min=WORKSPACE[0], workspace_max=WORKSPACE[1]
        )
        recognisers[binning] = Recognizer(database_from_scenario(base, cfg.descriptor), cfg)
    ppf_times: list[float] = []
    later: list[tuple[Scenario, SimFrame, dict[str, str]]] = []  # (layout, frame, classes) for the baseline's pass
    rng = np.random.default_rng(7)
    rows: list[tuple[str, str, str, float, float, float]] = []  # binning, object, class, adds/d, mssd/d, pos err
    times: dict[str, list[float]] = {b: [] for b in recognisers}
    false_detections = 0  # ours (PCL binning), any frame
    fused_hits: list[bool] = []  # per (trial, object partly occluded in some camera): fused pose correct
    fused_errors: dict[str, list[float]] = {"unrefined": [], "refined": []}  # position error, mm, every fused object
    fused_false = 0
    fused_held_right = 0  # correct fused objects another camera's frame contradicted
    moved_caught: list[bool] = []  # correct detections moved 20 cm: held back by the other cameras
    pair_hits: list[bool] = []  # per (trial, camera pair, object partly occluded in both): fused pose correct
    pair_false = 0
    cloud_hits: list[bool] = []  # per (trial, camera, object present): found in the cameras' points together
    cloud_false, cloud_added, cloud_times = 0, 0, []
    trials = 2 if quick else 12
    for trial in range(trials):
        s = random_layout(base, rng, tight=trial % 2 == 1)
        cell = SimCell(s)
        in_world: list[WorldDetection] = []  # ours, every camera of the trial
        views: list[CameraView] = []
        points: list[CameraPoints] = []
        right_ones: list[WorldDetection] = []
        partly_somewhere: set[str] = set()
        shares: dict[str, dict[str, float]] = {}  # camera -> object -> visible share
        for cam in s.cameras:
            frame = cell.render(cam.id, 0.0, trial)
            classes = {}
            shares[cam.id] = {}
            for obj in s.objects:
                share = shares[cam.id][obj.id] = visible_share(cell, s, cam.id, obj)
                if (cls := visibility_class(share)) is not None:
                    classes[obj.id] = cls
            for binning, rec in recognisers.items():
                t0 = time.perf_counter()
                cloud = depth_to_cloud(frame.depth_mm, frame.info.K)
                view = DepthView.of(cloud, frame.rgb)  # the worker keeps it to judge the other cameras' detections
                found = {d.object_id: d for d in rec.recognize(cloud, world_T_camera=frame.world_T_camera, view=view)}
                times[binning].append(time.perf_counter() - t0)
                if binning == "pcl":
                    views.append(CameraView(cam.id, 0, view, frame.world_T_camera))
                    near = voxel_downsample(rec.workspace_points(cloud, frame.world_T_camera), REFINE_VOXEL_M)
                    points.append(CameraPoints(cam.id, 0, near, frame.world_T_camera))
                    for oid, det in found.items():
                        obj = next(o for o in s.objects if o.id == oid)
                        gt = invert_pose(frame.world_T_camera) @ obj.world_T_object(0.0)
                        wrong = adds(shapes[oid], det.camera_T_object, gt) >= 0.1 * shapes[oid].diameter_m
                        false_detections += wrong
                        in_world.append(
                            WorldDetection(
                                cam.id, 0, frame.world_T_camera @ det.camera_T_object, det, frame.world_T_camera
                            )
                        )
                        if not wrong:
                            right_ones.append(in_world[-1])
                    partly_somewhere |= {oid for oid, cls in classes.items() if cls == "partly_occluded"}
                for obj in s.objects:
                    if obj.id not in classes:
                        continue
                    gt = invert_pose(frame.world_T_camera) @ obj.world_T_object(0.0)
                    sh = shapes[obj.id]
                    if obj.id in found:
                        est = found[obj.id].camera_T_object
                        e = (
                            adds(sh, est, gt) / sh.diameter_m,
                            mssd(sh, est, gt) / sh.diameter_m,
                            float(np.linalg.norm(est[:3, 3] - gt[:3, 3])),
                        )
                    else:
                        e = (np.inf, np.inf, np.inf)
                    rows.append((binning, obj.id, classes[obj.id], *e))
            later.append((s, frame, classes))
        judge = recognisers["pcl"].seen_through
        published, held = cross_checked(in_world, views, judge, 10**9)
        rec = recognisers["pcl"]
        # Recognition in all the cameras' points together, seen from each camera, every object: the
        # search's own recall and false detections (the worker searches only for what no camera found).
        present = [o for o in s.objects if max(shares[c][o.id] for c in shares) >= SCORED]
        for cv in views:
            t0 = time.perf_counter()
            in_cloud = {
                d.detection.object_id: d
                for d in found_in_cloud(
                    set(shapes), cv, points, lambda cloud, W, view: rec.recognize(cloud, world_T_camera=W, view=view)
                )
            }
            cloud_times.append(time.perf_counter() - t0)
            for oid, d in in_cloud.items():
                cloud_false += (
                    adds(shapes[oid], d.world_T_object, next(o for o in s.objects if o.id == oid).world_T_object(0.0))
                    >= 0.1 * shapes[oid].diameter_m
                )
            cloud_hits += [
                o.id in in_cloud
                and adds(shapes[o.id], in_cloud[o.id].world_T_object, o.world_T_object(0.0))
                < 0.1 * shapes[o.id].diameter_m
                for o in present
            ]
        added = searched(rec, published, views, points)
        cloud_added += len(added)
        published = published + added
        cfg = recognisers["pcl"].config
        refined = refined_in_cloud(
            published,
            points,
            recognisers["pcl"].db,
            cfg.icp_distance_m,
            cfg.descriptor.normal_radius_m,
            cfg.min_fitness,
        )
        for before, after in zip(published, refined):
            truth = next(o for o in s.objects if o.id == before.object_id).world_T_object(0.0)
            fused_errors["unrefined"].append(1000 * float(np.linalg.norm(before.world_T_object[:3, 3] - truth[:3, 3])))
            fused_errors["refined"].append(1000 * float(np.linalg.norm(after.world_T_object[:3, 3] - truth[:3, 3])))
        fused = {f.object_id: f.world_T_object for f in refined}
        for obj in s.objects:
            right = (
                obj.id in fused
                and adds(shapes[obj.id], fused[obj.id], obj.world_T_object(0.0)) < 0.1 * shapes[obj.id].diameter_m
            )
            fused_false += obj.id in fused and not right
            if obj.id in partly_somewhere:
                fused_hits.append(right)
        truth_of = {o.id: o.world_T_object(0.0) for o in s.objects}
        # Two cameras alone, for every object partly occluded in both: what the fusion gets when no
        # camera has the whole view.
        for a, b in itertools.combinations(sorted(shares), 2):
            hard = [o for o in s.objects if SCORED <= max(shares[a][o.id], shares[b][o.id]) < UNOCCLUDED]
            if not hard:
                continue
            pair = {
                f.object_id: f.world_T_object
                for f in cross_checked(
                    [d for d in in_world if d.camera_id in (a, b)],
                    [v for v in views if v.camera_id in (a, b)],
                    judge,
                    10**9,
                )[0]
            }
            for oid, T in pair.items():
                pair_false += adds(shapes[oid], T, truth_of[oid]) >= 0.1 * shapes[oid].diameter_m
            pair_hits += [
                o.id in pair and adds(shapes[o.id], pair[o.id], truth_of[o.id]) < 0.1 * shapes[o.id].diameter_m
                for o in hard
            ]
        fused_held_right += sum(
            any(
                adds(shapes[h.object_id], d.world_T_object, truth_of[h.object_id])
                < 0.1 * shapes[h.object_id].diameter_m
                for d in in_world
                if d.detection.object_id == h.object_id and d.camera_id in h.detected_by
            )
            for h in held
        )
        for d in right_ones:
            for shift in ((0.0, 0.0, 0.2), (0.2, 0.0, 0.0), (0.0, 0.2, 0.0)):
                moved = WorldDetection(
                    d.camera_id, 0, make_pose(np.eye(3), shift) @ d.world_T_object, d.detection, d.world_T_camera
                )
                moved_caught.append(not cross_checked([moved], views, judge, 10**9)[0])
    # The baseline in a pass of its own over the same frames, so that nothing it leaves behind
    # (large temporary arrays) is in our timings.
    baseline = PpfBaseline.of(recognisers["pcl"])
    for s, frame, classes in later[:: 2 if quick else 1]:  # --quick: every other frame, to finish in a minute
        t0 = time.perf_counter()
        poses = baseline(depth_to_cloud(frame.depth_mm, frame.info.K), frame.world_T_camera)
        ppf_times.append(time.perf_counter() - t0)
        for obj in s.objects:
            if obj.id in classes:
                gt = invert_pose(frame.world_T_camera) @ obj.world_T_object(0.0)
                ok = obj.id in poses and adds(shapes[obj.id], poses[obj.id], gt) < 0.1 * shapes[obj.id].diameter_m
                rows.append(("ppf", obj.id, classes[obj.id], 0.0 if ok else np.inf, np.inf, np.inf))
    out: dict[str, float] = real_scenes()
    out["false_positives_per_frame_sim"] = false_detections / len(times["pcl"])
    out["adds_recall_fused"] = float(np.mean(fused_hits)) if fused_hits else float("nan")
    out["objects_partly_occluded_somewhere"] = len(fused_hits)
    for kind, suffix in (("refined", ""), ("unrefined", "_unrefined")):
        e = np.array(fused_errors[kind])
        out[f"fused_position_error_mm_p50{suffix}"] = float(np.median(e))
        out[f"fused_position_error_mm_p90{suffix}"] = float(np.percentile(e, 90))
        out[f"fused_position_error_mm_max{suffix}"] = float(e.max())
    out["false_positives_per_trial_fused"] = fused_false / trials
    out["adds_recall_fused_pairs"] = float(np.mean(pair_hits)) if pair_hits else float("nan")
    out["objects_partly_occluded_in_both_of_a_pair"] = len(pair_hits)
    out["false_positives_fused_pairs"] = pair_false
    out["fused_held_back_right"] = fused_held_right
    out["adds_recall_fused_cloud"] = float(np.mean(cloud_hits))
    out["false_detections_fused_cloud"] = float(cloud_false)
    out["fused_cloud_frames"] = float(len(cloud_times))
    out["fused_cloud_ms_p50"] = 1000 * float(np.median(cloud_times))
    out["fused_cloud_added"] = float(cloud_added)
    out["cross_view_caught_moved"] = float(np.mean(moved_caught)) if moved_caught else float("nan")
    out["frame_ms_p50"] = 1000 * float(np.median(times["pcl"]))
    out["frame_ms_p95"] = 1000 * float(np.percentile(times["pcl"], 95))
    for binning in recognisers:
        suffix = "" if binning == "pcl" else "_pcl17"
        for cls in ("unoccluded", "partly_occluded"):
            sel = [r for r in rows if r[0] == binning and r[2] == cls]
            out[f"views_{cls}{suffix}"] = len(sel)
            if not sel:
                continue
            a = np.array([r[3] for r in sel])
            m = np.array([r[4] for r in sel])
            out[f"adds_recall_{cls}{suffix}"] = float(np.mean(a < 0.1))
            out[f"ar_mssd_{cls}{suffix}"] = float(np.mean([np.mean(m < t) for t in MSSD_THRESHOLDS]))
            if binning == "pcl":
                for oid in shapes:
                    o = [r for r in sel if r[1] == oid]
                    if o:
                        out[f"adds_recall_{cls}_{oid}"] = float(np.mean([r[3] < 0.1 for r in o]))
                        ok = [r[5] for r in o if np.isfinite(r[5])]
                        if ok:
                            out[f"position_error_mm_median_{cls}_{oid}"] = 1000 * float(np.median(ok))
    out["frame_ms_p50_pcl17"] = 1000 * float(np.median(times["pcl17"]))
    out["ppf_frame_ms_p50"] = 1000 * float(np.median(ppf_times))
    out["ppf_frames"] = len(ppf_times)
    for cls in ("unoccluded", "partly_occluded"):
        sel = [r for r in rows if r[0] == "ppf" and r[2] == cls]
        if sel:
            out[f"ppf_adds_recall_{cls}"] = float(np.mean([r[3] < 0.1 for r in sel]))
    out["frame_time_over_ppf"] = out["frame_ms_p50"] / out["ppf_frame_ms_p50"]
    for colour in (True, False):
        out.update(distractors(recognisers["pcl"], 2 if quick else 12, colour))
    out["distractor_trials"] = 2 if quick else 12
    out.update(clutter(recognisers["pcl"], 2 if quick else 24))
    out.update(rough_sensor(recognisers["pcl"], 2 if quick else 12))
    return out


if __name__ == "__main__":
    main("recognition", __doc__.splitlines()[0], run)
