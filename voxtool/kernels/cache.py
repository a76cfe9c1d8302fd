"""OctoCache kernels: a bucketed voxel cache in front of the octree (seed: octocache.md, Sec. 4).

Bucket b holds up to `slots` cells (Morton code, accumulated log-odds) in insertion order,
oldest first, at cell indices b*slots .. b*slots+count[b]-1. The bucket of a voxel is its Morton
code mod w (w a power of two).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def cache_insert(packed, start, count, cell_code, cell_val, slots, seed, hit, miss, cmin, cmax):
    """Insert a scan's updates (code << 1 | occupied) from index `start`. A miss is seeded with
    seed[i], the octree's value of that voxel (NaN: unknown, the prior 0), before the update, so
    the cache always holds the value the octree would. Buckets may exceed tau during a batch (as
    in the paper); when one runs out of its `slots`, this returns early so the caller can widen
    the buckets and resume. Returns (hits, index reached)."""
    wmask = count.shape[0] - 1
    hits = 0
    for i in range(start, packed.shape[0]):
        code = packed[i] >> 1
        upd = hit if (packed[i] & 1) else miss
        b = code & wmask
        base = b * slots
        c = count[b]
        j = 0
        while j < c and cell_code[base + j] != code:
            j += 1
        if j < c:
            hits += 1
            v = cell_val[base + j] + upd
        else:
            if c == slots:
                return hits, i
            prior = seed[i]
            v = (np.float32(0.0) if prior != prior else prior) + upd
            cell_code[base + c] = code
            count[b] = c + 1
        cell_val[base + j] = min(max(v, cmin), cmax)  # no branch: a free voxel often reaches the clamp
    return hits, packed.shape[0]


@njit(cache=True, nogil=True)
def cache_evict(count, cell_code, cell_val, slots, tau, ev_code, ev_val, n_ev):
    """Every bucket above `tau` cells gives up its oldest cells down to `tau` (bucket sweep
    order). Returns the new number of evicted cells in ev_*."""
    for b in range(count.shape[0]):
        c = count[b]
        if c > tau:
            drop = c - tau
            base = b * slots
            for k in range(drop):
                ev_code[n_ev] = cell_code[base + k]
                ev_val[n_ev] = cell_val[base + k]
                n_ev += 1
            for k in range(tau):
                cell_code[base + k] = cell_code[base + drop + k]
                cell_val[base + k] = cell_val[base + drop + k]
            count[b] = tau
    return n_ev


@njit(cache=True, nogil=True)
def cache_lookup(count, cell_code, cell_val, slots, codes, out, found):
    """Cached log-odds of `codes` (found[i] = 1), leaving other entries untouched."""
    wmask = count.shape[0] - 1
    for i in range(codes.shape[0]):
        code = codes[i]
        b = code & wmask
        base = b * slots
        for j in range(count[b]):
            if cell_code[base + j] == code:
                out[i] = cell_val[base + j]
                found[i] = 1
                break


@njit(cache=True, nogil=True)
def cache_drain(count, cell_code, cell_val, slots, ev_code, ev_val):
    """Move every cached cell to ev_* (flush); returns how many."""
    n = 0
    for b in range(count.shape[0]):
        base = b * slots
        for k in range(count[b]):
            ev_code[n] = cell_code[base + k]
            ev_val[n] = cell_val[base + k]
            n += 1
        count[b] = 0
    return n
