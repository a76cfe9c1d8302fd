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
from voxtool.io.delta_planes import BLOCK, PlanesEncoder, decode_blocks, encode_planes, rechunk

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


CODECS = ("zstd", "raw", "zstd-delta8", "delta8")  # delta8: io.delta_planes, then zstd or not
PLANED = ("zstd-delta8", "delta8")
UNCOMPRESSED = ("raw", "delta8")  # stored bytes = raw bytes
DEFAULT_PLANED = ("leaf_codes",)  # arrays a zstd snapshot stores as delta8 planes (sorted int64)


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


def _stored(raw, compressor, codec: str) -> bytes:
    """Bytes as the payload holds them; `compressor`: a zstd compressor or stream (compress())."""
    return compressor.compress(raw) if codec.startswith("zstd") else bytes(raw)


def _array_codec(name: str, dtype_name: str, codec: str, planed: tuple[str, ...]) -> str:
    """An array's codec: the snapshot's, in the delta8 layout for the `planed` int64 arrays."""
    if name in planed and dtype_name == "int64":
        return "zstd-delta8" if codec == "zstd" else "delta8"
    return codec


def _stored_chunked(group: ChunkedArrays, level: int, codecs: list[str]) -> dict[str, tuple[bytes, int]]:
    """name -> (stored bytes, raw bytes) of every array of a group, in one pass over its chunks
    (a compressor each: one zstd context streams one frame at a time). The largest array's
    stream has every core when it is large, the others one worker each: a multi-threaded stream
    holds ~45 MiB of jobs per worker, and the bytes do not depend on the workers."""
    sizes = [group.length * np.dtype(DTYPES[d]).itemsize for d in group.dtypes]
    largest = int(np.argmax(sizes)) if max(sizes) >= ALL_CORES_FROM else -1
    streams = [zstandard.ZstdCompressor(level=level, threads=-1 if k == largest else 1).compressobj(size=n)
               if codecs[k].startswith("zstd") else None for k, n in enumerate(sizes)]
    planers = [PlanesEncoder() if codecs[k] in PLANED else None for k in range(len(sizes))]
    out: list[list[bytes]] = [[] for _ in group.names]
    for pieces in group.chunks():
        for k, piece in enumerate(pieces):
            raw = _raw(piece, group.dtypes[k]) if planers[k] is None else planers[k].encode(piece)
            out[k].append(_stored(raw, streams[k], codecs[k]))
    for k, stream in enumerate(streams):
        if planers[k] is not None:
            out[k].append(_stored(planers[k].finish(), stream, codecs[k]))
        if stream is not None:
            out[k].append(stream.flush())
    return {name: (b"".join(parts), n) for name, parts, n in zip(group.names, out, sizes)}


