"""Filling a picture's pixels with the leaves that project onto them (voxtool.io.picture)."""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16


@njit(cache=True, nogil=True)
def fill_leaves(state, depth, width, kmin_u, kmin_w, shift, u, w, a, from_plus, layer,
                codes, depths, values, threshold):
    """Project leaves (Morton code, depth, log-odds) onto pixels of 2^shift x 2^shift keys along
    axis `a` (the picture's axes u and w; kmin_*: the keys of its first pixel): state = max(state,
    2 occupied / 1 free), and where occupied, depth = max(depth, signed key of the voxel nearest
    the viewer). layer >= 0: only leaves holding that z key. One pass over the covered pixels,
    whatever the leaves' sizes, with no per-leaf arrays."""
    for i in range(codes.shape[0]):
        edge = np.int64(1) << (16 - np.int64(depths[i]))
        lo_u = compact16(codes[i] >> u)
        lo_w = compact16(codes[i] >> w)
        lo_a = compact16(codes[i] >> a)
        if layer >= 0:
            lo_z = compact16(codes[i] >> 2)
            if layer < lo_z or layer > lo_z + edge - 1:
                continue
        occupied = values[i] > threshold
        s = np.int8(2) if occupied else np.int8(1)
        near = np.float64(lo_a + edge - 1) if from_plus else -np.float64(lo_a)
        x0 = (lo_u - kmin_u) >> shift
        x1 = (lo_u + edge - 1 - kmin_u) >> shift
        y0 = (lo_w - kmin_w) >> shift
        y1 = (lo_w + edge - 1 - kmin_w) >> shift
        for y in range(y0, y1 + 1):
            row = y * width
            for x in range(x0, x1 + 1):
                if s > state[row + x]:
                    state[row + x] = s
                if occupied and near > depth[row + x]:
                    depth[row + x] = near
