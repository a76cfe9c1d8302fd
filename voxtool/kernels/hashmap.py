"""Kernels of the `hashmap` backend (seed: voxel-mapping-hash-map-sharing.md, Alg. 1-3).

A voxel is one 64-byte record (the paper's voxel object; its "pointers" are record numbers),
so everything an update reads or writes about a voxel lies in one cache line. An
open-addressing table of (Morton code, record) pairs, also one line per probe, finds records.
The history buffer is a doubly linked list through the records' prev / next fields.
States: 0 free, 1 occupied, 2 unknown; state -1 marks an unused record.
"""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit, prange

from voxtool.kernels.morton import compact16, morton3
from voxtool.kernels.prefetch import prefetch
from voxtool.kernels.raycast import _coord_key, ray_setup

RECORD = np.dtype({
    "names": ["code", "last", "prev", "next", "l", "inf", "radius", "hits", "misses", "state", "in_occ", "ilist"],
    "formats": ["<i8", "<i8", "<i8", "<i8", "<f4", "<i4", "<i4", "<i4", "<i4", "i1", "u1", "<i8"],
    "offsets": [0, 8, 16, 24, 32, 36, 40, 44, 48, 52, 53, 56],
    "itemsize": 64,
})
EMPTY = -1
TOMB = -2
NOT_IN_HISTORY = -2
AHEAD = 8  # look-ups a software pipeline requests ahead of use
MAX_RECORDS = (1 << 31) - 1  # table slots hold int32 record numbers (128 GiB of records)
# meta fields: history head / tail / size, free-list top, live records, tombstones, next unused
# record, records with inflation count > 0, bricks and brick tombstones of the brick table
M_HEAD, M_TAIL, M_HSIZE, M_FREE_TOP, M_LIVE, M_TOMBS, M_NEXT, M_NINF, M_BRICKS, M_BTOMBS = range(10)
META_FIELDS = 10
_MULT = np.int64(-7046029254386353131)
if "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    # OpenMP first for trace_parts (its workers busy-wait between scans, so the next scan's
    # cast starts at once); numba's default tries TBB first and warns on stderr when the TBB it
    # finds is older than it supports (open3d loads one)
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]


def new_records(n: int) -> np.ndarray:
    """Room for n records, aligned to 64 bytes so that each record is one cache line. Records
    from meta[M_NEXT] on are never read before _new_record fills them, so none is initialised
    here (growing a large map stays cheap)."""
    raw = np.empty(n * RECORD.itemsize + 64, dtype=np.uint8)
    skip = (-raw.ctypes.data) % 64
    return raw[skip: skip + n * RECORD.itemsize].view(RECORD)


def new_lists(size: int) -> tuple[np.ndarray, np.ndarray]:
    """The pool of inflation look-up tables (int32 record numbers, `size` of them) and its meta:
    [0] first unused int, [1 + radius] head of the free blocks of that radius (-1: none)."""
    imeta = np.full(66, -1, dtype=np.int64)
    imeta[0] = 0
    return np.zeros(size, dtype=np.int32), imeta


def new_table(size: int) -> np.ndarray:
    """An empty hash table of `size` (a power of two) slots, each a record number (EMPTY, TOMB).
    The code to compare lies in the record, which a successful look-up reads anyway: 4 bytes a
    slot instead of a (code, record) pair keeps the table a quarter of the size."""
    return np.full(size, EMPTY, dtype=np.int32)


@njit(cache=True, inline="always")
def _slot(code, mask):
    return ((code * _MULT) >> 20) & mask


@njit(cache=True)
def find(tab, R, code):
    """Record of voxel `code`, or -1."""
    mask = tab.shape[0] - 1
    s = _slot(code, mask)
    while True:
        r = tab[s]
        if r == EMPTY:
            return -1
        if r >= 0 and R[r].code == code:
            return r
        s = (s + 1) & mask


@njit(cache=True)
def _insert(tab, rec, code, meta):
    mask = tab.shape[0] - 1
    s = _slot(code, mask)
    while tab[s] >= 0:
        s = (s + 1) & mask
    if tab[s] == TOMB:
        meta[M_TOMBS] -= 1
    tab[s] = rec


