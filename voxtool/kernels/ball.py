"""The integer offsets of a ball of voxels: the neighbours `clean` judges a point's voxel with,
and the cells a hash-map voxel inflates (voxtool.maps.hashmap)."""

from __future__ import annotations

import numpy as np
from numba import njit


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
