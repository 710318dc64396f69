from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Pose(_message.Message):
    __slots__ = ("x", "y", "z", "qx", "qy", "qz", "qw")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    qx: float
    qy: float
    qz: float
    qw: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ...) -> None: ...

class MarkerObservation(_message.Message):
    __slots__ = ("marker_id", "dictionary", "side_m", "corners_px", "candidate_a", "reprojection_error_a_px", "candidate_b", "reprojection_error_b_px", "camera_T_marker", "covariance", "depth_refined", "ambiguous")
    MARKER_ID_FIELD_NUMBER: _ClassVar[int]
    DICTIONARY_FIELD_NUMBER: _ClassVar[int]
    SIDE_M_FIELD_NUMBER: _ClassVar[int]
    CORNERS_PX_FIELD_NUMBER: _ClassVar[int]
    CANDIDATE_A_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_ERROR_A_PX_FIELD_NUMBER: _ClassVar[int]
    CANDIDATE_B_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_ERROR_B_PX_FIELD_NUMBER: _ClassVar[int]
    CAMERA_T_MARKER_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    DEPTH_REFINED_FIELD_NUMBER: _ClassVar[int]
    AMBIGUOUS_FIELD_NUMBER: _ClassVar[int]
    marker_id: int
    dictionary: str
    side_m: float
    corners_px: _containers.RepeatedScalarFieldContainer[float]
    candidate_a: Pose
    reprojection_error_a_px: float
    candidate_b: Pose
    reprojection_error_b_px: float
    camera_T_marker: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    depth_refined: bool
    ambiguous: bool
    def __init__(self, marker_id: _Optional[int] = ..., dictionary: _Optional[str] = ..., side_m: _Optional[float] = ..., corners_px: _Optional[_Iterable[float]] = ..., candidate_a: _Optional[_Union[Pose, _Mapping]] = ..., reprojection_error_a_px: _Optional[float] = ..., candidate_b: _Optional[_Union[Pose, _Mapping]] = ..., reprojection_error_b_px: _Optional[float] = ..., camera_T_marker: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., depth_refined: _Optional[bool] = ..., ambiguous: _Optional[bool] = ...) -> None: ...

class MarkerObservations(_message.Message):
    __slots__ = ("camera_id", "stamp_ns", "image_width", "image_height", "markers")
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    IMAGE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    IMAGE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    MARKERS_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    stamp_ns: int
    image_width: int
    image_height: int
    markers: _containers.RepeatedCompositeFieldContainer[MarkerObservation]
    def __init__(self, camera_id: _Optional[str] = ..., stamp_ns: _Optional[int] = ..., image_width: _Optional[int] = ..., image_height: _Optional[int] = ..., markers: _Optional[_Iterable[_Union[MarkerObservation, _Mapping]]] = ...) -> None: ...

