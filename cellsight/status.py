"""What is running and how well: driver rates, estimator camera states and poses, objects,
liveliness, and messages refused as implausible or malformed (rich tables)."""

from __future__ import annotations

import logging
from collections import Counter

from rich.console import Group, RenderableType
from rich.table import Table

from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus
from schemas.codec import StampedPose
from schemas.errors import DecodeError

log = logging.getLogger(__name__)

_DRIVER = {v.number: v.name.lower() for v in m.DriverStatus.State.DESCRIPTOR.values}
_CAMERA = {v.number: v.name.lower() for v in m.CameraState.State.DESCRIPTOR.values}


class StatusBoard:
    """Keeps the newest driver status, estimator status, camera poses and objects of a cell."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.drivers: dict[str, m.DriverStatus] = {}
        self.estimator: m.EstimatorStatus | None = None
        self.cameras: dict[str, StampedPose] = {}
        self.objects: m.ObjectDetections | None = None
        self._cameras_msg: m.PosesWithCovariance | None = None
        cell = bus.cell
        self._subs = [
            bus.subscribe(
                keys.all_cameras(cell, "status"),
                m.DriverStatus,
                callback=lambda r: self.drivers.__setitem__(r.msg.camera_id, r.msg),
            ),
            bus.subscribe(
                keys.estimate_status(cell), m.EstimatorStatus, callback=lambda r: setattr(self, "estimator", r.msg)
            ),
            bus.subscribe(keys.estimate_cameras(cell), m.PosesWithCovariance, callback=self._on_cameras),
            bus.subscribe(keys.objects(cell), m.ObjectDetections, callback=lambda r: setattr(self, "objects", r.msg)),
        ]

    def _on_cameras(self, received) -> None:
        self._cameras_msg = received.msg  # decoded when a table is drawn: poses arrive at 30 Hz, tables at 2

    def table(self, alive: list[str] | None = None) -> RenderableType:
        """The cameras' table, and the objects' when any were reported."""
        if (msg := self._cameras_msg) is not None:
            self._cameras_msg = None
            try:
                self.cameras.update(codec.poses_from_msg(msg))
            except DecodeError as exc:  # one bad message must not take the table down
                log.warning("camera poses skipped: %s", exc)
        t = Table(title=f"cellsight cell {self.bus.cell}")
        for col in (
            "camera",
            "driver",
            "rate (Hz)",
            "frames",
            "dropped",
            "state",
            "segment",
            "markers",
            "x, y, z (m)",
            "sigma (mm)",
        ):
            t.add_column(col, no_wrap=True)
        est = {c.camera_id: c for c in self.estimator.cameras} if self.estimator else {}
        for cid in sorted(set(self.drivers) | set(est)):
            d, e = self.drivers.get(cid), est.get(cid)
            t.add_row(
                cid,
                _DRIVER.get(d.state, "?") if d else "-",
                f"{d.rate_hz:.1f}" if d else "-",
                str(d.frames) if d else "-",
                str(d.dropped) if d else "-",
                _CAMERA.get(e.state, "?") if e else "-",
                str(e.segment) if e else "-",
                str(e.markers_seen) if e else "-",
                _xyz(self.cameras[cid].T) if cid in self.cameras else "-",
                f"{e.position_sigma_m * 1000:.1f}" if e and e.position_sigma_m else "-",
            )
        if self.estimator is not None:
            s = self.estimator
            flagged = f", anchors flagged: {list(s.flagged_anchors)}" if s.flagged_anchors else ""
            t.caption = f"observations {s.observations}, rejected {s.rejected}, unknown markers {s.unknown_markers}, update {s.update_ms:.1f} ms, factors rebuilt {s.factors_rebuilt}{flagged}"
        if alive is not None:
            t.caption = (t.caption or "") + "\nalive: " + ", ".join(a.split("/alive/")[1] for a in alive)
        tables: list[RenderableType] = [t]
        if refused := self.refused():
            r = Table(title="refused messages (by the estimator and by this viewer)")
            for col in ("key", "reason", "count"):
                r.add_column(col, no_wrap=True)
            for (key, reason), count in sorted(refused.items()):
                r.add_row(key, reason, str(count))
            tables.append(r)
        if self.objects is None or not self.objects.objects:
            return Group(*tables) if len(tables) > 1 else t
        o = Table(title="objects (world frame)")
        for col in ("object", "x, y, z (m)", "cameras", "fitness", "rmse (mm)"):
            o.add_column(col, no_wrap=True)
        for det in self.objects.objects:
            T = codec.pose_from_msg(det.world_T_object, det.object_id)
            o.add_row(
                det.object_id, _xyz(T), ", ".join(det.camera_ids), f"{det.fitness:.2f}", f"{det.rmse_m * 1000:.1f}"
            )
        return Group(*tables, o)

    def refused(self) -> Counter[tuple[str, str]]:
        """(key, reason) -> messages refused: the estimator's (from its status) and this board's own."""
        out: Counter[tuple[str, str]] = Counter()
        if self.estimator is not None:
            for r in self.estimator.rejections:
                out[r.key, r.reason] += r.count
        for sub in self._subs:
            out.update(sub.rejected)
        return out

    def close(self) -> None:
        for s in self._subs:
            s.close()


def _xyz(T) -> str:
    return ", ".join(f"{v:+.3f}" for v in T[:3, 3])
