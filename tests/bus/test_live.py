"""The Foxglove live view: a real WebSocket client sees the bus's keys with their schemas."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np
import websockets

from cellsight.live import FoxgloveBridge
from schemas import codec, keys
from schemas import messages as m
from schemas.bus import Bus, TransportConfig
from tests.conftest import free_port
from tests.helpers import wait_until

CELL = "live"


async def advertised(port: int, want: set[str], timeout_s: float) -> dict[str, str]:
    """Topics -> schema names the server advertises, until ``want`` are all there."""
    seen: dict[str, str] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
        deadline = time.monotonic() + timeout_s
        while not want <= set(seen) and time.monotonic() < deadline:
            raw = await asyncio.wait_for(ws.recv(), timeout=max(deadline - time.monotonic(), 0.1))
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg.get("op") == "advertise":
                    seen.update({c["topic"]: c.get("schemaName", "") for c in msg["channels"]})
    return seen


def test_bus_keys_appear_in_foxglove_with_their_schemas(client_transport: TransportConfig) -> None:
    with Bus(client_transport, CELL) as bridge_bus, Bus(client_transport, CELL) as pub_bus:
        bridge = FoxgloveBridge(bridge_bus, port=free_port())
        try:
            status = pub_bus.publisher(keys.status(CELL, "cam1"))
            tf_pub = pub_bus.publisher(keys.estimate_status(CELL))
            cloud_pub = pub_bus.publisher(keys.points(CELL))
            cloud = codec.points_to_msg(1, "world", np.zeros((4, 3)), np.full((4, 4), 255, np.uint8))

            def publish() -> bool:
                status.put(m.DriverStatus(camera_id="cam1", stamp_ns=1))
                tf_pub.put(m.EstimatorStatus(stamp_ns=1))
                cloud_pub.put(cloud)
                return bridge.forwarded >= 3

            wait_until(publish, 5.0, "forwarded messages")
            want = {keys.status(CELL, "cam1"), keys.estimate_status(CELL), keys.points(CELL)}
            seen = asyncio.run(advertised(bridge.port, want, 5.0))
        finally:
            bridge.close()
    assert seen[keys.status(CELL, "cam1")] == "cellsight.DriverStatus"
    assert seen[keys.estimate_status(CELL)] == "cellsight.EstimatorStatus"
    assert seen[keys.points(CELL)] == "foxglove.PointCloud"  # the fused cloud, drawn by the 3-D panel
