"""All message classes that travel on the bus: our own (``schemas/proto``) and Foxglove's."""

from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from schemas.gen.cellsight.cellsight_pb2 import (
    CameraState,
    DriverStatus,
    EstimatorStatus,
    Map,
    MarkerObservation,
    MarkerObservations,
    ObjectDetection,
    ObjectDetections,
    Pose,
    PosesWithCovariance,
    PoseWithCovariance,
    Rejection,
)

__all__ = [
    "CameraCalibration",
    "CameraState",
    "DriverStatus",
    "EstimatorStatus",
    "FrameTransform",
    "FrameTransforms",
    "Map",
    "MarkerObservation",
    "MarkerObservations",
    "ObjectDetection",
    "ObjectDetections",
    "PointCloud",
    "Pose",
    "PosesWithCovariance",
    "PoseWithCovariance",
    "RawImage",
    "Rejection",
    "SceneUpdate",
]