@njit(cache=True)
def _erase(tab, rec, code, meta):
    mask = tab.shape[0] - 1
    s = _slot(code, mask)
    while tab[s] != rec:
        s = (s + 1) & mask
    tab[s] = TOMB
    meta[M_TOMBS] += 1


@njit(cache=True)
def _new_record(code, R, free, meta, tab):
    if meta[M_FREE_TOP] > 0:
        meta[M_FREE_TOP] -= 1
        r = free[meta[M_FREE_TOP]]
    else:
        r = meta[M_NEXT]
        meta[M_NEXT] += 1
    v = R[r]
    v.code = code
    v.last = 0
    v.prev = NOT_IN_HISTORY
    v.next = NOT_IN_HISTORY
    v.l = 0.0
    v.inf = 0
    v.radius = -1
    v.hits = 0
    v.misses = 0
    v.state = 2
    v.in_occ = 0
    v.ilist = -1
    meta[M_LIVE] += 1
    _insert(tab, r, code, meta)
    return r


@njit(cache=True)
def _drop_record(r, R, free, meta, tab):
    R[r].state = -1
    _erase(tab, r, R[r].code, meta)
    free[meta[M_FREE_TOP]] = r
    meta[M_FREE_TOP] += 1
    meta[M_LIVE] -= 1


# The occupancy map's voxels as bricks of 8x8x8: an open-addressing table of brick ids with a
# 512-bit mask each (which of the brick's voxels the occupancy map holds), kept exact as voxels
# enter and leave. Rays consult it once per brick crossed and test a bit per step inside an
# occupied brick, so misses that fall in empty space cost no voxel look-up.


def new_bricks(size: int) -> tuple[np.ndarray, np.ndarray]:
    """An empty brick table of `size` (a power of two) slots: ids and 512-bit masks."""
    return np.full(size, EMPTY, dtype=np.int64), np.zeros((size, 8), dtype=np.int64)


@njit(cache=True, inline="always")
def _brick_id(kx, ky, kz):
    return ((kx >> 3) << 26) | ((ky >> 3) << 13) | (kz >> 3)


@njit(cache=True, inline="always")
def _in_brick(kx, ky, kz):
    return (kx & 7) | ((ky & 7) << 3) | ((kz & 7) << 6)


@njit(cache=True, inline="always")
def _brick_home(b, mask):
    return ((b * _MULT) >> 24) & mask


@njit(cache=True, inline="always")
def brick_find(bkeys, b):
    """Slot of brick id b, or -1."""
    mask = bkeys.shape[0] - 1
    s = _brick_home(b, mask)
    while True:
        k = bkeys[s]
        if k == b:
            return s
        if k == EMPTY:
            return -1
        s = (s + 1) & mask


@njit(cache=True)
def _mark_present(code, bkeys, bmask, meta):
    """The occupancy map now holds voxel `code`."""
    kx, ky, kz = compact16(code), compact16(code >> 1), compact16(code >> 2)
    b = _brick_id(kx, ky, kz)
    s = brick_find(bkeys, b)
    if s < 0:
        mask = bkeys.shape[0] - 1
        s = _brick_home(b, mask)
        while bkeys[s] != EMPTY and bkeys[s] != TOMB:
            s = (s + 1) & mask
        if bkeys[s] == TOMB:
            meta[M_BTOMBS] -= 1
        bkeys[s] = b
        bmask[s, :] = 0
        meta[M_BRICKS] += 1
    v = _in_brick(kx, ky, kz)
    bmask[s, v >> 6] |= np.int64(1) << (v & 63)


@njit(cache=True)
def _clear_present(code, bkeys, bmask, meta):
    """Voxel `code` left the occupancy map; a brick left empty leaves the table."""
    kx, ky, kz = compact16(code), compact16(code >> 1), compact16(code >> 2)
    s = brick_find(bkeys, _brick_id(kx, ky, kz))
    v = _in_brick(kx, ky, kz)
    bmask[s, v >> 6] &= ~(np.int64(1) << (v & 63))
    for w in range(8):
        if bmask[s, w] != 0:
            return
    bkeys[s] = TOMB
    meta[M_BRICKS] -= 1
    meta[M_BTOMBS] += 1


