"""Configuration of sensors and of the marker front-end."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.keys import check_name


class IntrinsicsConfig(BaseModel):
    """Pinhole intrinsics; omitted in a camera section means Kinect v1 defaults for its size."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)


class MarkerConfig(BaseModel):
    """What the marker front-end looks for."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    dictionary: str = Field(default="DICT_APRILTAG_36h11", description="OpenCV predefined dictionary name")
    side_m: float = Field(default=0.15, gt=0, description="printed black-square side length")
    sides_m: dict[int, Annotated[float, Field(gt=0)]] = Field(
        default_factory=dict, description="per-id side lengths overriding side_m"
    )
    use_depth: bool = Field(default=True, description="refine poses with the registered depth when available")
    corner_refinement: Literal["edges", "none", "subpix", "contour", "apriltag"] = Field(
        default="edges",
        description="edges: lines fitted to the black border's outer edges, corners where they meet (needs a light margin "
        "round the marker; falls back to OpenCV's corners where an edge is not found); otherwise OpenCV's refinement",
    )
    detector_params: Path | None = Field(
        default=None, description="OpenCV DetectorParameters YAML; the values it gives override ours"
    )
    pixel_sigma: float = Field(default=0.25, gt=0, description="corner noise (px) behind the covariance model")
    opencv_threads: int = Field(
        default=1,
        ge=0,
        description="OpenCV's threads in each driver process (0: OpenCV's default, a pool over every core). One costs "
        "the least where drivers share the cores: 2-28 % less CPU a frame at 1, 2 and 4 drivers on 2 cores, poses no later",
    )

    def side_for(self, marker_id: int) -> float:
        return self.sides_m.get(marker_id, self.side_m)


class CameraConfig(BaseModel):
    """One sensor and the driver process that serves it."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: str
    source: Literal["sim", "openni2", "realsense", "ros2"] = "sim"
    uri: str = Field(default="", description="openni2: device URI, 'Dummy' or a .oni file; empty = first device")
    serial: str = Field(default="", description="realsense: the device's serial number; empty = first device")
    recording: Path | None = Field(
        default=None, description="realsense: play this .bag/.db3 recording instead of a device"
    )
    color_topic: str = Field(
        default="/camera/camera/color/image_raw", description="ros2: colour image topic (rgb8/bgr8)"
    )
    depth_topic: str = Field(
        default="/camera/camera/aligned_depth_to_color/image_raw",
        description="ros2: depth aligned to colour (16UC1 mm or 32FC1 m)",
    )
    info_topic: str = Field(
        default="/camera/camera/color/camera_info", description="ros2: the colour camera's CameraInfo"
    )
    width: int = Field(default=640, gt=0)
    height: int = Field(default=480, gt=0)
    rate_hz: float = Field(default=30.0, gt=0)
    intrinsics: IntrinsicsConfig | None = None
    publish_images: bool = Field(default=True, description="publish color/depth (markers are always published)")
    prerender_frames: int = Field(
        default=0,
        ge=0,
        description="sim: render this many frames up front and loop them (benchmarks: no renderer cost)",
    )
    openni2_path: Path | None = Field(default=None, description="folder holding libOpenNI2.so (default: system)")

    @model_validator(mode="after")
    def _id_is_a_key(self) -> CameraConfig:
        check_name(self.id, "camera id")
        return self
