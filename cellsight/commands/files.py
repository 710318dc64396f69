"""Commands on single files: ``model build``, ``recognize``, ``sim snapshot``, ``markers detect``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from cellsight.commands.common import (
    CellConfigOpt,
    ScenarioOpt,
    VerboseOpt,
    fail,
    load,
    setup_logging,
    stderr,
)

model_app = typer.Typer(help="Recognition model databases.", no_args_is_help=True)
sim_app = typer.Typer(help="The simulated work cell.", no_args_is_help=True)
markers_app = typer.Typer(help="The marker front-end on single images.", no_args_is_help=True)


@model_app.command("build")
def model_build(
    out: Annotated[Path, typer.Option("--out", help="database folder to write")],
    scenario: Annotated[Path | None, typer.Option("--scenario", help="every object of this scenario TOML")] = None,
    demo: Annotated[bool, typer.Option("--demo", help="every object of the built-in demo cell")] = False,
    mesh: Annotated[
        list[str] | None,
        typer.Option("--mesh", help="ID=FILE: a mesh (PLY/OBJ/STL), metres; coloured by its vertex colours or texture"),
    ] = None,
    cloud: Annotated[
        list[str] | None,
        typer.Option("--cloud", help="ID=FILE: a point cloud (PCD/PLY), metres, captured from its origin"),
    ] = None,
    points: Annotated[
        list[str] | None,
        typer.Option("--points", help="ID=FILE: points over the whole surface (PLY/PCD/XYZ), metres, object frame"),
    ] = None,
    recording: Annotated[
        list[str] | None,
        typer.Option("--recording", help="ID=LOG.mcap: a camera walking round the object on the --board"),
    ] = None,
    board: Annotated[
        Path | None,
        typer.Option("--board", help="marker board TOML of the recordings (see drivers/sim/capture_board.toml)"),
    ] = None,
    distance: Annotated[
        list[float] | None,
        typer.Option(
            help="virtual camera distance for the views of --mesh and --points models and the scenario's, m; repeat for "
            "several (default: 2.0 and 0.8)"
        ),
    ] = None,
    scale: Annotated[
        float, typer.Option(help="metres per unit of the --mesh, --cloud and --points files (0.001: millimetres)")
    ] = 1.0,
    cell_config: CellConfigOpt = None,
) -> None:
    """Build a recognition model database (views from a tessellated sphere; descriptors as configured)."""
    from rich.progress import Progress

    from cellsight.model_build import VIEWS_PER_OBJECT, build_database, load_board
    from drivers.sim.scenario import load_scenario
    from recognition.models import VIEW_DISTANCES_M

    def pairs(items: list[str] | None, what: str) -> dict[str, Path]:
        out_ = {}
        for item in items or []:
            oid, sep, path = item.partition("=")
            if not sep or not oid or not path:
                raise fail(f"--{what} {item!r}: write it as ID=FILE", 2)
            out_[oid] = Path(path)
        return out_

    meshes, clouds, recordings = pairs(mesh, "mesh"), pairs(cloud, "cloud"), pairs(recording, "recording")
    surfaces = pairs(points, "points")
    if not (scenario or demo or meshes or clouds or surfaces or recordings):
        raise fail(
            "nothing to build: give --demo, --scenario FILE, --mesh ID=FILE, --cloud ID=FILE, --points ID=FILE or --recording ID=LOG",
            2,
        )
    cfg = load(cell_config)
    sc = load_scenario(scenario) if (scenario or demo) else None
    board_cfg = load_board(board) if board else None
    distances = tuple(distance) if distance else VIEW_DISTANCES_M
    if not all(d > 0 for d in distances):
        raise fail(f"--distance {list(distances)}: each must be positive", 2)
    rendered = len(distances) * ((len(sc.objects) if sc else 0) + len(meshes) + len(surfaces))
    total = VIEWS_PER_OBJECT * (rendered + len(clouds) + len(recordings))
    with Progress(console=stderr(), transient=True) as bar:
        task = bar.add_task("rendering and describing views", total=total)
        db = build_database(
            cfg.recognition.descriptor,
            scenario=sc,
            meshes=meshes,
            clouds=clouds,
            points=surfaces,
            recordings=recordings,
            board=board_cfg,
            distances_m=distances,
            scale=scale,
            progress=lambda: bar.advance(task),
        )
    db.save(out)
    for oid, mdl in sorted(db.models.items()):
        colour = "in colour" if mdl.colours is not None else "no colour: verified on depth alone"
        typer.echo(
            f"{oid}: {len(mdl.views)} views, {len(mdl.points)} model points, diameter {mdl.diameter_m:.3f} m ({mdl.source}, {colour})"
        )
    typer.echo(f"wrote {out}/")


def recognize_cmd(
    models: Annotated[Path, typer.Option("--models", help="model database folder (cellsight model build)")],
    scene: Annotated[
        Path, typer.Option("--scene", help="scene: PCD/PLY cloud (m), or 16-bit depth image (mm); see --scale")
    ],
    rgb: Annotated[
        Path | None,
        typer.Option(
            "--rgb", help="colour image registered to a depth image scene (same size): verification then judges colour"
        ),
    ] = None,
    fx: Annotated[float | None, typer.Option(help="depth image focal length x, px (default Kinect v1)")] = None,
    fy: Annotated[float | None, typer.Option(help="depth image focal length y, px")] = None,
    cx: Annotated[float | None, typer.Option(help="depth image principal point x, px")] = None,
    cy: Annotated[float | None, typer.Option(help="depth image principal point y, px")] = None,
    scale: Annotated[
        float | None,
        typer.Option(
            help="metres per unit of the scene (default: 1 for a cloud, 0.001 for a depth image in mm; 0.0001 for 0.1 mm depth)"
        ),
    ] = None,
    standing: Annotated[
        bool,
        typer.Option(
            "--standing",
            help="every object stands on its base on the table or floor: "
            "take that plane as level ([recognition] level_support)",
        ),
    ] = False,
    picture: Annotated[
        Path | None,
        typer.Option(
            "--picture",
            help="write the scene (its colour, else its depth) with each object found drawn on it: its "
            "visible points, outline, axes, id and fitness (.png or .jpg)",
        ),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
    cell_config: CellConfigOpt = None,
    verbose: VerboseOpt = False,
) -> None:
    """Recognise the database's objects in one scene and print their poses in the camera frame."""
    from cellsight.recognize_cmd import recognize_file
    from recognition.models import ModelDatabase

    setup_logging(verbose)
    cfg = load(cell_config)
    db = ModelDatabase.load(models)
    update = {"descriptor": db.descriptor} | ({"level_support": True} if standing else {})
    result = recognize_file(
        scene,
        db,
        cfg.recognition.model_copy(update=update),
        picture=picture,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        scale=scale,
        rgb=rgb,
    )
    typer.echo(result.to_json() if as_json else result.to_text())
    if not result.detections:
        raise typer.Exit(1)