@njit(cache=True)
def brick_rehash(old_keys, old_mask, bkeys, bmask):
    """Move the live bricks of one table into an empty, larger one (drops tombstones)."""
    mask = bkeys.shape[0] - 1
    for i in range(old_keys.shape[0]):
        b = old_keys[i]
        if b >= 0:
            s = _brick_home(b, mask)
            while bkeys[s] != EMPTY:
                s = (s + 1) & mask
            bkeys[s] = b
            bmask[s, :] = old_mask[i, :]


@njit(cache=True, inline="always")
def _set_add(seen, slots, n, update):
    """Add `update` (code << 1 | hit) to the open-addressing set `seen` (a hit wins over a
    miss); `slots` lists the used slots in insertion order. Returns the new count."""
    mask = seen.shape[0] - 1
    code = update >> 1
    s = ((code * _MULT) >> 24) & mask
    while True:
        v = seen[s]
        if v == EMPTY:
            seen[s] = update
            slots[n] = s
            return n + 1
        if v >> 1 == code:
            seen[s] = v | (update & 1)
            return n
        s = (s + 1) & mask


@njit(cache=True, nogil=True)
def discretize(points, resolution, seen, slots, out):
    """OctoMap's computeDiscreteUpdate: one point per distinct end voxel, the voxel's centre
    (keyToCoord: float32 of (key - 32768 + 0.5) x resolution), in first-occurrence order, into
    `out` (room for every point). `seen` (all EMPTY, left so) needs room for 2 x points.
    Returns the count."""
    res_factor = 1.0 / resolution
    n = 0
    for i in range(points.shape[0]):
        kx = _coord_key(points[i, 0], res_factor)
        ky = _coord_key(points[i, 1], res_factor)
        kz = _coord_key(points[i, 2], res_factor)
        m = _set_add(seen, slots, n, morton3(kx, ky, kz) << 1)
        if m > n:
            out[n, 0] = np.float32((np.float64(kx - 32768) + 0.5) * resolution)
            out[n, 1] = np.float32((np.float64(ky - 32768) + 0.5) * resolution)
            out[n, 2] = np.float32((np.float64(kz - 32768) + 0.5) * resolution)
            n = m
    for j in range(n):
        seen[slots[j]] = EMPTY
    return n


@njit(cache=True, nogil=True)
def trace_present(points, origin, resolution, max_range, bkeys, bmask, seen, slots, out):
    """One scan's rays with OctoMap's DDA and max-range rule (the same keys as
    kernels.raycast.scan_bricks), keeping what the hash map can use: the endpoint voxels (hits),
    and the voxels rays pass through that the occupancy map holds (misses; a miss elsewhere
    changes nothing: known-free space is not stored). A ray crossing an 8x8x8 brick that holds
    no map voxel only steps the DDA. The DDA is written out in scalars, as in scan_bricks,
    rather than through raycast's array-based _ray_* helpers: those measured slower here.

    Each voxel once, a hit winning over a miss, in `out` as code << 1 | hit, sorted; `seen`
    (all EMPTY, left so) is the de-duplicating set, `slots` its scratch. Returns (n, steps);
    n = -1 when the set would pass half full (the caller grows it and calls again)."""
    res_factor = 1.0 / resolution
    okx = _coord_key(origin[0], res_factor)
    oky = _coord_key(origin[1], res_factor)
    okz = _coord_key(origin[2], res_factor)
    limit = seen.shape[0] // 2
    n = 0
    steps = 0
    for i in range(points.shape[0]):
        if n >= limit:
            break
        cut, ekx, eky, ekz, tx, ty, tz, ux, uy, uz, sx, sy, sz, length64 = ray_setup(
            points, i, origin, okx, oky, okz, resolution, max_range)
        if not cut:
            n = _set_add(seen, slots, n, (morton3(ekx, eky, ekz) << 1) | 1)
        if ekx == okx and eky == oky and ekz == okz:
            continue
        # the key that starts a new brick when stepping along each axis
        bx = 0 if sx > 0 else 7
        by = 0 if sy > 0 else 7
        bz = 0 if sz > 0 else 7
        kx, ky, kz = okx, oky, okz
        # every step moves one axis one voxel towards the end key, so the ray can reach it only
        # after exactly this many steps (an axis that overshoots never comes back)
        to_end = abs(ekx - okx) + abs(eky - oky) + abs(ekz - okz)
        bs = brick_find(bkeys, _brick_id(kx, ky, kz))
        while True:
            if bs >= 0:
                v = _in_brick(kx, ky, kz)
                if (bmask[bs, v >> 6] >> (v & 63)) & 1 == 1 and n < limit:
                    n = _set_add(seen, slots, n, morton3(kx, ky, kz) << 1)
            steps += 1
            if tx < ty:
                if tx < tz:
                    kx += sx
                    tx += ux
                    crossed = (kx & 7) == bx
                else:
                    kz += sz
                    tz += uz
                    crossed = (kz & 7) == bz
            else:
                if ty < tz:
                    ky += sy
                    ty += uy
                    crossed = (ky & 7) == by
                else:
                    kz += sz
                    tz += uz
                    crossed = (kz & 7) == bz
            to_end -= 1
            if to_end == 0 and kx == ekx and ky == eky and kz == ekz:
                break
            if min(tx, min(ty, tz)) > length64:
                break
            if crossed:
                bs = brick_find(bkeys, _brick_id(kx, ky, kz))
    for j in range(n):
        out[j] = seen[slots[j]]
        seen[slots[j]] = EMPTY
    if n >= limit:
        return -1, steps
    out[:n].sort()  # here, on the tracing thread: numba sorts these small arrays ~4x faster than numpy
    return n, steps


