"""ROS 1 bags read record by record, without their index: what `rosbag reindex` does before it
writes a new index. voxtool reads a bag this way when rosbags cannot open it through its index:
the recording was killed (no index was written), the file was cut short, or the index is
damaged. Reading stops, cleanly, at the first record that cannot be read; what was read before
it (and how much of the file that is) is what a --bad-scans skip build uses.

Format (ROS bag 2.0): a `#ROSBAG V2.0` line, then records of
`header_len u32 | header | data_len u32 | data`; a header is fields of `len u32 | name=value`.
Records by their `op` field: 0x03 bag header, 0x05 chunk (its data: compressed records), 0x07
connection (data: topic, type, message_definition as header fields), 0x02 message data
(header: conn u32, time u32 sec + u32 nsec)."""

from __future__ import annotations

import mmap
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from voxtool.errors import SourceError

MAGIC = b"#ROSBAG V2.0\n"
OLD_MAGIC = b"#ROSRECORD"  # ROS bags before format 2.0 (ROS before 2010)
OP_MESSAGE, OP_CHUNK, OP_CONNECTION = 0x02, 0x05, 0x07
MOST_HEADER = 1 << 20  # bytes: a real record header is a few hundred (a connection's: its definition)
MOST_RECORD = 1 << 31  # bytes: beyond what a real chunk or message holds: the length is garbage


@dataclass
class Connection:
    id: int
    topic: str
    msgtype: str  # as rosbags names types: pkg/msg/Name
    msgdef: str


def _fields(header: bytes) -> dict[str, bytes]:
    """A record header's name=value fields (a field that runs past the header: ValueError)."""
    out, pos = {}, 0
    while pos < len(header):
        if pos + 4 > len(header):
            raise ValueError("a header field length runs past its header")
        (n,) = struct.unpack_from("<I", header, pos)
        field = header[pos + 4: pos + 4 + n]
        if len(field) != n or b"=" not in field:
            raise ValueError("a header field runs past its header")
        name, value = field.split(b"=", 1)
        out[name.decode("ascii", "replace")] = value
        pos += 4 + n
    return out


