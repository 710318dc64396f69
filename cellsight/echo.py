"""Human- and machine-readable printing of bus messages (``cellsight bus echo`` / ``bus list``)."""

from __future__ import annotations

import json
import time
from collections import Counter

from google.protobuf import json_format, text_format
from google.protobuf.message import Message

from schemas.bus import Bus

_BULK_FIELDS = ("data",)  # image / point-cloud payloads: shown as a size, never dumped


def _summarised(msg: Message) -> Message:
    out = type(msg)()
    out.CopyFrom(msg)
    for name in _BULK_FIELDS:
        if name in out.DESCRIPTOR.fields_by_name and getattr(out, name):
            setattr(out, name, b"")
    return out


def format_message(key: str, msg: Message, as_json: bool) -> str:
    """One message as text (``key:`` then protobuf text format) or one JSON line."""
    bulk = {n: len(getattr(msg, n)) for n in _BULK_FIELDS if n in msg.DESCRIPTOR.fields_by_name}
    slim = _summarised(msg)
    if as_json:
        body = json_format.MessageToDict(slim, preserving_proto_field_name=True)
        body.update({f"{n}_bytes": v for n, v in bulk.items()})
        return json.dumps({"key": key, "type": msg.DESCRIPTOR.full_name, "message": body})
    text = text_format.MessageToString(slim, as_one_line=False)
    extra = "".join(f"{n}: <{v} bytes>\n" for n, v in bulk.items())
    return f"--- {key} ({msg.DESCRIPTOR.full_name})\n{text}{extra}"


def sample_rates(bus: Bus, duration_s: float) -> tuple[dict[str, tuple[str, int]], Counter]:
    """Listen to every key of the bus's cell for ``duration_s``: {key: (type, count)}, bad counts."""
    counts: Counter[str] = Counter()
    types: dict[str, str] = {}

    def on_msg(item) -> None:
        counts[item.key] += 1
        types[item.key] = item.msg.DESCRIPTOR.full_name

    from schemas import keys

    sub = bus.subscribe(keys.everything(bus.cell), callback=on_msg)
    time.sleep(duration_s)
    sub.close()
    return {k: (types[k], counts[k]) for k in counts}, sub.bad
