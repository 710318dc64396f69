"""Recognition on annotated frames in the BOP format: ADD-S recall and false detections, with point-pair voting in the same run.

``--dataset DIR`` measures any dataset in the format public pose datasets ship in (BOP: LM-O,
YCB-V, T-LESS, ...; ``cellsight.evaluation.bop``): the database is built from its models (``--models``: their
folder, by default the first of ``models``, ``models_cad``, ``models_reconst``, ``models_eval`` it
has; mm; meshes rendered from 42 viewpoints at each ``--distance``, point models by hidden-point
removal, their colours where the files carry them, vertex colours or texture) and every frame of
``--split`` (the challenge's target images where the dataset lists them; ``--frames N`` keeps N
spread over them) goes through
``Recognizer.recognize`` as ``cellsight recognize`` runs it: camera frame, no workspace box, colour
judged where the frame has it. A world pose in ``scene_camera.json`` is used only where its z is up
(a plane the frame shows is level in it; ``--world-z-up`` takes every one): a dataset's world may
be a marker board's on a wall, and recognition stands objects on the pose's z. Where it is used,
objects are still tried any way up and lying, as without a pose (``free_with_pose``): a dataset's
objects need not stand on their model's +z (its frames may have any axes; with every model turned
at random, an ad hoc set read 0.27 standing-only against 0.96); ``--standing`` tries them only
standing, as the cell does. An annotated
instance is found when a detection of its object lies within ADD-S 0.1 x diameter
(``models_info.json``'s); a detection matching no instance is false (on datasets that annotate only
some of the objects in view, as LM does, an unannotated one counts false too). Instances under 40 %
visible (``visib_fract``) are not scored; classes as ``benchmarks.recognition``: unoccluded >= 95 %,
partly occluded 40-95 %.

Baseline in the same run: point-pair-feature voting then ICP (``benchmarks.recognition``'s), given
the objects annotated in each frame (BOP's localisation task: which objects are there is known to
it, not to ours), its best pose per object scored the same way.

Without ``--dataset`` it measures a dataset it writes first: the simulated demo cell (crate, can,
tote; random layouts, every camera, ground truth from the simulator; the cameras' poses in the cell
given, so the cell's workspace crops the frames as in the running cell; as many layouts again seen
from close, each camera 0.8 m from the table's centre and 0.5 m above it, as datasets are taken:
``bop_adds_recall_near`` / ``_far`` split at 1.2 m; as many again with every object lying on its
side, from far and close, as a dataset's objects may lie, the frames without the cameras' poses:
``bop_adds_recall_lying``, apart from the other figures and without the baseline, which takes ~30 s
a frame with the whole room in view) and PCL's real Kinect frames
re-packed as depth + colour images (intrinsics fitted to their organised clouds), none of which
holds a demo object: every detection there is false. The simulated frames are recognised once more
without their pose (``..._camera_frame``), as ``cellsight recognize`` sees a saved frame: the room's
floor and walls in view, which the planes removed after the first take away; and once more with
``level_support`` (``..._camera_frame_level_support``: the dominant plane taken as level, so the
upright test and the support apply as with a pose). ``..._upside_down_...`` counts the found
objects standing on their base reported with their +z against the true one: ADD-S scores a
symmetric shape's flipped pose as right, a robot reading the object's frame would not. (PCL's milk
carton is no BOP model: it is one captured view, and a BOP model is the whole surface;
``benchmarks.recognition`` finds it.) The frames (the lying ones aside) once more with six
look-alike models in the database, never in a frame (``LOOKALIKES``: boxes and cans of other sizes,
the crate and the can in other colours; not with ``--quick``): ``..._lookalikes``. Once more on
depth alone, as a sensor or models without colour leave it (``..._depth_only``; a ``--dataset``'s
too, not the default's with ``--quick``). And a dataset of
objects that are no box or cylinder (``drivers.sim.shapes``: a mug, a duck, a drill, a cone; 3 layouts from
the cell and from close, not with ``--quick``): ``bop_shapes_...``. So the reader,
the model build from files in millimetres and the scoring run on every change, and a held-back
dataset is one flag away. ``--rough-sensor`` renders the simulated frames by ``benchmarks.recognition``'s
rougher sensor (flying pixels, light 15 % warmer or cooler, washed-out colour, colour 3 px off): the
same figures, for a sensor less kind than the simulated Kinect. ``--pictures OUT`` draws every frame a pass got wrong (a miss or a false
detection) into OUT, named by the pass, scene and image: what was found, and the annotated poses
outlined in white.

One pinned core, as ``benchmarks.recognition``.
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from rich.progress import track  # noqa: E402

from benchmarks.common import PCL_DATA, main  # noqa: E402
from benchmarks.recognition import (  # pins this process to one core first
    WORKSPACE,
    PpfBaseline,
    random_layout,
    rough,
    visibility_class,
    visible_share,
)
from cellsight.config import load_config  # noqa: E402
from cellsight.errors import ConfigError  # noqa: E402
from cellsight.evaluation.bop import (  # noqa: E402
    MODEL_FOLDERS,
    BopDataset,
    BopFrame,
    BopWriter,
    depth_of_organised,
    level_world_pose,
    score,
)
from cellsight.evaluation.pictures import draw_recognition  # noqa: E402
from cellsight.model_build import build_database  # noqa: E402
from drivers.sim.render import SimCell, object_mesh  # noqa: E402
from drivers.sim.scenario import ObjectSpec, Scenario, load_scenario  # noqa: E402
from drivers.sim.shapes import shapes  # noqa: E402
from recognition.cloud import read_coloured_cloud  # noqa: E402
from recognition.config import RecognitionConfig  # noqa: E402
from recognition.models import VIEW_DISTANCES_M, ModelDatabase, model_from_mesh  # noqa: E402
from recognition.pipeline import Recognizer  # noqa: E402
from schemas.geometry import invert_pose  # noqa: E402

NEAR_M = 1.2  # instances nearer the camera than this (m) are scored apart too (``bop_adds_recall_near``)
#: PCL's real Kinect frames (organised clouds, fx = fy = 525 px), none holding a demo object.
REAL_FRAMES = (
    "milk_cartoon_all_small_clorox.pcd",
    "office1.pcd",
    "five_people.pcd",
    *(f"grabber_sequences/pcd/{p.name}" for p in sorted((PCL_DATA / "grabber_sequences" / "pcd").glob("*.pcd"))),
)
KINECT_F = 525.0  # the PCL frames' focal length, px (data README)
#: The pass on objects that are no box or cylinder (``drivers.sim.shapes``; not with --quick): its layouts, and
#: the figures it reports, named bop_shapes_...
SHAPE_LAYOUTS = 3
SHAPE_FIGURES = (
    "bop_instances_scored",
    "bop_adds_recall",
    "bop_adds_recall_near",
    "bop_adds_recall_far",
    "bop_false_detections",
    "bop_ppf_adds_recall",
    "bop_adds_recall_camera_frame",
    "bop_false_detections_camera_frame",
    "bop_adds_recall_depth_only",
    "bop_false_detections_depth_only",
)
#: Models added to the database in a pass of their own (``bop_adds_recall_lookalikes``), never in a
#: frame: boxes and cans a fifth smaller or larger than the demo's, the crate's and the can's shapes
#: in other colours. A dataset's database holds such families (YCB-V: four boxes, four cans).
LOOKALIKES = (
    ObjectSpec(id="small_box", shape="box", size=(0.20, 0.15, 0.12), color=(0.6, 0.3, 0.6)),
    ObjectSpec(id="red_crate", shape="box", size=(0.24, 0.18, 0.14), color=(0.75, 0.2, 0.2)),
    ObjectSpec(id="big_tote", shape="box", size=(0.34, 0.25, 0.12), color=(0.3, 0.6, 0.3)),
    ObjectSpec(id="thin_can", shape="cylinder", size=(0.045, 0.045, 0.16), color=(0.2, 0.5, 0.8)),
    ObjectSpec(id="tall_can", shape="cylinder", size=(0.06, 0.06, 0.26), color=(0.9, 0.9, 0.9)),
    ObjectSpec(id="grey_can", shape="cylinder", size=(0.06, 0.06, 0.2), color=(0.5, 0.5, 0.5)),
)


def kinect_frame(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One of PCL's real organised clouds as depth (H, W, m), intrinsics K (3, 3) and colour (H, W, 3 uint8)."""
    cloud, rgb = read_coloured_cloud(PCL_DATA / name, organised=True)
    depth, K = depth_of_organised(cloud, KINECT_F)
    return depth, K, rgb


