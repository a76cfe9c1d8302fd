"""Kernels of `voxtool clean` (voxtool.clean): void evidence kept away from a scan's hits, and
the neighbours a point's voxel is judged with."""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16, morton3

_HASH_MULT = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)


@njit(cache=True, inline="always")
def _slot(code, mask):
    return ((code * _HASH_MULT) >> 20) & mask


@njit(cache=True, nogil=True)
def ball_offsets(radius):
    """(n, 3) integer offsets of the voxels within `radius` voxels (Euclidean, centre included)."""
    r = int(radius)
    n = 0
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            for dz in range(-r, r + 1):
                if dx * dx + dy * dy + dz * dz <= r * r:
                    n += 1
    out = np.empty((n, 3), dtype=np.int64)
    k = 0
    for dx in range(-r, r + 1):
        for dy in range(-r, r + 1):
            for dz in range(-r, r + 1):
                if dx * dx + dy * dy + dz * dz <= r * r:
                    out[k, 0] = dx
                    out[k, 1] = dy
                    out[k, 2] = dz
                    k += 1
    return out


@njit(cache=True, inline="always")
def _moved(code, dx, dy, dz):
    """The Morton code of the voxel `code` moved by (dx, dy, dz) voxels; -1 outside the key range."""
    x = compact16(code) + dx
    y = compact16(code >> 1) + dy
    z = compact16(code >> 2) + dz
    if x < 0 or y < 0 or z < 0 or x > 0xFFFF or y > 0xFFFF or z > 0xFFFF:
        return np.int64(-1)
    return morton3(x, y, z)


@njit(cache=True, inline="always")
def _brick_row(keys, brick, mask, insert):
    """(row of `brick` in the open-addressing table, whether this call inserted it); row -1:
    absent and not inserted, -2: the table is full."""
    s = _slot(brick, mask)
    for _ in range(keys.shape[0]):
        k = keys[s]
        if k == brick:
            return s, False
        if k == -1:
            if not insert:
                return -1, False
            keys[s] = brick
            return s, True
        s = (s + 1) & mask
    return -2, False


@njit(cache=True, nogil=True)
def free_away_from_hits(packed, offsets, keys, bits):
    """Free voxel codes of a scan's Morton-sorted updates (code << 1 | occupied) that lie
    outside the offsets' ball around every voxel the scan hit (DUFOMap's d_s: porous surfaces
    such as foliage, seen through in gaps between the hits of one scan, stay unvoided).

    The voxels near hits are bits of 8x8x8-brick masks (`keys`: brick codes, -1 empty, a
    power-of-two length; `bits`: (len(keys), 8) int64, zero) found by hashing; the free codes
    come Morton-sorted, so each run of them in one brick costs one look-up. Returns None when
    the table is too small (the caller doubles it)."""
    mask = keys.shape[0] - 1
    used = 0
    n_free = 0
    last_brick = np.int64(-1)
    row = -1
    for i in range(packed.shape[0]):
        item = packed[i]
        if item & 1 == 0:
            n_free += 1
            continue
        code = item >> 1
        for j in range(offsets.shape[0]):
            near = _moved(code, offsets[j, 0], offsets[j, 1], offsets[j, 2])
            if near < 0:
                continue
            brick = near >> 9
            if brick != last_brick:
                row, new = _brick_row(keys, brick, mask, True)
                used += new
                if row < 0 or used * 2 > keys.shape[0]:
                    return None
                last_brick = brick
            inner = near & 511
            bits[row, inner >> 6] |= np.int64(1) << (inner & 63)
    out = np.empty(n_free, dtype=np.int64)
    k = 0
    last_brick = -1
    row = -1
    for i in range(packed.shape[0]):
        item = packed[i]
        if item & 1:
            continue
        code = item >> 1
        brick = code >> 9
        if brick != last_brick:
            row = _brick_row(keys, brick, mask, False)[0]
            last_brick = brick
        inner = code & 511
        if row < 0 or (bits[row, inner >> 6] >> (inner & 63)) & 1 == 0:
            out[k] = code
            k += 1
    return out[:k]


@njit(cache=True, nogil=True)
def neighbour_codes(codes, offsets, out):
    """out[i, j]: the code of codes[i] moved by offsets[j]; -1 outside the key range."""
    for i in range(codes.shape[0]):
        for j in range(offsets.shape[0]):
            out[i, j] = _moved(codes[i], offsets[j, 0], offsets[j, 1], offsets[j, 2])
