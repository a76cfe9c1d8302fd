"""Map-change packets: bytes on the wire (specified in formats/packet.md).

A packet = 96-byte little-endian header + payload (compressed per `codec`). Schemes:
  hilbert / nested  box of changed voxels, 2 bits per cell (0 free, 1 occupied, 2 unknown,
                    3 unchanged) in Hilbert or x-fastest nested order, 4 cells per byte; with
                    codec `cm` (nested only) the cells are range-coded by a 3D context model
  racer             changed voxels as addresses (linear index in the map box, minimum whole byte
                    width) + 2-bit states
  occupied          newly occupied voxels of the last k frames (ring buffer), as varints of the
                    differences of their sorted Morton codes (version 1: keys as 3 x uint16)
Kind 0 is a delta (unchanged cells allowed), kind 1 a full-state keyframe of a box (no unchanged).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import numpy as np
import zstandard

from voxtool.codec.varint import decode_deltas, encode_deltas
from voxtool.compression import check_expansion, zstd_exact
from voxtool.errors import FormatError
from voxtool.keys import key_bounds, morton_decode

MAGIC = b"VXPK"
VERSION = 2  # 2: `occupied` frames as varint Morton deltas; version-1 packets still decode
READABLE_VERSIONS = (1, 2)
SCHEMES = ("hilbert", "nested", "racer", "occupied")
# cm and cm1: voxtool.codec.cm, the nested scheme only (cm1: the first cm coder, which codes every cell)
CODECS = ("none", "zstd", "zlib", "cm1", "cm")
CM_CODECS = ("cm1", "cm")
MAX_CM_PLANE = 1 << 26  # cells in one plane of a cm box: a coder keeps three planes of classes
KIND_DELTA, KIND_KEYFRAME = 0, 1
FREE, OCCUPIED, UNKNOWN, UNCHANGED = 0, 1, 2, 3
HEADER = struct.Struct("<4sBBBB16sIqd3d3H3HIIII")
MAX_CELLS = 1 << 31  # a box larger than this is refused before anything is allocated
MAX_RAW = 1 << 30  # 1 GiB of uncompressed payload at most
# a cm decision never costs less than -log2(1 - 16/65536) = 3.5e-4 bits, so a stream of L bytes
# holds at most ~22,700 L cells: 32,768 per byte leaves a margin (formats/packet.md)
CM_CELLS_PER_BYTE = 32768
ZSTD_LEVEL = 9  # bytes vs speed on the real streams: docs/packets.md
ZLIB_LEVEL = 6


@dataclass
class Packet:
    """A decoded packet: header fields plus the voxels it sets (Morton codes, states)."""

    robot: str
    seq: int
    stamp_ns: int
    scheme: str
    codec: str
    kind: int
    resolution: float
    map_origin: tuple[float, float, float]
    box_min: tuple[int, int, int]
    box_dims: tuple[int, int, int]
    count: int
    raw_size: int
    stored_size: int
    keys: np.ndarray = field(repr=False)  # (N, 3) uint16 keys of the voxels the packet sets
    states: np.ndarray = field(repr=False)  # (N,) uint8: FREE / OCCUPIED / UNKNOWN
    frames: list = field(default_factory=list, repr=False)  # occupied: [(frame seq, int64 keys)]

    @property
    def wire_bytes(self) -> int:
        return HEADER.size + self.stored_size


def pack_2bit(codes: np.ndarray) -> bytes:
    """Four 2-bit codes per byte, cell i in bits 2*(i % 4) of byte i // 4; padding cells = 3."""
    n = codes.shape[0]
    padded = np.full(((n + 3) // 4) * 4, UNCHANGED, dtype=np.uint8)
    padded[:n] = codes
    q = padded.reshape(-1, 4)
    return (q[:, 0] | (q[:, 1] << 2) | (q[:, 2] << 4) | (q[:, 3] << 6)).astype(np.uint8).tobytes()


def unpack_2bit(data: bytes, n: int) -> np.ndarray:
    b = np.frombuffer(data, dtype=np.uint8)
    out = np.empty((b.shape[0], 4), dtype=np.uint8)
    for k in range(4):
        out[:, k] = (b >> (2 * k)) & 3
    return out.reshape(-1)[:n]


def _compress(raw: bytes, codec: str) -> bytes:
    if codec == "zstd":
        return zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(raw)
    if codec == "zlib":
        return zlib.compress(raw, ZLIB_LEVEL)
    return raw


def _decompress(stored: bytes, codec: str, raw_size: int, where: str) -> bytes:
    if codec != "raw":
        # a box of mostly unchanged cells compresses far: 64 MiB of slack, then 1024x
        check_expansion(raw_size, len(stored), f"{where}: payload", small=64 << 20, ratio=1024)
    try:
        if codec == "zstd":
            data = zstd_exact(stored, raw_size, f"{where}: payload")
        elif codec == "zlib":
            d = zlib.decompressobj()
            data = d.decompress(stored, raw_size)
            if d.unconsumed_tail:
                raise FormatError(f"{where}: payload decompresses to more than the declared {raw_size} bytes")
        else:
            data = stored
    except (zstandard.ZstdError, zlib.error) as err:
        raise FormatError(f"{where}: payload does not decompress ({err})") from err
    if len(data) != raw_size:
        raise FormatError(f"{where}: payload is {len(data)} bytes, header declares {raw_size}")
    return data


def address_width(dims) -> int:
    """Minimum whole bytes to address every cell of a box (the paper's Fig. 5 rule for RACER)."""
    cells = int(np.prod(np.asarray(dims, dtype=np.int64)))
    return max(1, (max(cells - 1, 1).bit_length() + 7) // 8)


def _ranks(scheme: str, rel: np.ndarray, dims) -> np.ndarray:
    """Each cell's position in the payload: its curve rank (hilbert) or nested index."""
    if scheme == "hilbert":
        from voxtool.codec.hilbert import ranks_of

        return ranks_of(rel, dims)
    return rel[:, 0] + int(dims[0]) * (rel[:, 1] + int(dims[1]) * rel[:, 2])


def _changed_cells(raw: bytes, scheme: str, dims, lo, count: int, where: str,
                   ordered: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(uint16 keys, codes) of a delta payload's cells that are not 'unchanged', in nested order
    (x fastest) or, where not `ordered`, as found; found by the bytes that differ from four
    unchanged cells; more or fewer than the header's `count` is an error."""
    from voxtool.kernels.cells2bit import nested_keys, scan

    cells = int(np.prod(np.asarray(dims, dtype=np.int64)))
    data = np.frombuffer(raw, dtype=np.uint8)
    capacity = min(count, 4 * data.shape[0])  # a header cannot make it allocate beyond its payload
    # three spare entries: the scan writes a byte's four cells before counting its changed ones
    ranks, codes = np.empty(capacity + 3, dtype=np.int64), np.empty(capacity + 3, dtype=np.uint8)
    found = scan(data, cells, UNCHANGED, ranks, codes)
    if found < 0:
        raise FormatError(f"{where}: more changed cells than the header's {count}")
    if found != count:
        raise FormatError(f"{where}: {found} changed cells, header declares {count}")
    ranks, codes = ranks[:found], codes[:found]
    if scheme == "hilbert":
        from voxtool.codec.hilbert import cells_at

        keys = cells_at(ranks, dims, lo, np.uint16)  # straight to keys: no nested index between
        if not ordered:
            return keys, codes
        idx = keys[:, 0] + int(dims[0]) * (keys[:, 1] + int(dims[1]) * keys[:, 2].astype(np.int64))
        order = np.argsort(idx, kind="stable")
        return keys[order], codes[order]
    keys = np.empty((found, 3), dtype=np.uint16)
    nested_keys(ranks, int(dims[0]), int(dims[1]), lo, keys)
    return keys, codes


def _cell_order(scheme: str, dims) -> np.ndarray | None:
    if scheme == "hilbert":
        from voxtool.codec.hilbert import box_order

        return box_order(int(dims[0]), int(dims[1]), int(dims[2]))
    return None  # nested: the natural x-fastest order


def occupied_frame(fseq: int, codes: np.ndarray) -> bytes:
    """One frame of an `occupied` payload: frame sequence, voxel count, and the varints of the
    voxels' Morton codes in increasing order (sorted and de-duplicated here if they are not)."""
    codes = np.asarray(codes, dtype=np.int64)
    if codes.shape[0] > 1 and np.any(codes[1:] <= codes[:-1]):
        codes = np.unique(codes)
    return struct.pack("<II", fseq, codes.shape[0]) + encode_deltas(codes)


def encode_packet(robot: str, seq: int, stamp_ns: int, scheme: str, codec: str, resolution: float,
                  keys: np.ndarray, states: np.ndarray, kind: int = KIND_DELTA,
                  box: tuple[np.ndarray, np.ndarray] | None = None,
                  map_origin=(0.0, 0.0, 0.0), frames: list[bytes] | None = None) -> bytes:
    """Encode voxels (uint16 keys, states) as one packet.

    hilbert/nested: `box` = (min key, dims) defaults to the keys' bounding box; a keyframe must
    give `states` for every cell of the box (keys then ignored, states in nested order).
    racer: `box` is the map's address space. occupied: `frames` = the ring's frames, each
    encoded by occupied_frame() (once: a frame rides in k packets)."""
    if scheme not in SCHEMES or codec not in CODECS:
        raise ValueError(f"unknown scheme/codec {scheme}/{codec}")
    if codec in CM_CODECS and scheme != "nested":
        raise ValueError(f"codec {codec} codes a box in x-fastest order: scheme {scheme} cannot use it (use nested)")
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    states = np.asarray(states, dtype=np.uint8)
    if scheme == "occupied":
        frames = frames or []
        raw = b"".join(frames)
        lo, dims, count = np.zeros(3, np.int64), np.zeros(3, np.int64), len(frames)
    else:
        if box is None:
            if keys.shape[0]:
                lo, hi = key_bounds(keys)
                dims = hi - lo + 1
            else:
                lo, dims = np.zeros(3, np.int64), np.zeros(3, np.int64)
        else:
            lo, dims = np.asarray(box[0], np.int64), np.asarray(box[1], np.int64)
        cells = int(np.prod(dims))
        if scheme == "racer":
            rel = keys - lo
            addr = rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2])
            width = address_width(dims)
            a = addr.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :width]
            raw = a.tobytes() + pack_2bit(states)
            count = keys.shape[0]
        else:
            if codec == "cm":
                from voxtool.codec.cm import compress_cells

                # cm codes the changed cells with their neighbourhood, never the whole box
                if kind == KIND_KEYFRAME:
                    if states.shape[0] != cells:
                        raise ValueError("keyframe states must cover every cell of the box")
                    idx = np.flatnonzero(states != UNKNOWN)
                    vals, count, background = states[idx], cells, UNKNOWN
                else:
                    from voxtool.kernels.sort import sort_codes

                    rel = keys - lo
                    # nested order by a radix sort of (index, state) packed (a third of argsort's time)
                    packed = ((rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2])) << 2) | states
                    sort_codes(packed, np.empty_like(packed))
                    idx, vals, count, background = packed >> 2, (packed & 3).astype(np.uint8), int(keys.shape[0]), UNCHANGED
                stored = compress_cells(idx, vals, dims, background)
                return _assemble(robot, seq, stamp_ns, scheme, codec, kind, resolution, map_origin, lo, dims, count,
                                 (cells + 3) // 4, stored)
            if kind == KIND_DELTA and codec != "cm1":
                # the changed cells placed at their ranks in a payload of unchanged ones
                from voxtool.kernels.cells2bit import place

                rel = keys - lo
                ranks = _ranks(scheme, rel, dims)
                payload = np.empty((cells + 3) // 4, dtype=np.uint8)
                place(ranks, states, cells, UNCHANGED, payload)
                raw = payload.tobytes()
                return _assemble(robot, seq, stamp_ns, scheme, codec, kind, resolution, map_origin, lo, dims,
                                 int(keys.shape[0]), len(raw), _compress(raw, codec))
            if kind == KIND_KEYFRAME:
                grid = states
                if grid.shape[0] != cells:
                    raise ValueError("keyframe states must cover every cell of the box")
            else:
                grid = np.full(cells, UNCHANGED, dtype=np.uint8)
                rel = keys - lo
                grid[rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2])] = states
            count = int(keys.shape[0]) if kind == KIND_DELTA else cells
            if codec == "cm1":
                from voxtool.codec.cm import compress_box

                # cm codes the cells themselves; the header still declares the 2-bit payload's size
                stored = compress_box(grid, dims, UNCHANGED if kind == KIND_DELTA else UNKNOWN)
                return _assemble(robot, seq, stamp_ns, scheme, codec, kind, resolution, map_origin, lo, dims, count,
                                 (cells + 3) // 4, stored)
            order = _cell_order(scheme, dims)
            raw = pack_2bit(grid[order] if order is not None else grid)
    return _assemble(robot, seq, stamp_ns, scheme, codec, kind, resolution, map_origin, lo, dims, count, len(raw),
                     _compress(raw, codec))


def _assemble(robot, seq, stamp_ns, scheme, codec, kind, resolution, map_origin, lo, dims, count, raw_size,
              stored) -> bytes:
    """Header (CRC over the header and the stored payload) + stored payload."""
    name = robot.encode()[:16]
    head = HEADER.pack(MAGIC, VERSION, kind, SCHEMES.index(scheme), CODECS.index(codec), name, seq, stamp_ns,
                       resolution, *map(float, map_origin), *map(int, lo), *map(int, dims), count, raw_size,
                       len(stored), 0)
    crc = zlib.crc32(stored, zlib.crc32(head[:-4]))
    return head[:-4] + struct.pack("<I", crc) + stored


def keyframe_packet(robot: str, seq: int, stamp_ns: int, scheme: str, codec: str, resolution: float,
                    codes: np.ndarray, states: np.ndarray, map_origin=(0.0, 0.0, 0.0)) -> bytes:
    """Full-state keyframe of known voxels (Morton codes, FREE/OCCUPIED states): every cell of
    their bounding box, unknown where no voxel is given, no 'unchanged'."""
    keys = morton_decode(codes).astype(np.int64)
    if keys.shape[0]:
        lo, hi = key_bounds(keys)
        dims = hi - lo + 1
    else:
        lo, dims = np.zeros(3, np.int64), np.ones(3, np.int64)
    grid = np.full(int(np.prod(dims)), UNKNOWN, dtype=np.uint8)
    rel = keys - lo
    grid[rel[:, 0] + dims[0] * (rel[:, 1] + dims[1] * rel[:, 2])] = states
    return encode_packet(robot, seq, stamp_ns, scheme, codec, resolution, keys[:0], grid, kind=KIND_KEYFRAME,
                         box=(lo, dims), map_origin=map_origin)


def decode_packet(blob: bytes, where: str = "packet", ordered: bool = True) -> Packet:
    """Parse and decode one packet, checking magic, version, CRC and every size before use.
    A box's voxels come in nested order (x fastest), or as found where not `ordered`."""
    if len(blob) < HEADER.size:
        raise FormatError(f"{where}: {len(blob)} bytes is shorter than the {HEADER.size}-byte packet header")
    f = HEADER.unpack_from(blob, 0)
    magic, version, kind, scheme_i, codec_i, name, seq, stamp, res = f[:9]
    origin, lo, dims = f[9:12], f[12:15], f[15:18]
    count, raw_size, stored_size, crc = f[18:22]
    if magic != MAGIC:
        raise FormatError(f"{where}: not a voxtool packet (bad magic)")
    if version not in READABLE_VERSIONS:
        raise FormatError(f"{where}: packet version {version} is not supported (this voxtool reads "
                          f"{', '.join(map(str, READABLE_VERSIONS))})")
    if scheme_i >= len(SCHEMES) or codec_i >= len(CODECS) or kind not in (KIND_DELTA, KIND_KEYFRAME):
        raise FormatError(f"{where}: unknown scheme {scheme_i}, codec {codec_i} or kind {kind}")
    if HEADER.size + stored_size != len(blob):
        raise FormatError(f"{where}: declares {stored_size} payload bytes, holds {len(blob) - HEADER.size}")
    if zlib.crc32(blob[HEADER.size:], zlib.crc32(blob[: HEADER.size - 4])) != crc:
        raise FormatError(f"{where}: CRC mismatch")
    if raw_size > MAX_RAW or not (res > 0 and np.isfinite(res)):
        raise FormatError(f"{where}: declared payload of {raw_size} bytes or resolution {res} out of range")
    scheme, codec = SCHEMES[scheme_i], CODECS[codec_i]
    cells = int(np.prod(np.asarray(dims, dtype=np.int64)))
    lo_a = np.asarray(lo, dtype=np.int64)
    dims_a = np.asarray(dims, dtype=np.int64)
    if scheme in ("hilbert", "nested", "racer"):
        if cells > MAX_CELLS or np.any(lo_a + dims_a > 65536):
            raise FormatError(f"{where}: box {dims} at {lo} exceeds the key range or {MAX_CELLS} cells")
    if scheme in ("hilbert", "nested") and raw_size != (cells + 3) // 4:
        raise FormatError(f"{where}: box of {cells} cells needs {(cells + 3) // 4} bytes, header declares {raw_size}")
    if scheme == "racer":
        width = address_width(dims_a)
        if raw_size != count * width + (count + 3) // 4 or count > cells:
            raise FormatError(f"{where}: {count} RACER entries do not fit {raw_size} bytes")
    frames: list[tuple[int, np.ndarray]] = []
    grid = keys = None
    if codec in CM_CODECS and scheme != "nested":
        raise FormatError(f"{where}: codec {codec} with scheme {scheme} (cm codes nested boxes only)")
    if codec == "cm":
        from voxtool.kernels.cm import BLOCK

        blocks = int(np.prod((dims_a + BLOCK - 1) // BLOCK))
        limit = CM_CELLS_PER_BYTE * (stored_size + 8)
        # every block and every cell costs the range coder a minimum fraction of a bit: refuse what
        # a stream this short cannot hold before allocating or decoding anything
        if blocks > limit or count > limit or int(dims_a[0] * dims_a[1]) > MAX_CM_PLANE:
            raise FormatError(f"{where}: a cm stream of {stored_size} bytes cannot hold a box of {dims} cells "
                              f"with {count} {'changes' if kind == KIND_DELTA else 'cells'} (or a plane of more than "
                              f"{MAX_CM_PLANE} cells)")
        from voxtool.codec.cm import decompress_cells

        background = UNCHANGED if kind == KIND_DELTA else UNKNOWN
        idx, vals = decompress_cells(blob[HEADER.size:], dims_a, background, count, where)
        if kind == KIND_KEYFRAME:
            grid = np.full(cells, UNKNOWN, dtype=np.uint8)
            grid[idx] = vals
        else:
            if np.any(vals == UNCHANGED):
                raise FormatError(f"{where}: cm stream codes an 'unchanged' cell")
            idx_changed, states = idx, vals
    elif codec == "cm1":
        if cells > CM_CELLS_PER_BYTE * (stored_size + 8):
            # every cell costs the range coder a minimum fraction of a bit: refuse a box that a
            # stream this short cannot hold before allocating or decoding anything
            raise FormatError(f"{where}: a cm stream of {stored_size} bytes cannot hold a box of {cells} cells")
        from voxtool.codec.cm import decompress_box

        background = UNCHANGED if kind == KIND_DELTA else UNKNOWN
        grid = decompress_box(blob[HEADER.size:], dims_a, background, where)
    else:
        raw = _decompress(blob[HEADER.size:], codec, raw_size, where)
        if scheme in ("hilbert", "nested") and kind == KIND_DELTA:
            keys, states = _changed_cells(raw, scheme, dims_a, lo_a, count, where, ordered)
        elif scheme in ("hilbert", "nested"):
            codes = unpack_2bit(raw, cells)
            order = _cell_order(scheme, dims_a)
            grid = np.empty(cells, dtype=np.uint8)
            if order is not None:
                grid[order] = codes
            else:
                grid = codes
    if scheme in ("hilbert", "nested"):
        if grid is not None:
            if kind == KIND_KEYFRAME and np.any(grid == UNCHANGED):
                raise FormatError(f"{where}: keyframe holds 'unchanged' cells")
            idx_changed = np.flatnonzero(grid != UNCHANGED)
            states = grid[idx_changed]
        if keys is None:  # cells found as nested indices (a keyframe's grid, a cm stream)
            if kind == KIND_DELTA and idx_changed.shape[0] != count:
                raise FormatError(f"{where}: {idx_changed.shape[0]} changed cells, header declares {count}")
            from voxtool.kernels.cells2bit import nested_keys

            keys = np.empty((idx_changed.shape[0], 3), dtype=np.uint16)
            nested_keys(np.ascontiguousarray(idx_changed, dtype=np.int64), int(dims_a[0]), int(dims_a[1]), lo_a, keys)
    elif scheme == "racer":
        width = address_width(dims_a)
        a = np.zeros((count, 8), dtype=np.uint8)
        a[:, :width] = np.frombuffer(raw[: count * width], dtype=np.uint8).reshape(count, width)
        addr = a.view("<u8").reshape(-1).astype(np.int64)
        if np.any(addr >= cells):
            raise FormatError(f"{where}: RACER address outside the map box")
        states = unpack_2bit(raw[count * width :], count)
        if np.any(states == UNCHANGED):
            raise FormatError(f"{where}: RACER entry with state 'unchanged'")
        keys = np.stack([addr % dims_a[0], (addr // dims_a[0]) % dims_a[1], addr // (dims_a[0] * dims_a[1])], axis=1) + lo_a
    else:
        frames = _read_frames(raw, count, version, where)
        keys = np.concatenate([k for _, k in frames]) if frames else np.zeros((0, 3), np.int64)
        states = np.full(keys.shape[0], OCCUPIED, dtype=np.uint8)
    if np.any(states > UNKNOWN):
        raise FormatError(f"{where}: invalid voxel state")
    return Packet(name.rstrip(b"\0").decode(errors="replace"), seq, stamp, scheme, codec, kind, res, tuple(origin),
                  tuple(lo), tuple(dims), count, raw_size, stored_size, keys.astype(np.uint16, copy=False), states, frames)


def _read_frames(raw: bytes, count: int, version: int, where: str) -> list[tuple[int, np.ndarray]]:
    """The (frame seq, int64 keys) of an `occupied` payload: version 1 stores 3 x uint16 keys,
    version 2 varint Morton deltas."""
    frames, pos = [], 0
    for _ in range(count):
        if pos + 8 > len(raw):
            raise FormatError(f"{where}: occupied frame list truncated")
        fseq, n = struct.unpack_from("<II", raw, pos)
        pos += 8
        if version == 1:
            if pos + 6 * n > len(raw):
                raise FormatError(f"{where}: occupied frame declares {n} voxels beyond the payload")
            keys = np.frombuffer(raw, dtype="<u2", count=3 * n, offset=pos).reshape(n, 3).astype(np.int64)
            pos += 6 * n
        else:
            if n > len(raw) - pos:  # every voxel takes at least one byte
                raise FormatError(f"{where}: occupied frame declares {n} voxels beyond the payload")
            codes, pos = decode_deltas(raw, pos, n, where)
            keys = morton_decode(codes).astype(np.int64)
        frames.append((fseq, keys))
    if pos != len(raw):
        raise FormatError(f"{where}: {len(raw) - pos} trailing payload bytes")
    return frames
