"""3D Hilbert order of the cells of a box.

Construction (our choice, see formats/packet.md): Skilling's transpose algorithm ("Programming the
Hilbert curve", 2004) over the power-of-two cube anchored at the box's minimum corner, keeping only
the cells inside the box. `hilbert_index` is that algorithm, cell by cell (the reference);
`box_order` walks the same curve recursively with a state table derived from it, skipping sub-cubes
outside the box, so its cost is proportional to the box's volume.
"""

from __future__ import annotations

from functools import lru_cache
from itertools import permutations

import numpy as np
from numba import njit


def hilbert_index(x: int, y: int, z: int, bits: int) -> int:
    """Skilling's AxestoTranspose, then the transposed bits interleaved (x first)."""
    v = [int(x), int(y), int(z)]
    m = 1 << (bits - 1) if bits > 0 else 0
    q = m
    while q > 1:
        p = q - 1
        for i in range(3):
            if v[i] & q:
                v[0] ^= p
            else:
                t = (v[0] ^ v[i]) & p
                v[0] ^= t
                v[i] ^= t
        q >>= 1
    for i in range(1, 3):
        v[i] ^= v[i - 1]
    t = 0
    q = m
    while q > 1:
        if v[2] & q:
            t ^= q - 1
        q >>= 1
    for i in range(3):
        v[i] ^= t
    h = 0
    for level in range(bits - 1, -1, -1):
        for i in range(3):
            h = (h << 1) | ((v[i] >> level) & 1)
    return h


def _signed_perms():
    for perm in permutations(range(3)):
        for flips in range(8):
            yield perm, tuple((flips >> i) & 1 for i in range(3))


def _apply(t, c):
    perm, flips = t
    return tuple(c[perm[i]] ^ flips[i] for i in range(3))


