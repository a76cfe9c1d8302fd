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
def sort_codes(a, scratch):
    """Sort the non-negative int64 values of `a` in place, ascending; `scratch` is working room
    of at least a's length. Each pass sorts by the next DIGIT_BITS bits from the lowest bit
    that differs between the values, skipping bits they all share."""
    n = a.shape[0]
    if n < 2:
        return
    differ = np.int64(0)  # the bits that are not the same in every value
    for i in range(n):
        differ |= a[i] ^ a[0]
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
