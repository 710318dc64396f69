"""A simulated camera as a frame source, paced in real time, with its ground truth."""

from __future__ import annotations

import time
from dataclasses import replace

from drivers.frames import Frame
from drivers.sim.render import SimCell
from drivers.sim.scenario import Scenario
from schemas import keys
from schemas.codec import StampedPose


class SimSource:
    """Frames of one scenario camera at its rate. Scenario time 0 is ``epoch_ns`` (default: now).

    When rendering falls behind the wall clock, the source skips to the newest due frame and
    counts the skipped ones in ``dropped`` (a real sensor drops frames the same way).
    ``prerender`` > 0 renders that many frames up front and then plays them in a loop with live
    stamps: the rest of the pipeline at a real sensor's rate without the renderer's cost (for a
    static scene: a looped frame shows what a new one would, up to its noise).
    """

    def __init__(
        self,
        scenario: Scenario,
        camera_id: str,
        *,
        epoch_ns: int | None = None,
        realtime: bool = True,
        cell: SimCell | None = None,
        prerender: int = 0,
    ) -> None:
        self.scenario = scenario
        self.camera = scenario.camera(camera_id)
        self.name = f"sim:{scenario.name}/{camera_id}"
        self.cell = cell or SimCell(scenario)
        self.epoch_ns = time.time_ns() if epoch_ns is None else int(epoch_ns)
        self.realtime = realtime
        self.index = 0
        self.dropped = 0
        self.t_s = 0.0
        self._loop = [self.cell.render(self.camera.id, i / self.camera.rate_hz, i) for i in range(prerender)]
        self._truth_cache: dict[tuple[float, bool], tuple[list[StampedPose], list[StampedPose], list[StampedPose]]] = {}

    def read(self) -> Frame | None:
        period = 1.0 / self.camera.rate_hz
        if self.realtime:
            now = (time.time_ns() - self.epoch_ns) * 1e-9
            due = int(now / period)
            if due > self.index:  # behind: newest frame wins
                self.dropped += due - self.index
                self.index = due
            else:
                time.sleep(max(self.index * period - now, 0.0))
        self.t_s = self.index * period
        if self.t_s > self.scenario.duration_s:
            return None
        f = (
            self._loop[self.index % len(self._loop)]
            if self._loop
            else self.cell.render(self.camera.id, self.t_s, self.index)
        )
        self.index += 1
        return Frame(self.camera.id, self.epoch_ns + int(round(self.t_s * 1e9)), f.rgb, f.depth_mm, f.info)

    def truth(
        self, t_s: float, with_map: bool = True
    ) -> tuple[list[StampedPose], list[StampedPose], list[StampedPose]]:
        """(cameras, markers, objects) world poses at scenario time ``t_s``; stamps on the same clock.
        Without ``with_map`` only the camera (markers and objects empty: they cost most). A
        prerendered source's truth is that of the looped frame shown at ``t_s`` (what its pixels
        show), computed once per looped frame."""
        stamp = self.epoch_ns + int(round(t_s * 1e9))
        if not self._loop:
            return self._truth_at(t_s, with_map, stamp)
        shown = (int(round(t_s * self.camera.rate_hz)) % len(self._loop)) / self.camera.rate_hz
        if (shown, with_map) not in self._truth_cache:
            self._truth_cache[(shown, with_map)] = self._truth_at(shown, with_map, 0)
        cams, markers, objects = (
            [replace(p, stamp_ns=stamp) for p in group] for group in self._truth_cache[(shown, with_map)]
        )
        return cams, markers, objects

    def _truth_at(
        self, t_s: float, with_map: bool, stamp: int
    ) -> tuple[list[StampedPose], list[StampedPose], list[StampedPose]]:
        s = self.scenario
        cams = [StampedPose("world", self.camera.id, stamp, self.camera.world_T_camera(t_s))]
        if not with_map:
            return cams, [], []
        markers = [StampedPose("world", keys.marker_frame(mk.id), stamp, s.world_T_marker(mk, t_s)) for mk in s.markers]
        objects = [StampedPose("world", keys.object_frame(o.id), stamp, o.world_T_object(t_s)) for o in s.objects]
        return cams, markers, objects

    def close(self) -> None:
        pass
