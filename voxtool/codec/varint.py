"""Sorted Morton codes as LEB128 varints of their successive differences (formats/packet.md,
`occupied` frames of version 2): neighbouring voxels of a frame differ by small numbers, so most
take one or two bytes before compression. Encoding and decoding are vectorized."""

from __future__ import annotations

import numpy as np

from voxtool.errors import FormatError

_MAX_BYTES = 7  # 7 x 7 bits hold a 48-bit Morton code


def encode_deltas(codes: np.ndarray) -> bytes:
    """Strictly increasing Morton codes (< 2^48) -> varints of code[0], code[1] - code[0], ..."""
    codes = np.asarray(codes, dtype=np.int64)
    if codes.size == 0:
        return b""
    deltas = np.diff(codes, prepend=0).astype(np.uint64)
    lengths = np.ones(deltas.shape[0], dtype=np.int64)
    for k in range(1, _MAX_BYTES):
        lengths += deltas >= np.uint64(1 << (7 * k))
    starts = np.cumsum(lengths) - lengths
    out = np.empty(int(lengths.sum()), dtype=np.uint8)
    for b in range(_MAX_BYTES):
        has = lengths > b
        group = (deltas[has] >> np.uint64(7 * b)) & np.uint64(0x7F)
        more = (lengths[has] > b + 1).astype(np.uint64) << np.uint64(7)
        out[starts[has] + b] = (group | more).astype(np.uint8)
    return out.tobytes()


def decode_deltas(data: bytes, pos: int, n: int, where: str) -> tuple[np.ndarray, int]:
    """n varints from data[pos:] -> (strictly increasing codes, position after them)."""
    if n == 0:
        return np.zeros(0, dtype=np.int64), pos
    buf = np.frombuffer(data, dtype=np.uint8, offset=pos, count=min(len(data) - pos, n * _MAX_BYTES))
    ends = np.flatnonzero(buf < 0x80)
    if ends.shape[0] < n:
        raise FormatError(f"{where}: frame declares {n} voxels, its varints end early")
    ends = ends[:n]
    starts = np.concatenate([[0], ends[:-1] + 1])
    if np.any(ends - starts >= _MAX_BYTES):
        raise FormatError(f"{where}: varint longer than {_MAX_BYTES} bytes")
    used = buf[: ends[-1] + 1]
    index_in_varint = np.arange(used.shape[0]) - np.repeat(starts, ends - starts + 1)
    groups = (used & 0x7F).astype(np.uint64) << (np.uint64(7) * index_in_varint.astype(np.uint64))
    deltas = np.add.reduceat(groups, starts)
    codes = np.cumsum(deltas.astype(np.int64))
    # codes must rise strictly and stay below 2^48 (a hostile sum that wraps shows as a fall)
    if codes[0] < 0 or codes[-1] >= 1 << 48 or np.any(np.diff(codes) <= 0):
        raise FormatError(f"{where}: voxel codes repeat or leave the key range")
    return codes, pos + int(ends[-1]) + 1