@sim_app.command("snapshot")
def sim_snapshot(
    out: Annotated[Path, typer.Option("--out", help="folder for <camera>_rgb.png and <camera>_depth.png")],
    scenario: ScenarioOpt = None,
    time_s: Annotated[float, typer.Option("--time", help="scenario time in seconds")] = 1.0,
) -> None:
    """Render every camera once and write RGB and false-colour depth PNGs to look at."""
    from cellsight.evaluation.pictures import write_snapshot
    from drivers.sim.scenario import load_scenario

    written = write_snapshot(load_scenario(scenario), out, time_s)
    for p in written:
        typer.echo(str(p))


@markers_app.command("detect")
def markers_detect(
    image: Annotated[Path, typer.Argument(help="image file (PNG, JPEG)")],
    dictionary: Annotated[
        str, typer.Option("--dict", help="OpenCV dictionary name or a .yml file")
    ] = "DICT_APRILTAG_36h11",
    camera_info: Annotated[
        Path | None,
        typer.Option(
            "--camera-info", help="OpenCV YAML with camera_matrix and distortion_coefficients (default: Kinect v1)"
        ),
    ] = None,
    size: Annotated[float, typer.Option("--size", help="marker side length in metres")] = 0.15,
    depth: Annotated[Path | None, typer.Option("--depth", help="registered 16-bit depth PNG in millimetres")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False,
    annotate: Annotated[
        Path | None, typer.Option("--annotate", help="write the image with markers and axes drawn")
    ] = None,
) -> None:
    """Detect markers in one image and print ids, corners and poses."""
    from cellsight.detect import detect_file

    result = detect_file(image, dictionary, camera_info, size, depth, annotate)
    typer.echo(result.to_json() if as_json else result.to_text())
