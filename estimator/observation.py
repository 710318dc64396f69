"""The estimator's input: markers seen by one camera, as single observations or as arrays of rows.

The wire (``schemas.codec.MarkerArrays``) carries both planar-PnP (IPPE) candidates as sent; which
one is the "other" branch a flip would be is the estimator's decision, made here once per row.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from schemas import codec
from schemas import messages as m
from schemas.codec import MarkerArrays, MarkerFields
from schemas.errors import DecodeError
from schemas.geometry import matrices_from_quats
from schemas.limits import DEFAULT_LIMITS, WireLimits


@dataclass(frozen=True)
class Observation:
    """``camera_T_marker`` (4x4) with its 6x6 covariance (ROS order x y z rx ry rz, marker frame).

    ``alternative`` is the other planar-PnP (IPPE) solution, used when the chosen one turns out to
    be a flip; ``stamp_ns`` is the capture time in integer nanoseconds.
    """

    camera_id: str
    stamp_ns: int
    marker_id: int
    camera_T_marker: np.ndarray
    covariance: np.ndarray
    alternative: np.ndarray | None = None
    ambiguous: bool = False


@dataclass(frozen=True)
class ObservationRows:
    """Observations as arrays, one row per marker: ids (N,), camera_T_marker (N, 4, 4), the other
    IPPE branch (N, 4, 4), covariances (N, 6, 6, ROS order), ambiguous flags (N,) and the index (N,)
    of the frame each row came from."""

    ids: np.ndarray
    poses: np.ndarray
    alternatives: np.ndarray
    covariances: np.ndarray
    ambiguous: np.ndarray
    frame: np.ndarray

    def rows(self, keep: np.ndarray) -> ObservationRows:
        """The rows selected by a boolean mask or index array."""
        return ObservationRows(
            self.ids[keep],
            self.poses[keep],
            self.alternatives[keep],
            self.covariances[keep],
            self.ambiguous[keep],
            self.frame[keep],
        )

    def of_frames(self, frames: np.ndarray) -> ObservationRows:
        """The rows of the frames ``frames`` (ascending frame indices), renumbered 0, 1, ... in that order."""
        a = self.rows(np.isin(self.frame, frames))
        return dataclasses.replace(a, frame=np.searchsorted(frames, a.frame))


def observation_rows(a: MarkerArrays) -> ObservationRows:
    """The wire's arrays with the other IPPE branch of each row chosen.

    The chosen pose is either candidate after depth refinement: a new rotation toward the plane's
    normal and the plane's range. The other branch is the candidate further from it in rotation
    (smaller |q . q'|) at the chosen position: the candidates' own positions are planar PnP's (tens
    of mm off in range at 3 m), and a flip the estimator corrects must not bring that error back.
    """
    q = a.quaternions
    further_a = np.abs(np.einsum("ij,ij->i", q[:, 0], q[:, 1])) < np.abs(np.einsum("ij,ij->i", q[:, 0], q[:, 2]))
    alternatives = a.poses.copy()
    alternatives[:, :3, :3] = matrices_from_quats(np.where(further_a[:, None], q[:, 1], q[:, 2]))
    return ObservationRows(a.ids, a.poses, alternatives, a.covariances, a.ambiguous, a.frame)


@dataclass(frozen=True)
class ValidatedFrames:
    """What ``validated_rows`` kept: indices of the good frames, their rows (``frame`` indexes the
    kept frames; None when none was good) and, per dropped frame, (its index, what was wrong, the
    reason: one of ``schemas.limits.REASONS``)."""

    kept: list[int]
    rows: ObservationRows | None
    dropped: list[tuple[int, str, str]]


def validated_rows(msgs: Sequence[m.MarkerObservations], limits: WireLimits = DEFAULT_LIMITS) -> ValidatedFrames:
    """``validated_fields`` of the messages' fields: frames of any cameras, whose ids the caller
    checked (the daemon validates each update's frames in one pass; ``ObservationRows.of_frames``
    splits them by camera)."""
    return _validated(len(msgs), codec.marker_fields(msgs), limits)


def validated_fields(
    camera_id: str, frames: int, fields: MarkerFields, limits: WireLimits = DEFAULT_LIMITS
) -> ValidatedFrames:
    """Check a camera's frames together, in numpy, and convert the good ones once: a frame with
    any bad marker is dropped whole (the rest of it is not trusted either). The one validation of
    marker observations on both the live and the offline path."""
    try:
        codec.check_id(camera_id, "marker observations camera_id")
    except DecodeError as exc:
        return ValidatedFrames([], None, [(i, str(exc), exc.reason) for i in range(frames)])
    return _validated(frames, fields, limits)


def _validated(frames: int, fields: MarkerFields, limits: WireLimits) -> ValidatedFrames:
    problems = codec.marker_problems(fields, limits)
    frame_of = fields.rows[:, 1].astype(np.int64)
    why: dict[int, tuple[str, str]] = {}
    for row, what, reason in problems:
        why.setdefault(int(frame_of[row]), (what, reason))
    if not why:
        return ValidatedFrames(list(range(frames)), observation_rows(fields.arrays()), [])
    kept = [i for i in range(frames) if i not in why]
    keep_rows = ~np.isin(frame_of, list(why))
    rows = None
    if kept:
        rows = observation_rows(fields.arrays(keep_rows)).of_frames(
            np.array(kept)
        )  # frame indices among the kept frames
    return ValidatedFrames(kept, rows, [(i, what, reason) for i, (what, reason) in sorted(why.items())])


def observations_of(camera_id: str, stamp_ns: int, a: ObservationRows) -> list[Observation]:
    """Rows of one frame as single observations."""
    return [
        Observation(
            camera_id, stamp_ns, int(a.ids[i]), a.poses[i], a.covariances[i], a.alternatives[i], bool(a.ambiguous[i])
        )
        for i in range(len(a.ids))
    ]
