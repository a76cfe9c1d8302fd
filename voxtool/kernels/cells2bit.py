"""2-bit cell payloads built and read by their few non-background cells.

A box payload is one 2-bit code per cell, four to a byte (formats/packet.md). A delta's box is
mostly the background code (unchanged), so a payload is written as the background byte repeated
with the changed cells placed at their ranks, and read by scanning for the bytes that differ
from it: memory traffic of a byte per four cells, no per-cell index array.
"""

from __future__ import annotations

from numba import njit

UNCHANGED = 3


@njit(cache=True, nogil=True)
def place(ranks, codes, cells, background, out):
    """Fill `out` ((cells + 3) // 4 bytes) with `background` in every cell, the padding cells
    after the last with UNCHANGED, then put codes[i] at cell ranks[i]."""
    fill = background * 0x55
    for i in range(out.shape[0]):
        out[i] = fill
    for r in range(cells, out.shape[0] * 4):  # padding, as pack_2bit writes it
        out[r >> 2] = (out[r >> 2] & ~(3 << (2 * (r & 3)))) | (UNCHANGED << (2 * (r & 3)))
    for i in range(ranks.shape[0]):
        r = ranks[i]
        shift = 2 * (r & 3)
        out[r >> 2] = (out[r >> 2] & ~(3 << shift)) | (codes[i] << shift)


@njit(cache=True, nogil=True)
def scan(data, cells, background, out_ranks, out_codes):
    """The cells (rank, code) of `data` (2-bit codes, four a byte) whose code is not
    `background`, in rank order, skipping whole bytes of background cells (most of a delta;
    padding cells past `cells` are not cells). Returns how many, or -1 when there are more than
    `out_ranks` holds less three: a byte's four cells are written whatever their codes and the
    count moves on by the changed ones (no branch to mispredict on each cell of a changed byte),
    so the last byte may write three entries beyond the count."""
    fill = background * 0x55
    limit = out_ranks.shape[0] - 3
    m = 0
    full = cells >> 2  # bytes whose four cells are all cells; the last byte may hold padding
    for i in range(full):
        b = data[i]
        if b == fill:
            continue
        if m >= limit:
            return -1  # this byte has a changed cell, and there is no room for it
        x = b ^ fill
        for k in range(4):
            out_ranks[m] = 4 * i + k
            out_codes[m] = (b >> (2 * k)) & 3
            m += ((x >> (2 * k)) & 3) != 0
    for r in range(4 * full, cells):
        c = (data[r >> 2] >> (2 * (r & 3))) & 3
        if c != background:
            if m == limit:
                return -1
            out_ranks[m] = r
            out_codes[m] = c
            m += 1
    return m if m <= limit else -1


@njit(cache=True, nogil=True)
def nested_keys(idx, dx, dy, lo, out):
    """out[i]: the key (uint16 x, y, z) of the cell at nested index idx[i] of a box of dx x dy
    columns whose first key is lo."""
    for i in range(idx.shape[0]):
        v = idx[i]
        out[i, 0] = lo[0] + v % dx
        out[i, 1] = lo[1] + (v // dx) % dy
        out[i, 2] = lo[2] + v // (dx * dy)