@njit(cache=True, parallel=True, nogil=True)
def trace_parts(points, cuts, origin, resolution, max_range, bkeys, bmask, seen, slots, out, counts, merged, spare):
    """trace_present over the runs points[cuts[w]:cuts[w + 1]] on one thread each (row w of
    seen, slots, out and counts is run w's; counts[w] = (n, steps)), then the sorted lists
    merged into `merged` (`spare`: scratch of its size). One numba parallel region rather than a
    Python thread pool: waking the pool's worker and then this thread on its result took ~0.13 ms
    a scan, and OpenMP's workers, still busy-waiting from the last scan, start at once
    (docs/backends.md). Returns the merged count, or -1 when a run's set would pass half full."""
    parts = cuts.shape[0] - 1
    for w in prange(parts):
        n, steps = trace_present(points[cuts[w]:cuts[w + 1]], origin, resolution, max_range, bkeys, bmask, seen[w],
                                 slots[w], out[w])
        counts[w, 0] = n
        counts[w, 1] = steps
    return merge_runs(out, counts, merged, spare)


@njit(cache=True, nogil=True)
def merge_runs(out, counts, merged, spare):
    """trace_parts' runs (out[w, :counts[w, 0]]) merged into `merged` pair by pair, round by
    round (`spare` the other side of each round): log2(runs) passes over the updates where
    merging run after run took one a run (16 runs: 16 passes). -1 if a run overflowed. Apart
    from the parallel kernel: there numba's array analysis asserted wrongly on this loop."""
    parts = counts.shape[0]
    for w in range(parts):
        if counts[w, 0] < 0:
            return -1
    m = (parts + 1) // 2  # segments after the first round, out's rows into merged
    starts = np.empty(m, np.int64)
    lens = np.empty(m, np.int64)
    off = 0
    for i in range(m):
        a = out[2 * i, :counts[2 * i, 0]]
        b = out[2 * i + 1, :counts[2 * i + 1, 0]] if 2 * i + 1 < parts else out[2 * i, :0]
        starts[i] = off
        lens[i] = merge_updates(a, b, merged[off:])
        off += a.shape[0] + b.shape[0]  # room for both: duplicates across runs only shrink it
    src, dst = merged, spare
    in_merged = True
    while m > 1:
        k = (m + 1) // 2
        off = 0
        for i in range(k):  # starts[i] is written after starts[2i] and starts[2i + 1] were read
            s0, n0 = starts[2 * i], lens[2 * i]
            s1, n1 = (starts[2 * i + 1], lens[2 * i + 1]) if 2 * i + 1 < m else (s0, 0)
            starts[i] = off
            lens[i] = merge_updates(src[s0:s0 + n0], src[s1:s1 + n1], dst[off:])
            off += n0 + n1
        m = k
        src, dst = dst, src
        in_merged = not in_merged
    n = lens[0]
    if not in_merged:  # the last round wrote spare (its first segment starts at 0)
        merged[:n] = spare[:n]
    return n