_CORNERS = [((k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1) for k in range(8)]


@lru_cache(maxsize=1)
def state_tables() -> tuple[np.ndarray, np.ndarray]:
    """(OCTANT[state, digit], NEXT[state, digit]) of the curve, derived from Skilling's index.

    A state is the symmetry of the cube that maps the canonical curve onto a sub-curve; digit h
    of a state visits octant OCTANT (x + 2y + 4z) and continues in state NEXT."""
    order1 = sorted(_CORNERS, key=lambda c: hilbert_index(*c, 1))  # canonical 2x2x2 curve
    cells2 = sorted(((x, y, z) for x in range(4) for y in range(4) for z in range(4)),
                    key=lambda c: hilbert_index(*c, 2))
    sub_maps = []
    for h in range(8):
        block = cells2[8 * h : 8 * h + 8]
        octant = tuple(v >> 1 for v in block[0])
        local = [tuple(v & 1 for v in c) for c in block]
        assert all(tuple(v >> 1 for v in c) == octant for c in block)
        assert octant == order1[h]
        t = next(t for t in _signed_perms() if [_apply(t, c) for c in order1] == local)
        sub_maps.append(t)
    # states as the images of the 8 corners (a hashable signed permutation)
    identity = tuple(_CORNERS)
    states = {identity: 0}
    queue = [identity]
    octant_rows, next_rows = [], []
    while queue:
        s = queue.pop(0)
        s_map = dict(zip(_CORNERS, s))
        oct_row, next_row = [], []
        for h in range(8):
            c = s_map[order1[h]]
            oct_row.append(c[0] + 2 * c[1] + 4 * c[2])
            t_map = dict(zip(_CORNERS, [_apply(sub_maps[h], c0) for c0 in _CORNERS]))
            child = tuple(s_map[t_map[c0]] for c0 in _CORNERS)
            if child not in states:
                states[child] = len(states)
                queue.append(child)
            next_row.append(states[child])
        octant_rows.append(oct_row)
        next_rows.append(next_row)
    return np.array(octant_rows, dtype=np.int64), np.array(next_rows, dtype=np.int64)


# The three walks below (every cell; ranks of given cells; cells of given ranks) share one
# depth-first descent: a stack row per open sub-cube (its state on the curve, the next child to
# visit, its corner), children taken in curve order by the state tables.
STATE, NEXT_CHILD, X, Y, Z = range(5)


@njit(cache=True, inline="always")
def _open_stack(bits):
    return np.zeros((bits + 1, 5), dtype=np.int64)


@njit(cache=True, inline="always")
def _next_child(stack, lvl, bits, octant):
    """(h, octant, half, x, y, z) of the next child of the sub-cube open at depth `lvl` (its
    digit on the curve, the octant it fills, its side, its corner); h = -1 when all eight were."""
    h = stack[lvl, NEXT_CHILD]
    if h == 8:
        return -1, 0, 0, 0, 0, 0
    stack[lvl, NEXT_CHILD] = h + 1
    o = octant[stack[lvl, STATE], h]
    half = 1 << (bits - lvl - 1)
    return (h, o, half, stack[lvl, X] + (o & 1) * half, stack[lvl, Y] + ((o >> 1) & 1) * half,
            stack[lvl, Z] + ((o >> 2) & 1) * half)


@njit(cache=True, inline="always")
def _open(stack, lvl, state, x, y, z):
    """Open a sub-cube at depth `lvl` (its first child next)."""
    stack[lvl, STATE] = state
    stack[lvl, NEXT_CHILD] = 0
    stack[lvl, X] = x
    stack[lvl, Y] = y
    stack[lvl, Z] = z


@njit(cache=True, nogil=True)
def _walk(dx, dy, dz, bits, octant, nxt, out):
    """Nested index x + dx * (y + dy * z) of every in-box cell, in curve order."""
    if bits == 0:
        out[0] = 0
        return 1
    stack = _open_stack(bits)
    k = 0
    lvl = 0  # stack depth; cube size at depth l is 2^(bits - l)
    while lvl >= 0:
        h, o, half, x, y, z = _next_child(stack, lvl, bits, octant)
        if h < 0:
            lvl -= 1
            continue
        if x >= dx or y >= dy or z >= dz:
            continue  # sub-cube starts outside the box (the box is anchored at 0)
        if half == 1:
            out[k] = x + dx * (y + dy * z)
            k += 1
            continue
        _open(stack, lvl + 1, nxt[stack[lvl, STATE], h], x, y, z)
        lvl += 1
    return k


def bits_for(dims) -> int:
    m = max(int(d) for d in dims)
    return max(0, int(m - 1).bit_length())


CACHE_CELLS = 1 << 20  # orders of boxes up to this size are cached (8 MiB each, 16 kept)


def box_order(dx: int, dy: int, dz: int) -> np.ndarray:
    """int64 nested indices of the box's cells in Hilbert order (small boxes cached)."""
    if dx * dy * dz <= CACHE_CELLS:
        return _cached_order(dx, dy, dz)
    return _order(dx, dy, dz)


@lru_cache(maxsize=16)
def _cached_order(dx: int, dy: int, dz: int) -> np.ndarray:
    return _order(dx, dy, dz)


box_order.cache_clear = _cached_order.cache_clear  # type: ignore[attr-defined]


def _order(dx: int, dy: int, dz: int) -> np.ndarray:
    octant, nxt = state_tables()
    out = np.empty(dx * dy * dz, dtype=np.int64)
    if out.shape[0] == 0:  # a box without cells (an empty packet, or a hostile header)
        out.setflags(write=False)
        return out
    n = _walk(dx, dy, dz, bits_for((dx, dy, dz)), octant, nxt, out)
    assert n == out.shape[0]
    out.setflags(write=False)
    return out


# Placing only the changed cells. A delta's box is mostly "unchanged" cells (kaist03 at full range:
# 1.07 G cells for 9.5 M changes), so instead of the order of every cell (8 bytes each) each given
# cell is found by one descent from the cube to the cell: its rank is the in-box volume of the
# sub-cubes the curve visits before it, summed level by level. `cells_at` is its inverse (ranks to
# cells), for decoding.


@lru_cache(maxsize=1)
def digit_table() -> np.ndarray:
    """DIGIT[state, octant]: the digit on the curve at which a state visits an octant (the
    inverse of OCTANT in state_tables)."""
    octant, _ = state_tables()
    digit = np.empty_like(octant)
    for s in range(octant.shape[0]):
        digit[s, octant[s]] = np.arange(8)
    return digit


@njit(cache=True, nogil=True)
def _ranks(rel, dx, dy, dz, bits, octant, digit, nxt, out):
    """out[i]: the rank on the box's curve of cell rel[i] (inside the box anchored at 0).

    Below a sub-cube that lies wholly in the box, every sibling before the cell's is whole too:
    the rank grows by digit * volume, one table step a level. Only sub-cubes across the box's far
    faces need their earlier siblings' in-box volumes added one by one. Cells in Morton order
    (as a packet's are) share their leading levels with the cell before: the descent is taken
    again from the first level where the two differ."""
    # per level of the last descent: state, corner and rank on entering it, and whether it is whole
    path = np.zeros((bits + 1, 6), dtype=np.int64)
    px = py = pz = -1
    for i in range(rel.shape[0]):
        x, y, z = rel[i, 0], rel[i, 1], rel[i, 2]
        start = 0
        if i > 0:
            d = (x ^ px) | (y ^ py) | (z ^ pz)
            if d == 0:
                out[i] = out[i - 1]
                continue
            top = 0
            while d >> (top + 1):
                top += 1
            start = bits - 1 - top
        px, py, pz = x, y, z
        state, cx, cy, cz, rank, whole = path[start, 0], path[start, 1], path[start, 2], path[start, 3], \
            path[start, 4], path[start, 5] != 0
        for lvl in range(start, bits):
            shift = bits - lvl - 1
            half = np.int64(1) << shift
            o = ((x >> shift) & 1) | (((y >> shift) & 1) << 1) | (((z >> shift) & 1) << 2)
            h = digit[state, o]
            if not whole:
                whole = cx + 2 * half <= dx and cy + 2 * half <= dy and cz + 2 * half <= dz
            if whole:
                rank += h * half * half * half
            else:
                for hh in range(h):
                    oo = octant[state, hh]
                    sx = cx + (oo & 1) * half
                    sy = cy + ((oo >> 1) & 1) * half
                    sz = cz + ((oo >> 2) & 1) * half
                    if sx < dx and sy < dy and sz < dz:
                        rank += min(half, dx - sx) * min(half, dy - sy) * min(half, dz - sz)
            cx += (o & 1) * half
            cy += ((o >> 1) & 1) * half
            cz += ((o >> 2) & 1) * half
            state = nxt[state, h]
            path[lvl + 1, 0], path[lvl + 1, 1], path[lvl + 1, 2], path[lvl + 1, 3] = state, cx, cy, cz
            path[lvl + 1, 4], path[lvl + 1, 5] = rank, whole
        out[i] = rank


@njit(cache=True, nogil=True)
def _cells(ranks, dx, dy, dz, bits, octant, nxt, lo, out):
    """out[i] = lo + (x, y, z) of the cell at rank ranks[i] on the box's curve (ranks sorted,
    unique, below the box's cell count); `out` may be of any integer type that holds them."""
    n = ranks.shape[0]
    if bits == 0:
        for i in range(n):
            out[i, 0] = lo[0]
            out[i, 1] = lo[1]
            out[i, 2] = lo[2]
        return
    stack = _open_stack(bits)
    # the path to the last cell read inside a whole cube: the state and corner before each of
    # its digits. Sorted ranks close together share their leading digits, so the next cell's
    # path is taken again from the first digit that differs, not from the cube's top.
    path = np.zeros((bits + 1, 4), dtype=np.int64)
    rank = 0
    p = 0
    lvl = 0
    while lvl >= 0 and p < n:
        h, o, half, x, y, z = _next_child(stack, lvl, bits, octant)
        if h < 0:
            lvl -= 1
            continue
        if x >= dx or y >= dy or z >= dz:
            continue
        volume = min(half, dx - x) * min(half, dy - y) * min(half, dz - z)
        if ranks[p] >= rank + volume:
            rank += volume  # the next wanted rank lies beyond this sub-cube
            continue
        child = nxt[stack[lvl, STATE], h]
        if volume == half * half * half:
            # a whole cube inside the box: its cells follow the curve without gaps, so each wanted
            # rank in it is read digit by digit (3 bits of the rank, a table step each), no
            # sibling visited
            digits = 0
            while (1 << digits) < half:
                digits += 1
            path[0, 0], path[0, 1], path[0, 2], path[0, 3] = child, x, y, z
            before = -1
            while p < n and ranks[p] < rank + volume:
                r = ranks[p] - rank
                first = 0  # the first digit to take: the highest one that differs from the last cell's
                if before >= 0:
                    d = (r ^ before) >> 3
                    first = digits - 1
                    while d != 0:
                        d >>= 3
                        first -= 1
                for j in range(first, digits):
                    shift = digits - 1 - j
                    digit = (r >> (3 * shift)) & 7
                    state = path[j, 0]
                    oo = octant[state, digit]
                    path[j + 1, 0] = nxt[state, digit]
                    path[j + 1, 1] = path[j, 1] + ((oo & 1) << shift)
                    path[j + 1, 2] = path[j, 2] + (((oo >> 1) & 1) << shift)
                    path[j + 1, 3] = path[j, 3] + (((oo >> 2) & 1) << shift)
                out[p, 0] = lo[0] + path[digits, 1]
                out[p, 1] = lo[1] + path[digits, 2]
                out[p, 2] = lo[2] + path[digits, 3]
                before = r
                p += 1
            rank += volume
            continue
        _open(stack, lvl + 1, child, x, y, z)
        lvl += 1


def ranks_of(rel: np.ndarray, dims) -> np.ndarray:
    """The curve ranks (int64) of cells given as (N, 3) coordinates inside a box anchored at 0."""
    dx, dy, dz = (int(d) for d in dims)
    # one array type whatever the count (a one-row slice would type as another layout, another kernel)
    rel = np.ascontiguousarray(rel, dtype=np.int64).reshape(-1, 3)
    ranks = np.empty(rel.shape[0], dtype=np.int64)
    octant, nxt = state_tables()
    _ranks(rel, dx, dy, dz, bits_for((dx, dy, dz)), octant, digit_table(), nxt, ranks)
    return ranks


def cells_at(ranks: np.ndarray, dims, lo=(0, 0, 0), dtype=np.int64) -> np.ndarray:
    """(N, 3) coordinates of the cells at these curve ranks (sorted ascending, unique), plus `lo`:
    a packet's keys (uint16) where lo is its box's first key."""
    dx, dy, dz = (int(d) for d in dims)
    out = np.empty((ranks.shape[0], 3), dtype=dtype)
    octant, nxt = state_tables()
    _cells(np.asarray(ranks, dtype=np.int64), dx, dy, dz, bits_for((dx, dy, dz)), octant, nxt,
           np.asarray(lo, dtype=np.int64), out)
    return out
