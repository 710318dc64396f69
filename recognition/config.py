"""Configuration of recognition: descriptor parameters (shared with the model database) and the pipeline."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.spec import PoseSpec


class DescriptorConfig(BaseModel):
    """How a cloud becomes a descriptor. A database stores the values it was built with; a recogniser
    using different ones would compare unlike histograms, so loading checks they agree."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    voxel_m: float = Field(default=0.01, gt=0, description="voxel side for downsampling, m")
    normal_radius_m: float = Field(default=0.03, gt=0, description="neighbourhood radius for normals, m")
    binning: Literal["pcl", "pcl17"] = Field(
        default="pcl", description="VFH f2/f3 binning: 'pcl' = PCL >= 1.10.1 (default), 'pcl17' = PCL 1.7 (the paper's)"
    )


class ObjectMarkerConfig(BaseModel):
    """A fiducial fixed on an object: seeing it names the object and gives a pose prior."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    marker_id: int = Field(ge=0)
    object_id: str
    object_T_marker: PoseSpec


class BoardMarker(BaseModel):
    """One marker of a capture board: its id and ``board_T_marker``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    marker_id: int = Field(ge=0)
    board_T_marker: PoseSpec


class BoardConfig(BaseModel):
    """A marker board for capturing an object's model: the object stands on it, a camera walks round.

    The board frame has z up out of the board; the object frame is the board frame moved by
    ``board_T_object`` (default: the same). Points inside ``object_min``..``object_max`` (board
    frame, m) belong to the object; the bottom of that box keeps clear of the board itself.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    markers: list[BoardMarker] = Field(
        min_length=3, description="at least three, not in a line: placed from their centres"
    )
    board_T_object: PoseSpec = Field(default_factory=PoseSpec)
    object_min: tuple[float, float, float] = (-0.2, -0.2, 0.005)
    object_max: tuple[float, float, float] = (0.2, 0.2, 0.4)
    min_view_angle_deg: float = Field(default=10.0, ge=0, description="a view is kept if this far from every kept one")
    max_views: int = Field(default=60, ge=1)

    @model_validator(mode="after")
    def _box(self) -> BoardConfig:
        if not all(a < b for a, b in zip(self.object_min, self.object_max)):
            raise ValueError(f"object_min {self.object_min} must be below object_max {self.object_max}")
        if len({mk.marker_id for mk in self.markers}) != len(self.markers):
            raise ValueError("board marker ids must be distinct")
        return self


class RecognitionConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(default=True, description="run the recognition worker in `cellsight run`")
    models: Path | None = Field(default=None, description="model database directory (cellsight model build)")
    descriptor: DescriptorConfig = Field(default_factory=DescriptorConfig)
    max_range_m: float = Field(default=3.5, gt=0, description="scene points farther than this are ignored")
    workspace_min: tuple[float, float, float] | None = Field(
        default=None, description="world-frame box where objects can be (m); used once the camera is localized"
    )
    workspace_max: tuple[float, float, float] | None = None
    plane_distance_m: float = Field(default=0.012, gt=0, description="RANSAC inlier distance for plane removal")
    plane_noise_per_m2: float = Field(
        default=0.0043, ge=0, description="plane band grows as this x range^2 (3 sigma of Kinect depth noise, 1/m)"
    )
    max_planes: int = Field(
        default=4,
        ge=0,
        description="planes removed: the first holds min_plane_fraction of the scene (the table, or the "
        "floor; everything behind it goes too), each further one 1 % and a connected patch twice as wide as the largest "
        "object (walls, a table seen across a room); with a workspace box (a localized camera) the first only",
    )
    min_plane_fraction: float = Field(
        default=0.1, gt=0, le=1, description="a dominant plane holds this share of the scene"
    )
    plane_seed: int = Field(
        default=0,
        ge=0,
        description="seed of the plane RANSAC: its draw decides which planes a room's frame loses "
        "(docs/design/recognition.md, Segmentation)",
    )
    cluster_tolerance_m: float = Field(default=0.035, gt=0, description="Euclidean clustering distance")
    cluster_min_points: int = Field(default=30, ge=3)
    cluster_max_points: int = Field(default=25000, ge=3)
    candidates: int = Field(default=4, ge=1, description="nearest model views tried per object and cluster")
    roll_peaks: int = Field(default=2, ge=1, description="roll angles tried per view")
    icp_distance_m: float = Field(default=0.015, gt=0, description="ICP correspondence distance (coarse pass: 2x)")
    icp_iterations: int = Field(
        default=15, ge=1, description="iterations of the ICP that refines the best screened starts"
    )
    min_fitness: float = Field(default=0.5, ge=0, le=1, description="share of the visible model explained by the scene")
    min_coverage: float = Field(default=0.5, ge=0, le=1, description="share of the cluster explained by the model")
    verify: bool = Field(
        default=True,
        description="check every hypothesis against the whole frame from the camera's viewpoint (recognition.verify)",
    )
    min_visible_fitness: float = Field(
        default=0.85,
        ge=0,
        le=1,
        description="verification: share of the judgeable visible model on the measured surface, not in front of it "
        "(midway between the simulated hypotheses within 2 cm and 10 deg of the rendered pose, min 0.94, and the real "
        "scenes' false ones that pass the other tests, max 0.76: a tote fitted over a smaller box in PCL's grabber frames)",
    )
    min_visible_support: float = Field(
        default=0.6,
        ge=0,
        le=1,
        description="verification: share of the visible model found on the measured surface (simulated true detections: min 0.67)",
    )
    min_facing_share: float = Field(
        default=0.5,
        ge=0,
        le=1,
        description="verification: share of the posed model's pixels where its nearest surface faces the camera; below "
        "it the camera looks at a captured view from behind, the side it has no surface for (the rule that keeps a "
        "captured view's viewpoints; true detections in benchmarks.bop's frames: min 0.76 of 997; a milk carton's "
        "captured view posed back to front on office1.pcd by a damped ICP: 0.32-0.39)",
    )
    max_clutter: float = Field(
        default=0.2,
        ge=0,
        le=1,
        description="verification: largest share of the measured outline where the scene continues the model's surface "
        "(fitted onto part of a larger surface; simulated true detections: max 0.12; a milk carton on a person in PCL's "
        "five_people.pcd: 0.26)",
    )
    max_flush: float = Field(
        default=0.5,
        ge=0,
        le=1,
        description="verification: largest share of the measured outline flush with the model's edge beside it (no "
        "depth step; where the object meets its support aside): the model drawn on a surface that goes on, which the "
        "clutter test misses where the model's edge curves away (a can's side; simulated true detections: max 0.18 of "
        "1,073; a can and a tote on people's backs in PCL's five_people.pcd: 0.80, 0.81)",
    )
    min_outline_seen: float = Field(
        default=0.6,
        ge=0,
        le=1,
        description="verification: share of the outline with measured depth; below it nothing shows the object ends "
        "there (simulated true detections: min 0.89; PCL's milk in its scene 0.84; a false milk in office1.pcd 0.48)",
    )
    colour_tolerance: float = Field(
        default=0.1,
        gt=0,
        le=1,
        description="verification: a scene pixel has the model's colour when its rg-chromaticity (r, g over r + g + b) "
        "is within this, in r and in g, of the colours the model has within 1 cm of the point there (the demo's red can "
        "against a grey box: 0.36 in r; sensor noise on the simulated objects: median 0.01)",
    )
    colour_min_saturation: float = Field(
        default=0.5,
        gt=0,
        le=1,
        description="verification: a scene pixel also has the model's colour when it is the model's paled towards grey, "
        "down to this share of its saturation (a sensor's colour response, a model textured by another camera), never so "
        "far that grey would agree (1: off; the demo objects rendered at 0.7 of their saturation: 0.69 of them found "
        "without it, all with it)",
    )
    max_shape_error: float = Field(
        default=2.0,
        ge=0,
        description="verification: largest spread of the inliers' depth residual, its shift and tilt taken out, beyond "
        "1 mm, in depth-noise sigmas at the object's depth (plane_noise_per_m2 / 3 z^2; simulated true detections: max 1.0 "
        "of 1,041; cans laid along a box's edge in PCL's grabber frames 3.6-4.3)",
    )
    min_colour_agreement: float = Field(
        default=0.3,
        ge=0,
        le=1,
        description="verification, where frame and model have colour: share of the inlier pixels with the model's "
        "colour (simulated true detections: min 0.49 of 462 on four layout seeds, edge pixels take the background's; "
        "grey look-alikes fitted as the red can: max 0.02 of 24; 0: colour off)",
    )
    max_penetration: float = Field(
        default=0.01,
        ge=0,
        le=1,
        description="verification: largest share of the visible model hidden by a removed support plane and over "
        "icp_distance_m behind it, i.e. inside the table (simulated true detections: 0 over 104; a crate posed into "
        "a tote and the table: 0.016, 0.02)",
    )
    max_float_m: float = Field(
        default=0.02,
        ge=0,
        description="objects rest on a level support or on another object found under them: a detection whose lowest "
        "point is more than this above both is rejected; applies once the camera's world pose is known, or without it on "
        "the level plane a frame shows (0: off; simulated false detections: totes fitted over a crate's top, 3-4 cm up; "
        "a milk carton fitted to a leg in PCL's five_people.pcd, the floor removed)",
    )
    min_fitness_shared: float = Field(
        default=0.8,
        ge=0,
        le=1,
        description="fitness that accepts a match covering only part of a cluster (touching objects)",
    )
    max_rmse_m: float = Field(default=0.01, gt=0, description="inlier RMSE above which a match is rejected")
    upright: bool = Field(
        default=True,
        description="objects stand on their base (object +z within 45 deg of world up): rejects the flipped poses a "
        "symmetric shape allows; applies once the camera's world pose is known",
    )
    free_with_pose: bool = Field(
        default=False,
        description="with the camera's world pose too, try each object both any way up and standing on the support "
        "(and lying on its sides, in frames with colour), as stand_on_level does without one: for a dataset's frames, "
        "whose objects need not stand on their model's +z; a cell's objects stand, so off by default",
    )
    level_support: bool = Field(
        default=False,
        description="without the camera's world pose (cellsight recognize, a dataset's frames): take the removed plane "
        "whose normal is nearest the image's up (the table, or the floor; the camera mounted upright) as level, its normal "
        "as world up, so that the upright test applies and objects stand on the level plane nearest the camera; for scenes "
        "whose objects all stand on their base (stand_on_level tries them both ways)",
    )
    stand_on_level: bool = Field(
        default=True,
        description="without the camera's world pose and level_support: try each object both any way up and standing "
        "on that level plane (its normal as world up, the upright test, the pieces path), and let verification choose; "
        "about twice the work of a frame",
    )
    rest_on_sides: bool = Field(
        default=True,
        description="with stand_on_level, in frames with colour: also try each object lying on that plane on each of "
        "its four sides (+-x, +-y of its frame), as a dataset's objects may lie; a lying hypothesis is kept only if its "
        "colour could be judged",
    )
    object_markers: list[ObjectMarkerConfig] = Field(default_factory=list)

    @model_validator(mode="after")
    def _box(self) -> RecognitionConfig:
        if (self.workspace_min is None) != (self.workspace_max is None):
            raise ValueError("give both workspace_min and workspace_max, or neither")
        if self.workspace_min is not None and not all(a < b for a, b in zip(self.workspace_min, self.workspace_max)):
            raise ValueError(f"workspace_min {self.workspace_min} must be below workspace_max {self.workspace_max}")
        return self

    rate_hz: float = Field(
        default=1.0, gt=0, description="worker: frames recognised per camera per second (one takes ~0.1 s of a core)"
    )
    min_cross_view_fitness: float = Field(
        default=0.35,
        ge=0,
        le=1,
        description="worker: a detection another localized camera can judge (its last frame, within "
        "cross_view_max_age_s) with less than this share of what it could judge on its measured surface, the rest in "
        "front of it, was seen through there and is not reported (simulated correct detections in other cameras' "
        "views: min 0.41 over 846; poses shifted 10-20 cm: 63 % below 0.35; 0: no check)",
    )
    cross_view_max_age_s: float = Field(
        default=2.0,
        gt=0,
        description="worker: how far apart (s) a detection and another camera's frame may be for that frame to judge it",
    )
    refine_in_cloud: bool = Field(
        default=False,
        description="worker: fit each fused object to every localized camera's points around it (their last frames "
        "within cross_view_max_age_s), so its pose is held on all its sides at once (recognition.fusion.refined_in_cloud; "
        "with true camera poses fused position error p50 2.0 -> 1.2 mm, p90 4.7 -> 2.3; on the rendered demo, camera "
        "poses estimated and the tote sliding, no better and ~15 % fewer frames recognised: off by default)",
    )
    refine_period_s: float = Field(
        default=2.0,
        ge=0,
        description="worker: fit the fused objects at most this often (s; a fit of the demo's 3 objects in 4 cameras' "
        "points takes ~0.15 s of a core); between fits an object keeps its last fitted pose while its fused pose stays "
        "within 5 mm and 2 deg of the one fitted",
    )
    search_fused_cloud: bool = Field(
        default=True,
        description="worker: look for the objects no camera found in every localized camera's points together, put in one "
        "camera's frame and verified against it, then cross-checked by the others (recognition.fusion.found_in_cloud); "
        "one camera's frame a search_period_s, in turn, only while an object is missing (~0.17 s of a core a search)",
    )
    search_period_s: float = Field(default=2.0, gt=0, description="worker: at most one such search this often (s)")
    cloud_voxel_m: float = Field(
        default=0.03,
        ge=0,
        description="worker: voxel of the fused world point cloud it publishes on `points` (0: none)",
    )