@njit(cache=True, nogil=True)
def merge_updates(a, b, out):
    """Merge two Morton-sorted update lists (code << 1 | hit, each code once per list) into
    `out`: each code once, the hit if either list hit it. Returns the count."""
    i = j = n = 0
    while i < a.shape[0] or j < b.shape[0]:
        if j == b.shape[0] or (i < a.shape[0] and a[i] >> 1 < b[j] >> 1):
            out[n] = a[i]
            i += 1
        elif i == a.shape[0] or b[j] >> 1 < a[i] >> 1:
            out[n] = b[j]
            j += 1
        else:
            out[n] = a[i] | b[j]
            i += 1
            j += 1
        n += 1
    return n


@njit(cache=True, nogil=True)
def count_hits(packed):
    """(hits, distinct bricks they fall in) of Morton-sorted updates: the room input_update may
    need (a brick's voxels are adjacent in Morton order)."""
    hits = bricks = 0
    last = np.int64(-1)
    for i in range(packed.shape[0]):
        if packed[i] & 1 == 1:
            hits += 1
            b = packed[i] >> 10
            if b != last:
                bricks += 1
                last = b
    return hits, bricks


@njit(cache=True, nogil=True)
def input_update(packed, stamp, l_init, l_hit, l_miss, l_min, l_max, l_occ, l_free, R, free, meta, tab,
                 bkeys, bmask, out_touched, out_changed):
    """Alg. 1 + occupancy check over Morton-sorted (code << 1 | hit) updates. Hits create voxels
    (prior l_init); misses update only voxels the occupancy map holds (known-free space is never
    stored).
    Returns (n touched, n occ-changed)."""
    nt = 0
    nc = 0
    # software pipeline (see _inflate_sphere): the home slot of update i + 2 * AHEAD and the
    # record in the slot of update i + AHEAD are on their way while update i is applied
    mask = tab.shape[0] - 1
    n = packed.shape[0]
    for i in range(min(2 * AHEAD, n)):
        prefetch(tab, _slot(packed[i] >> 1, mask))
    for i in range(n):
        if i + 2 * AHEAD < n:
            prefetch(tab, _slot(packed[i + 2 * AHEAD] >> 1, mask))
        if i + AHEAD < n:
            t = tab[_slot(packed[i + AHEAD] >> 1, mask)]
            if t >= 0:
                prefetch(R, t)
        code = packed[i] >> 1
        hit = (packed[i] & 1) == 1
        r = find(tab, R, code)
        is_new = False
        if hit:
            if r < 0:
                r = _new_record(code, R, free, meta, tab)
            v = R[r]
            if v.in_occ == 0:
                # entering the occupancy map (new, or until now only inflated): misses apply from now on
                _mark_present(code, bkeys, bmask, meta)
                v.in_occ = 1
                v.l = l_init
                v.state = 2
                is_new = True
            x = v.l + l_hit
            v.hits += 1
        else:
            if r < 0 or R[r].in_occ == 0:
                continue
            v = R[r]
            x = v.l + l_miss
            v.misses += 1
        if x < l_min:
            x = l_min
        elif x > l_max:
            x = l_max
        v.l = x
        was_occ = v.state == 1 and not is_new
        v.state = 1 if x > l_occ else (0 if x < l_free else 2)
        v.last = stamp
        out_touched[nt] = r
        nt += 1
        if was_occ != (v.state == 1):
            out_changed[nc] = r
            nc += 1
    return nt, nc


@njit(cache=True, inline="always")
def _sphere_code(x, y, z, offsets, j):
    """Morton code of voxel (x, y, z) + offsets[j], or -1 outside the key range."""
    nx = x + offsets[j, 0]
    ny = y + offsets[j, 1]
    nz = z + offsets[j, 2]
    if nx < 0 or ny < 0 or nz < 0 or nx > 65535 or ny > 65535 or nz > 65535:
        return np.int64(-1)
    return morton3(nx, ny, nz)


@njit(cache=True, inline="always")
def _list_alloc(size, ipool, imeta, radius):
    """A block of 1 + size ints of the look-up pool (room is reserved by the caller); freed
    blocks of the same radius are reused first (imeta[1 + radius] heads their free list)."""
    b = imeta[1 + radius]
    if b >= 0:
        imeta[1 + radius] = ipool[b]
        return b
    b = imeta[0]
    imeta[0] += 1 + size
    return b


