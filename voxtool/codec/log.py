"""Packet logs: MCAP files with one channel per robot carrying voxtool packets.

A ROS 2 log (profile ros2): messages of type `voxtool_msgs/msg/MapPacket` (its ros2msg definition
is the schema, CDR written by mcap-ros2-support), so Foxglove, rosbags and ROS 2 tools decode the
header fields without voxtool; the field `packet` holds the packet verbatim (formats/packet.md).
Topic `/voxtool/packets/<robot>`, log time = publish time = packet stamp. A metadata record
`voxtool` per robot records how the packets were made (sensor model, map parameters, scheme,
codec) and the raw sensor bytes and time span of the source, so bandwidth can be compared with
what was not sent. Logs in the first layout (schema `voxtool/MapPacket`, the packet as the
whole message) still read.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from zlib import error as zlib_error

from voxtool.atomic import atomic_writer
from voxtool.codec.packet import CODECS, HEADER, MAGIC, SCHEMES
from voxtool.errors import FormatError, mcap_problem

MESSAGE_TYPE = "voxtool_msgs/msg/MapPacket"
MESSAGE_DEFINITION = """\
# A voxtool map-change packet (formats/packet.md). The fields before `packet` repeat its header
# so that readers without voxtool can index and plot a log; `packet` is the packet verbatim.
string robot            # sender id (1..16 bytes)
uint32 sequence         # per robot, from 0
int64 stamp_ns          # scan time of the change, ns
uint8 version           # packet format version
uint8 kind              # 0 delta (unchanged cells allowed), 1 keyframe
string scheme           # hilbert | nested | racer | occupied
string codec            # none | zstd | zlib | cm1 | cm
float64 resolution      # voxel edge, m
float64[3] map_origin   # world position of the key-32768 corner, m
uint16[3] box_min       # first key of the changed box
uint16[3] box_size      # voxels per axis of the box
uint32 count            # cells or voxels the payload holds
uint32 raw_size         # payload bytes before compression
uint32 stored_size      # payload bytes as sent
uint8[] packet          # 96-byte header + payload: the bytes a robot sends
"""
# definitions this voxtool decodes: its own, and the earlier one whose map_origin comment said
# "key 0" (the same fields, so the same CDR; only the comment was wrong)
READ_DEFINITIONS = {MESSAGE_DEFINITION.encode(), MESSAGE_DEFINITION.replace(
    "world position of the key-32768 corner, m", "world position of key 0, m").encode()}
LEGACY_SCHEMA = "voxtool/MapPacket"  # the first layout: the packet is the whole message
MAX_MESSAGE = 1 << 31


def packet_message(blob: bytes) -> dict:
    """The MapPacket fields of a packet (its header, read without checking the payload)."""
    f = HEADER.unpack_from(blob, 0)
    name = lambda names, i: names[i] if i < len(names) else f"unknown {i}"  # noqa: E731 (a bad packet still logs)
    return {"robot": f[5].rstrip(b"\0").decode("utf-8", "replace"), "sequence": f[6], "stamp_ns": f[7],
            "version": f[1], "kind": f[2], "scheme": name(SCHEMES, f[3]), "codec": name(CODECS, f[4]), "resolution": f[8],
            "map_origin": list(f[9:12]), "box_min": list(f[12:15]), "box_size": list(f[15:18]), "count": f[18],
            "raw_size": f[19], "stored_size": f[20], "packet": blob}


class PacketLogWriter:
    """Write packets of one or more robots to an MCAP file, atomically (temp file + rename)."""

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        self._ctx = atomic_writer(path)
        self._handle = self._ctx.__enter__()
        self._writer = Writer(self._handle, compression=CompressionType.NONE)  # payloads are compressed already
        self._schema = self._writer.register_msgdef(MESSAGE_TYPE, MESSAGE_DEFINITION)

    def write(self, robot: str, seq: int, stamp_ns: int, blob: bytes) -> None:
        self._writer.write_message(f"/voxtool/packets/{robot}", self._schema, packet_message(blob), log_time=stamp_ns,
                                   publish_time=stamp_ns, sequence=seq & 0xFFFFFFFF)

    def metadata(self, robot: str, info: dict) -> None:
        from voxtool import __version__

        self._writer.add_metadata("voxtool", {"robot": robot, "writer": f"voxtool {__version__}",
                                              "info": json.dumps(info, sort_keys=True)})

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


@dataclass(frozen=True)
class PacketHeader:
    """What a packet's header says (the MapPacket message's fields), read without its payload."""

    robot: str
    stamp_ns: int
    kind: int
    scheme: str
    codec: str
    count: int
    raw_size: int
    stored_size: int
    box_cells: int
    packet: Callable[[], bytes]  # the packet itself, decoded from the message when asked

    @property
    def wire_bytes(self) -> int:
        return HEADER.size + self.stored_size


def _header_decoder(schema):
    """A CDR decoder of a MapPacket message's fields before `packet`: CDR is read front to back,
    so the packet's bytes are never copied (14 us a message, against the whole message's decode)."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    fields = "\n".join(line for line in schema.data.decode().splitlines() if not line.startswith("uint8[] packet"))
    return DecoderFactory().decoder_for("cdr", Schema(id=schema.id, name=schema.name, encoding=schema.encoding,
                                                      data=fields.encode()))