def lying_layout(s: Scenario, rng: np.random.Generator) -> Scenario:
    """The scenario's objects laid on their side at random table positions and yaws, apart as
    ``random_layout`` keeps upright ones: each object turned a quarter about its x axis, its height
    along the table."""

    def stand_in(o: ObjectSpec) -> ObjectSpec:  # its outline lying down, as an upright box's
        width = 2 * o.size[0] if o.shape == "cylinder" else o.size[0]
        return o.model_copy(update={"shape": "box", "size": (width, o.size[2], 0.1)})

    placed = {
        o.id: o.world_T_object(0.0)
        for o in random_layout(
            s.model_copy(update={"objects": [stand_in(o) for o in s.objects]}), rng, tight=False
        ).objects
    }
    objects = []
    for o in s.objects:
        T = placed[o.id]
        yaw = float(np.arctan2(T[1, 0], T[0, 0]))
        # The base centre sits half the object's length back from the outline's centre.
        base = T[:2, 3] + 0.5 * o.size[2] * np.array([-np.sin(yaw), np.cos(yaw)])
        objects.append(o.laid_on_side((base[0], base[1]), np.degrees(yaw), T[2, 3]))
    return s.model_copy(update={"objects": objects})


def write_default(
    root: Path, layouts: int, lying: int, objects: list[ObjectSpec] | None = None, rough_sensor: bool = False
) -> Path:
    """The dataset measured without --dataset (module docstring): simulated scenes 1..layouts from
    the cell's cameras, layouts+1..2 layouts from close, ``lying`` more after them with the objects
    on their side (every other one from close, without the cameras' poses), the real frames scene
    100. ``objects``: others than the demo cell's (without the real frames, and without the markers
    the cell's objects carry). ``rough_sensor``: the simulated scenes rendered by
    ``benchmarks.recognition``'s rougher sensor (``rough``)."""
    base = load_scenario()
    if objects is not None:
        base = base.model_copy(update={"objects": objects, "markers": [m for m in base.markers if m.object is None]})
    ids = {o.id: i + 1 for i, o in enumerate(base.objects)}
    w = BopWriter(root)
    for obj in base.objects:
        mesh = object_mesh(obj).paint_uniform_color(obj.color)
        w.add_model(ids[obj.id], np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_colors))
    rng = np.random.default_rng(7)
    # Seen from close: each camera moved in along its line to 0.8 m from the table's centre, 0.5 m
    # above it, as datasets' frames are taken.
    near = [c.moved_in(0.8, 1.25, (0.0, 0.0, 0.8)) for c in base.cameras]
    for scene in range(1, 2 * layouts + lying + 1):
        close = layouts < scene <= 2 * layouts or (scene > 2 * layouts and scene % 2 == 0)
        s = base.model_copy(update={"cameras": near}) if close else base
        s = random_layout(s, rng, tight=scene % 2 == 0) if scene <= 2 * layouts else lying_layout(s, rng)
        s = rough(s, scene) if rough_sensor else s
        cell = SimCell(s)
        for image_id, cam in enumerate(s.cameras):
            frame = cell.render(cam.id, 0.0, scene)
            truth = [
                (
                    ids[o.id],
                    invert_pose(frame.world_T_camera) @ o.world_T_object(0.0),
                    visible_share(cell, s, cam.id, o),
                )
                for o in s.objects
            ]
            # Lying objects are no cell's (its upright test turns them down): their frames go without
            # the camera's pose, as a dataset's.
            w.add_frame(
                scene,
                image_id,
                frame.depth_mm * 0.001,
                frame.info.K,
                truth,
                frame.rgb,
                depth_scale_mm=1.0,
                world_T_camera=frame.world_T_camera if scene <= 2 * layouts else None,
            )
    for image_id, name in enumerate(REAL_FRAMES if objects is None else ()):
        depth, K, rgb = kinect_frame(name)
        w.add_frame(100, image_id, depth, K, [], rgb)
    return w.close()


