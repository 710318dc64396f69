"""Configuration of the estimator: anchors (the world frame) and solver settings."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field, field_validator

from schemas.spec import PoseSpec


class AnchorConfig(BaseModel):
    """A marker with a surveyed world pose; it becomes a prior factor."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    marker_id: int = Field(ge=0)
    world_T_marker: PoseSpec
    sigma_position_m: float = Field(default=0.001, gt=0, description="surveyed position sigma")
    sigma_rotation_deg: float = Field(default=0.1, gt=0, description="surveyed rotation sigma")


class KeyframeConfig(BaseModel):
    """Moving-camera frames as poses of their own, in the offline solve and (a fixed lag) in the daemon."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(
        default=True, description="add moving cameras' frames as poses of their own to the offline solve"
    )
    online: bool = Field(
        default=True,
        description="the daemon adds a move's frames too, once the camera is still again and its new segment is in the graph "
        "(measured: see docs/performance.md, online_keyframes_over_without_max and estimator_scale --arm)",
    )
    max_live: int = Field(
        default=60,
        ge=1,
        description="online: the newest this many moving frames stay in the graph, older ones leave it",
    )
    max_markers_online: int = Field(
        default=0,
        ge=0,
        description="online: a moving frame's factors go to at most this many of its markers, the best-determined "
        "(smallest position covariance; 0: all). A latency knob for cells whose cameras each see dozens of markers, at a "
        "cost in accuracy (docs/design/estimator.md)",
    )
    lag_s: float = Field(
        default=2.0,
        ge=0,
        description="online: a camera still moving enters its held frames once they are this old, min_frames at a time (a "
        "camera on an arm never stops; 0: only when its move ends)",
    )
    min_gap_s: float = Field(default=0.1, gt=0, description="at most one frame per camera this often")
    max_frames: int = Field(
        default=2000, ge=1, description="past this, every other kept frame is dropped and the gap doubles"
    )
    new_view_deg: float = Field(
        default=0.2,
        ge=0,
        description="a frame is a new view only if it turned this much (or moved new_view_m) from its camera's segments and "
        "from the frame kept before it: one pixel is 0.11 deg, and frames of a camera settling after a move see what its next "
        "segment sees, with the same bias",
    )
    new_view_m: float = Field(default=0.005, ge=0, description="see new_view_deg")
    min_frames: int = Field(
        default=8,
        ge=1,
        description="a move's frames join only if at least this many are new views: a few single frames bring their noise "
        "and biases more than they inform (a camera caught at ~5 frames/s during a 2 s tilt leaves 3-4; at 30 Hz, ~20)",
    )
    weigh_by_fit: bool = Field(
        default=True,
        description="scale a move's frames' covariances by how much better the static pairs fit than their covariances "
        "claim, against how the frames fit theirs (a-posteriori variance factors, estimator/variance.py; never below 1)",
    )
    max_inflation: float = Field(
        default=10.0,
        ge=1,
        description="with weigh_by_fit, a move's frames are left out when their covariances would be scaled by more than "
        "this: twenty frames then count for under two, less than a static pair's refresh gives, for twenty poses in the graph",
    )


class LinkConfig(BaseModel):
    """Object markers seen by several cameras at one instant, offline and in the daemon (``estimator.links``)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    enabled: bool = Field(default=True, description="link cameras through object markers they see at the same instant")
    min_gap_s: float = Field(default=0.2, gt=0, description="at most one linked instant per marker this often")
    sync_ms: float = Field(
        default=2.0,
        ge=0,
        description="sightings further apart than this are not the same instant (an object at 0.5 m/s moves 1 mm in 2 ms)",
    )
    max_links: int = Field(
        default=2000, ge=1, description="past this, every other instant is dropped and the gap doubles"
    )
    online: bool = Field(
        default=True,
        description="the daemon links cameras too, over its newest max_live instants that are new views and add at "
        "least min_gain (where static markers already hold every camera, as on the rendered demo, none do; along a "
        "weak chain they halve the far cameras' errors: docs/performance.md, online_links_* and chain_links_*)",
    )
    max_live: int = Field(
        default=100, ge=1, description="linked instants in the daemon's graph; older ones leave it (a fixed lag)"
    )
    min_gain: float = Field(
        default=0.5,
        ge=0,
        le=1,
        description="online, an instant enters only if, for two of its cameras, it removes at least this share of the "
        "predicted variance of their relative position at the marker. One frame's evidence removing a share g helps only "
        "while the fused factors it meets overstate their errors by less than sqrt((2 - g) / (1 - g)) (1.45x at 0.1, "
        "1.7x at 0.5), and its own bias moves the cameras by g of it (the rendered demo's instants: 0.06-0.37; a "
        "corridor's far cameras: up to 0.9). 0: every instant",
    )


class EstimatorConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    anchors: list[AnchorConfig] = Field(default_factory=list)
    object_markers: list[int] = Field(
        default_factory=list, description="markers on moving objects: posed per frame, never fused into the map"
    )
    known_markers: list[int] | None = Field(
        default=None, description="ids the cell uses; others are counted as unknown (None: accept all)"
    )
    huber_k: float = Field(default=1.345, gt=0, description="Huber threshold in whitened units")
    relinearize_threshold: float = Field(
        default=0.001,
        gt=0,
        description="iSAM2 relinearises a camera (or keyframe, object) variable once its update exceeds this in any "
        "component (rad, m)",
    )
    relinearize_threshold_markers: float = Field(
        default=0.002,
        gt=0,
        description="the same for marker variables: a large cell's far markers drift by more than 0.001 between "
        "checks, and relinearising them re-eliminated most of its Bayes tree (64 cameras, 1,000 markers: ~500 of "
        "1,064 variables every 10 updates). At 0.005 the rendered demo's camera errors were up to a third (0.1-0.35 mm) "
        "above a converged solve's of the same factors; 0.002 matches that solve there and cost the 64-camera cell "
        "nothing measurable",
    )
    reorder_fill: float = Field(
        default=1.5,
        ge=0,
        description="iSAM2 re-orders every variable in one batch once its Bayes tree's fill-in grows past this multiple "
        "of the last batch's (0: never). An update orders only the variables it touches, so in a cell whose cameras "
        "keep moving the tree degrades: 16 cameras and 250 markers after 25 moves, one refreshed factor cost 4.0 ms "
        "(0.6 ms in a freshly ordered tree); with 1.5, update p99 15 -> 5.3 ms, a batch taking 5-10 ms",
    )
    refresh_s: float = Field(default=1.0, gt=0, description="how often a fused pair factor is replaced")
    refresh_sigma: float = Field(
        default=0.05,
        ge=0,
        description="a settled pair's factor is rebuilt only when its mean moved this many of the factor's own sigmas "
        "(Mahalanobis, 6 dof) or its covariance 10 %; the solution then stays within refresh_sigma x sqrt(pairs) of "
        "rebuilding every refresh_s, in its own covariance's units (0: rebuild every refresh_s)",
    )
    max_fused: int = Field(
        default=4,
        ge=1,
        description="cap on how many observations a fused factor counts as independent: a static view repeats its bias "
        "(pixel grid, depth quantisation), so averaging stops paying after a few (with OpenCV's corners the bias was ~1 "
        "single-frame sigma at 3 m; with the edge-fitted ones 16 changed nothing measurable on the demo cell)",
    )
    view_rotation_sigma_deg: float = Field(
        default=0.3,
        ge=0,
        description="rotation error of one static view of a marker that averaging its frames does not remove (corner "
        "and edge positions the pixel grid biases the same way every frame, quantised depth; the demo cell's fused views "
        "are off by 0.09 deg median, 0.36 p90); added to every pair factor's rotation covariance, so a camera is placed "
        "by where its markers are more than by how they look turned (0: trust the detector's rotations)",
    )
    update_hz: float = Field(
        default=10.0,
        gt=0,
        description="solver updates per second in the daemon when no frames arrive; also the most the map (markers, status) is published",
    )
    max_update_hz: float = Field(
        default=30.0,
        gt=0,
        description="arriving frames trigger an update at once, at most this often (what arrives meanwhile goes in together)",
    )
    stale_after_s: float = Field(default=0.7, gt=0, description="a camera with no frames this long is stale")
    clock_jump_s: float = Field(
        default=5.0,
        gt=0,
        description="a camera's stamps and their arrival times disagreeing by more than this between two frames is a jump of "
        "that sensor's clock (an NTP step), which the daemon takes out; well above transport delay under load (~1 s)",
    )
    bump_position_m: float = Field(
        default=0.01,
        gt=0,
        description="marker shift in the camera frame (the median marker's, or the camera's own in a rigid fit of them all) that signals a move",
    )
    bump_frames: int = Field(
        default=2, ge=1, description="consecutive frames above the threshold before a camera counts as moved"
    )
    settle_frames: int = Field(
        default=5, ge=1, description="consecutive still frames before a moved camera gets a new segment"
    )
    fold_after_s: float = Field(
        default=2.0,
        ge=0,
        description="a camera segment that ended is folded into the camera's history when the next enters the graph, or at the latest this long after it began",
    )
    anchor_check_m: float = Field(default=0.05, gt=0, description="anchor disagreement that flags a moved anchor")
    state_file: Path | None = Field(default=None, description="where the daemon persists its map")
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    links: LinkConfig = Field(default_factory=LinkConfig)

    @field_validator("reorder_fill")
    @classmethod
    def _fill_above_one(cls, v: float) -> float:
        if 0 < v <= 1:
            raise ValueError(
                f"reorder_fill {v} would re-order the whole tree on every update: give 0 (never) or more than 1"
            )
        return v
