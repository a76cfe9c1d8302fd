"""Flat-array OctoMap octree: node pool kernels.

Layout (struct of arrays, one entry per node slot):
  child[n]  int32  slot of the first of n's 8 child slots, or -1 when n has no children
  mask[n]   uint8  bit i set when child i exists (OctoMap allows partial children)
  value[n]  float32 log-odds (leaves) or max of the children (inner nodes)
Children are allocated as blocks of 8 consecutive slots; block 0 holds the root in slot 0.
`meta` = [top (next never-used slot), n_free_blocks, has_root]; `free` is a stack of freed
block starts.

Updates are applied in Morton order with a path stack: nodes shared with the previous key are
not walked again, and each node left behind is finalized once (pruned when its 8 children are
equal leaves, else set to the max of its children). The final tree equals OctoMap's eager
per-update prune/updateOccupancyChildren; see docs/backends.md for the argument.
"""

from __future__ import annotations

import numpy as np
from numba import njit

META_TOP = 0
META_NFREE = 1
META_ROOT = 2
FLT_MAX = np.float32(3.4028234663852886e38)
BLOCK_RESERVE = 17 * 8  # slots one update may need at most (16 levels + 1)


def new_pool(capacity_slots: int = 1 << 16):
    cap = max(capacity_slots, 64)
    child = np.full(cap, -1, dtype=np.int32)
    mask = np.zeros(cap, dtype=np.uint8)
    value = np.zeros(cap, dtype=np.float32)
    free = np.zeros(cap // 8 + 1, dtype=np.int32)
    meta = np.zeros(3, dtype=np.int64)
    meta[META_TOP] = 8  # block 0 reserved for the root
    return child, mask, value, free, meta


@njit(cache=True)
def slots_available(meta, capacity):
    return (capacity - meta[META_TOP]) + meta[META_NFREE] * 8


@njit(cache=True, inline="always")
def _alloc_block(free, meta):
    if meta[META_NFREE] > 0:
        meta[META_NFREE] -= 1
        return free[meta[META_NFREE]]
    b = meta[META_TOP]
    meta[META_TOP] += 8
    return b


@njit(cache=True, inline="always")
def _common_depth(a, b):
    """Depth of the deepest node shared by the paths to finest-level codes a and b."""
    x = a ^ b
    if x == 0:
        return 16
    t = 0  # index of the highest differing 3-bit level; sorted neighbours differ low down
    while (x >> (3 * (t + 1))) != 0:
        t += 1
    return 15 - t


@njit(cache=True)
def _finalize(n, child, mask, value, free, meta):
    """Prune n if its 8 children are equal leaves, else set it to the max of its children."""
    m = mask[n]
    if m == 0:
        return
    b = child[n]
    if m == 0xFF:
        v0 = value[b]
        ok = mask[b] == 0
        if ok:
            for j in range(1, 8):
                if mask[b + j] != 0 or value[b + j] != v0:
                    ok = False
                    break
        if ok:
            value[n] = v0
            child[n] = -1
            mask[n] = 0
            free[meta[META_NFREE]] = b
            meta[META_NFREE] += 1
            return
    best = -FLT_MAX
    for j in range(8):
        if m & (1 << j):
            if value[b + j] > best:
                best = value[b + j]
    value[n] = best


ADD = 0  # items are code << 1 | occupied: add hit/miss log-odds, clamp (OctoMap updateNode)
SET = 1  # items are codes, values[i] is the new log-odds (writing back cached voxels)


@njit(cache=True, nogil=True)
def apply_updates(child, mask, value, free, meta, path, pstate, items, values, mode, start, hit, miss, cmin, cmax):
    """Apply leaf updates from index `start`; any order works, Morton order is fastest.

    mode ADD: items are Morton code << 1 | occupied, OctoMap's clamped log-odds update with its
    early abort for already clamped leaves. mode SET: items are Morton codes and the leaf is set
    to values[i] (skipped when it already holds that value).
    Returns the index where it stopped: len(items) when done, less when the pool needs to grow
    (the caller grows the arrays and calls again; `path`/`pstate` carry the state across).
    pstate = [deepest valid depth of path (-1: none), previous code].
    """
    n_upd = items.shape[0]
    capacity = child.shape[0]
    i = start
    while i < n_upd:
        if slots_available(meta, capacity) < BLOCK_RESERVE:
            return i
        if mode == ADD:
            code = items[i] >> 1
            upd = hit if (items[i] & 1) else miss
        else:
            code = items[i]
            upd = values[i]
        plen = pstate[0]
        root_created = False
        if meta[META_ROOT] == 0:
            meta[META_ROOT] = 1
            child[0] = -1
            mask[0] = 0
            value[0] = 0.0
            path[0] = 0
            plen = 0
            common = 0
            root_created = True
        elif plen < 0:
            path[0] = 0
            common = 0
        else:
            common = _common_depth(code, pstate[1])
            if common > plen:
                common = plen
            for d in range(plen, common, -1):
                if d < 16:
                    _finalize(path[d], child, mask, value, free, meta)
        # read-only search (OctoMap's early abort when nothing would change)
        d = common
        nd = path[d]
        found = True
        while d < 16:
            pos = (code >> (3 * (15 - d))) & 7
            if mask[nd] & (1 << pos):
                nd = child[nd] + pos
                d += 1
                path[d] = nd
            elif mask[nd] == 0:
                break
            else:
                found = False
                break
        if found and not root_created:
            v = value[nd]
            if mode == ADD:
                unchanged = (upd >= 0 and v >= cmax) or (upd <= 0 and v <= cmin)
            else:
                unchanged = v == upd
            if unchanged:
                pstate[0] = d
                pstate[1] = code
                i += 1
                continue
        # modifying descent from where the search stopped
        created = root_created and d == 0
        while d < 16:
            pos = (code >> (3 * (15 - d))) & 7
            if mask[nd] & (1 << pos) == 0:
                if mask[nd] == 0 and not created:
                    # expand a pruned leaf: 8 children inherit its value
                    b = _alloc_block(free, meta)
                    for j in range(8):
                        child[b + j] = -1
                        mask[b + j] = 0
                        value[b + j] = value[nd]
                    child[nd] = b
                    mask[nd] = 0xFF
                    created = False
                else:
                    if mask[nd] == 0:
                        child[nd] = _alloc_block(free, meta)
                    s = child[nd] + pos
                    child[s] = -1
                    mask[s] = 0
                    value[s] = 0.0
                    mask[nd] |= 1 << pos
                    created = True
            else:
                created = False
            nd = child[nd] + pos
            d += 1
            path[d] = nd
        if mode == ADD:
            v = value[nd] + upd
            if v < cmin:
                v = cmin
            elif v > cmax:
                v = cmax
        else:
            v = upd
        value[nd] = v
        pstate[0] = 16
        pstate[1] = code
        i += 1
    # batch done: finalize the last path up to the root
    plen = pstate[0]
    if plen >= 0:
        for d in range(plen, -1, -1):
            if d < 16:
                _finalize(path[d], child, mask, value, free, meta)
    pstate[0] = -1
    return n_upd


@njit(cache=True, nogil=True)
def lookup(child, mask, value, meta, codes, out_value, out_depth):
    """Value and depth of the leaf holding each finest-level code; depth -1 (NaN) where unknown.

    Each walk restarts from the deepest node shared with the previous code, so Morton-sorted
    queries cost little more than one level each."""
    path = np.zeros(17, dtype=np.int64)
    plen = -1
    prev = np.int64(0)
    for i in range(codes.shape[0]):
        out_depth[i] = -1
        out_value[i] = np.nan
        if meta[META_ROOT] == 0:
            continue
        code = codes[i]
        d = 0
        if plen > 0:
            d = _common_depth(code, prev)
            if d > plen:
                d = plen
        nd = path[d]
        while True:
            if mask[nd] == 0 or d == 16:
                if mask[nd] == 0:
                    out_depth[i] = d
                    out_value[i] = value[nd]
                break
            pos = (code >> (3 * (15 - d))) & 7
            if mask[nd] & (1 << pos) == 0:
                break
            nd = child[nd] + pos
            d += 1
            path[d] = nd
        plen = d
        prev = code


@njit(cache=True)
def count_nodes(child, mask, meta):
    """(leaf nodes, inner nodes, max depth-first stack) of the tree."""
    if meta[META_ROOT] == 0:
        return 0, 0
    stack = np.empty(16 * 8 + 8, dtype=np.int64)
    stack[0] = 0
    sp = 1
    leaves = 0
    inner = 0
    while sp > 0:
        sp -= 1
        nd = stack[sp]
        m = mask[nd]
        if m == 0:
            leaves += 1
            continue
        inner += 1
        b = child[nd]
        for j in range(8):
            if m & (1 << j):
                stack[sp] = b + j
                sp += 1
    return leaves, inner


@njit(cache=True)
def extract_leaves(child, mask, value, meta, n_leaves):
    """Leaves in Morton (depth-first) order: code of the first covered voxel, depth, value."""
    codes = np.empty(n_leaves, dtype=np.int64)
    depths = np.empty(n_leaves, dtype=np.uint8)
    values = np.empty(n_leaves, dtype=np.float32)
    if meta[META_ROOT] == 0:
        return codes[:0], depths[:0], values[:0]
    st_node = np.empty(16 * 8 + 8, dtype=np.int64)
    st_code = np.empty(16 * 8 + 8, dtype=np.int64)
    st_depth = np.empty(16 * 8 + 8, dtype=np.int64)
    st_node[0] = 0
    st_code[0] = 0
    st_depth[0] = 0
    sp = 1
    k = 0
    while sp > 0:
        sp -= 1
        nd = st_node[sp]
        code = st_code[sp]
        d = st_depth[sp]
        m = mask[nd]
        if m == 0:
            codes[k] = code
            depths[k] = d
            values[k] = value[nd]
            k += 1
            continue
        b = child[nd]
        # push in reverse so child 0 pops first (Morton order)
        for j in range(7, -1, -1):
            if m & (1 << j):
                st_node[sp] = b + j
                st_code[sp] = code | (np.int64(j) << (3 * (15 - d)))
                st_depth[sp] = d + 1
                sp += 1
    return codes[:k], depths[:k], values[:k]


@njit(cache=True)
def insert_leaves(child, mask, value, free, meta, path, pstate, codes, depths, values, start):
    """Rebuild a tree from Morton-ordered leaves (snapshot load). Same resume protocol as
    apply_updates; inner values and pruning are settled by the same finalize pass."""
    n = codes.shape[0]
    capacity = child.shape[0]
    i = start
    while i < n:
        if slots_available(meta, capacity) < BLOCK_RESERVE:
            return i
        code = codes[i]
        depth = depths[i]
        plen = pstate[0]
        if meta[META_ROOT] == 0:
            meta[META_ROOT] = 1
            child[0] = -1
            mask[0] = 0
            value[0] = 0.0
            path[0] = 0
            common = 0
        elif plen < 0:
            path[0] = 0
            common = 0
        else:
            common = _common_depth(code, pstate[1])
            if common > plen:
                common = plen
            for d in range(plen, common, -1):
                if d < 16:
                    _finalize(path[d], child, mask, value, free, meta)
        d = common
        nd = path[d]
        while d < depth:
            pos = (code >> (3 * (15 - d))) & 7
            if mask[nd] & (1 << pos) == 0:
                if mask[nd] == 0:
                    child[nd] = _alloc_block(free, meta)
                s = child[nd] + pos
                child[s] = -1
                mask[s] = 0
                value[s] = 0.0
                mask[nd] |= 1 << pos
            nd = child[nd] + pos
            d += 1
            path[d] = nd
        value[nd] = values[i]
        pstate[0] = depth
        pstate[1] = code
        i += 1
    plen = pstate[0]
    if plen >= 0:
        for d in range(plen, -1, -1):
            if d < 16:
                _finalize(path[d], child, mask, value, free, meta)
    pstate[0] = -1
    return n