@dataclass
class Tally:
    """One pass's scores: per scored instance its class (``_class``), whether it is nearer the
    camera than NEAR_M, and whether it was found; the false detections, the found objects standing
    on their base reported upside down (their +z against the true one), and frame times (s)."""

    rows: list[tuple[str, bool, bool]] = field(default_factory=list)
    false: int = 0
    upside_down: int = 0
    times: list[float] = field(default_factory=list)

    def add(
        self, frame: BopFrame, found: list[tuple[str, np.ndarray]], db: ModelDatabase, diameter: dict[str, float]
    ) -> bool:
        """Score a frame's detections (object id, camera_T_object) against its annotations: whether
        all was right (no false detection, every scored instance found)."""
        s = score(frame.truth, found, {oid: m.points for oid, m in db.models.items()}, diameter)
        self.false += len(s.false)
        for inst, hit, j in zip(frame.truth, s.found, s.matched):
            if (cls := _class(inst.visible_share)) is not None:
                self.rows.append((cls, bool(np.linalg.norm(inst.camera_T_object[:3, 3]) < NEAR_M), hit))
            if (
                j is not None
                and db.models[inst.object_id].stands_on_z
                and found[j][1][:3, 2] @ inst.camera_T_object[:3, 2] < 0
            ):
                self.upside_down += 1
        scored = [hit for inst, hit in zip(frame.truth, s.found) if _class(inst.visible_share) is not None]
        return not s.false and all(scored)

    def recall(self, cls: str | None = None, near: bool | None = None) -> float | None:
        """Share found of the scored instances of a class and band (None: all); None if there are none."""
        hits = [hit for c, n, hit in self.rows if cls in (None, c) and near in (None, n)]
        return float(np.mean(hits)) if hits else None


