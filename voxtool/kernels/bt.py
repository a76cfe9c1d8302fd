"""OctoMap binary (.bt) tree codec kernels: 2 bits per child, depth-first.

Child code (bits 2i..2i+1 of the node's 16-bit word, children 0-3 in the first byte):
0 unknown, 1 free leaf, 2 occupied leaf, 3 inner node (its own word follows, depth-first).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def parse_bt(data, max_leaves):
    """Leaves of a .bt body: (codes, depths, occupied, nodes, bytes consumed, status).

    status 0 ok, -1 truncated, -2 inner node below depth 16, -3 more leaves than max_leaves."""
    codes = np.empty(max_leaves, dtype=np.int64)
    depths = np.empty(max_leaves, dtype=np.uint8)
    occ = np.empty(max_leaves, dtype=np.uint8)
    n_data = data.shape[0]
    if n_data == 0:
        return codes[:0], depths[:0], occ[:0], 0, 0, 0
    st_word = np.zeros(17, dtype=np.int64)
    st_code = np.zeros(17, dtype=np.int64)
    st_next = np.zeros(17, dtype=np.int64)
    if n_data < 2:
        return codes[:0], depths[:0], occ[:0], 0, 0, -1
    st_word[0] = np.int64(data[0]) | (np.int64(data[1]) << 8)
    st_code[0] = 0
    st_next[0] = 0
    pos = 2
    nodes = 1
    k = 0
    d = 0
    while d >= 0:
        i = st_next[d]
        if i == 8:
            d -= 1
            continue
        st_next[d] = i + 1
        c = (st_word[d] >> (2 * i)) & 3
        if c == 0:
            continue
        nodes += 1
        ccode = st_code[d] | (np.int64(i) << (3 * (15 - d)))
        if c == 3:
            if d + 1 >= 16:
                return codes[:k], depths[:k], occ[:k], nodes, pos, -2
            if pos + 2 > n_data:
                return codes[:k], depths[:k], occ[:k], nodes, pos, -1
            d += 1
            st_word[d] = np.int64(data[pos]) | (np.int64(data[pos + 1]) << 8)
            st_code[d] = ccode
            st_next[d] = 0
            pos += 2
        else:
            if k >= max_leaves:
                return codes[:k], depths[:k], occ[:k], nodes, pos, -3
            codes[k] = ccode
            depths[k] = d + 1
            occ[k] = 1 if c == 2 else 0
            k += 1
    return codes[:k], depths[:k], occ[:k], nodes, pos, 0


@njit(cache=True)
def serialize_bt(codes, depths, occupied, out):
    """OctoMap's binary tree stream of canonical (pruned) Morton-ordered leaves: depth-first, a
    16-bit word per inner node, 2 bits per child (0 unknown, 1 free leaf, 2 occupied leaf, 3
    inner). Writes into `out` when it is large enough; returns the bytes needed."""
    n = codes.shape[0]
    if n == 0 or (n == 1 and depths[0] == 0):
        return 0
    # stack of inner nodes to write: (first code, depth, leaf range)
    st_code = np.empty(17 * 8, dtype=np.int64)
    st_depth = np.empty(17 * 8, dtype=np.int64)
    st_lo = np.empty(17 * 8, dtype=np.int64)
    st_hi = np.empty(17 * 8, dtype=np.int64)
    st_code[0] = 0
    st_depth[0] = 0
    st_lo[0] = 0
    st_hi[0] = n
    sp = 1
    pos = 0
    c_lo = np.empty(8, dtype=np.int64)
    c_hi = np.empty(8, dtype=np.int64)
    while sp > 0:
        sp -= 1
        first, d, lo, hi = st_code[sp], st_depth[sp], st_lo[sp], st_hi[sp]
        shift = 3 * (15 - d)
        word = 0
        i = lo
        for j in range(8):
            c_lo[j] = i
            while i < hi and (codes[i] >> shift) & 7 == j:
                i += 1
            c_hi[j] = i
            if c_hi[j] > c_lo[j]:
                if c_hi[j] - c_lo[j] == 1 and depths[c_lo[j]] == d + 1:
                    word |= (2 if occupied[c_lo[j]] else 1) << (2 * j)
                else:
                    word |= 3 << (2 * j)
        if pos + 2 <= out.shape[0]:
            out[pos] = word & 0xFF
            out[pos + 1] = (word >> 8) & 0xFF
        pos += 2
        for j in range(7, -1, -1):
            if (word >> (2 * j)) & 3 == 3:
                st_code[sp] = first | (np.int64(j) << shift)
                st_depth[sp] = d + 1
                st_lo[sp] = c_lo[j]
                st_hi[sp] = c_hi[j]
                sp += 1
    return pos
