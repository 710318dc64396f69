"""``cellsight compare A.mcap B.mcap``: what moved between two solved logs (e.g. two days' calibrations).

For every camera and marker in both: the newest pose each log holds (``estimate/cameras`` and
``estimate/markers``, as written by ``cellsight resolve`` or recorded from the daemon), the
difference, and a verdict against the two covariances together: ``moved`` when the 6-dof
difference is beyond chi-square 99.9 % (22.46) and over ``min_mm`` / ``min_deg``, else
``unchanged``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from schemas import codec, keys
from schemas.codec import StampedPose
from schemas.geometry import mahalanobis_sq, pose_difference, pose_error
from schemas.log import ReadReport, read_log

CHI2_6DOF_999 = 22.46


@dataclass(frozen=True)
class Change:
    frame: str
    position_mm: float
    rotation_deg: float
    sigmas: float | None  # sqrt of the chi-square statistic; None without covariances
    verdict: str  # moved | unchanged | only in A | only in B


def newest_poses(path: Path) -> tuple[dict[str, StampedPose], ReadReport]:
    """The newest pose of every camera and static marker in a log. Markers on objects move by
    design, so those the log names (``cellsight resolve`` output, or a recording's embedded
    config) are left out."""
    report = ReadReport()
    newest: dict[str, StampedPose] = {}
    for lm in read_log(path, None, report):
        topic = keys.parse(lm.key).topic
        if topic in ("estimate/cameras", "estimate/markers"):
            for child, p in codec.poses_from_msg(lm.msg).items():
                if child not in newest or p.stamp_ns >= newest[child].stamp_ns:
                    newest[child] = p
    for mk in object_markers_of(report):
        newest.pop(keys.marker_frame(mk), None)
    return newest, report


def object_markers_of(report: ReadReport) -> list[int]:
    """Object-marker ids a log's metadata names: resolve's list, or the recorder's embedded config."""
    from cellsight.errors import ConfigError
    from cellsight.evaluation.resolve_report import config_of_log

    meta = report.metadata.get("cellsight", {})
    if "object_markers" in meta:
        return [int(v) for v in meta["object_markers"].split()]
    try:
        cfg = config_of_log(report)
    except ConfigError:  # a damaged embedded config says nothing about objects; compare everything
        return []
    return [] if cfg is None else list(cfg.estimator.object_markers)


def compare(
    a: dict[str, StampedPose], b: dict[str, StampedPose], min_mm: float = 1.0, min_deg: float = 0.05
) -> list[Change]:
    out = []
    for frame in sorted(set(a) | set(b)):
        if frame not in b or frame not in a:
            out.append(Change(frame, math.nan, math.nan, None, "only in A" if frame in a else "only in B"))
            continue
        pa, pb = a[frame], b[frame]
        dp, dr = pose_error(pb.T, pa.T)
        sig = None
        if pa.covariance is not None and pb.covariance is not None:  # both ROS order, as the difference
            sig = math.sqrt(max(float(mahalanobis_sq(pose_difference(pa.T, pb.T), pa.covariance + pb.covariance)), 0.0))
        beyond_noise = sig is None or sig**2 > CHI2_6DOF_999
        verdict = "moved" if beyond_noise and (dp > min_mm or dr > min_deg) else "unchanged"
        out.append(Change(frame, dp, dr, sig, verdict))
    return out