def _recognised(
    rec: Recognizer,
    frames: list[BopFrame],
    pose_of: dict[tuple[int, int], np.ndarray | None],
    db: ModelDatabase,
    diameter: dict[str, float],
    progress: str,
    colour: bool = True,
    pictures: Path | None = None,
) -> Tally:
    """The frames through ``rec`` with colour (unless not ``colour``: depth alone), each with its
    world pose in ``pose_of`` (absent: none), scored; ``progress`` names the pass on its progress bar.
    pictures: a folder for a picture of each frame with a miss or a false detection
    (``draw_recognition``: what was found, the annotated poses outlined in white), named by the pass,
    the scene and the image."""
    tally = Tally()
    for frame in track(frames, description=progress):
        cloud, rgb = frame.load()
        t0 = time.perf_counter()
        found = rec.recognize(
            cloud, world_T_camera=pose_of.get((frame.scene_id, frame.image_id)), rgb=rgb if colour else None
        )
        tally.times.append(time.perf_counter() - t0)
        right = tally.add(frame, [(d.object_id, d.camera_T_object) for d in found], db, diameter)
        if pictures is not None and not right:
            truth = [(inst.object_id, inst.camera_T_object) for inst in frame.truth]
            name = f"{re.sub(r'[^a-z]+', '_', progress)}_{frame.scene_id:06d}_{frame.image_id:06d}.png"
            pictures.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(pictures / name), draw_recognition(cloud, rgb if colour else None, found, rec.db, truth))
    return tally


