"""``--foxglove``: the cell's bus, live in the Foxglove app over WebSocket (loopback by default).

The same bridge as the recorder, into Foxglove's server instead of a file: every key becomes a
channel with its protobuf schema (Foxglove's own for images, calibration and tf), payloads pass
through untouched. Images (RawImage and camera_info share the camera id as frame_id, and tf has
world -> camera), so the 3-D panel shows camera frustums, marker axes and camera poses; with the
recognition worker running it also shows the fused world cloud (``points``, a colour per camera)
and the objects' boxes (``objects/scene``).
Images come at most ``max_image_hz`` per camera (to spare the WebSocket, the drivers and any link
between hosts: ``schemas.bus.CellTap``).
"""

from __future__ import annotations

import logging
import threading

import foxglove
from mcap_protobuf.schema import build_file_descriptor_set

from schemas import keys
from schemas.bus import Bus
from schemas.errors import SchemaError

log = logging.getLogger(__name__)


class FoxgloveBridge:
    def __init__(self, bus: Bus, port: int = 8765, host: str = "127.0.0.1", max_image_hz: float | None = 5.0) -> None:
        self.server = foxglove.start_server(name=f"cellsight {bus.cell}", host=host, port=port)
        self.port = self.server.port
        self.max_image_hz = max_image_hz
        self._channels: dict[str, foxglove.Channel] = {}
        self._schemas: dict[str, foxglove.Schema] = {}
        self._lock = threading.Lock()
        self.forwarded = 0
        self._sub = (
            bus.tap_cell(self._on_sample, max_image_hz)
            if max_image_hz
            else bus.subscribe_raw(keys.everything(bus.cell), self._on_sample)
        )
        log.info("Foxglove live view on ws://%s:%d (open it in the Foxglove app)", host, self.port)

    def _channel(self, key: str, msg_type) -> foxglove.Channel:
        ch = self._channels.get(key)
        if ch is None:
            name = msg_type.DESCRIPTOR.full_name
            if name not in self._schemas:
                self._schemas[name] = foxglove.Schema(
                    name=name, encoding="protobuf", data=build_file_descriptor_set(msg_type).SerializeToString()
                )
            ch = self._channels[key] = foxglove.Channel(key, schema=self._schemas[name], message_encoding="protobuf")
        return ch

    def _on_sample(self, key: str, payload: bytes, receive_ns: int) -> None:
        try:
            msg_type = keys.message_type(key)
        except SchemaError:
            return
        with self._lock:
            self._channel(key, msg_type).log(payload, log_time=receive_ns)
            self.forwarded += 1

    def close(self) -> None:
        self._sub.undeclare()
        self.server.stop()
