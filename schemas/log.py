"""MCAP logs of bus traffic: one writer (recorder, resolve) and one tolerant reader.

Every channel is a key expression; its schema is the protobuf ``FileDescriptorSet`` of the type
the key carries (Foxglove's schemas for images, calibration, tf and scenes), so a log opens in
Foxglove and decodes with the plain ``mcap`` + ``mcap-protobuf-support`` readers. log_time is the
receive time, publish_time the sensor stamp (both integer ns).
"""

from __future__ import annotations

import io
import logging
import struct
import zlib
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import Message
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Footer, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import MAGIC_SIZE, CRCValidationError, StreamReader
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

from schemas import codec, keys
from schemas.errors import DecodeError, SchemaError
from schemas.limits import DEFAULT_LIMITS, WireLimits

log = logging.getLogger(__name__)
_RECORD = struct.Struct("<BQ")  # opcode, content length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time; then the payload
_UINT64 = 1 << 64


def stamp_of(msg: Message, default_ns: int) -> int:
    """The sensor stamp (ns) a message carries, or ``default_ns`` if it has none."""
    fields = msg.DESCRIPTOR.fields_by_name
    if "stamp_ns" in fields and msg.stamp_ns:
        return int(msg.stamp_ns)
    if "timestamp" in fields and msg.HasField("timestamp"):
        return codec.timestamp_to_stamp(msg.timestamp)
    if "transforms" in fields and len(msg.transforms):
        return codec.timestamp_to_stamp(msg.transforms[0].timestamp)
    return default_ns


class _UnbufferedFile:
    """A file whose every write reaches the OS completely and at once (raw writes may be partial)."""

    def __init__(self, path: Path) -> None:
        self._f = open(path, "wb", buffering=0)
        self._pos = 0

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view:
            n = self._f.write(view)
            view = view[n:]
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self._f.close()


class LogWriter:
    """Append bus messages to an MCAP file, registering schemas and channels on first use.

    lz4 chunks (zstd cannot keep up with four cameras on two cores). The file is opened
    unbuffered so every finished chunk reaches the OS at once: a writer killed with SIGKILL
    leaves a file readable up to its last complete chunk.
    """

    def __init__(self, path: Path, chunk_size: int = 4 * 1024 * 1024, metadata: dict[str, str] | None = None) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file = _UnbufferedFile(path)
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.LZ4)
        self._writer.start(profile="", library="cellsight")
        if metadata:
            self._writer.add_metadata("cellsight", metadata)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.messages = 0

    def add_metadata(self, name: str, metadata: dict[str, str]) -> None:
        """An MCAP metadata record (``mcap list metadata`` shows it), written where the log has got to."""
        self._writer.add_metadata(name, metadata)

    def _channel(self, key: str, msg_type: type[Message]) -> int:
        if key not in self._channels:
            name = msg_type.DESCRIPTOR.full_name
            if name not in self._schemas:
                fds = build_file_descriptor_set(msg_type)
                self._schemas[name] = self._writer.register_schema(name, "protobuf", fds.SerializeToString())
            self._channels[key] = self._writer.register_channel(key, "protobuf", self._schemas[name])
        return self._channels[key]

    def write(self, key: str, msg: Message, log_time_ns: int, publish_time_ns: int | None = None) -> None:
        self.write_raw(
            key, type(msg), msg.SerializeToString(), log_time_ns, publish_time_ns or stamp_of(msg, log_time_ns)
        )

    def write_raw(
        self, key: str, msg_type: type[Message], payload: bytes, log_time_ns: int, publish_time_ns: int
    ) -> None:
        """Append one message; a time MCAP cannot hold (negative, or past 2^64 ns) raises ``DecodeError``
        before anything is written: the writer would fail half-way through the record, and the log
        would not read past it."""
        for name, t in (("log time", log_time_ns), ("publish time", publish_time_ns)):
            if not 0 <= t < _UINT64:
                raise DecodeError(f"{key}: {name} {t} ns cannot be written (MCAP times are unsigned 64-bit)", "stamp")
        self._writer.add_message(self._channel(key, msg_type), log_time_ns, payload, publish_time_ns)
        self.messages += 1

    def close(self) -> None:
        self._writer.finish()
        self._file.close()

    def abandon(self) -> None:
        """Close the file without a footer, after a failed write: it stays readable up to its last
        complete chunk, as after a crash."""
        self._file.close()


class _Capped:
    """A file opened for reading whose ``read(n)`` never asks for more than is left in it: a damaged
    length field (up to 2^64) then reads as a truncation instead of allocating its size."""

    def __init__(self, f, size: int) -> None:
        self._f = f
        self._size = size

    def read(self, n: int = -1) -> bytes:
        left = max(self._size - self._f.tell(), 0)
        return self._f.read(left if n is None or n < 0 else min(n, left))


@dataclass(frozen=True)
class LogMessage:
    key: str
    msg: Message
    log_time_ns: int
    publish_time_ns: int


@dataclass
class ReadReport:
    """What a tolerant read got through: messages decoded, skipped and why it stopped early."""

    messages: int = 0
    undecodable: int = 0
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # MCAP metadata records by name
    unknown_keys: set[str] = field(default_factory=set)
    stopped_early: str | None = None  # where and why the log could not be read further
    #: (key, reason) -> messages skipped as a live receiver would have refused them
    refused: Counter[tuple[str, str]] = field(default_factory=Counter)

    def gaps(self) -> list[Gap]:
        """The silences the recorder marked (metadata records ``gap/<camera>/<from_ns>``), oldest first."""
        found = [
            Gap(md["camera"], int(md["from_ns"]), int(md["to_ns"]))
            for name, md in self.metadata.items()
            if name.startswith(GAP_PREFIX) and {"camera", "from_ns", "to_ns"} <= md.keys()
        ]
        return sorted(found, key=lambda g: g.from_ns)


