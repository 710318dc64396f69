"""Shared benchmark plumbing: ``python -m benchmarks.NAME [--quick] [--json FILE]``.

Each benchmark returns a flat dict of named figures with the unit in the name; this prints it as a
table (with the machine) and writes it as JSON when asked.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from rich.console import Console
from rich.table import Table

from cellsight.errors import CellsightError


def demo_cell_text(duration_s: float) -> str:
    """The demo cell's scenario file, running ``duration_s`` (s) instead of its 30: a simulated camera
    stops at its scenario's end, and a benchmark's cell may run longer."""
    from drivers.sim.scenario import DEMO_CELL  # not at the top: numpy must start after a benchmark pins itself

    text = DEMO_CELL.read_text()
    if text.count("duration_s = 30.0") != 1:
        raise ValueError(f"{DEMO_CELL} no longer says duration_s = 30.0 once: update demo_cell_text")
    return text.replace("duration_s = 30.0", f"duration_s = {duration_s:.1f}")


def launch_demo_cell(tmp: Path, cell: str, duration_s: float) -> tuple[subprocess.Popen, Path, int]:
    """The demo cell (its scenario running ``duration_s``) under ``cellsight run --record`` in
    ``tmp/run`` on a router at a free loopback port; returns (the launcher, the run folder, the port)
    once every process is started (the recognition models are built first). Stop it with SIGTERM."""
    from tests.conftest import free_port

    port = free_port()
    run_dir = tmp / "run"
    (tmp / "scenario.toml").write_text(demo_cell_text(duration_s))
    (tmp / "cell.toml").write_text(
        f'[cell]\nname = "{cell}"\nscenario = "scenario.toml"\n[transport]\nconnect = ["tcp/127.0.0.1:{port}"]\n'
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "cellsight.cli", "run", str(tmp / "cell.toml"), "--out", str(run_dir), "--record"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 300
    while not (run_dir / "processes.json").exists():
        if time.monotonic() > deadline or proc.poll() is not None:
            proc.kill()
            raise RuntimeError(f"the cell did not start (see {run_dir}/logs)")
        time.sleep(0.5)
    return proc, run_dir, port


#: The repository's public real data (``data/``), and PCL's real clouds in it.
REAL_DATA = Path(__file__).resolve().parents[1] / "data"
PCL_DATA = REAL_DATA / "pcl"


def pin_one_core() -> int:
    """Pin this process, and the thread pools it starts from now on, to one CPU; cap OpenCV's own
    pool at one thread. Returns the CPU. Call it first: numpy's and Open3D's pools size themselves
    when they start, and threads inherit the affinity mask."""
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    import cv2

    cv2.setNumThreads(1)
    return cpu


@contextmanager
def one_core() -> Iterator[int]:
    """``pin_one_core`` for a stretch of work, then this process's affinity and OpenCV's pool as they
    were (processes started after it must not inherit the pin)."""
    import cv2

    affinity, threads = os.sched_getaffinity(0), cv2.getNumThreads()
    try:
        yield pin_one_core()
    finally:
        os.sched_setaffinity(0, affinity)
        cv2.setNumThreads(threads)


class CoresUsed:
    """Measured cores over a stretch of work: this process's CPU time (all threads, getrusage)
    over the wall time between ``start`` and ``stop``; ~1.0 when pinned and busy."""

    def start(self) -> CoresUsed:
        self._cpu, self._wall = time.process_time(), time.perf_counter()
        return self

    def stop(self) -> float:
        return (time.process_time() - self._cpu) / max(time.perf_counter() - self._wall, 1e-9)


def machine() -> str:
    cpu = "unknown cpu"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}"


def main(
    name: str,
    description: str,
    run: Callable[[bool], dict[str, float]],
    extra_args: Callable[[argparse.ArgumentParser], None] | None = None,
) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.{name}", description=description)
    parser.add_argument("--quick", action="store_true", help="a smaller run that finishes within a minute")
    parser.add_argument("--json", type=Path, help="write the figures to this JSON file")
    parser.add_argument(
        "--record",
        action="store_true",
        help=f"keep the run in {RESULTS.relative_to(RESULTS.parents[1])}/ (figures, machine, date, commit, command): "
        "docs/performance.md is generated from there (python -m benchmarks.report)",
    )
    if extra_args:
        extra_args(parser)
    args = parser.parse_args()
    t0 = time.perf_counter()
    try:
        figures = run(args.quick) if extra_args is None else run(args.quick, args)
    except CellsightError as exc:  # a dataset or config given on the command line is wrong: say what, no traceback
        parser.exit(2, f"{parser.prog}: {exc}\n")
    elapsed = time.perf_counter() - t0
    table = Table(title=f"benchmarks.{name}{' --quick' if args.quick else ''} ({elapsed:.0f} s)")
    table.add_column("figure")
    table.add_column("value", justify="right")
    for k, v in figures.items():
        table.add_row(k, f"{v:.4g}" if isinstance(v, float) else str(v))
    console = Console()
    console.print(table)
    console.print(f"machine: {machine()}")
    if args.json:
        args.json.write_text(json.dumps({**figures, "machine": machine(), "quick": args.quick}, indent=2))
    if args.record:
        path = record(name, figures, quick=args.quick, argv=[a for a in sys.argv[1:] if a != "--record"])
        console.print(f"recorded in {path}")


@dataclass(frozen=True)
class Row:
    """One figure as ``docs/performance.md`` shows it: what it measures (``{name}`` placeholders take
    other figures of the same run), what it is judged against, whether it met that (None: no
    target, the row informs), and which figures say the option it judges acted at all."""

    figure: str
    what: str
    target: str = "-"
    met: Callable[[float], bool] | None = None
    #: Figures counting what the option under test did in the run (instants, frames entered): a row
    #: none of them counts is "not exercised", neither met nor missed.
    exercised: tuple[str, ...] = ()


#: Where recorded runs are kept; ``docs/performance.md`` is generated from them.
RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


def record(name: str, figures: dict[str, float], quick: bool, argv: list[str]) -> Path:
    """Keep one run's figures in ``RESULTS/NAME.json`` (``NAME-quick.json`` for ``--quick``) with
    what is needed to judge them: the machine, the date (UTC), the commit (``+dirty`` when the tree
    had changes) and the command."""
    import datetime as dt

    def git(*cmd: str) -> str:
        out = subprocess.run(["git", *cmd], cwd=RESULTS.parents[1], capture_output=True, text=True)
        return out.stdout.strip() if out.returncode == 0 else ""

    commit = (git("rev-parse", "--short", "HEAD") or "unknown") + (
        "+dirty" if git("status", "--porcelain", "-uno") else ""
    )
    run = {
        "benchmark": name,
        "command": " ".join([f"python -m benchmarks.{name}", *argv]),
        "commit": commit,
        "date": dt.datetime.now(dt.UTC).date().isoformat(),
        "machine": machine(),
        "figures": figures,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}{'-quick' if quick else ''}.json"
    path.write_text(json.dumps(run, indent=1) + "\n")
    return path