@njit(cache=True, inline="always")
def _sphere_codes(r, radius, offsets, offset_start, R, codes):
    """The Morton codes of the voxels within `radius` voxels of record r's voxel (inside the key
    range) into `codes`; returns their count."""
    code = R[r].code
    x = compact16(code)
    y = compact16(code >> 1)
    z = compact16(code >> 2)
    m = 0
    for j in range(offset_start[radius], offset_start[radius + 1]):
        c = _sphere_code(x, y, z, offsets, j)
        if c >= 0:
            codes[m] = c
            m += 1
    return m


@njit(cache=True, inline="always")
def _inflate_cells(r, radius, codes, m, offset_start, R, free, meta, tab, ipool, imeta):
    """Add 1 to the inflation count of the m voxels `codes`, r's sphere of `radius` (creating
    inflated-only records as needed), and keep their record numbers: r's look-up table of what
    it inflated (the paper's T_inf), so that removal needs no hash look-up."""
    block = _list_alloc(offset_start[radius + 1] - offset_start[radius], ipool, imeta, radius)
    for j in range(m):
        c = codes[j]
        t = find(tab, R, c)
        if t < 0:
            t = _new_record(c, R, free, meta, tab)
        v = R[t]
        if v.inf == 0:
            meta[M_NINF] += 1
        v.inf += 1
        ipool[block + 1 + j] = t
    ipool[block] = m
    R[r].ilist = block


@njit(cache=True)
def _inflate_sphere(r, radius, offsets, offset_start, R, free, meta, tab, ipool, imeta, codes):
    """Inflate the sphere of `radius` round r (_inflate_cells), one voxel at a time (a snapshot's
    load; a scan's update pipelines several voxels: inflate()).

    Memory latency bounds this loop (random table slots and records), so it first requests
    the sphere's home slots, then the records they name, with prefetches: the cache misses
    overlap instead of following one another, and the look-ups that follow hit the cache.
    `codes` is scratch room for the sphere's Morton codes (one per row of `offsets`)."""
    m = _sphere_codes(r, radius, offsets, offset_start, R, codes)
    mask = tab.shape[0] - 1
    for j in range(m):
        prefetch(tab, _slot(codes[j], mask))
    for j in range(m):
        t = tab[_slot(codes[j], mask)]
        if t >= 0:
            prefetch(R, t)
    _inflate_cells(r, radius, codes, m, offset_start, R, free, meta, tab, ipool, imeta)


@njit(cache=True)
def _deflate(r, R, free, meta, tab, ipool, imeta):
    """Undo r's inflation through its look-up table (_deflate_cells), its records requested
    first (see _inflate_sphere)."""
    block = R[r].ilist
    for j in range(1, ipool[block] + 1):
        prefetch(R, ipool[block + j])
    _deflate_cells(r, R, free, meta, tab, ipool, imeta)


@njit(cache=True, inline="always")
def _deflate_cells(r, R, free, meta, tab, ipool, imeta):
    """Undo r's inflation through its look-up table; inflated-only voxels left uninflated go."""
    block = R[r].ilist
    n = ipool[block]
    for j in range(1, n + 1):
        t = ipool[block + j]
        v = R[t]
        v.inf -= 1
        if v.inf == 0:
            meta[M_NINF] -= 1
            if v.in_occ == 0:
                _drop_record(t, R, free, meta, tab)
    radius = R[r].radius
    ipool[block] = imeta[1 + radius]
    imeta[1 + radius] = block
    R[r].ilist = -1


