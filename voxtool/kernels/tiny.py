"""TinyOctoMap kernels: an octree of small integer words in a fixed memory pool.

Word layout (docs/backends.md): low 4 bits = occupancy level (0 unknown, 1..15 known), the other
bits = index of the node's first child block (0 = no children; block 0 holds the root). Siblings
are the 8 consecutive words of a block. uint16 words give 12 index bits (4096 blocks, 64 KiB: the
paper's pool); uint32 words give 28 bits for larger pools.

Packed finest level (32-bit pools): the 8 finest voxels under a node of depth `depth - 1` are
one uint32 of a second pool, `leaves`, 4 bits a voxel (voxel j in bits 4j..4j+3), and that
node's index bits point there (leaf block 0 is never used). 76-81 % of a surface map's blocks
are at the finest level: 4 bytes instead of 32 each.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16, morton3

T_FREE_TOP = 0  # meta: number of free-list entries
T_NEXT = 1  # next never-used block
T_BLOCKS = 2  # pool capacity in blocks
T_DROPPED = 3  # updates dropped because no block was left
T_OUTSIDE = 4  # updates outside the map extent
T_LEAF_FREE_TOP = 5  # the packed finest level's pool (`leaves`): free-list entries,
T_LEAF_NEXT = 6  # next never-used leaf block (from 1),
T_LEAF_BLOCKS = 7  # capacity
META_SIZE = 8
NIBBLES = 0x11111111  # a level times this: 8 voxels of that level


@njit(cache=True, inline="always")
def _alloc(free, meta, top, nxt, cap):
    if meta[top] > 0:
        meta[top] -= 1
        return free[meta[top]]
    if meta[nxt] < meta[cap]:
        b = meta[nxt]
        meta[nxt] += 1
        return b
    return -1


@njit(cache=True)
def tiny_apply(pool, free, leaves, leaf_free, meta, packed, offset, depth, hit, miss, prior, lmin, lmax, start, grow,
               pack):
    """Apply one scan's updates (OctoMap Morton code << 1 | occupied) from index `start`, each
    with eager pruning on the way back up, as OctoMap does. Updates outside the map are dropped
    and counted. An update that needs a block when the pool is exhausted: with `grow`, the
    kernel stops and returns its index (the caller grows the pools and calls again from there;
    blocks it already split stay split, children holding their parent's level, which is the
    same tree); without, it is dropped and counted, the tree staying valid. `pack`: the finest
    level lives in `leaves` (module docstring). Returns len(packed) when done."""
    path = np.zeros(depth + 1, dtype=np.int64)
    size = 1 << depth
    for i in range(start, packed.shape[0]):
        code = packed[i] >> 1
        step = hit if (packed[i] & 1) else -miss
        x = compact16(code) - offset
        y = compact16(code >> 1) - offset
        z = compact16(code >> 2) - offset
        if x < 0 or y < 0 or z < 0 or x >= size or y >= size or z >= size:
            meta[T_OUTSIDE] += 1
            continue
        s = 0
        path[0] = 0
        ok = True
        nib = -1  # the finest voxel's nibble in leaves[child], packed
        for d in range(depth):
            w = np.int64(pool[s])
            child = w >> 4
            lvl = w & 15
            into_leaves = pack and d == depth - 1
            if child == 0:
                # a leaf above the finest level: pruned (known) or never seen (unknown)
                if lvl != 0 and ((step > 0 and lvl >= lmax) or (step < 0 and lvl <= lmin)):
                    ok = False  # OctoMap's early abort: already clamped this way
                    break
                if into_leaves:
                    b = _alloc(leaf_free, meta, T_LEAF_FREE_TOP, T_LEAF_NEXT, T_LEAF_BLOCKS)
                else:
                    b = _alloc(free, meta, T_FREE_TOP, T_NEXT, T_BLOCKS)
                if b < 0:
                    if grow:
                        return i
                    meta[T_DROPPED] += 1
                    ok = False
                    break
                if into_leaves:
                    leaves[b] = lvl * NIBBLES
                else:
                    for j in range(8):
                        pool[b * 8 + j] = lvl
                pool[s] = (b << 4) | lvl
                child = b
            bit = depth - 1 - d
            pos = ((x >> bit) & 1) | (((y >> bit) & 1) << 1) | (((z >> bit) & 1) << 2)
            if into_leaves:
                nib = child * 8 + pos
            else:
                s = child * 8 + pos
                path[d + 1] = s
        if not ok:
            continue
        if nib >= 0:
            word = np.int64(leaves[nib >> 3])
            lvl = (word >> (4 * (nib & 7))) & 15
        else:
            lvl = np.int64(pool[s]) & 15
        if lvl == 0:
            lvl = prior
        lvl += step
        if lvl < lmin:
            lvl = lmin
        elif lvl > lmax:
            lvl = lmax
        top = depth - 1
        if nib >= 0:
            shift = 4 * (nib & 7)
            word = (word & ~(np.int64(15) << shift)) | (lvl << shift)
            leaves[nib >> 3] = word
            n = path[depth - 1]
            b = nib >> 3
            first = word & 15
            if first != 0 and word == first * NIBBLES:  # 8 equal known voxels: pruned
                pool[n] = first
                leaf_free[meta[T_LEAF_FREE_TOP]] = b
                meta[T_LEAF_FREE_TOP] += 1
            else:
                best = 0
                for j in range(8):
                    v = (word >> (4 * j)) & 15
                    if v > best:
                        best = v
                pool[n] = (b << 4) | best
            top = depth - 2
        else:
            pool[s] = lvl
        for d in range(top, -1, -1):
            n = path[d]
            b = np.int64(pool[n]) >> 4
            first = np.int64(pool[b * 8])
            same = (first >> 4) == 0 and (first & 15) != 0
            best = 0
            for j in range(8):
                w = np.int64(pool[b * 8 + j])
                if (w & 15) > best:
                    best = w & 15
                if w != first or (w >> 4) != 0:
                    same = False
            if same:
                pool[n] = first & 15
                free[meta[T_FREE_TOP]] = b
                meta[T_FREE_TOP] += 1
            else:
                pool[n] = (b << 4) | best
    return packed.shape[0]


@njit(cache=True)
def tiny_leaves(pool, leaves, pack, offset, depth, out_codes, out_depth, out_level):
    """Known leaves as (OctoMap Morton code of the first voxel, OctoMap depth, level), in
    depth-first order; returns how many. The root leaf (whole map one value) is split in 8.
    `pack`: the finest level lives in `leaves`."""
    st_s = np.zeros(8 * depth + 16, dtype=np.int64)
    st_d = np.zeros(8 * depth + 16, dtype=np.int64)
    st_x = np.zeros(8 * depth + 16, dtype=np.int64)
    st_y = np.zeros(8 * depth + 16, dtype=np.int64)
    st_z = np.zeros(8 * depth + 16, dtype=np.int64)
    sp = 0
    k = 0
    root = np.int64(pool[0])
    if root >> 4 == 0:
        if root & 15 == 0:
            return 0
        # expand a whole-map leaf into its 8 octants so every leaf is aligned in OctoMap keys
        for j in range(7, -1, -1):
            st_s[sp] = -1 - (root & 15)
            st_d[sp] = 1
            half = 1 << (depth - 1)
            st_x[sp] = (j & 1) * half
            st_y[sp] = ((j >> 1) & 1) * half
            st_z[sp] = ((j >> 2) & 1) * half
            sp += 1
    else:
        st_s[0] = 0
        sp = 1
    while sp > 0:
        sp -= 1
        s = st_s[sp]
        d = st_d[sp]
        x, y, z = st_x[sp], st_y[sp], st_z[sp]
        if s < 0:
            w = -1 - s  # a level pushed directly (split root leaf)
        else:
            w = np.int64(pool[s])
        if s < 0 or (w >> 4) == 0:
            lvl = w & 15
            if lvl != 0:
                out_codes[k] = morton3(x + offset, y + offset, z + offset)
                out_depth[k] = 16 - (depth - d)
                out_level[k] = lvl
                k += 1
            continue
        b = w >> 4
        half = 1 << (depth - d - 1)
        if pack and d == depth - 1:  # 8 finest voxels packed in one word
            word = np.int64(leaves[b])
            for j in range(8):
                lvl = (word >> (4 * j)) & 15
                if lvl != 0:
                    out_codes[k] = morton3(x + (j & 1) + offset, y + ((j >> 1) & 1) + offset, z + ((j >> 2) & 1) + offset)
                    out_depth[k] = 16
                    out_level[k] = lvl
                    k += 1
            continue
        for j in range(7, -1, -1):
            st_s[sp] = b * 8 + j
            st_d[sp] = d + 1
            st_x[sp] = x + (j & 1) * half
            st_y[sp] = y + ((j >> 1) & 1) * half
            st_z[sp] = z + ((j >> 2) & 1) * half
            sp += 1
    return k