def measure(
    dataset: BopDataset,
    frames: int | None,
    distances_m: tuple[float, ...],
    cfg: RecognitionConfig,
    lying_scenes: frozenset[int] = frozenset(),
    world_z_up: bool = False,
    lookalikes: tuple[ObjectSpec, ...] = (),
    depth_only: bool = True,
    pictures: Path | None = None,
) -> dict[str, float]:
    """Ours and the point-pair baseline on ``frames`` of the dataset's frames (all if None), the
    database built from its models with views at ``distances_m`` (m): the figures of the module
    docstring; ``bop_adds_recall_lying`` over the scenes in ``lying_scenes``. A frame's world pose is
    used when ``world_z_up`` says the dataset's world has z up, else only if a plane the frame shows
    is level in it (``level_world_pose``; the others: ``bop_frames_world_pose_set_aside``). With
    ``lookalikes``, the frames but the lying ones once more, those objects' models added; with
    ``depth_only``, once more without their colour (``..._depth_only``). ``pictures``: a folder for
    a picture of each frame a pass got wrong (``_recognised``)."""
    meshes = {m.object_id: m.path for m in dataset.models.values() if m.is_mesh}
    points = {m.object_id: m.path for m in dataset.models.values() if not m.is_mesh}
    t0 = time.perf_counter()
    db = build_database(cfg.descriptor, meshes=meshes, points=points, scale=0.001, distances_m=distances_m)
    build_s = time.perf_counter() - t0
    rec = Recognizer(db, cfg)
    diameter = {oid: dataset.models[oid].diameter_m or m.diameter_m for oid, m in db.models.items()}
    chosen = dataset.frames
    if frames is not None and frames < len(chosen):
        chosen = [chosen[i] for i in np.linspace(0, len(chosen) - 1, frames).round().astype(int)]
    standing = [f for f in chosen if f.scene_id not in lying_scenes]
    posed = [f for f in standing if f.world_T_camera is not None]
    pose_of = {
        (f.scene_id, f.image_id): f.world_T_camera
        if world_z_up
        else level_world_pose(rec, f.load()[0], f.world_T_camera)
        for f in posed
    }
    ours = _recognised(rec, standing, pose_of, db, diameter, "recognising", pictures=pictures)
    lying_frames = [f for f in chosen if f.scene_id in lying_scenes]
    lying = _recognised(rec, lying_frames, {}, db, diameter, "lying", pictures=pictures)
    wide = None
    if lookalikes:
        wide = _with_lookalikes(db, cfg, distances_m, lookalikes, standing, pose_of, diameter, pictures)
    # As a sensor without colour, or models without it, leave recognition: shape alone.
    depth = None
    if depth_only:
        depth = _recognised(rec, standing, pose_of, db, diameter, "depth alone", colour=False, pictures=pictures)
    # The frames with the camera's world pose once more without it, as `cellsight recognize` sees a
    # saved frame: the whole view, the room's floor and walls included.
    alone = _recognised(rec, posed, {}, db, diameter, "camera frame", pictures=pictures)
    level = Recognizer(db, cfg.model_copy(update={"level_support": True}))
    alone_level = _recognised(level, posed, {}, db, diameter, "camera frame, level support", pictures=pictures)
    theirs, ppf_times = _baseline(rec, standing, pose_of, db, diameter)
    out = {
        "bop_frames": float(len(chosen)),
        "bop_instances_scored": float(len(ours.rows)),
        "bop_models": float(len(db.models)),
        "bop_model_build_s": build_s,
        "bop_frames_world_pose_set_aside": float(sum(p is None for p in pose_of.values())),
    }
    for name, tally in (("bop_adds_recall", ours), ("bop_ppf_adds_recall", theirs)):
        out[name] = tally.recall() if tally.rows else float("nan")
        for cls in ("unoccluded", "partly_occluded"):
            if (r := tally.recall(cls)) is not None:
                out[f"{name}_{cls}"] = r
    for near, band in ((True, "near"), (False, "far")):
        if (r := ours.recall(near=near)) is not None:
            out[f"bop_adds_recall_{band}"] = r
            out[f"bop_instances_{band}"] = float(sum(n == near for _, n, _ in ours.rows))
    if lying.rows:
        out["bop_adds_recall_lying"] = lying.recall()
        out["bop_instances_lying"] = float(len(lying.rows))
    out["bop_false_detections"] = float(ours.false + lying.false)
    if wide is not None and wide.rows:
        out["bop_adds_recall_lookalikes"] = wide.recall()
        out["bop_false_detections_lookalikes"] = float(wide.false)
        out["bop_frame_ms_p50_lookalikes"] = 1000 * float(np.median(wide.times))
    out["bop_false_detections_per_frame"] = (ours.false + lying.false) / len(chosen)
    if depth is not None and depth.rows:
        out["bop_adds_recall_depth_only"] = depth.recall()
        out["bop_false_detections_depth_only"] = float(depth.false)
    for tally, suffix in ((alone, ""), (alone_level, "_level_support")):
        if tally.rows:
            out[f"bop_adds_recall_camera_frame{suffix}"] = tally.recall()
            out[f"bop_false_detections_camera_frame{suffix}"] = float(tally.false)
            out[f"bop_upside_down_camera_frame{suffix}"] = float(tally.upside_down)
    out["bop_frame_ms_p50"] = 1000 * float(np.median(ours.times))
    if alone.times:
        out["bop_frame_ms_p50_camera_frame"] = 1000 * float(np.median(alone.times))
    out["bop_frame_ms_p95"] = 1000 * float(np.percentile(ours.times, 95))
    if ppf_times:
        out["bop_ppf_frame_ms_p50"] = 1000 * float(np.median(ppf_times))
    return out