@njit(cache=True, nogil=True)
def inflate(changed, n_changed, sx, sy, sz, inf_range, resolution, radius_now, offsets, offset_start,
            R, free, meta, tab, ipool, imeta):
    """Alg. 2: occupancy-changed voxels within inf_range of the sensor (re)inflate: a voxel that
    became occupied inflates the sphere of the current radius (remembered per voxel), one that
    stopped being occupied removes exactly the sphere it added. Returns voxels processed.

    A software pipeline over those voxels (see _inflate_sphere): while voxel i is applied, the
    records in the sphere's table slots of voxel i + 1 and the slots of voxel i + 2 are on their
    way (a deflating voxel: its look-up table, then the records it names). Requests only: what
    is applied, and in which order, is what applying one voxel after another does."""
    # which voxels change their inflation, and which way: record + 1 inflates, -(record + 1)
    # deflates. Decided before any is applied: they are all in the occupancy map, so applying
    # one never drops or changes another's record.
    work = np.empty(n_changed, np.int64)
    k = 0
    for i in range(n_changed):
        r = changed[i]
        state = R[r].state
        if state < 0:
            continue
        code = R[r].code
        px = (np.float64(compact16(code)) - 32768 + 0.5) * resolution - sx
        py = (np.float64(compact16(code >> 1)) - 32768 + 0.5) * resolution - sy
        pz = (np.float64(compact16(code >> 2)) - 32768 + 0.5) * resolution - sz
        if inf_range >= 0 and px * px + py * py + pz * pz > inf_range * inf_range:
            continue
        radius = R[r].radius
        if state == 1 and radius < 0:
            work[k] = r + 1
            k += 1
        elif state != 1 and radius >= 0:
            work[k] = -(r + 1)
            k += 1
    size = offset_start[radius_now + 1] - offset_start[radius_now]
    codes = np.empty((3, size), np.int64)  # the sphere codes of the voxels in flight, row i % 3
    counts = np.zeros(3, np.int64)
    mask = tab.shape[0] - 1
    for i in range(-2, k):
        if i + 2 < k:  # two ahead: the table slots
            w = work[i + 2]
            if w > 0:
                row = (i + 2) % 3
                counts[row] = _sphere_codes(w - 1, radius_now, offsets, offset_start, R, codes[row])
                for j in range(counts[row]):
                    prefetch(tab, _slot(codes[row, j], mask))
            else:
                prefetch(ipool, R[-w - 1].ilist)
        if 0 <= i + 1 < k:  # one ahead: the records
            w = work[i + 1]
            if w > 0:
                row = (i + 1) % 3
                for j in range(counts[row]):
                    t = tab[_slot(codes[row, j], mask)]
                    if t >= 0:
                        prefetch(R, t)
            else:
                block = R[-w - 1].ilist
                for j in range(1, ipool[block] + 1):
                    prefetch(R, ipool[block + j])
        if i >= 0:
            w = work[i]
            if w > 0:
                R[w - 1].radius = radius_now
                _inflate_cells(w - 1, radius_now, codes[i % 3], counts[i % 3], offset_start, R, free, meta, tab,
                               ipool, imeta)
            else:
                _deflate_cells(-w - 1, R, free, meta, tab, ipool, imeta)  # its records requested one voxel ago
                R[-w - 1].radius = -1
    return k


@njit(cache=True)
def _unlink(r, R, meta):
    p, n = R[r].prev, R[r].next
    if p >= 0:
        R[p].next = n
    else:
        meta[M_HEAD] = n
    if n >= 0:
        R[n].prev = p
    else:
        meta[M_TAIL] = p
    R[r].prev = NOT_IN_HISTORY
    R[r].next = NOT_IN_HISTORY
    meta[M_HSIZE] -= 1


@njit(cache=True)
def _push_back(r, R, meta):
    tail = meta[M_TAIL]
    R[r].prev = tail
    R[r].next = -1
    if tail >= 0:
        R[tail].next = r
    else:
        meta[M_HEAD] = r
    meta[M_TAIL] = r
    meta[M_HSIZE] += 1


@njit(cache=True)
def _remove_from_map(r, R, free, meta, tab, bkeys, bmask, ipool, imeta, out_codes, out_values, listed):
    """Take r out of the occupancy map, listing it (code, log-odds before it left) at out_*[listed];
    its inflation goes with it (exact, whatever the range). Returns the new count listed."""
    out_codes[listed] = R[r].code
    out_values[listed] = R[r].l
    if R[r].radius >= 0:
        _deflate(r, R, free, meta, tab, ipool, imeta)
        R[r].radius = -1
    if R[r].prev != NOT_IN_HISTORY:
        _unlink(r, R, meta)
    R[r].in_occ = 0
    _clear_present(R[r].code, bkeys, bmask, meta)
    if R[r].inf == 0:
        _drop_record(r, R, free, meta, tab)
    else:
        R[r].state = 2  # stays only as an inflated voxel of the inflation map
    return listed + 1