def _record(data, pos: int) -> tuple[dict[str, bytes], memoryview, int, int]:
    """The record at `pos`: (header fields, data, end offset, where its data length sits).
    EOFError where the file ends inside it, ValueError where it cannot be a record."""
    size = len(data)
    if pos + 4 > size:
        raise EOFError("it ends inside a record: the file is truncated")
    (hlen,) = struct.unpack_from("<I", data, pos)
    if hlen > MOST_HEADER:
        raise ValueError(f"a record header of {hlen:,} bytes at byte {pos:,}")
    if pos + 8 + hlen > size:
        raise EOFError("it ends inside a record: the file is truncated")
    header = _fields(bytes(data[pos + 4: pos + 4 + hlen]))
    if "op" not in header:
        raise ValueError(f"a record without an op field at byte {pos:,}")
    (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
    if dlen > MOST_RECORD:
        raise ValueError(f"a record of {dlen:,} bytes at byte {pos:,}")
    end = pos + 8 + hlen + dlen
    return header, memoryview(data)[pos + 8 + hlen: min(end, size)], end, pos + 4 + hlen


def _records(data: bytes, start: int) -> Iterator[tuple[dict[str, bytes], memoryview, int]]:
    """(header fields, data, end offset) of each whole record of a chunk's records."""
    pos = start
    while pos < len(data):
        header, body, end, _ = _record(data, pos)
        if end > len(data):
            raise ValueError("a record runs past the end of its chunk")
        yield header, body, end
        pos = end


_OPS = (b"op=\x02", b"op=\x03", b"op=\x04", b"op=\x05", b"op=\x06", b"op=\x07")


def _next_header(data, start: int, size: int) -> int | None:
    """The first offset at or after `start` where a whole record header parses (found by its op
    field, the header start tried a few hundred bytes before it)."""
    at = start
    while True:
        hits = [h for h in (data.find(op, at) for op in _OPS) if h >= 0]
        if not hits:
            return None
        m = min(hits)
        for begin in range(max(start, m - 4 - 512), m - 7):
            try:
                _, _, end, _ = _record(data, begin)
            except (ValueError, EOFError, struct.error):
                continue
            if end <= size and begin + 4 <= m - 4:
                return begin
        at = m + 1


def _errors() -> tuple:
    from voxtool.sources.bag_limits import bag_errors

    return bag_errors()


def _msgtype(ros1: str) -> str:
    pkg, _, name = ros1.partition("/")
    return f"{pkg}/msg/{name}" if name and "/msg/" not in ros1 else ros1


class LinearBag:
    """A ROS 1 bag read start to end: `connections`, `counts` (messages read per connection),
    `messages(topics)` in file order, and after reading, `read_bytes` of `size` (where reading
    stopped) and `stop_reason`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            head = f.readline(64)
        if head.startswith(OLD_MAGIC):
            raise SourceError(f"{self.path}: a ROS bag older than format 2.0 ({head.strip().decode('ascii', 'replace')}"
                              "); voxtool reads format 2.0: rewrite it with ROS 1's `rosbag fix` or "
                              "`rosbag filter in.bag out.bag True`")
        if not head.startswith(MAGIC):
            raise SourceError(f"{self.path}: not a ROS 1 bag (it does not start with '#ROSBAG V2.0')")
        self.connections: dict[int, Connection] = {}
        self.counts: dict[int, int] = {}
        self.read_bytes = 0
        self.stop_reason = ""
        self.skipped_bytes = 0  # bytes passed over between records that could not be read
        self.damaged = 0  # records that could not be read (reading went on from the next header)
        self.damage = ""  # the last one's problem
        self._store = None
        for _ in self._walk(count=True):  # connections and counts; the messages are read again by messages()
            pass

    def _walk(self, count: bool = False) -> Iterator[tuple[Connection, int, memoryview]]:
        """(connection, stamp ns, raw message) of every message record, chunks opened. A record
        that cannot be read is skipped to the next record header found after the last good
        record's header (a record whose length field is wrong swallows the next one's start:
        2010 bags wrote index records so); the bytes passed over count as lost."""
        self.read_bytes, self.stop_reason, self.skipped_bytes, self.damaged = len(MAGIC), "", 0, 0
        with open(self.path, "rb") as f:
            if self.size <= len(MAGIC):
                self.stop_reason = "it holds no records"
                return
            data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)  # the OS pages it in as it is read
        pos, last_header = len(MAGIC), len(MAGIC)
        while pos < self.size:
            try:
                header, body, end, header_end = _record(data, pos)
                if end > self.size:
                    raise EOFError("it ends inside a record: the file is truncated")
                yield from self._top(header, body, count)
            except EOFError as err:
                self.stop_reason = str(err)
                return
            except (SourceError, *_errors()) as err:
                # the next header after the last good one: it may lie inside the record that
                # failed (a wrong length swallowed it); never the failing record itself again
                found = _next_header(data, last_header, self.size)
                if found == pos:
                    found = _next_header(data, pos + 1, self.size)
                problem = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
                if found is None:
                    self.stop_reason = problem
                    return
                self.skipped_bytes += max(0, found - pos)
                self.damaged += 1
                self.damage = problem
                pos = last_header = found
                continue
            last_header, pos = header_end, end
            self.read_bytes = end

    def _top(self, header: dict, body: memoryview, count: bool) -> Iterator:
        from voxtool.sources.bag_limits import bounded_chunk_decompressor

        op = header.get("op", b"\0")[0]
        if op == OP_CHUNK:
            kind = header.get("compression", b"none").decode("ascii", "replace")
            raw = bytes(body) if kind == "none" else bounded_chunk_decompressor(kind)(body)
            yield from self._inner(raw, count)
        elif op in (OP_CONNECTION, OP_MESSAGE):  # an unchunked bag (rare) keeps them at the top
            yield from self._one(header, body, count)

    def _inner(self, raw: bytes, count: bool) -> Iterator:
        for header, body, _ in _records(raw, 0):
            yield from self._one(header, body, count)

    def _one(self, header: dict, body: memoryview, count: bool) -> Iterator:
        op = header.get("op", b"\0")[0]
        if op == OP_CONNECTION:
            cid = struct.unpack("<I", header["conn"])[0]
            info = _fields(bytes(body))
            topic = (info.get("topic") or header.get("topic", b"")).decode("utf-8", "replace")
            self.connections.setdefault(cid, Connection(cid, "/" + topic.lstrip("/"),
                                                        _msgtype(info["type"].decode("ascii", "replace")),
                                                        info.get("message_definition", b"").decode("utf-8", "replace")))
        elif op == OP_MESSAGE:
            cid = struct.unpack("<I", header["conn"])[0]
            conn = self.connections.get(cid)
            if conn is None:
                return
            sec, nsec = struct.unpack("<II", header["time"])
            if count:
                self.counts[cid] = self.counts.get(cid, 0) + 1
            yield conn, sec * 1_000_000_000 + nsec, body

    @property
    def topics(self) -> dict[str, str]:
        from voxtool.sources.tf import topic_type

        names = dict.fromkeys(c.topic for c in self.connections.values())  # in connection order
        return {name: topic_type(c.msgtype for c in self.connections.values() if c.topic == name) for name in names}

    def messages(self, topics: list[str]) -> Iterator[tuple[Connection, int, memoryview]]:
        wanted = set(topics)
        for conn, stamp, raw in self._walk():
            if conn.topic in wanted:
                yield conn, stamp, raw

    def deserialize(self, raw, msgtype: str):
        if self._store is None:
            # ROS 1's types first: a bag's own definitions may leave some out (2010 bags name
            # roslib/Header, not the std_msgs/Header their fields refer to)
            from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

            self._store = get_typestore(Stores.ROS1_NOETIC)
            for conn in self.connections.values():
                try:
                    self._store.register(get_types_from_msg(conn.msgdef, conn.msgtype))
                except (TypesysError, ValueError, KeyError):
                    pass  # a type ROS 1 defines otherwise keeps ROS 1's definition (or none: its messages fail alone)
        return self._store.deserialize_ros1(bytes(raw), msgtype)

    def lost(self) -> str:
        """How much of the file could not be read, in words (empty when all of it was)."""
        parts = []
        if self.damaged:
            parts.append(f"{self.damaged} damaged records were passed over ({self.skipped_bytes:,} bytes lost; "
                         f"{self.damage})")
        if self.stop_reason:
            gone = self.size - self.read_bytes
            parts.append(f"the last {gone:,} of {self.size:,} bytes could not be read ({self.stop_reason})")
        return "; ".join(parts)
