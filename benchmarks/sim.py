"""Simulated cell render rate per camera on one core: static (cached geometry) and moving cameras.

The process is pinned to one core (``pin_one_core``) so Open3D's ray casting cannot spread over
the machine; ``cores_measured`` is its CPU time over wall time (should read ~1.0). Static: the demo cell's cam3 (its geometry cached; the moving tote re-cast in
its bounding box every frame; noise drawn every frame). Moving: cam1 during its tilt, cast in full
every frame. Target: at least 30 frames/s per static camera.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from benchmarks.common import CoresUsed, Row, main, pin_one_core

if TYPE_CHECKING:
    from drivers.sim.render import SimCell


def fps(cell: SimCell, cam: str, t0: float, frames: int) -> float:
    cell.render(cam, t0, 0)  # warm the cache and the ray buffers
    start = time.perf_counter()
    for k in range(1, frames + 1):
        cell.render(cam, t0 + k / 30.0, k)
    return frames / (time.perf_counter() - start)


def run(quick: bool) -> dict[str, float]:
    pin_one_core()
    # After the pin: numpy's and Open3D's thread pools start with their first import, and a thread
    # keeps the affinity it started with (the pin once measured 1.6 cores with them imported first).
    from drivers.sim.render import SimCell
    from drivers.sim.scenario import load_scenario

    s = load_scenario()
    frames = 30 if quick else 150
    cores = CoresUsed().start()
    static = fps(SimCell(s), "cam3", 1.0, frames)
    moving = fps(SimCell(s), "cam1", 8.0, frames // 3)  # cam1 tilts between 8 and 10 s
    return {"static_fps_per_camera": static, "moving_fps_per_camera": moving, "cores_measured": cores.stop()}


#: The rows of ``docs/performance.md`` this benchmark's recorded runs give.
ROWS = (
    Row(
        "static_fps_per_camera",
        "simulated Kinect render rate, static camera, one pinned core",
        ">= 30",
        lambda v: v >= 30,
    ),
    Row("moving_fps_per_camera", "the same, camera moving (a full ray cast per frame)"),
    Row("cores_measured", "cores used while timing (pinned)", "~1.0", lambda v: 0.9 <= v <= 1.1),
)


if __name__ == "__main__":
    main("sim", __doc__.splitlines()[0], run)