@njit(cache=True, nogil=True)
def manage(touched, n_touched, n_lim, oldest_allowed, R, free, meta, tab, bkeys, bmask, ipool, imeta,
           out_codes, out_values):
    """Alg. 3: touched occupied voxels move to the back of the history, known-free ones leave the
    map, then the oldest leave until at most n_lim remain (and those older than the TTL).
    Every voxel that leaves the occupancy map is listed in out_codes / out_values (its log-odds
    before it left; room for n_touched + history size). Returns how many are listed."""
    for i in range(n_touched):  # request the history neighbours first (see _inflate_sphere)
        r = touched[i]
        p, n = R[r].prev, R[r].next
        if p >= 0:
            prefetch(R, p)
        if n >= 0:
            prefetch(R, n)
    listed = 0
    for i in range(n_touched):
        r = touched[i]
        if R[r].state < 0 or R[r].in_occ == 0:
            continue
        if R[r].prev != NOT_IN_HISTORY:
            _unlink(r, R, meta)
        if R[r].state == 1:
            _push_back(r, R, meta)
        elif R[r].state == 0:
            listed = _remove_from_map(r, R, free, meta, tab, bkeys, bmask, ipool, imeta, out_codes, out_values, listed)
    mask = tab.shape[0] - 1
    while meta[M_HSIZE] > 0 and (meta[M_HSIZE] > n_lim or R[meta[M_HEAD]].last < oldest_allowed):
        r = meta[M_HEAD]
        # the oldest voxels are cold: while this one leaves, the next one's look-up list and
        # table slot, and the record after it, are on their way (a linked list: one step ahead)
        nxt = R[r].next
        if nxt >= 0:
            if R[nxt].ilist >= 0:
                prefetch(ipool, R[nxt].ilist)
            prefetch(tab, _slot(R[nxt].code, mask))
            if R[nxt].next >= 0:
                prefetch(R, R[nxt].next)
        listed = _remove_from_map(r, R, free, meta, tab, bkeys, bmask, ipool, imeta, out_codes, out_values, listed)
    return listed


@njit(cache=True)
def lookup(tab, R, codes, out):
    """Log-odds of each voxel the occupancy map holds, NaN elsewhere."""
    for i in range(codes.shape[0]):
        r = find(tab, R, codes[i])
        out[i] = R[r].l if r >= 0 and R[r].in_occ == 1 else np.nan


@njit(cache=True)
def rehash(tab, R, n_records):
    """Rebuild the table from the live records (drops tombstones)."""
    tab[:] = EMPTY
    mask = tab.shape[0] - 1
    for r in range(n_records):
        if R[r].state >= 0:
            s = _slot(R[r].code, mask)
            while tab[s] != EMPTY:
                s = (s + 1) & mask
            tab[s] = r


@njit(cache=True)
def load_records(codes, values, l_occ, l_free, R, free, meta, tab, bkeys, bmask):
    """Snapshot load: every stored voxel back into the occupancy map (inflation is rebuilt as
    the map is used again)."""
    for i in range(codes.shape[0]):
        r = _new_record(codes[i], R, free, meta, tab)
        x = values[i]
        R[r].l = x
        R[r].in_occ = 1
        R[r].state = 1 if x > l_occ else (0 if x < l_free else 2)
        _mark_present(codes[i], bkeys, bmask, meta)


@njit(cache=True)
def restore(radius, last, hits, misses, history, offsets, offset_start, R, free, meta, tab, ipool, imeta):
    """After load_records (same order as the stored voxels): per-voxel radius, stamps and counts,
    the inflation map re-derived from the radii, and the history list in its stored order."""
    codes = np.empty(offsets.shape[0], dtype=np.int64)
    n = radius.shape[0]
    for r in range(n):
        R[r].hits = hits[r]
        R[r].misses = misses[r]
        R[r].last = last[r]
        if radius[r] >= 0:
            R[r].radius = radius[r]
            _inflate_sphere(r, radius[r], offsets, offset_start, R, free, meta, tab, ipool, imeta, codes)
    for i in range(history.shape[0]):
        _push_back(history[i], R, meta)