def _with_lookalikes(
    db: ModelDatabase,
    cfg: RecognitionConfig,
    distances_m: tuple[float, ...],
    lookalikes: tuple[ObjectSpec, ...],
    frames: list[BopFrame],
    pose_of: dict[tuple[int, int], np.ndarray | None],
    diameter: dict[str, float],
    pictures: Path | None = None,
) -> Tally:
    """The frames recognised with the look-alikes' models added to ``db`` (their views at
    ``distances_m``), each with the world pose the main pass gave it (``pose_of``)."""
    wider = ModelDatabase(db.descriptor, dict(db.models))
    for o in lookalikes:
        wider.add(
            model_from_mesh(o.id, object_mesh(o).paint_uniform_color(o.color), cfg.descriptor, distances_m=distances_m)
        )
    return _recognised(Recognizer(wider, cfg), frames, pose_of, db, diameter, "with look-alikes", pictures=pictures)


def _baseline(
    rec: Recognizer,
    frames: list[BopFrame],
    pose_of: dict[tuple[int, int], np.ndarray | None],
    db: ModelDatabase,
    diameter: dict[str, float],
) -> tuple[Tally, list[float]]:
    """Point-pair voting on the frames that hold objects, given which: scored, and its frame times
    (s). In a pass of its own, so that nothing it leaves behind is in our timings; not on lying
    frames (the whole room in view, ~30 s a frame)."""
    baseline, tally, times = PpfBaseline.of(rec), Tally(), []
    for frame in track(frames, description="point-pair voting"):
        if not frame.truth:
            continue
        cloud, _ = frame.load()
        t0 = time.perf_counter()
        poses = baseline(cloud, pose_of.get((frame.scene_id, frame.image_id)), {i.object_id for i in frame.truth})
        times.append(time.perf_counter() - t0)
        tally.add(frame, list(poses.items()), db, diameter)
    return tally, times


def _class(visible: float | None) -> str | None:
    """The scoring class of an instance by its visible share (None: too hidden to score)."""
    return "all" if visible is None else visibility_class(visible)


