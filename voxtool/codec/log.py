"""Packet logs: MCAP files with one channel per robot carrying voxtool packets.

Schema `voxtool/MapPacket` (encoding `voxtool-packet-v1`, the bytes of formats/packet.md), topic
`/voxtool/packets/<robot>`, log time = publish time = packet stamp. A metadata record `voxtool`
per robot records how the packets were made (sensor model, map parameters, scheme, codec) and the
raw sensor bytes and time span of the source, so bandwidth can be compared with what was not sent.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from pathlib import Path
from zlib import error as zlib_error

from voxtool.atomic import atomic_writer
from voxtool.codec.packet import HEADER
from voxtool.errors import FormatError, mcap_problem

SCHEMA_NAME = "voxtool/MapPacket"
SCHEMA_ENCODING = "voxtool-packet-v1"
SCHEMA_TEXT = b"voxtool map-change packet v1: 96-byte little-endian header + payload; see formats/packet.md"
MAX_MESSAGE = 1 << 31


class PacketLogWriter:
    """Write packets of one or more robots to an MCAP file, atomically (temp file + rename)."""

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import CompressionType, Writer

        self._ctx = atomic_writer(path)
        self._handle = self._ctx.__enter__()
        self._writer = Writer(self._handle, compression=CompressionType.NONE)  # payloads are compressed already
        self._writer.start(profile="", library="voxtool")
        self._schema = self._writer.register_schema(SCHEMA_NAME, SCHEMA_ENCODING, SCHEMA_TEXT)
        self._channels: dict[str, int] = {}

    def channel(self, robot: str) -> int:
        if robot not in self._channels:
            self._channels[robot] = self._writer.register_channel(
                f"/voxtool/packets/{robot}", SCHEMA_ENCODING, self._schema, {"robot": robot})
        return self._channels[robot]

    def write(self, robot: str, seq: int, stamp_ns: int, blob: bytes) -> None:
        self._writer.add_message(self.channel(robot), stamp_ns, blob, stamp_ns, sequence=seq & 0xFFFFFFFF)

    def metadata(self, robot: str, info: dict) -> None:
        self._writer.add_metadata("voxtool", {"robot": robot, "info": json.dumps(info, sort_keys=True)})

    def close(self, ok: bool = True) -> None:
        if ok:
            self._writer.finish()
            self._ctx.__exit__(None, None, None)
        else:
            import sys

            self._ctx.__exit__(*sys.exc_info())

    def __enter__(self) -> PacketLogWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self._writer.finish()
            self._ctx.__exit__(None, None, None)
        else:
            self._ctx.__exit__(exc_type, exc, tb)


class Messages:
    """The packets of a log, (robot, log time, packet bytes) in file order, read as iterated;
    `count`: how many the log's summary declares."""

    def __init__(self, iterator: Iterator[tuple[str, int, bytes]], count: int | None) -> None:
        self._iterator = iterator
        self.count = count

    def __iter__(self) -> Iterator[tuple[str, int, bytes]]:
        return self._iterator


def read_log(path: str | Path, handle=None) -> tuple[dict[str, dict], Messages]:
    """(metadata per robot, the packets as Messages). `handle` (a seekable binary stream) is
    read instead of opening `path`, which then only names the input in messages."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    path = Path(path)
    if handle is None:
        try:
            handle = open(path, "rb")
        except OSError as err:
            raise FormatError(f"{path}: cannot read: {err.strerror}") from err
    try:
        reader = make_reader(handle, validate_crcs=True)
        meta = {}
        for record in reader.iter_metadata():
            if record.name == "voxtool":
                meta[record.metadata.get("robot", "")] = json.loads(record.metadata.get("info", "{}"))
        summary = reader.get_summary()
    except (McapError, ValueError, EOFError, AssertionError, json.JSONDecodeError, KeyError, struct.error,
            UnicodeDecodeError, OverflowError, MemoryError) as err:
        handle.close()
        raise FormatError(f"{path}: cannot be read as a packet log: {mcap_problem(err)}") from err
    if summary is None or not any(s.name == SCHEMA_NAME for s in summary.schemas.values()):
        handle.close()
        raise FormatError(f"{path}: MCAP holds no '{SCHEMA_NAME}' schema (not a voxtool packet log)")

    def messages() -> Iterator[tuple[str, int, bytes]]:
        try:
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if schema is None or schema.name != SCHEMA_NAME:
                    continue
                if len(message.data) < HEADER.size or len(message.data) > MAX_MESSAGE:
                    raise FormatError(f"{path}: message {message.sequence} on {channel.topic} has {len(message.data)} bytes")
                yield channel.metadata.get("robot", channel.topic.rsplit("/", 1)[-1]), message.log_time, message.data
        except (McapError, ValueError, EOFError, AssertionError, KeyError, struct.error, UnicodeDecodeError,
                OverflowError, zlib_error) as err:
            raise FormatError(f"{path}: cannot be read as a packet log: {mcap_problem(err)}") from err
        finally:
            handle.close()

    stats = summary.statistics
    return meta, Messages(messages(), int(stats.message_count) if stats is not None else None)
