"""Morton codes inside compiled kernels (voxtool.keys has the numpy twins for whole arrays).

48-bit codes in int64: key bits interleaved ... z1 y1 x1 z0 y0 x0 (see voxtool.keys)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def spread16(v):
    """16 key bits -> every third bit of 48."""
    v = v & 0xFFFF
    v = (v | (v << 16)) & 0x0000FF0000FF
    v = (v | (v << 8)) & 0x00F00F00F00F
    v = (v | (v << 4)) & 0x0C30C30C30C3
    v = (v | (v << 2)) & 0x249249249249
    return v


@njit(cache=True, inline="always")
def compact16(v):
    """Every third bit of 48 -> 16 key bits (inverse of spread16)."""
    v = v & 0x249249249249
    v = (v | (v >> 2)) & 0x0C30C30C30C3
    v = (v | (v >> 4)) & 0x00F00F00F00F
    v = (v | (v >> 8)) & 0x0000FF0000FF
    v = (v | (v >> 16)) & 0xFFFF
    return v


@njit(cache=True, inline="always")
def morton3(kx, ky, kz):
    return spread16(np.int64(kx)) | (spread16(np.int64(ky)) << 1) | (spread16(np.int64(kz)) << 2)


@njit(cache=True)
def ready(x):
    """A kernel that does nothing: loading it sets numba up (voxtool.jit.start)."""
    return x


@njit(cache=True, nogil=True)
def point_codes(points, resolution, out):
    """out[i]: the Morton code of the voxel holding points[i], OctoMap's coordToKey (float64
    floor) fused with the interleaving. Returns the first point outside the key range, or -1
    (its code and the later ones are then unset)."""
    inv = 1.0 / resolution
    for i in range(points.shape[0]):
        kx = np.floor(inv * np.float64(points[i, 0])) + 32768.0
        ky = np.floor(inv * np.float64(points[i, 1])) + 32768.0
        kz = np.floor(inv * np.float64(points[i, 2])) + 32768.0
        if not (0.0 <= kx < 65536.0 and 0.0 <= ky < 65536.0 and 0.0 <= kz < 65536.0):
            return i
        out[i] = morton3(np.int64(kx), np.int64(ky), np.int64(kz))
    return -1


@njit(cache=True, nogil=True)
def key_codes(keys, out):
    """out[i]: the Morton code of keys[i] ((N, 3) uint16): keys.morton_encode in one pass."""
    for i in range(keys.shape[0]):
        out[i] = morton3(keys[i, 0], keys[i, 1], keys[i, 2])


@njit(cache=True, nogil=True)
def code_keys(codes, out):
    """out[i]: the (3,) uint16 key of codes[i]: keys.morton_decode in one pass."""
    for i in range(codes.shape[0]):
        c = codes[i]
        out[i, 0] = compact16(c)
        out[i, 1] = compact16(c >> 1)
        out[i, 2] = compact16(c >> 2)