def _legacy_header(robot: str, stamp: int, blob: bytes) -> PacketHeader:
    from dataclasses import replace

    return replace(_packet_header(HEADER.unpack_from(blob, 0), stamp, lambda: blob), robot=robot)


def _header_of_message(message, channel: int, header_of, decode, packet_at: dict) -> PacketHeader:
    """A MapPacket message's PacketHeader. The fields before `packet` are the same size in every
    message of a channel (one robot, scheme and codec), so the packet starts at the same offset:
    the decoder finds it on a channel's first message, and later ones are read there with the
    packet's own header (1 us against the decoder's 14), each checked (magic, the length its
    header declares) and decoded by the decoder where a check fails."""
    data = message.data
    start = packet_at.get(channel)
    if start is not None and len(data) >= start + HEADER.size:
        f = HEADER.unpack_from(data, start)
        if f[0] == MAGIC and start + HEADER.size + f[20] == len(data):
            return _packet_header(f, message.log_time, lambda: bytes(data[start:]))
    fields = header_of(data)
    packet_at[channel] = len(data) - HEADER.size - fields.stored_size
    x, y, z = fields.box_size
    return PacketHeader(fields.robot, message.log_time, fields.kind, fields.scheme, fields.codec, fields.count,
                        fields.raw_size, fields.stored_size, x * y * z, lambda: bytes(decode(data).packet))


def _packet_header(f: tuple, stamp: int, packet) -> PacketHeader:
    """A PacketHeader from a packet header's unpacked fields."""
    name = lambda names, i: names[i] if i < len(names) else f"unknown {i}"  # noqa: E731
    return PacketHeader(f[5].rstrip(b"\0").decode("utf-8", "replace"), stamp, f[2], name(SCHEMES, f[3]),
                        name(CODECS, f[4]), f[18], f[19], f[20], f[15] * f[16] * f[17], packet)


class Messages:
    """The packets of a log, (robot, log time, packet bytes) in file order, read as iterated;
    `count`: how many the log's summary declares."""

    def __init__(self, iterator: Iterator[tuple[str, int, bytes]], count: int | None) -> None:
        self._iterator = iterator
        self.count = count

    def __iter__(self) -> Iterator[tuple[str, int, bytes]]:
        return self._iterator


def read_log(path: str | Path, handle=None, headers: bool = False) -> tuple[dict[str, dict], Messages]:
    """(metadata per robot, the packets as Messages). `handle` (a seekable binary stream) is
    read instead of opening `path`, which then only names the input in messages. `headers`: the
    messages are PacketHeaders (what `stats` needs, read at the speed of the file) instead of
    (robot, log time, packet bytes)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from voxtool.compression import check_mcap_chunks

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
        check_mcap_chunks(handle, summary, str(path))
    except FormatError:
        handle.close()
        raise
    except (McapError, ValueError, EOFError, AssertionError, json.JSONDecodeError, KeyError, struct.error,
            UnicodeDecodeError, OverflowError, MemoryError) as err:
        handle.close()
        raise FormatError(f"{path}: cannot be read as a packet log: {mcap_problem(err)}") from err
    names = {s.name for s in summary.schemas.values()} if summary is not None else set()
    if not names & {MESSAGE_TYPE, LEGACY_SCHEMA}:
        handle.close()
        raise FormatError(f"{path}: MCAP holds no '{MESSAGE_TYPE}' messages (not a voxtool packet log)")
    decode = None
    if MESSAGE_TYPE in names:
        schema = next(s for s in summary.schemas.values() if s.name == MESSAGE_TYPE)
        if schema.data not in READ_DEFINITIONS:  # decode only the definitions this voxtool knows
            handle.close()
            raise FormatError(f"{path}: its {MESSAGE_TYPE} definition is not one this voxtool reads "
                              "(another version's log, or a damaged schema)")
        decode = DecoderFactory().decoder_for("cdr", schema)
        header_of = _header_decoder(schema) if headers else None
    packet_at: dict[int, int] = {}  # channel -> where its messages' packets start (see _header_of_message)

    def messages() -> Iterator[tuple[str, int, bytes]]:
        try:
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if schema is None or schema.name not in (MESSAGE_TYPE, LEGACY_SCHEMA):
                    continue
                if headers and schema.name == MESSAGE_TYPE:
                    yield _header_of_message(message, channel.id, header_of, decode, packet_at)
                    continue
                if schema.name == MESSAGE_TYPE:
                    fields = decode(message.data)
                    robot, blob = fields.robot, fields.packet
                else:
                    robot, blob = channel.metadata.get("robot", channel.topic.rsplit("/", 1)[-1]), message.data
                if len(blob) < HEADER.size or len(blob) > MAX_MESSAGE:
                    raise FormatError(f"{path}: message {message.sequence} on {channel.topic} has {len(blob)} bytes")
                yield _legacy_header(robot, message.log_time, blob) if headers else (robot, message.log_time, blob)
        except (McapError, ValueError, EOFError, AssertionError, KeyError, struct.error, UnicodeDecodeError,
                OverflowError, zlib_error, IndexError, TypeError) as err:
            raise FormatError(f"{path}: cannot be read as a packet log: {mcap_problem(err)}") from err
        finally:
            handle.close()

    stats = summary.statistics
    return meta, Messages(messages(), int(stats.message_count) if stats is not None else None)
