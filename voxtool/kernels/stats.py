"""Map statistics in one pass over a leaf table (no temporaries: a 100 MB array's page faults
cost more than the arithmetic here)."""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16


@njit(cache=True, nogil=True)
def leaf_summary(codes, depths, values, threshold):
    """(occupied voxels, free voxels, lowest key, highest key) of leaves at the finest
    resolution (a leaf at depth d covers 8^(16 - d) voxels); keys per axis, over the occupied
    voxels (0 / 0 when none is occupied)."""
    occ = np.int64(0)
    free = np.int64(0)
    lo = np.full(3, 1 << 16, dtype=np.int64)
    hi = np.full(3, -1, dtype=np.int64)
    for i in range(codes.shape[0]):
        span = np.int64(1) << (3 * (16 - np.int64(depths[i])))
        if values[i] > threshold:
            occ += span
            last = codes[i] + span - 1
            for a in range(3):
                k0 = compact16(codes[i] >> a)
                k1 = compact16(last >> a)
                if k0 < lo[a]:
                    lo[a] = k0
                if k1 > hi[a]:
                    hi[a] = k1
        else:
            free += span
    if occ == 0:
        lo[:] = 0
        hi[:] = 0
    return occ, free, lo, hi


@njit(cache=True, nogil=True)
def leaf_problem(codes, depths, values):
    """What is wrong with a leaf table, in one pass: (problem, leaf), problem 0 nothing, 1 a
    depth above 16, 2 a code outside the 48-bit key space, 3 a code not aligned to its depth,
    4 not sorted or overlapping, 5 a log-odds not finite (the first problem found)."""
    end = np.int64(0)
    for i in range(codes.shape[0]):
        d = np.int64(depths[i])
        if d > 16 or d < 0:
            return 1, i
        span = np.int64(1) << np.int64(3 * (16 - d))
        c = codes[i]
        if c < 0 or c + span > (np.int64(1) << np.int64(48)):
            return 2, i
        if c & (span - 1):
            return 3, i
        if i > 0 and c < end:
            return 4, i
        end = c + span
        if not np.isfinite(values[i]):
            return 5, i
    return 0, 0
