"""Map snapshots (.vxm): versioned, self-describing, lossless, CRC-checked, written atomically.

Byte layout (all integers little endian), specified in formats/snapshot.md:
  0   8  magic  b"\\x89VXM\\r\\n\\x1a\\n"
  8   2  uint16 format version (1)
  10  2  uint16 flags (0)
  12  4  uint32 header length H (<= 1 MiB)
  16  H  header: UTF-8 JSON object (backend, resolution, sensor model, source, version, arrays)
  ..     array payloads, in the order of header["arrays"], each zstd-compressed
  end 4  uint32 CRC-32 of every byte before it
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zstandard

from voxtool.atomic import atomic_writer
from voxtool.compression import zstd_exact
from voxtool.errors import FormatError

MAGIC = b"\x89VXM\r\n\x1a\n"
VERSION = 1
MAX_HEADER = 1 << 20
MAX_ARRAY_BYTES = 1 << 34  # 16 GiB: a declared size beyond this is refused before allocating
DTYPES = {"int64": "<i8", "uint8": "u1", "float32": "<f4", "int32": "<i4", "uint16": "<u2", "uint32": "<u4",
          "float64": "<f8", "int16": "<i2", "uint64": "<u8"}
_FIXED = struct.Struct("<8sHHI")
ALL_CORES_FROM = 48 << 20  # bytes: a streamed array this large is compressed on every core


@dataclass
class Snapshot:
    header: dict
    arrays: dict[str, np.ndarray]


CODECS = ("zstd", "raw")


@dataclass
class ChunkedArrays:
    """Arrays of one length written without being held whole (a large map's leaves): `chunks()`
    yields tuples of consecutive pieces, one per name, each compressed before the next is asked
    for. The bytes are those of the joined arrays (zstd is told the size first)."""

    names: tuple[str, ...]
    dtypes: tuple[str, ...]
    length: int
    chunks: Callable[[], Iterable[tuple[np.ndarray, ...]]]


def _raw(array: np.ndarray, dtype_name: str) -> memoryview:
    """The array's bytes as stored (little endian), without a copy where they already are."""
    return memoryview(np.ascontiguousarray(array, dtype=DTYPES[dtype_name])).cast("B")


def _stored(raw: memoryview, compressor, codec: str) -> bytes:
    """Bytes as the payload holds them; `compressor`: a zstd compressor or stream (compress())."""
    return compressor.compress(raw) if codec == "zstd" else raw.tobytes()


def _stored_chunked(group: ChunkedArrays, level: int, codec: str) -> dict[str, tuple[bytes, int]]:
    """name -> (stored bytes, raw bytes) of every array of a group, in one pass over its chunks
    (a compressor each: one zstd context streams one frame at a time). The largest array's
    stream has every core when it is large, the others one worker each: a multi-threaded stream
    holds ~45 MiB of jobs per worker, and the bytes do not depend on the workers."""
    sizes = [group.length * np.dtype(DTYPES[d]).itemsize for d in group.dtypes]
    largest = int(np.argmax(sizes)) if max(sizes) >= ALL_CORES_FROM else -1
    streams = [zstandard.ZstdCompressor(level=level, threads=-1 if k == largest else 1).compressobj(size=n)
               if codec == "zstd" else None for k, n in enumerate(sizes)]
    out: list[list[bytes]] = [[] for _ in group.names]
    for pieces in group.chunks():
        for k, piece in enumerate(pieces):
            out[k].append(_stored(_raw(piece, group.dtypes[k]), streams[k], codec))
    for k, stream in enumerate(streams):
        if stream is not None:
            out[k].append(stream.flush())
    return {name: (b"".join(parts), n) for name, parts, n in zip(group.names, out, sizes)}


def _snapshot_parts(header: dict, arrays: dict[str, np.ndarray | ChunkedArrays], codec: str, level: int) -> list:
    """The snapshot's bytes before its CRC, as pieces (fixed fields and header, then each
    payload): the header lists every payload's size and CRC, so all are compressed first."""
    compressor = zstandard.ZstdCompressor(level=level, threads=-1)
    payloads = []
    table = []
    offset = 0
    grouped: dict[str, tuple[bytes, int]] = {}
    for name, array in arrays.items():
        if isinstance(array, ChunkedArrays):
            if name not in grouped:
                grouped.update(_stored_chunked(array, level, codec))
            dtype_name, shape = array.dtypes[array.names.index(name)], [array.length]
            stored, raw_bytes = grouped[name]
        else:
            dtype_name, shape = np.dtype(array.dtype).name, list(array.shape)
            if dtype_name not in DTYPES:
                raise ValueError(f"array {name}: dtype {dtype_name} not storable")
            stored = _stored(_raw(array, dtype_name), compressor, codec)
            raw_bytes = array.nbytes
        table.append({"name": name, "dtype": dtype_name, "shape": shape, "codec": codec,
                      "offset": offset, "stored_bytes": len(stored), "raw_bytes": raw_bytes,
                      "crc32": zlib.crc32(stored)})
        payloads.append(stored)
        offset += len(stored)
    full = dict(header)
    full["arrays"] = table
    head = json.dumps(full, sort_keys=True, separators=(",", ":")).encode()
    if len(head) > MAX_HEADER:
        raise ValueError("snapshot header too large")
    return [_FIXED.pack(MAGIC, VERSION, 0, len(head)) + head, *payloads]


def snapshot_bytes(header: dict, arrays: dict[str, np.ndarray | ChunkedArrays], codec: str = "zstd", level: int = 3) -> bytes:
    """Encode a snapshot. `header` must be JSON-serialisable; 'arrays' is filled in here.
    codec "raw" stores arrays uncompressed (byte-exact golden vectors across zstd versions).
    zstd runs on every core: its multi-threaded frames are the same bytes whatever the number
    of threads, so a snapshot does not depend on the machine that wrote it."""
    body = b"".join(_snapshot_parts(header, arrays, codec, level))
    return body + struct.pack("<I", zlib.crc32(body))


def write_snapshot(path: str | Path, header: dict, arrays: dict[str, np.ndarray | ChunkedArrays]) -> None:
    """snapshot_bytes written piece by piece (no joined copies of the compressed payloads)."""
    crc = 0
    with atomic_writer(path) as handle:
        for part in _snapshot_parts(header, arrays, "zstd", 3):
            handle.write(part)
            crc = zlib.crc32(part, crc)
        handle.write(struct.pack("<I", crc))


def parse_snapshot(blob: bytes, where: str = "snapshot") -> Snapshot:
    """Decode snapshot bytes, checking magic, version, every length and every CRC first."""
    if len(blob) < _FIXED.size + 4:
        raise FormatError(f"{where}: file of {len(blob)} bytes is too short to be a snapshot")
    magic, version, _flags, head_len = _FIXED.unpack_from(blob, 0)
    if magic != MAGIC:
        raise FormatError(f"{where}: not a voxtool snapshot (bad magic)")
    if version > VERSION:
        raise FormatError(f"{where}: snapshot format version {version} is newer than this voxtool reads ({VERSION})")
    if version < 1:
        raise FormatError(f"{where}: snapshot format version {version} is invalid")
    if head_len > MAX_HEADER or _FIXED.size + head_len + 4 > len(blob):
        raise FormatError(f"{where}: header length {head_len} exceeds the file ({len(blob)} bytes) or the 1 MiB limit")
    (crc,) = struct.unpack_from("<I", blob, len(blob) - 4)
    if zlib.crc32(memoryview(blob)[:-4]) != crc:
        raise FormatError(f"{where}: CRC mismatch (file is corrupt or truncated)")
    try:
        header = json.loads(bytes(blob[_FIXED.size : _FIXED.size + head_len]).decode())
    except (UnicodeDecodeError, ValueError) as err:
        raise FormatError(f"{where}: header is not valid JSON ({err})") from err
    if not isinstance(header, dict) or not isinstance(header.get("arrays"), list):
        raise FormatError(f"{where}: header lacks the 'arrays' table")
    payload_start = _FIXED.size + head_len
    payload_end = len(blob) - 4
    arrays: dict[str, np.ndarray] = {}
    for entry in header["arrays"]:
        try:
            name, dtype_name, shape = str(entry["name"]), str(entry["dtype"]), [int(s) for s in entry["shape"]]
            offset, stored, raw = int(entry["offset"]), int(entry["stored_bytes"]), int(entry["raw_bytes"])
            want_crc = int(entry["crc32"])
        except (KeyError, TypeError, ValueError) as err:
            raise FormatError(f"{where}: array table entry is malformed ({err})") from err
        codec = entry.get("codec")
        if dtype_name not in DTYPES or codec not in CODECS:
            raise FormatError(f"{where}: array '{name}' has unknown dtype/codec {dtype_name}/{entry.get('codec')}")
        itemsize = np.dtype(DTYPES[dtype_name]).itemsize
        count = int(np.prod(shape, dtype=np.int64)) if shape else 1
        if min(shape + [0]) < 0 or raw != count * itemsize or raw > MAX_ARRAY_BYTES:
            raise FormatError(f"{where}: array '{name}' declares {raw} bytes for shape {shape} ({dtype_name})")
        lo = payload_start + offset
        if offset < 0 or stored < 0 or lo + stored > payload_end:
            raise FormatError(f"{where}: array '{name}' lies beyond the end of the file")
        chunk = blob[lo : lo + stored]
        if zlib.crc32(chunk) != want_crc:
            raise FormatError(f"{where}: array '{name}' CRC mismatch")
        data = bytes(chunk) if codec == "raw" else zstd_exact(chunk, raw, f"{where}: array '{name}'")
        if len(data) != raw:
            raise FormatError(f"{where}: array '{name}' decompressed to {len(data)} bytes, declared {raw}")
        arrays[name] = np.frombuffer(data, dtype=DTYPES[dtype_name]).reshape(shape).copy()
    return Snapshot(header, arrays)


def read_snapshot(path: str | Path) -> Snapshot:
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise FormatError(f"{path}: cannot read: {err.strerror}") from err
    return parse_snapshot(blob, str(path))
