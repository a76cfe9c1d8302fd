"""LZF decompression (the codec of PCD `DATA binary_compressed`), bounds-checked."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def lzf_decompress(src, out):
    """Decompress `src` into `out`; returns bytes written, or a negative error code:
    -1 output overflow, -2 truncated input, -3 back reference before the start."""
    ip = 0
    op = 0
    n_in = src.shape[0]
    n_out = out.shape[0]
    while ip < n_in:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if op + length > n_out:
                return -1
            if ip + length > n_in:
                return -2
            for k in range(length):
                out[op + k] = src[ip + k]
            op += length
            ip += length
        else:
            length = ctrl >> 5
            ref = op - ((ctrl & 0x1F) << 8) - 1
            if length == 7:
                if ip >= n_in:
                    return -2
                length += np.int64(src[ip])
                ip += 1
            if ip >= n_in:
                return -2
            ref -= np.int64(src[ip])
            ip += 1
            length += 2
            if op + length > n_out:
                return -1
            if ref < 0:
                return -3
            for k in range(length):
                out[op + k] = out[ref + k]
            op += length
    return op
