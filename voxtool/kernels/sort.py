"""Sorting Morton codes inside compiled kernels.

A scan's updates are a few thousand codes of one neighbourhood: most of their 49 bits are the
same in all of them. An LSD radix sort over only the bits that differ takes 3-4 passes over
them with no data-dependent branches; numba's quicksort, whose branches mispredict on every
other comparison, took 3x longer on 2,850 updates (docs/design/backends.md).
"""

from __future__ import annotations

import numpy as np
from numba import njit

DIGIT_BITS = 11  # 2,048 buckets: their counts (16 KB) stay in L1 and a pass costs ~n + 2,048


@njit(cache=True, nogil=True)
def sort_codes(a, scratch, first_bit=0):
    """Sort the non-negative int64 values of `a` in place, ascending; `scratch` is working room
    of at least a's length. Each pass sorts by the next DIGIT_BITS bits from the lowest bit
    that differs between the values, skipping bits they all share. Bits below `first_bit` are
    not sorted by: values equal above it keep their order (the sort is stable)."""
    n = a.shape[0]
    if n < 2:
        return
    differ = np.int64(0)  # the bits that are not the same in every value
    for i in range(n):
        differ |= a[i] ^ a[0]
    differ &= ~((np.int64(1) << first_bit) - 1)
    mask = (1 << DIGIT_BITS) - 1
    start = np.empty(1 << DIGIT_BITS, np.int64)
    src, dst = a, scratch[:n]
    in_a = True
    shift = 0
    while shift < 63 and differ >> shift != 0:
        while (differ >> shift) & 1 == 0:
            shift += 1
        start[:] = 0
        for i in range(n):
            start[(src[i] >> shift) & mask] += 1
        total = 0
        for d in range(mask + 1):  # counts to where each digit's run starts
            c = start[d]
            start[d] = total
            total += c
        for i in range(n):  # stable: equal digits keep the order of the pass before
            v = src[i]
            d = (v >> shift) & mask
            dst[start[d]] = v
            start[d] += 1
        src, dst = dst, src
        in_a = not in_a
        shift += DIGIT_BITS
    if not in_a:
        a[:] = src


@njit(cache=True, nogil=True)
def latest_per_code(codes, states):
    """(sorted unique codes, the state each had last) of changes listed in the order they came.
    The codes are sorted with their states packed below them and de-duplicated in place: `codes`
    is consumed, and the codes returned are a view of it (no second array of the batch)."""
    n = codes.shape[0]
    for i in range(n):
        codes[i] = (codes[i] << 2) | states[i]  # states are 2-bit codes; the sort keeps their order
    sort_codes(codes, np.empty(n, dtype=np.int64), 2)
    k = 0
    for i in range(n):
        if i + 1 < n and (codes[i + 1] >> 2) == (codes[i] >> 2):
            continue  # a later change of the same voxel follows
        codes[k] = codes[i]  # k <= i: in place
        k += 1
    out_states = np.empty(k, dtype=np.uint8)
    for i in range(k):
        out_states[i] = codes[i] & 3
        codes[i] >>= 2
    return codes[:k], out_states


@njit(cache=True, nogil=True)
def drop_state(codes, states, n, state):
    """Remove the entries of the first n whose state is `state`, in place, keeping the order of the
    rest; returns how many are left."""
    k = 0
    for i in range(n):
        if states[i] != state:
            codes[k] = codes[i]
            states[k] = states[i]
            k += 1
    return k


@njit(cache=True, nogil=True)
def prune_into(codes, values, out_codes, out_depths, out_values):
    """OctoMap's pruned leaves of finest-level voxels (sorted unique Morton codes, their values:
    log-odds, or 2-bit states): eight sibling leaves of one value become their parent, level by
    level. One pass with a stack: siblings are consecutive in Morton order, so they meet on top of
    it. The stack never outgrows what it has read, so `out_codes`/`out_values` may be `codes`/
    `values` themselves (pruned in place). Returns how many leaves."""
    n = codes.shape[0]
    top = 0
    for i in range(n):
        out_codes[top] = codes[i]
        out_depths[top] = 16
        out_values[top] = values[i]
        top += 1
        while top >= 8:
            d = out_depths[top - 1]
            if d == 0:
                break
            span = np.int64(1) << (3 * (16 - d))  # codes a node of depth d covers
            first = out_codes[top - 8]
            if first & (8 * span - 1) != 0:
                break  # the eighth from the top is not the first child of a parent
            merge = True
            for k in range(8):
                j = top - 8 + k
                if out_depths[j] != d or out_values[j] != out_values[top - 1] or out_codes[j] != first + k * span:
                    merge = False
                    break
            if not merge:
                break
            top -= 8
            out_codes[top] = first
            out_depths[top] = d - 1
            top += 1
    return top


@njit(cache=True, nogil=True)
def move_leaves(codes, depths, values, src, dst, n):
    """Move n leaves from place src down to place dst (dst <= src), in place: the leaves pruned
    in a part of the arrays joined to those of the parts before."""
    for i in range(n):
        codes[dst + i] = codes[src + i]
        depths[dst + i] = depths[src + i]
        values[dst + i] = values[src + i]


@njit(cache=True, nogil=True)
def merge_latest_into(codes, states, n, codes_b, states_b):
    """The union of a sorted, unique change set (the first n entries of `codes`/`states`) and
    another (b), b's state where both hold a voxel, written in place: the buffers hold
    at least n + len(b) entries. Merged from the back (the largest first, into the free end), then
    moved to the front where duplicates left a gap. Returns the merged count."""
    i, j, k = n - 1, codes_b.shape[0] - 1, n + codes_b.shape[0] - 1
    while j >= 0:
        if i >= 0 and codes[i] > codes_b[j]:
            codes[k] = codes[i]
            states[k] = states[i]
            i -= 1
        else:
            if i >= 0 and codes[i] == codes_b[j]:
                i -= 1  # b's state wins: a's entry is dropped
            codes[k] = codes_b[j]
            states[k] = states_b[j]
            j -= 1
        k -= 1
    # entries 0..i stay where they are; the merged tail starts at k + 1, after a gap of k - i
    gap = k - i
    total = n + codes_b.shape[0] - gap
    if gap > 0:
        for t in range(i + 1, total):
            codes[t] = codes[t + gap]
            states[t] = states[t + gap]
    return total
