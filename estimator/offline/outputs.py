"""What the offline solve writes: object markers placed through the solved cameras, the solution
on the daemon's keys (``resolved.mcap``) and TUM trajectories (for evo and other tools)."""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import TextIO

import numpy as np

from estimator.estimate import BestView
from estimator.offline.solve import ObjectRows, ResolveResult, SegmentResult, place_objects
from schemas import codec, keys
from schemas.codec import StampedPose
from schemas.geometry import quat_from_matrix
from schemas.log import LogWriter

OBJECT_GAP_NS = 100_000_000  # object markers: sightings kept per camera and poses written per marker at <= 10 Hz

#: ``source`` in the metadata of the logs resolve writes (``resolved.mcap``).
RESOLVE_SOURCE = "cellsight resolve"


class ObjectSpool:
    """Object-marker sightings from the log's static frames, kept on disk until the cameras are
    solved: an hour of four cameras at 10 Hz is ~10^5 rows per marker, and memory holds one chunk."""

    DTYPE = np.dtype(
        [
            ("stamp", "<i8"),
            ("segment", "<i8"),
            ("marker", "<i8"),
            ("camera", "<i8"),
            ("pose", "<f8", (4, 4)),
            ("cov", "<f8", (6, 6)),
        ]
    )

    def __init__(self, directory: Path) -> None:
        self._file = tempfile.TemporaryFile(dir=directory, prefix=".objects-")
        self.cameras: list[str] = []
        self._last: dict[tuple[str, int], int] = {}
        self.rows = 0

    def add(self, rows: ObjectRows) -> None:
        """Append the rows, at most one per camera and marker per ``OBJECT_GAP_NS``."""
        keep = []
        for i, (stamp, mk) in enumerate(zip(rows.stamps.tolist(), rows.ids.tolist())):
            last = self._last.get((rows.camera_id, mk))
            if last is None or stamp - last >= OBJECT_GAP_NS:
                self._last[(rows.camera_id, mk)] = stamp
                keep.append(i)
        if not keep:
            return
        if rows.camera_id not in self.cameras:
            self.cameras.append(rows.camera_id)
        a = np.zeros(len(keep), self.DTYPE)
        a["stamp"], a["segment"], a["marker"] = rows.stamps[keep], rows.segments[keep], rows.ids[keep]
        a["camera"], a["pose"], a["cov"] = self.cameras.index(rows.camera_id), rows.poses[keep], rows.covariances[keep]
        a.tofile(self._file)
        self.rows += len(keep)

    def chunks(self, n: int = 20_000) -> Iterator[np.ndarray]:
        """The rows in log order, ``n`` at a time (structured arrays of ``DTYPE``)."""
        self._file.flush()
        self._file.seek(0)
        while len(a := np.fromfile(self._file, dtype=self.DTYPE, count=n)):
            yield a

    def close(self) -> None:
        self._file.close()