class DriverStatus(_message.Message):
    __slots__ = ("camera_id", "stamp_ns", "state", "source", "rate_hz", "frames", "dropped", "message")
    class State(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATE_UNKNOWN: _ClassVar[DriverStatus.State]
        STARTING: _ClassVar[DriverStatus.State]
        RUNNING: _ClassVar[DriverStatus.State]
        NO_DEVICE: _ClassVar[DriverStatus.State]
        ERROR: _ClassVar[DriverStatus.State]
        STOPPED: _ClassVar[DriverStatus.State]
    STATE_UNKNOWN: DriverStatus.State
    STARTING: DriverStatus.State
    RUNNING: DriverStatus.State
    NO_DEVICE: DriverStatus.State
    ERROR: DriverStatus.State
    STOPPED: DriverStatus.State
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    stamp_ns: int
    state: DriverStatus.State
    source: str
    rate_hz: float
    frames: int
    dropped: int
    message: str
    def __init__(self, camera_id: _Optional[str] = ..., stamp_ns: _Optional[int] = ..., state: _Optional[_Union[DriverStatus.State, str]] = ..., source: _Optional[str] = ..., rate_hz: _Optional[float] = ..., frames: _Optional[int] = ..., dropped: _Optional[int] = ..., message: _Optional[str] = ...) -> None: ...

class PoseWithCovariance(_message.Message):
    __slots__ = ("parent_frame_id", "child_frame_id", "stamp_ns", "pose", "covariance")
    PARENT_FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    CHILD_FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    parent_frame_id: str
    child_frame_id: str
    stamp_ns: int
    pose: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, parent_frame_id: _Optional[str] = ..., child_frame_id: _Optional[str] = ..., stamp_ns: _Optional[int] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...

class PosesWithCovariance(_message.Message):
    __slots__ = ("stamp_ns", "poses")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    poses: _containers.RepeatedCompositeFieldContainer[PoseWithCovariance]
    def __init__(self, stamp_ns: _Optional[int] = ..., poses: _Optional[_Iterable[_Union[PoseWithCovariance, _Mapping]]] = ...) -> None: ...

class CameraState(_message.Message):
    __slots__ = ("camera_id", "state", "segment", "last_stamp_ns", "markers_seen", "position_sigma_m")
    class State(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATE_UNKNOWN: _ClassVar[CameraState.State]
        LOCALIZED: _ClassVar[CameraState.State]
        UNANCHORED: _ClassVar[CameraState.State]
        MOVING: _ClassVar[CameraState.State]
        STALE: _ClassVar[CameraState.State]
    STATE_UNKNOWN: CameraState.State
    LOCALIZED: CameraState.State
    UNANCHORED: CameraState.State
    MOVING: CameraState.State
    STALE: CameraState.State
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_FIELD_NUMBER: _ClassVar[int]
    LAST_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    MARKERS_SEEN_FIELD_NUMBER: _ClassVar[int]
    POSITION_SIGMA_M_FIELD_NUMBER: _ClassVar[int]
    camera_id: str
    state: CameraState.State
    segment: int
    last_stamp_ns: int
    markers_seen: int
    position_sigma_m: float
    def __init__(self, camera_id: _Optional[str] = ..., state: _Optional[_Union[CameraState.State, str]] = ..., segment: _Optional[int] = ..., last_stamp_ns: _Optional[int] = ..., markers_seen: _Optional[int] = ..., position_sigma_m: _Optional[float] = ...) -> None: ...

class EstimatorStatus(_message.Message):
    __slots__ = ("stamp_ns", "cameras", "observations", "rejected", "unknown_markers", "flagged_anchors", "update_ms", "factors", "factors_rebuilt", "update_cpu_ms", "rejections")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    UNKNOWN_MARKERS_FIELD_NUMBER: _ClassVar[int]
    FLAGGED_ANCHORS_FIELD_NUMBER: _ClassVar[int]
    UPDATE_MS_FIELD_NUMBER: _ClassVar[int]
    FACTORS_FIELD_NUMBER: _ClassVar[int]
    FACTORS_REBUILT_FIELD_NUMBER: _ClassVar[int]
    UPDATE_CPU_MS_FIELD_NUMBER: _ClassVar[int]
    REJECTIONS_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    cameras: _containers.RepeatedCompositeFieldContainer[CameraState]
    observations: int
    rejected: int
    unknown_markers: int
    flagged_anchors: _containers.RepeatedScalarFieldContainer[int]
    update_ms: float
    factors: int
    factors_rebuilt: int
    update_cpu_ms: float
    rejections: _containers.RepeatedCompositeFieldContainer[Rejection]
    def __init__(self, stamp_ns: _Optional[int] = ..., cameras: _Optional[_Iterable[_Union[CameraState, _Mapping]]] = ..., observations: _Optional[int] = ..., rejected: _Optional[int] = ..., unknown_markers: _Optional[int] = ..., flagged_anchors: _Optional[_Iterable[int]] = ..., update_ms: _Optional[float] = ..., factors: _Optional[int] = ..., factors_rebuilt: _Optional[int] = ..., update_cpu_ms: _Optional[float] = ..., rejections: _Optional[_Iterable[_Union[Rejection, _Mapping]]] = ...) -> None: ...

class Rejection(_message.Message):
    __slots__ = ("key", "reason", "count")
    KEY_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    key: str
    reason: str
    count: int
    def __init__(self, key: _Optional[str] = ..., reason: _Optional[str] = ..., count: _Optional[int] = ...) -> None: ...

class Map(_message.Message):
    __slots__ = ("cameras", "markers", "status")
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    MARKERS_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    cameras: PosesWithCovariance
    markers: PosesWithCovariance
    status: EstimatorStatus
    def __init__(self, cameras: _Optional[_Union[PosesWithCovariance, _Mapping]] = ..., markers: _Optional[_Union[PosesWithCovariance, _Mapping]] = ..., status: _Optional[_Union[EstimatorStatus, _Mapping]] = ...) -> None: ...

class ObjectDetection(_message.Message):
    __slots__ = ("object_id", "camera_ids", "world_T_object", "covariance", "fitness", "rmse_m", "stamp_ns")
    OBJECT_ID_FIELD_NUMBER: _ClassVar[int]
    CAMERA_IDS_FIELD_NUMBER: _ClassVar[int]
    WORLD_T_OBJECT_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    FITNESS_FIELD_NUMBER: _ClassVar[int]
    RMSE_M_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    object_id: str
    camera_ids: _containers.RepeatedScalarFieldContainer[str]
    world_T_object: Pose
    covariance: _containers.RepeatedScalarFieldContainer[float]
    fitness: float
    rmse_m: float
    stamp_ns: int
    def __init__(self, object_id: _Optional[str] = ..., camera_ids: _Optional[_Iterable[str]] = ..., world_T_object: _Optional[_Union[Pose, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., fitness: _Optional[float] = ..., rmse_m: _Optional[float] = ..., stamp_ns: _Optional[int] = ...) -> None: ...

class ObjectDetections(_message.Message):
    __slots__ = ("stamp_ns", "objects")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    OBJECTS_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    objects: _containers.RepeatedCompositeFieldContainer[ObjectDetection]
    def __init__(self, stamp_ns: _Optional[int] = ..., objects: _Optional[_Iterable[_Union[ObjectDetection, _Mapping]]] = ...) -> None: ...
