"""VFH: our numpy descriptor against the Point Cloud Library's own C++ on the same cloud, same run.

Cloud: milk.pcd (13,704 points) with PCL's reference normals (radius 2 cm), viewpoint at the origin.
PCL: Debian's libpcl-dev 1.13 (installed here with apt-get when missing, as root: it is not a
dependency of cellsight), ``pcl::VFHEstimation<PointXYZ, Normal, VFHSignature308>`` from
libpcl_features, driven by ``benchmarks/pcl_vfh.cpp`` compiled with g++ -O2. PCL is timed two
ways: the feature alone (a search tree built once beforehand: VFH never searches) and a plain
``compute()`` that builds its own kd-tree, as PCL's tutorial code does; the ratio to beat (<= 2) is
against the feature alone. Rounds alternate between the two so that machine drift hits both.

Agreement: the largest bin difference between ours and PCL's (both parameter sets the reference
JSON lists), on the histogram each computes here, not on stored numbers.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import PCL_DATA, main
from recognition.cloud import read_cloud
from recognition.vfh import vfh

HERE = Path(__file__).resolve().parent
PCL_HEADER = Path("/usr/include/pcl-1.13/pcl/features/vfh.h")
SETTINGS = {"default": (False, False), "normalize_distance_and_size_component": (True, True)}


def ensure_pcl() -> None:
    """Install Debian's libpcl-dev (and g++) when missing; needs root and apt-get."""
    if PCL_HEADER.is_file() and shutil.which("g++"):
        return
    if os.geteuid() != 0 or not shutil.which("apt-get"):
        raise SystemExit(
            "benchmarks.vfh needs Debian's libpcl-dev and g++: run as root, or `apt-get install libpcl-dev g++`"
        )
    print("installing Debian's libpcl-dev (PCL 1.13) for the reference ...", flush=True)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run(["apt-get", "update", "-q"], check=True, env=env, stdout=subprocess.DEVNULL)
    subprocess.run(
        ["apt-get", "install", "-y", "-q", "--no-install-recommends", "libpcl-dev", "g++", "pkg-config"],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )


def build(workdir: Path) -> Path:
    """Compile pcl_vfh.cpp against the installed PCL; the executable's path."""
    flags = subprocess.run(
        ["pkg-config", "--cflags", "--libs", "pcl_features", "pcl_search"], check=True, capture_output=True, text=True
    ).stdout.split()
    exe = workdir / "pcl_vfh"
    cflags = [f for f in flags if not f.startswith(("-l", "-L"))]
    libs = [f for f in flags if f.startswith(("-l", "-L"))]
    subprocess.run(["g++", "-O2", "-std=c++17", *cflags, str(HERE / "pcl_vfh.cpp"), "-o", str(exe), *libs], check=True)
    return exe


def run_pcl(exe: Path, cloud_file: Path, reps: int, setting: str) -> tuple[list[float], list[float], np.ndarray]:
    """PCL's per-call times (ms; feature alone, and compute() with its own tree) and its histogram."""
    nd, size = SETTINGS[setting]
    out = subprocess.run(
        [str(exe), str(cloud_file), str(reps), str(int(nd)), str(int(size))], check=True, capture_output=True, text=True
    ).stdout.splitlines()
    return (
        [float(t) for t in out[0].split()],
        [float(t) for t in out[1].split()],
        np.array(out[2].split(), dtype=np.float64),
    )


def run_ours(points: np.ndarray, normals: np.ndarray, reps: int, setting: str) -> tuple[list[float], np.ndarray]:
    nd, size = SETTINGS[setting]
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        h = vfh(points, normals, normalize_distance=nd, size_component=size)
        times.append(1e3 * (time.perf_counter() - t0))
    return times, h.astype(np.float64)


def run(quick: bool) -> dict[str, float]:
    ensure_pcl()
    points = read_cloud(PCL_DATA / "milk.pcd")
    normals = np.array(
        json.loads((PCL_DATA / "reference" / "milk_normals_pcl.json").read_text())["normals"], dtype=np.float32
    )[:, :3]
    rounds, reps = (4, 20) if quick else (10, 50)
    with tempfile.TemporaryDirectory(prefix="cellsight-vfh-") as tmp:
        exe = build(Path(tmp))
        cloud_file = Path(tmp) / "milk.bin"
        cloud_file.write_bytes(
            np.int32(len(points)).tobytes() + np.hstack([points, normals]).astype(np.float32).tobytes()
        )
        diff = 0.0
        for setting in SETTINGS:  # agreement, both parameter sets
            _, _, h_pcl = run_pcl(exe, cloud_file, 1, setting)
            _, h_ours = run_ours(points, normals, 1, setting)
            diff = max(diff, float(np.max(np.abs(h_ours - h_pcl))))
        run_ours(points, normals, 5, "default")  # warm-up
        ours, pcl, pcl_tree = [], [], []
        for _ in range(rounds):
            feature, with_tree, _ = run_pcl(exe, cloud_file, reps, "default")
            pcl += feature
            pcl_tree += with_tree
            ours += run_ours(points, normals, reps, "default")[0]
    ours_ms, pcl_ms, tree_ms = (float(np.median(t)) for t in (ours, pcl, pcl_tree))
    return {
        "points": float(len(points)),
        "max_abs_bin_diff_vs_pcl": diff,
        "numpy_ms_p50": ours_ms,
        "pcl_ms_p50": pcl_ms,
        "pcl_with_kdtree_ms_p50": tree_ms,
        "numpy_over_pcl_time_ratio": ours_ms / pcl_ms,
        "numpy_over_pcl_with_kdtree_time_ratio": ours_ms / tree_ms,
    }


if __name__ == "__main__":
    main("vfh", __doc__.splitlines()[0], run)
