"""Two hosts on one machine: Linux network namespaces joined by a veth link (needs root and iproute2).

``two_hosts()`` creates namespaces ``<prefix>cell`` and ``<prefix>edge`` and a veth pair with
addresses it assigns to its own two ends (10.213.7.0/24: nothing leaves them), and removes them
all afterwards. Used by the multi-host test and the transport benchmark's cross-host figure.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

CELL_IP, EDGE_IP = "10.213.7.1", "10.213.7.2"
CELL_DEV, EDGE_DEV = "cs-veth-c", "cs-veth-e"


def can_make_hosts() -> bool:
    return os.geteuid() == 0 and shutil.which("ip") is not None


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@contextmanager
def two_hosts(prefix: str | None = None) -> Iterator[tuple[str, str]]:
    """(cell namespace, edge namespace), linked: cell at ``CELL_IP``, edge at ``EDGE_IP``."""
    prefix = prefix or f"cs{os.getpid()}"
    cell, edge = f"{prefix}cell", f"{prefix}edge"
    ip("netns", "add", cell)
    ip("netns", "add", edge)
    try:
        ip("link", "add", CELL_DEV, "type", "veth", "peer", "name", EDGE_DEV)
        ip("link", "set", CELL_DEV, "netns", cell)
        ip("link", "set", EDGE_DEV, "netns", edge)
        for ns, dev, addr in ((cell, CELL_DEV, CELL_IP), (edge, EDGE_DEV, EDGE_IP)):
            ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
            ip("-n", ns, "link", "set", dev, "up")
            ip("-n", ns, "link", "set", "lo", "up")
        yield cell, edge
    finally:
        ip("netns", "del", cell)  # takes the veth pair with it
        ip("netns", "del", edge)


def in_ns(ns: str, argv: list[str], log: Path | None = None, stdout: int | IO | None = None, **kw) -> subprocess.Popen:
    """Start ``argv`` inside namespace ``ns``; output to ``log`` (or ``stdout``), errors with it."""
    out = stdout if stdout is not None else (log.open("w") if log is not None else subprocess.DEVNULL)
    return subprocess.Popen(["ip", "netns", "exec", ns, *argv], stdout=out, stderr=subprocess.STDOUT, **kw)


def rx_bytes(ns: str, dev: str = CELL_DEV) -> int:
    """Bytes received so far on a namespace's interface."""
    out = subprocess.run(
        ["ip", "-n", ns, "-j", "-s", "link", "show", dev], check=True, capture_output=True, text=True
    ).stdout
    return int(json.loads(out)[0]["stats64"]["rx"]["bytes"])


def stop_all(procs: list[subprocess.Popen], grace_s: float = 20.0) -> None:
    """SIGTERM every process (last started first), then SIGKILL what has not exited within ``grace_s``."""
    for p in reversed(procs):
        p.terminate()
    for p in procs:
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            p.kill()
