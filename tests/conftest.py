"""Shared fixtures: a real zenoh router on loopback and client transports that reach it."""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path
from typing import Iterator

import pytest

from schemas.bus import TransportConfig, open_session

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def router_endpoint() -> Iterator[str]:
    """A zenoh router listening on a free loopback port, multicast off; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(TransportConfig.router([endpoint]))
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture()
def client_transport(router_endpoint: str) -> TransportConfig:
    return TransportConfig(mode="client", connect=[router_endpoint])


@pytest.fixture()
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"real test data missing: expected {SHARED_DATA} (the shared/ folder beside the repo)")
    return SHARED_DATA


@pytest.fixture()
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 16 MiB tmpfs mounted in tmp_path: a disk that really fills (writes fail with ENOSPC).
    Mounting needs root, which the set-up and CI run as."""
    where = tmp_path / "disk"
    where.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(where)], capture_output=True, text=True)
    if mounted.returncode != 0:
        # Set-up and CI run as root, where this must work; elsewhere say so rather than skip quietly.
        pytest.fail(f"cannot mount a small tmpfs to fill: {mounted.stderr.strip()} (needs root, as set-up and CI run)")
    try:
        yield where
    finally:
        subprocess.run(["umount", "--lazy", str(where)], check=True)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests are laid out by layer: ``core`` (pure cores), ``bus`` (services on a real zenoh bus),
    ``e2e`` (several processes, whole pipelines). Every end-to-end test is slow."""
    for item in items:
        if "e2e" in item.path.parts:
            item.add_marker(pytest.mark.slow)