def _snapshot_parts(header: dict, arrays: dict[str, np.ndarray | ChunkedArrays], codec: str, level: int,
                    planed: tuple[str, ...] | None = None) -> list:
    """The snapshot's bytes before its CRC, as pieces (fixed fields and header, then each
    payload): the header lists every payload's size and CRC, so all are compressed first.
    `planed`: the int64 arrays stored as delta8 planes (default: the leaf codes of a zstd
    snapshot, none of a raw one)."""
    if planed is None:
        planed = DEFAULT_PLANED if codec == "zstd" else ()
    compressor = zstandard.ZstdCompressor(level=level, threads=-1)
    payloads = []
    table = []
    offset = 0
    grouped: dict[str, tuple[bytes, int]] = {}
    for name, array in arrays.items():
        if isinstance(array, ChunkedArrays):
            dtype_name, shape = array.dtypes[array.names.index(name)], [array.length]
            array_codec = _array_codec(name, dtype_name, codec, planed)
            if name not in grouped:
                grouped.update(_stored_chunked(array, level, [_array_codec(n, d, codec, planed)
                                                              for n, d in zip(array.names, array.dtypes)]))
            stored, raw_bytes = grouped[name]
        else:
            dtype_name, shape = np.dtype(array.dtype).name, list(array.shape)
            if dtype_name not in DTYPES:
                raise ValueError(f"array {name}: dtype {dtype_name} not storable")
            array_codec = _array_codec(name, dtype_name, codec, planed)
            raw = encode_planes(array.ravel()) if array_codec in PLANED else _raw(array, dtype_name)
            stored = _stored(raw, compressor, array_codec)
            raw_bytes = array.nbytes
        table.append({"name": name, "dtype": dtype_name, "shape": shape, "codec": array_codec,
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


def snapshot_bytes(header: dict, arrays: dict[str, np.ndarray | ChunkedArrays], codec: str = "zstd", level: int = 3,
                   planed: tuple[str, ...] | None = None) -> bytes:
    """Encode a snapshot. `header` must be JSON-serialisable; 'arrays' is filled in here.
    codec "raw" stores arrays uncompressed (byte-exact golden vectors across zstd versions);
    `planed`: the int64 arrays stored as delta8 planes (_snapshot_parts). zstd runs on every
    core: its multi-threaded frames are the same bytes whatever the number of threads, so a
    snapshot does not depend on the machine that wrote it."""
    body = b"".join(_snapshot_parts(header, arrays, codec, level, planed))
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
    header, entries = _table(blob, where)
    arrays: dict[str, np.ndarray] = {}
    leaves = None
    if "leaf_codes" in entries:  # first, in bounded pieces: it says how large the rest may be
        e = entries.pop("leaf_codes")
        arrays["leaf_codes"] = np.concatenate(list(_leaf_code_pieces(blob, e, where, LEAF_PIECE)) or
                                              [np.empty(0, np.int64)])
        leaves = arrays["leaf_codes"].shape[0]
    for name, e in entries.items():
        _check_expansion(e, leaves, where)
        if e["codec"] in PLANED:
            arrays[name] = np.concatenate(list(_pieces(blob, e, where, BLOCK)) or [np.empty(0, np.int64)])
            arrays[name] = arrays[name].reshape(e["shape"])
            continue
        chunk = blob[e["lo"] : e["lo"] + e["stored"]]
        data = bytes(chunk) if e["codec"] == "raw" else zstd_exact(chunk, e["raw"], f"{where}: array '{name}'")
        if len(data) != e["raw"]:
            raise FormatError(f"{where}: array '{name}' decompressed to {len(data)} bytes, declared {e['raw']}")
        arrays[name] = np.frombuffer(data, dtype=DTYPES[e["dtype"]]).reshape(e["shape"]).copy()
    return Snapshot(header, arrays)


def _table(blob, where: str) -> tuple[dict, dict[str, dict]]:
    """(header, array table entries by name) of snapshot bytes (or a memory map of them), with
    the magic, version, header, every declared size and every CRC checked; nothing decompressed."""
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
    entries = {}
    for entry in header["arrays"]:
        e = _entry(entry, where, payload_start, payload_end)
        if zlib.crc32(memoryview(blob)[e["lo"] : e["lo"] + e["stored"]]) != e["crc"]:
            raise FormatError(f"{where}: array '{e['name']}' CRC mismatch")
        entries[e["name"]] = e
    return header, entries


def stream_arrays(path: str | Path, names: tuple[str, ...], piece: int = 1 << 22):
    """(header, pieces): the header of a snapshot file and `pieces()`, a fresh iterator each call
    of tuples, one piece of each named array (`piece` entries, the last shorter), decompressed as
    they are asked for, so that memory is bounded by a piece and the file (memory-mapped once),
    not the arrays. The arrays must be one-dimensional and of one length; `leaf_codes`, when
    named, is checked to rise strictly as parse_snapshot checks it. Every CRC is checked once,
    here, before any piece."""
    import mmap

    path = Path(path)
    try:
        handle = open(path, "rb")
    except OSError as err:
        raise FormatError(f"{path}: cannot read: {err.strerror}") from err
    with handle:
        try:
            blob = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError as err:  # an empty file
            raise FormatError(f"{path}: file of 0 bytes is too short to be a snapshot") from err
    header, entries = _table(blob, str(path))
    missing = [n for n in names if n not in entries]
    if missing:
        raise FormatError(f"{path}: snapshot lacks array '{missing[0]}'")
    chosen = [entries[n] for n in names]
    counts = {int(np.prod(e["shape"])) for e in chosen}
    if len(counts) != 1 or any(len(e["shape"]) != 1 for e in chosen):
        raise FormatError(f"{path}: arrays {', '.join(names)} differ in length")
    (count,) = counts
    for e in chosen:
        if e["name"] != "leaf_codes":
            _check_expansion(e, count if "leaf_codes" in names else None, str(path))

    def pieces():
        readers = [_leaf_code_pieces(blob, e, str(path), piece) if e["name"] == "leaf_codes"
                   else _pieces(blob, e, str(path), piece) for e in chosen]
        yield from zip(*readers, strict=True)

    return header, pieces


def _stream(blob, e: dict):
    import io

    chunk = memoryview(blob)[e["lo"] : e["lo"] + e["stored"]]
    return io.BytesIO(chunk) if e["codec"] in UNCOMPRESSED else zstandard.ZstdDecompressor().stream_reader(chunk)


def _pieces(blob, e: dict, where: str, piece: int):
    """An array's pieces of `piece` entries, decompressed (and, in delta8, rebuilt from its
    planes) one at a time."""
    dtype = np.dtype(DTYPES[e["dtype"]])
    total = 0
    try:
        with _stream(blob, e) as reader:
            if e["codec"] in PLANED:
                count = e["raw"] // 8

                def read(n: int) -> bytes:
                    nonlocal total
                    data = reader.read(n)
                    total += len(data)
                    return data

                yield from rechunk(decode_blocks(read, count), piece)
            else:
                while total < e["raw"]:
                    data = reader.read(min(piece * dtype.itemsize, e["raw"] - total))
                    if not data or len(data) % dtype.itemsize:
                        break
                    total += len(data)
                    yield np.frombuffer(data, dtype=dtype)
            if total == e["raw"] and reader.read(1):
                raise FormatError(f"{where}: array '{e['name']}' decompresses to more than its declared {e['raw']} bytes")
    except zstandard.ZstdError as err:
        raise FormatError(f"{where}: array '{e['name']}' does not decompress ({err})") from err
    if total != e["raw"]:
        raise FormatError(f"{where}: array '{e['name']}' decompressed to {total} bytes, declared {e['raw']}")


def _entry(entry, where: str, payload_start: int, payload_end: int) -> dict:
    """One array table entry, every field and declared size checked (nothing allocated yet)."""
    try:
        e = {"name": str(entry["name"]), "dtype": str(entry["dtype"]), "shape": [int(s) for s in entry["shape"]],
             "offset": int(entry["offset"]), "stored": int(entry["stored_bytes"]), "raw": int(entry["raw_bytes"]),
             "crc": int(entry["crc32"]), "codec": entry.get("codec")}
    except (KeyError, TypeError, ValueError) as err:
        raise FormatError(f"{where}: array table entry is malformed ({err})") from err
    name, shape, raw = e["name"], e["shape"], e["raw"]
    if e["dtype"] not in DTYPES or e["codec"] not in CODECS:
        raise FormatError(f"{where}: array '{name}' has unknown dtype/codec {e['dtype']}/{e['codec']}")
    itemsize = np.dtype(DTYPES[e["dtype"]]).itemsize
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if min(shape + [0]) < 0 or raw != count * itemsize or raw > MAX_ARRAY_BYTES:
        raise FormatError(f"{where}: array '{name}' declares {raw} bytes for shape {shape} ({e['dtype']})")
    e["lo"] = payload_start + e["offset"]
    if e["offset"] < 0 or e["stored"] < 0 or e["lo"] + e["stored"] > payload_end:
        raise FormatError(f"{where}: array '{name}' lies beyond the end of the file")
    if e["codec"] in UNCOMPRESSED and e["stored"] != raw:
        raise FormatError(f"{where}: array '{name}' is stored raw in {e['stored']} bytes, declared {raw}")
    if e["codec"] in PLANED and (e["dtype"] != "int64" or len(shape) != 1):
        raise FormatError(f"{where}: array '{name}' in codec {e['codec']} must be one-dimensional int64")
    return e


# A decompression bomb (a small file whose arrays declare and expand to gigabytes of zeros) is
# refused before what it declares is allocated. The leaf codes are read first, in pieces, and must
# rise strictly: a valid table of N leaves compresses ~8x (zstd on consecutive int64: 7.6-10.8x),
# so a file cannot declare more leaves than it holds. Every other array is either one entry per
# leaf, or small (a pool, a few counters), or it compresses as real data does.
LEAF_PIECE = 1 << 20  # leaf codes decompressed and checked this many at a time (8 MiB)
PER_LEAF_BYTES = 64  # what the other arrays of a snapshot may hold per leaf (the hash map's: 33)
SMALL_ARRAY = 64 << 20  # an array this small is never an expansion worth refusing
MAX_RATIO = 64  # beyond these: more than a real map's arrays expand (measured at most 11x, but uniform ones)


def _check_expansion(e: dict, leaves: int | None, where: str) -> None:
    if e["codec"] in UNCOMPRESSED or e["raw"] <= SMALL_ARRAY or e["raw"] <= MAX_RATIO * e["stored"]:
        return
    if leaves is not None and e["raw"] <= PER_LEAF_BYTES * max(leaves, 1):
        return
    raise FormatError(f"{where}: array '{e['name']}' declares {e['raw']:,} bytes from {e['stored']:,} stored, more "
                      f"than a map of {leaves or 0:,} leaves expands to: the file is corrupt (or a decompression bomb)")


def _leaf_code_pieces(blob, e: dict, where: str, piece: int):
    """The leaf codes, `piece` at a time, each checked to rise strictly inside the 48-bit key
    space (the tree's order) before the next is decompressed: a bomb of zeros stops at once."""
    if e["dtype"] != "int64" or len(e["shape"]) != 1:
        raise FormatError(f"{where}: array 'leaf_codes' must be one-dimensional int64")
    last, seen = -1, 0
    for codes in _pieces(blob, e, where, piece):
        if codes[0] <= last or np.any(codes[1:] <= codes[:-1]) or codes[-1] >= 1 << 48:
            raise FormatError(f"{where}: leaves are not sorted or overlap (leaf codes must rise strictly below "
                              f"2^48; found at leaf {seen + _first_fall(codes, last):,})")
        last = int(codes[-1])
        seen += codes.shape[0]
        yield codes


def _first_fall(piece: np.ndarray, last: int) -> int:
    """Index in `piece` of the first code that does not rise (or leaves the key space)."""
    bad = np.flatnonzero(np.diff(np.concatenate(([last], piece))) <= 0)
    out = np.flatnonzero(piece >= 1 << 48)
    return int(min(bad[0] if bad.size else piece.size, out[0] if out.size else piece.size))


def read_snapshot(path: str | Path) -> Snapshot:
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise FormatError(f"{path}: cannot read: {err.strerror}") from err
    return parse_snapshot(blob, str(path))
