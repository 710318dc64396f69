"""Shared fixtures: a real zenoh router on loopback and client transports that reach it."""

from __future__ import annotations

import socket
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