def object_poses(spool: ObjectSpool, result: ResolveResult) -> Iterator[StampedPose]:
    """Each object marker through the solved cameras, at most every ``OBJECT_GAP_NS``: of the
    sightings of one marker in one such period, the best view (``BestView``, as the daemon picks)."""
    segments = {(s.camera_id, s.segment): s for s in result.segments}
    best: BestView[tuple[int, int], StampedPose] = BestView()  # (marker, period) -> best so far
    newest = -1
    for a in spool.chunks():
        for ci, cam in enumerate(spool.cameras):
            rows = a[a["camera"] == ci]
            if not len(rows):
                continue
            T, cov, solved = place_objects(
                ObjectRows(cam, rows["stamp"], rows["segment"], rows["marker"], rows["pose"], rows["cov"]), segments
            )
            for stamp, mk, Ti, Ci in zip(rows["stamp"][solved].tolist(), rows["marker"][solved].tolist(), T, cov):
                best.offer((mk, stamp // OBJECT_GAP_NS), Ci, StampedPose("world", keys.marker_frame(mk), stamp, Ti, Ci))
        # Sightings arrive in log order, a few frames apart across cameras: periods two behind are final.
        newest = max([newest] + [p for _, p in best.keys()])
        for key in sorted(k for k in best.keys() if k[1] < newest - 1):
            yield best.pop(key)
    for key in sorted(best.keys()):
        yield best.pop(key)


def segment_at(result: ResolveResult, cam: str, stamp: int) -> SegmentResult | None:
    """The solved segment of ``cam`` that covers ``stamp`` (None if it was moving or unanchored)."""
    best = None
    for s in result.segments:
        if s.camera_id == cam and s.frames and s.first_stamp_ns <= stamp <= s.last_stamp_ns:
            best = s
    return best


def tum_pose(T: np.ndarray) -> str:
    """ "tx ty tz qx qy qz qw" of a 4x4 pose, as a TUM trajectory line has it after the time."""
    q, t = quat_from_matrix(T[:3, :3]), T[:3, 3]
    return f"{t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {q[0]:.8f} {q[1]:.8f} {q[2]:.8f} {q[3]:.8f}"


def write_solution(
    result: ResolveResult,
    out: Path,
    cell: str,
    spool: ObjectSpool | None = None,
    object_markers: list[int] | None = None,
    on_object: Callable[[StampedPose], None] | None = None,
) -> None:
    """``out/resolved.mcap`` and ``out/trajectories/*.tum``; ``on_object`` sees each object-marker
    pose as it is written (they are streamed: an hour is ~36,000 per marker)."""
    end = max((s.last_stamp_ns for s in result.segments), default=0)
    # resolved.mcap: each segment's pose at its first and last frame, moving frames, object markers
    # over time, static markers and tf at the end.
    w = LogWriter(
        out / "resolved.mcap",
        metadata={"source": RESOLVE_SOURCE, "object_markers": " ".join(map(str, object_markers or []))},
    )
    cameras = [
        (stamp, StampedPose("world", s.camera_id, stamp, s.world_T_camera, s.covariance))
        for s in result.segments
        for stamp in sorted({s.first_stamp_ns, s.last_stamp_ns})
    ]
    cameras += [
        (k.stamp_ns, StampedPose("world", k.camera_id, k.stamp_ns, k.world_T_camera, k.covariance))
        for k in result.keyframes
    ]
    for stamp, p in cameras:
        w.write(keys.estimate_cameras(cell), codec.poses_to_msg(stamp, [p]), stamp)
    tdir = out / "trajectories"
    tdir.mkdir(exist_ok=True)
    if spool is not None:
        with ExitStack() as files:
            tum: dict[str, TextIO] = {}
            for p in object_poses(spool, result):
                w.write(keys.estimate_markers(cell), codec.poses_to_msg(p.stamp_ns, [p]), p.stamp_ns)
                if p.child not in tum:
                    tum[p.child] = files.enter_context((tdir / f"{p.child}.tum").open("w"))
                tum[p.child].write(f"{p.stamp_ns / 1e9:.9f} {tum_pose(p.T)}\n")
                if on_object is not None:
                    on_object(p)
    markers = [StampedPose("world", keys.marker_frame(k), end, T, C) for k, (T, C) in result.markers.items()]
    w.write(keys.estimate_markers(cell), codec.poses_to_msg(end, markers), end)
    latest = {s.camera_id: s for s in result.segments}
    w.write(
        keys.tf(cell),
        codec.transforms_to_msg(
            end,
            [("world", c, s.world_T_camera) for c, s in latest.items()] + [("world", p.child, p.T) for p in markers],
        ),
        end,
    )
    w.close()
    # TUM: "t tx ty tz qx qy qz qw" per frame of a solved static segment and per moving frame.
    pose_text = {(s.camera_id, s.segment): tum_pose(s.world_T_camera) for s in result.segments}  # once: 10^5 frames/h
    for cam in sorted(set(result.frame_stamps) | {k.camera_id for k in result.keyframes}):
        rows = [
            (stamp, pose_text[(cam, seg)]) for stamp, seg in result.frame_stamps.get(cam, []) if (cam, seg) in pose_text
        ]
        rows += [(k.stamp_ns, tum_pose(k.world_T_camera)) for k in result.keyframes if k.camera_id == cam]
        lines = [f"{stamp / 1e9:.9f} {text}" for stamp, text in sorted(rows)]
        (tdir / f"{cam}.tum").write_text("\n".join(lines) + ("\n" if lines else ""))
