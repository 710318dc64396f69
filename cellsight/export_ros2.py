"""``cellsight export ros2``: a cellsight log as a ROS 2 bag (MCAP storage, CDR, ``ros2msg``
schemas) that ``ros2 bag play``, Foxglove and ``rosbags`` read.

    /tf                                tf2_msgs/TFMessage: world -> cameras (optical frames), markers, objects
    /cellsight/<camera>/pose           geometry_msgs/PoseWithCovarianceStamped: the camera in the world
    /cellsight/markers/poses           geometry_msgs/PoseArray: the mapped markers in the world
    /cellsight/objects                 vision_msgs/Detection3DArray: the recognised objects in the world
    /cellsight/points                  sensor_msgs/PointCloud2: the cameras' depth fused in the world
    /<camera>/markers                  geometry_msgs/PoseArray: each frame's marker observations, camera frame
    /<camera>/color/image_raw          sensor_msgs/Image (rgb8), and depth/image_raw (16UC1, mm)
    /<camera>/color/camera_info        sensor_msgs/CameraInfo

Bag time is the log time (when cellsight received it); header stamps are the sensors'. Ground
truth (``truth/`` keys) is not exported. A ``cellsight resolve`` output (``resolved.mcap``) becomes
the offline solution as tf over the log's time: each camera segment at its first and last frame,
moving frames, object markers at every instant, static markers at the end.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from estimator.offline.outputs import RESOLVE_SOURCE
from schemas import codec, keys
from schemas.errors import SchemaError
from schemas.log import ReadReport, read_log
from schemas.ros2 import CLOUD, DETECTIONS, WORLD, Ros2Types, optical_frame, ros2_types, ros_frame

TF, MARKER_POSES, OBJECTS, POINTS = "/tf", "/cellsight/markers/poses", "/cellsight/objects", "/cellsight/points"
TF_TYPE = "tf2_msgs/msg/TFMessage"


@dataclass(frozen=True)
class Export:
    """What was written: messages per ROS topic, and what the read of the log got through."""

    bag: Path
    messages: dict[str, int]
    read: ReadReport


def export_bag(
    log_path: Path, out: Path, distro: str = "jazzy", progress: Callable[[int, int], None] | None = None
) -> Export:
    """Write the log at ``log_path`` as a ROS 2 bag in the new folder ``out``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    types = ros2_types(distro)
    if out.exists():
        raise SchemaError(f"{out} exists: give a new folder for the bag")
    report, counts = ReadReport(), Counter()
    connections: dict[str, object] = {}
    with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:

        def put(topic: str, typename: str, msg: object, log_time_ns: int) -> None:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, typename, typestore=types.store)
            writer.write(connections[topic], log_time_ns, types.serialize(msg, typename))
            counts[topic] += 1

        for lm in read_log(log_path, None, report, progress):
            parsed = keys.parse(lm.key)
            resolved = (
                report.metadata.get("cellsight", {}).get("source") == RESOLVE_SOURCE
            )  # written before any message
            for topic, typename, msg in _convert(types, parsed.camera, parsed.topic, lm.msg, resolved):
                put(topic, typename, msg, lm.log_time_ns)
    return Export(out, dict(counts), report)


def _tf(types: Ros2Types, poses) -> Iterator[tuple[str, str, object]]:
    for p in poses:
        yield TF, TF_TYPE, types.tf_message(p.stamp_ns, [(p.parent, ros_frame(p.child), p.T)])


def _convert(
    types: Ros2Types, camera: str | None, topic: str, msg, resolved: bool = False
) -> Iterator[tuple[str, str, object]]:
    """(ROS topic, type name, message) for one of our messages; nothing for what is not exported.
    ``resolved``: the log is resolve's solution, whose estimates are the tf over time."""
    if topic == "tf" and resolved:
        return  # the final state again: the estimates below already carry it
    if topic in ("estimate/cameras", "estimate/markers") and resolved:
        yield from _tf(types, codec.poses_from_msg(msg).values())
    if topic == "tf":
        poses = codec.transforms_from_msg(msg)
        for tr in msg.transforms:  # one TFMessage per transform, each with its own stamp
            T = poses[(tr.parent_frame_id, tr.child_frame_id)]
            yield (
                TF,
                TF_TYPE,
                types.tf_message(
                    codec.timestamp_to_stamp(tr.timestamp), [(tr.parent_frame_id, ros_frame(tr.child_frame_id), T)]
                ),
            )
    elif topic == "estimate/cameras":
        for p in codec.poses_from_msg(msg).values():
            yield (
                f"/cellsight/{p.child}/pose",
                "geometry_msgs/msg/PoseWithCovarianceStamped",
                types.pose_with_covariance(p.stamp_ns, WORLD, p.T, p.covariance),
            )
    elif topic == "estimate/markers":
        poses = codec.poses_from_msg(msg)
        if poses:
            yield (
                MARKER_POSES,
                "geometry_msgs/msg/PoseArray",
                types.pose_array(msg.stamp_ns, WORLD, [p.T for p in poses.values()]),
            )
    elif topic == "objects":
        yield OBJECTS, DETECTIONS, types.detections(msg)
        for o in msg.objects:
            yield (
                TF,
                TF_TYPE,
                types.tf_message(
                    o.stamp_ns, [(WORLD, keys.object_frame(o.object_id), codec.pose_from_msg(o.world_T_object))]
                ),
            )
    elif topic == "points":
        yield (
            POINTS,
            CLOUD,
            types.point_cloud(codec.timestamp_to_stamp(msg.timestamp), msg.frame_id, *codec.points_from_msg(msg)),
        )
    elif topic == "markers":
        a = codec.marker_arrays(msg, check=False)  # read_log validated it
        yield (
            f"/{camera}/markers",
            "geometry_msgs/msg/PoseArray",
            types.pose_array(msg.stamp_ns, optical_frame(camera), list(a.poses)),
        )
    elif topic in ("color/image_raw", "depth/image_raw"):
        frame = optical_frame(camera)  # depth is registered to colour
        yield (
            f"/{camera}/{topic}",
            "sensor_msgs/msg/Image",
            types.image(codec.timestamp_to_stamp(msg.timestamp), frame, codec.image_from_msg(msg), msg.encoding),
        )
    elif topic == "camera_info":
        info = codec.CameraInfo.from_msg(msg)
        yield (
            f"/{camera}/color/camera_info",
            "sensor_msgs/msg/CameraInfo",
            types.camera_info(
                codec.timestamp_to_stamp(msg.timestamp), optical_frame(camera), info.width, info.height, info.K, info.D
            ),
        )
