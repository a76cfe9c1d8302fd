"""The `delta8` array codec of snapshots (formats/snapshot.md): int64 values as differences from
the previous value, each difference's 8 bytes split into 8 planes per block, so that the
mostly-zero high bytes of sorted Morton codes sit together and compress to almost nothing."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def to_planes(values, previous, out):
    """Write block `values` (int64) into `out` (uint8, 8 x n): plane k holds byte k of each
    difference from the value before (`previous` for the first). Returns the block's last value."""
    n = values.shape[0]
    for i in range(n):
        d = np.uint64(values[i] - previous)
        previous = values[i]
        for k in range(8):
            out[k * n + i] = np.uint8((d >> np.uint64(8 * k)) & np.uint64(0xFF))
    return previous


@njit(cache=True, nogil=True)
def from_planes(planes, previous, out):
    """The inverse of to_planes: `out` (int64, n) from `planes` (uint8, 8 x n). Returns the
    block's last value."""
    n = out.shape[0]
    for i in range(n):
        d = np.uint64(0)
        for k in range(8):
            d |= np.uint64(planes[k * n + i]) << np.uint64(8 * k)
        previous = previous + np.int64(d)
        out[i] = previous
    return previous