def run(quick: bool, args: argparse.Namespace) -> dict[str, float]:
    if args.dataset is not None and args.rough_sensor:
        raise ConfigError(
            "--rough-sensor renders the simulated dataset; a --dataset's frames are as its sensor took them"
        )
    if args.dataset is not None:
        cfg = load_config(args.cell_config).recognition if args.cell_config else RecognitionConfig()
        cfg = cfg.model_copy(update={"free_with_pose": not args.standing})
        dataset = BopDataset.open(args.dataset, args.split, args.models)
        return measure(
            dataset,
            args.frames or (10 if quick else None),
            tuple(args.distance),
            cfg,
            world_z_up=args.world_z_up,
            pictures=args.pictures,
        )
    # The simulated frames carry the cameras' poses in the cell, so the cell's workspace crops them,
    # as in the running cell; PCL's real frames have none and are recognised in the camera frame.
    cfg = RecognitionConfig(workspace_min=WORKSPACE[0], workspace_max=WORKSPACE[1])
    layouts, lying = (1, 1) if quick else (6, 6)
    with tempfile.TemporaryDirectory() as tmp:
        dataset = BopDataset.open(write_default(Path(tmp) / "demo", layouts, lying, rough_sensor=args.rough_sensor))
        out = measure(
            dataset,
            args.frames,
            tuple(args.distance),
            cfg,
            frozenset(range(2 * layouts + 1, 2 * layouts + lying + 1)),
            world_z_up=True,
            lookalikes=() if quick else LOOKALIKES,
            depth_only=not quick,
            pictures=args.pictures,
        )  # the cell's world, written here
        if not quick:
            (Path(tmp) / "meshes").mkdir()
            other = BopDataset.open(
                write_default(Path(tmp) / "shapes", SHAPE_LAYOUTS, 0, shapes(Path(tmp) / "meshes"), args.rough_sensor)
            )
            out |= {
                name.replace("bop_", "bop_shapes_", 1): value
                for name, value in measure(other, None, tuple(args.distance), cfg, world_z_up=True).items()
                if name in SHAPE_FIGURES
            }
        return out


def _args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--dataset",
        type=Path,
        help="a BOP dataset folder (models/, SPLIT/NNNNNN/...); default: one written from the simulator and PCL's real frames",
    )
    parser.add_argument("--split", default="test", help="the dataset's split folder (test, val, test_primesense, ...)")
    parser.add_argument(
        "--models",
        help="the dataset's model folder (default: the first of "
        f"{', '.join(MODEL_FOLDERS)} it has; T-LESS: models_cad or models_reconst)",
    )
    parser.add_argument(
        "--frames", type=int, help="at most this many frames, spread over the split (--quick: 10 of a given dataset)"
    )
    parser.add_argument(
        "--cell-config",
        type=Path,
        help="cell config TOML whose [recognition] is used (default: the defaults; "
        "its workspace crops frames whose scene_camera.json gives the camera's world pose)",
    )
    parser.add_argument(
        "--world-z-up",
        action="store_true",
        help="the dataset's world frame has z up: every frame's world pose is used (default: only where a "
        "plane the frame shows is level in it)",
    )
    parser.add_argument(
        "--standing",
        action="store_true",
        help="every object stands on its model's +z, as a cell's: in a frame with a world pose only "
        "standing objects are looked for (default: also any way up and lying, as without a pose)",
    )
    parser.add_argument(
        "--rough-sensor",
        action="store_true",
        help="render the simulated frames by benchmarks.recognition's rougher sensor (flying pixels, light 15 %% "
        "warmer or cooler, washed-out colour, colour 3 px off); not with --dataset",
    )
    parser.add_argument(
        "--pictures",
        type=Path,
        help="write a picture of each frame a pass got wrong to this folder: "
        "what was found drawn over the frame, the annotated poses outlined in white",
    )
    parser.add_argument(
        "--distance",
        type=float,
        nargs="+",
        default=list(VIEW_DISTANCES_M),
        help="virtual camera distances for the models' views, m (default: as cellsight model build)",
    )


if __name__ == "__main__":
    main("bop", __doc__.splitlines()[0], run, _args)