GAP_PREFIX = "gap/"


@dataclass(frozen=True)
class Gap:
    """A camera the recorder heard nothing from between two receive times (ns, recorder's clock)."""

    camera: str
    from_ns: int  # its last message before the silence
    to_ns: int  # its first message after it (or the end of the recording)

    @property
    def seconds(self) -> float:
        return (self.to_ns - self.from_ns) / 1e9

    def metadata(self) -> tuple[str, dict[str, str]]:
        """The record's name and content."""
        return f"{GAP_PREFIX}{self.camera}/{self.from_ns}", {
            "camera": self.camera,
            "from_ns": str(self.from_ns),
            "to_ns": str(self.to_ns),
            "seconds": f"{self.seconds:.3f}",
        }


def chunk_records(chunk: Chunk) -> Iterator[Channel | Schema | McapMessage]:
    """The channel, schema and message records inside a chunk, CRC checked.

    ``mcap``'s stream reader parses a chunk's records field by field in Python; a message record
    is a fixed header and a payload, so this unpacks it in one call (several times faster over a
    log of small messages). Damage raises ``struct.error``, ``McapError`` or a CRC error.
    """
    if chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "zstd":
        import zstandard

        data = zstandard.decompress(chunk.data, chunk.uncompressed_size)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise McapError(f"unsupported chunk compression {chunk.compression!r}")
    if chunk.uncompressed_crc != 0 and zlib.crc32(data) != chunk.uncompressed_crc:
        raise CRCValidationError(chunk.uncompressed_crc, zlib.crc32(data), chunk)
    pos, size = 0, len(data)
    while pos < size:
        opcode, length = _RECORD.unpack_from(data, pos)
        pos += _RECORD.size
        end = pos + length
        if end > size:
            raise McapError(f"a record of {length} bytes runs past the end of its chunk")
        if opcode == Opcode.MESSAGE:
            channel_id, sequence, log_time, publish_time = _MESSAGE.unpack_from(data, pos)
            yield McapMessage(
                channel_id=channel_id,
                log_time=log_time,
                data=data[pos + _MESSAGE.size : end],
                publish_time=publish_time,
                sequence=sequence,
            )
        elif opcode == Opcode.CHANNEL:
            yield Channel.read(ReadDataStream(io.BytesIO(data[pos:end])))
        elif opcode == Opcode.SCHEMA:
            yield Schema.read(ReadDataStream(io.BytesIO(data[pos:end])))
        pos = end


def _records(reader: StreamReader) -> Iterator[object]:
    """The reader's records with each chunk's contents in its place."""
    for record in reader.records:
        if isinstance(record, Chunk):
            yield from chunk_records(record)
        else:
            yield record


def read_log(
    path: Path,
    key_filter: set[str] | None = None,
    report: ReadReport | None = None,
    progress: Callable[[int, int], None] | None = None,
    deferred: frozenset[type[Message]] = frozenset(),
    limits: WireLimits = DEFAULT_LIMITS,
) -> Iterator[LogMessage]:
    """Stream a log in file order, decoding and validating each message.

    Messages of a ``deferred`` type are checked against the schema only: the caller validates
    their content itself, many at once (``codec.marker_batch``), and must not trust them before.
    Every message is checked as a live receiver checks it (``codec.check_on_key``, the recorder's
    receive time as the clock): what the bus would have refused is skipped here too, and counted in
    ``report.refused`` by key and reason.

    A truncated or damaged file yields everything before the damage; ``report.stopped_early``
    says where and why it stopped. Undecodable messages are counted and skipped.
    """
    report = report if report is not None else ReadReport()
    channels: dict[int, Channel] = {}
    total = Path(path).stat().st_size
    with open(path, "rb") as f:
        try:
            for record in _records(
                StreamReader(_Capped(f, total), skip_magic=False, emit_chunks=True, validate_crcs=True)
            ):
                if isinstance(record, Footer):
                    if f.tell() < total - MAGIC_SIZE:  # damage that reads as a footer, not the end of the file
                        raise McapError(f"a footer record at byte {f.tell()} of {total}")
                    return  # a complete file: the summary section holds nothing we need
                if progress is not None:
                    progress(f.tell(), total)
                if isinstance(record, Metadata):
                    report.metadata[record.name] = dict(record.metadata)
                    continue
                if isinstance(record, Schema):
                    continue
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, McapMessage):
                    ch = channels.get(record.channel_id)
                    if ch is None:  # its channel record was damaged
                        report.undecodable += 1
                        continue
                    if key_filter is not None and ch.topic not in key_filter:
                        continue
                    try:
                        parsed = keys.parse(ch.topic)
                        msg = codec.decode(
                            record.data, parsed.message_type, parsed.message_type not in deferred, limits
                        )
                        codec.check_on_key(msg, parsed.camera, record.log_time, limits)
                    except DecodeError as exc:
                        report.undecodable += 1
                        report.refused[ch.topic, exc.reason] += 1
                        continue
                    except SchemaError:
                        report.undecodable += 1
                        if ch.topic.startswith(keys.ROOT):
                            continue
                        report.unknown_keys.add(ch.topic)
                        continue
                    report.messages += 1
                    yield LogMessage(ch.topic, msg, record.log_time, record.publish_time)
        # RuntimeError: lz4 on a damaged chunk; struct.error: a record cut short of its length field
        except (McapError, EOFError, ValueError, OSError, RuntimeError, struct.error) as exc:
            report.stopped_early = f"cut or damaged at byte {f.tell():,} of {total:,} ({type(exc).__name__}: {exc})"
            log.warning("%s: stopped reading after %d messages: %s", path, report.messages, report.stopped_early)
