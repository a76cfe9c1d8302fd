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
def serialize_bt(child, mask, value, has_root, n_inner, threshold):
    """Depth-first 2-bit child words of a (max-likelihood, pruned) pool tree."""
    out = np.empty(2 * n_inner, dtype=np.uint8)
    if has_root == 0 or mask[0] == 0:
        return out[:0]
    stack = np.empty(16 * 8 + 8, dtype=np.int64)
    stack[0] = 0
    sp = 1
    pos = 0
    while sp > 0:
        sp -= 1
        nd = stack[sp]
        m = mask[nd]
        b = child[nd]
        word = 0
        for j in range(8):
            if m & (1 << j):
                s = b + j
                if mask[s] != 0:
                    code = 3
                elif value[s] > threshold:
                    code = 2
                else:
                    code = 1
                word |= code << (2 * j)
        out[pos] = word & 0xFF
        out[pos + 1] = (word >> 8) & 0xFF
        pos += 2
        for j in range(7, -1, -1):
            if m & (1 << j) and mask[b + j] != 0:
                stack[sp] = b + j
                sp += 1
    return out[:pos]
