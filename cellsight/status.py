"""What is running and how well: driver rates, estimator camera states, liveliness (a rich table)."""

from __future__ import annotations

from rich.table import Table

from schemas import keys
from schemas import messages as m
from schemas.bus import Bus

_DRIVER = {v.number: v.name.lower() for v in m.DriverStatus.State.DESCRIPTOR.values}
_CAMERA = {v.number: v.name.lower() for v in m.CameraState.State.DESCRIPTOR.values}


class StatusBoard:
    """Keeps the newest driver and estimator status messages of a cell."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.drivers: dict[str, m.DriverStatus] = {}
        self.estimator: m.EstimatorStatus | None = None
        self._subs = [
            bus.subscribe(keys.all_cameras(bus.cell, "status"), m.DriverStatus, callback=lambda r: self.drivers.__setitem__(r.msg.camera_id, r.msg)),
            bus.subscribe(keys.estimate_status(bus.cell), m.EstimatorStatus, callback=lambda r: setattr(self, "estimator", r.msg)),
        ]

    def table(self, alive: list[str] | None = None) -> Table:
        t = Table(title=f"cellsight cell {self.bus.cell}")
        for col in ("camera", "driver", "rate (Hz)", "frames", "dropped", "state", "segment", "markers", "sigma (mm)"):
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
                f"{e.position_sigma_m * 1000:.1f}" if e and e.position_sigma_m else "-",
            )
        if self.estimator is not None:
            s = self.estimator
            flagged = f", anchors flagged: {list(s.flagged_anchors)}" if s.flagged_anchors else ""
            t.caption = f"observations {s.observations}, rejected {s.rejected}, unknown markers {s.unknown_markers}, update {s.update_ms:.1f} ms{flagged}"
        if alive is not None:
            t.caption = (t.caption or "") + "\nalive: " + ", ".join(a.split("/alive/")[1] for a in alive)
        return t

    def close(self) -> None:
        for s in self._subs:
            s.close()
