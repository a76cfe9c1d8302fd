"""Kernels of the `hashmap` backend (seed: voxel-mapping-hash-map-sharing.md, Alg. 1-3).

A voxel of the occupancy map is one 64-byte record (the paper's voxel object; its "pointers"
are record numbers), so everything an update reads or writes about it lies in one cache line.
An open-addressing table of record numbers finds records. The history buffer is a doubly
linked list through the records' prev / next fields. States: 0 free, 1 occupied, 2 unknown;
state -1 marks an unused record. The inflation map is apart: 8x8x8 bricks of inflation counts
(see new_inflation).
"""

from __future__ import annotations

import os

import numba
import numpy as np
from numba import njit, prange

from voxtool.kernels.morton import compact16, morton3
from voxtool.kernels.prefetch import prefetch
from voxtool.kernels.raycast import _coord_key, ray_setup
from voxtool.kernels.sort import sort_codes

RECORD = np.dtype({
    "names": ["code", "last", "prev", "next", "l", "radius", "hits", "misses", "state"],
    "formats": ["<i8", "<i8", "<i8", "<i8", "<f4", "<i4", "<i4", "<i4", "i1"],
    "offsets": [0, 8, 16, 24, 32, 36, 40, 44, 48],
    "itemsize": 64,
})
EMPTY = -1
TOMB = -2
NOT_IN_HISTORY = -2
AHEAD = 8  # look-ups a software pipeline requests ahead of use
# How full the open-addressing tables may get, tombstones counted: the record table 1/2, the
# brick tables (occupancy and inflation) 1/4. The kernels' room checks (_room_for_voxel,
# inflation_room) and HashVoxelMap's growth (_reserve, _inflation_room) both read these: a kernel
# stops when a check fails, the map grows, the kernel resumes, which ends only while they agree.
RECORD_TABLE_LOAD = 2
BRICK_TABLE_LOAD = 4
MAX_RECORDS = (1 << 31) - 1  # table slots hold int32 record numbers (128 GiB of records)
# meta fields: history head / tail / size, free-list top, live records, tombstones, next unused
# record, voxels with inflation count > 0, bricks and brick tombstones of the brick table; the
# inflation map's bricks, its table's tombstones, its next unused row and free-row stack top
(M_HEAD, M_TAIL, M_HSIZE, M_FREE_TOP, M_LIVE, M_TOMBS, M_NEXT, M_NINF, M_BRICKS, M_BTOMBS,
 M_IBRICKS, M_ITOMBS, M_INEXT, M_IFREE_TOP) = range(14)
META_FIELDS = 14
MAX_RADIUS = 64  # voxels of inflation radius (d_inf)
ROW_BITS = 24  # an inflation-table slot holds brick id << ROW_BITS | row
ROW_MASK = (1 << ROW_BITS) - 1
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


@njit(cache=True, inline="always")
def _take(free, meta, top, unused):
    """An index from a pool: the last one freed (free[:meta[top]] is the stack of freed ones),
    else the first never used (meta[unused])."""
    if meta[top] > 0:
        meta[top] -= 1
        return np.int64(free[meta[top]])
    meta[unused] += 1
    return meta[unused] - 1


@njit(cache=True, inline="always")
def _give(free, meta, top, index):
    """Index back to its pool (_take hands the last one given out first)."""
    free[meta[top]] = index
    meta[top] += 1


@njit(cache=True)
def _new_record(code, logodds, R, free, meta, tab):
    """A record for voxel `code` entering the occupancy map with `logodds`, state unknown."""
    r = _take(free, meta, M_FREE_TOP, M_NEXT)
    v = R[r]
    v.code = code
    v.last = 0
    v.prev = NOT_IN_HISTORY
    v.next = NOT_IN_HISTORY
    v.l = logodds
    v.radius = -1
    v.hits = 0
    v.misses = 0
    v.state = 2
    meta[M_LIVE] += 1
    _insert(tab, r, code, meta)
    return r


@njit(cache=True)
def _drop_record(r, R, free, meta, tab):
    R[r].state = -1
    _erase(tab, r, R[r].code, meta)
    _give(free, meta, M_FREE_TOP, r)
    meta[M_LIVE] -= 1


# The occupancy map's voxels as bricks of 8x8x8: an open-addressing table of brick ids with a
# 512-bit mask each (which of the brick's voxels the occupancy map holds), kept exact as voxels
# enter and leave. Rays consult it once per brick crossed and test a bit per step inside an
# occupied brick, so misses that fall in empty space cost no voxel look-up.


def new_bricks(size: int) -> tuple[np.ndarray, np.ndarray]:
    """An empty brick table of `size` (a power of two) slots: ids and 512-bit masks, with one
    more mask past the slots that stays all zero: the mask of every absent brick (see
    brick_row)."""
    return np.full(size, EMPTY, dtype=np.int64), np.zeros((size + 1, 8), dtype=np.int64)


@njit(cache=True, inline="always")
def _brick_id(kx, ky, kz):
    return ((kx >> 3) << 26) | ((ky >> 3) << 13) | (kz >> 3)


@njit(cache=True, inline="always")
def _in_brick(kx, ky, kz):
    return (kx & 7) | ((ky & 7) << 3) | ((kz & 7) << 6)


def brick_cell_keys(bricks: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The keys (n x 3) of cell cells[i] of brick id bricks[i]: _brick_id and _in_brick undone,
    for the map's views (inflation_counts)."""
    return np.stack([((bricks >> 26) << 3) | (cells & 7), (((bricks >> 13) & 8191) << 3) | ((cells >> 3) & 7),
                     ((bricks & 8191) << 3) | (cells >> 6)], axis=1)


@njit(cache=True, inline="always")
def _brick_home(b, mask):
    return ((b * _MULT) >> 24) & mask


@njit(cache=True, inline="always")
def _brick_slot(keys, b, shift):
    """Slot of brick id b in a brick table whose slots hold id << shift (the inflation map's
    table keeps a row number below), or -1."""
    mask = keys.shape[0] - 1
    s = _brick_home(b, mask)
    while True:
        k = keys[s]
        if k == EMPTY:
            return -1
        if k >= 0 and k >> shift == b:
            return s
        s = (s + 1) & mask


@njit(cache=True, inline="always")
def _free_slot(keys, b):
    """The first slot from brick id b's home that holds no brick (empty, or a tombstone)."""
    mask = keys.shape[0] - 1
    s = _brick_home(b, mask)
    while keys[s] >= 0:
        s = (s + 1) & mask
    return s


@njit(cache=True, inline="always")
def brick_find(bkeys, b):
    """Slot of brick id b, or -1."""
    return _brick_slot(bkeys, b, 0)


@njit(cache=True, inline="always")
def brick_row(bkeys, b):
    """The mask row of brick id b: its slot, or the all-zero row past the slots when the table
    does not hold it. The ray casting asks this at every brick a ray enters; the first probe
    nearly always decides (the table is at most 1/4 full), and deciding it with a select rather
    than brick_find's loop spared a mispredicted branch at each of them (docs/design/backends.md)."""
    s = _brick_home(b, bkeys.shape[0] - 1)
    k = bkeys[s]
    if k != b and k != EMPTY:  # another brick in the home slot: probe on
        s = brick_find(bkeys, b)
        return s if s >= 0 else bkeys.shape[0]
    return s if k == b else bkeys.shape[0]


@njit(cache=True)
def _mark_present(code, bkeys, bmask, meta):
    """The occupancy map now holds voxel `code`."""
    kx, ky, kz = compact16(code), compact16(code >> 1), compact16(code >> 2)
    b = _brick_id(kx, ky, kz)
    s = brick_find(bkeys, b)
    if s < 0:
        s = _free_slot(bkeys, b)
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
    for i in range(old_keys.shape[0]):
        b = old_keys[i]
        if b >= 0:
            s = _free_slot(bkeys, b)
            bkeys[s] = b
            bmask[s, :] = old_mask[i, :]


@njit(cache=True, inline="always")
def set_limit(size):
    """The most updates a de-duplicating set of `size` slots takes in the ray casting: 3/4 full.
    A smaller set filled further measured faster than a larger one half full (on two cores a
    half scan's sets of 8,192 slots against 16,384: docs/design/backends.md)."""
    return size * 3 // 4


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
    changes nothing: known-free space is not stored). In an 8x8x8 brick that holds no map voxel
    a step tests the all-zero mask row. The DDA is written out in scalars, as in scan_bricks,
    rather than through raycast's array-based _ray_* helpers: those measured slower here.

    Each voxel once, a hit winning over a miss, in `out` as code << 1 | hit, sorted; `seen`
    (all EMPTY, left so) is the de-duplicating set, `slots` its scratch (room for set_limit of
    it). Returns (n, steps); n = -1 when the set would pass set_limit (the caller grows it and
    calls again)."""
    res_factor = 1.0 / resolution
    okx = _coord_key(origin[0], res_factor)
    oky = _coord_key(origin[1], res_factor)
    okz = _coord_key(origin[2], res_factor)
    limit = set_limit(seen.shape[0])
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
        bs = brick_row(bkeys, _brick_id(kx, ky, kz))
        while True:
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
                bs = brick_row(bkeys, _brick_id(kx, ky, kz))
    for j in range(n):
        out[j] = seen[slots[j]]
        seen[slots[j]] = EMPTY
    if n >= limit:
        return -1, steps
    sort_codes(out[:n], slots)  # here, on the tracing thread; slots is free again
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
    """(hits, distinct bricks they fall in) of Morton-sorted updates: the room the rest of a
    scan's updates may need when input_update stopped for want of it (a brick's voxels are
    adjacent in Morton order)."""
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


@njit(cache=True, inline="always")
def _room_for_voxel(R, free, meta, tab, bkeys):
    """A record, table room and brick-table room for one more voxel (the loads above)."""
    return ((meta[M_FREE_TOP] > 0 or meta[M_NEXT] < R.shape[0])
            and RECORD_TABLE_LOAD * (meta[M_LIVE] + 1 + meta[M_TOMBS]) <= tab.shape[0]
            and BRICK_TABLE_LOAD * (meta[M_BRICKS] + 1 + meta[M_BTOMBS]) <= bkeys.shape[0])


@njit(cache=True, nogil=True)
def input_update(packed, start, counts, stamp, l_init, l_hit, l_miss, l_min, l_max, l_occ, l_free, R, free, meta,
                 tab, bkeys, bmask, out_touched, out_changed, out_occupied):
    """Alg. 1 + occupancy check over Morton-sorted (code << 1 | hit) updates, from packed[start].
    Hits create voxels (prior l_init); misses update only voxels the occupancy map holds
    (known-free space is never stored). Lists the records touched, those whose occupancy
    changed, and the codes of the voxels that became occupied (what map sharing sends);
    counts = (n touched, n occ-changed, n became occupied) so far, updated. Returns where it
    stopped: packed's length, or the first update that needs room for a new voxel (the caller
    makes room and calls again from there; nothing of that update was applied). Checking room
    per new voxel spared a pass over the updates before every scan."""
    nt = counts[0]
    nc = counts[1]
    no = counts[2]
    # software pipeline: the home slot of update i + 2 * AHEAD and the record in the slot of
    # update i + AHEAD are on their way while update i is applied (memory latency bounds this
    # loop: random table slots and records; the requests overlap their cache misses)
    mask = tab.shape[0] - 1
    n = packed.shape[0]
    for i in range(start, min(start + 2 * AHEAD, n)):
        prefetch(tab, _slot(packed[i] >> 1, mask))
    for j in range(1, min(AHEAD, meta[M_FREE_TOP]) + 1):  # the freed records new voxels will take
        prefetch(R, free[meta[M_FREE_TOP] - j])
    stop = n
    for i in range(start, n):
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
            if r < 0:  # entering the occupancy map: misses apply from now on
                if not _room_for_voxel(R, free, meta, tab, bkeys):
                    stop = i
                    break
                if meta[M_FREE_TOP] > AHEAD:
                    prefetch(R, free[meta[M_FREE_TOP] - 1 - AHEAD])
                r = _new_record(code, l_init, R, free, meta, tab)
                _mark_present(code, bkeys, bmask, meta)
                is_new = True
            v = R[r]
            x = v.l + l_hit
            v.hits += 1
        else:
            if r < 0:
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
            if not was_occ:
                out_occupied[no] = code
                no += 1
    counts[0] = nt
    counts[1] = nc
    counts[2] = no
    return stop


# The inflation map (Alg. 2's inflation counts) as 8x8x8 bricks of counts, one row of
# `icounts` a brick, found through an open-addressing table of brick id << ROW_BITS | row. A
# voxel that inflates adds 1 to every cell of its sphere: 33 cells at radius 2, in one to eight
# bricks, so a sphere costs a few brick look-ups and counts written in place, where a record per
# inflated voxel cost a table look-up and a 64-byte record per cell (docs/design/backends.md).
# Removal recomputes the sphere from the voxel's remembered radius: the paper's look-up table of
# inflated voxels (T_inf) spares hash look-ups that the bricks no longer need.


def count_dtype(radius: int) -> np.dtype:
    """Inflation counts for spheres of at most `radius` voxels: a voxel's count is at most the
    cells of one sphere (every voxel of its own sphere inflating it), 123 for radius 3, so one
    byte up to there (a brick takes 512 B instead of 2 KB; the shipped sample at 0.2 m fills
    its bricks to 3 %), int32 beyond."""
    return np.dtype(np.uint8) if radius <= 3 else np.dtype(np.int32)


def new_inflation(slots: int, rows: int, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An empty inflation map: its brick table (`slots`, a power of two), `rows` bricks of counts
    of `dtype` (count_dtype; all zero: a row is handed out only while all zero), each row's
    count of non-zero cells, and the stack of freed rows."""
    return (np.full(slots, EMPTY, np.int64), np.zeros((rows, 512), dtype), np.zeros(rows, np.int32),
            np.zeros(rows, np.int32))


@njit(cache=True, inline="always")
def bricks_per_sphere(radius):
    """The most 8x8x8 bricks a sphere of `radius` voxels can reach (2r + 1 keys an axis)."""
    a = 1 + (2 * radius + 7) // 8
    return a * a * a


@njit(cache=True, inline="always")
def _ibrick_row(ikeys, b):
    """Row of inflation brick b, or -1."""
    s = _brick_slot(ikeys, b, ROW_BITS)
    return ikeys[s] & ROW_MASK if s >= 0 else -1


@njit(cache=True)
def _ibrick_add(ikeys, b, meta, ifree):
    """A new (all-zero) brick b; returns its row. Room is the caller's (inflation_room)."""
    row = _take(ifree, meta, M_IFREE_TOP, M_INEXT)
    s = _free_slot(ikeys, b)
    if ikeys[s] == TOMB:
        meta[M_ITOMBS] -= 1
    ikeys[s] = (b << ROW_BITS) | row
    meta[M_IBRICKS] += 1
    return row


@njit(cache=True)
def _ibrick_drop(ikeys, b, row, meta, ifree):
    """Brick b, all counts zero again, leaves; its row goes back to the stack."""
    ikeys[_brick_slot(ikeys, b, ROW_BITS)] = TOMB
    meta[M_ITOMBS] += 1
    meta[M_IBRICKS] -= 1
    _give(ifree, meta, M_IFREE_TOP, row)


@njit(cache=True, inline="always")
def inflation_room(ikeys, icounts, meta, bricks):
    """Whether `bricks` more bricks fit: free rows, and the table within BRICK_TABLE_LOAD."""
    rows = icounts.shape[0] - meta[M_INEXT] + meta[M_IFREE_TOP]
    return rows >= bricks and BRICK_TABLE_LOAD * (meta[M_IBRICKS] + meta[M_ITOMBS] + bricks) <= ikeys.shape[0]


@njit(cache=True)
def sphere_add(code, radius, sign, offsets, offset_start, meta, ikeys, icounts, inz, ifree):
    """Add `sign` (+1 or -1) to the inflation count of every voxel within `radius` voxels of
    voxel `code` (inside the key range). Adding needs room for bricks_per_sphere(radius) new
    bricks (inflation_room); removing only ever removes what an adding put there."""
    x = compact16(code)
    y = compact16(code >> 1)
    z = compact16(code >> 2)
    last = np.int64(-1)
    row = -1
    for j in range(offset_start[radius], offset_start[radius + 1]):
        nx = x + offsets[j, 0]
        ny = y + offsets[j, 1]
        nz = z + offsets[j, 2]
        if nx < 0 or ny < 0 or nz < 0 or nx > 65535 or ny > 65535 or nz > 65535:
            continue
        b = _brick_id(nx, ny, nz)
        if b != last:  # the offsets run along z first: most cells lie in the brick before
            row = _ibrick_row(ikeys, b)
            if row < 0:
                row = _ibrick_add(ikeys, b, meta, ifree)
            last = b
        v = _in_brick(nx, ny, nz)
        c = icounts[row, v] + sign
        icounts[row, v] = c
        if sign > 0:
            if c == 1:
                inz[row] += 1
                meta[M_NINF] += 1
        elif c == 0:
            meta[M_NINF] -= 1
            inz[row] -= 1
            if inz[row] == 0:  # none of this sphere's later cells lies in it: each counts >= 1
                _ibrick_drop(ikeys, b, row, meta, ifree)
                last = -1


@njit(cache=True)
def ibrick_rehash(old_keys, ikeys):
    """Move the live bricks of one inflation table into an empty one (drops tombstones)."""
    for i in range(old_keys.shape[0]):
        k = old_keys[i]
        if k >= 0:
            ikeys[_free_slot(ikeys, k >> ROW_BITS)] = k


@njit(cache=True, nogil=True)
def inflate(changed, n_changed, sx, sy, sz, inf_range, resolution, radius_now, offsets, offset_start, R, meta,
            ikeys, icounts, inz, ifree):
    """Alg. 2: occupancy-changed voxels within inf_range of the sensor (re)inflate: a voxel that
    became occupied inflates the sphere of the current radius (remembered per voxel), one that
    stopped being occupied removes exactly the sphere it added. Returns the voxels processed,
    or -1 when the inflation map has no room for the next sphere: the caller makes room and
    calls again (those done have changed their radius, so are not done twice)."""
    k = 0
    need = bricks_per_sphere(radius_now)
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
            if not inflation_room(ikeys, icounts, meta, need):
                return -1
            R[r].radius = radius_now
            sphere_add(code, radius_now, 1, offsets, offset_start, meta, ikeys, icounts, inz, ifree)
            k += 1
        elif state != 1 and radius >= 0:
            sphere_add(code, radius, -1, offsets, offset_start, meta, ikeys, icounts, inz, ifree)
            R[r].radius = -1
            k += 1
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
def _remove_from_map(r, R, free, meta, tab, bkeys, bmask, offsets, offset_start, ikeys, icounts, inz, ifree, out_codes,
                     out_values, listed):
    """Take r out of the occupancy map, listing it (code, log-odds before it left) at out_*[listed];
    its inflation goes with it (exact, whatever the range). Returns the new count listed."""
    code = R[r].code
    out_codes[listed] = code
    out_values[listed] = R[r].l
    if R[r].radius >= 0:
        sphere_add(code, R[r].radius, -1, offsets, offset_start, meta, ikeys, icounts, inz, ifree)
    if R[r].prev != NOT_IN_HISTORY:
        _unlink(r, R, meta)
    _clear_present(code, bkeys, bmask, meta)
    _drop_record(r, R, free, meta, tab)
    return listed + 1


@njit(cache=True, nogil=True)
def manage(touched, n_touched, n_lim, oldest_allowed, R, free, meta, tab, bkeys, bmask, offsets, offset_start, ikeys,
           icounts, inz, ifree, out_codes, out_values):
    """Alg. 3: touched occupied voxels move to the back of the history, known-free ones leave the
    map, then the oldest leave until at most n_lim remain (and those older than the TTL).
    Every voxel that leaves the occupancy map is listed in out_codes / out_values (its log-odds
    before it left; room for n_touched + history size). Returns how many are listed."""
    for i in range(n_touched):  # request the history neighbours first (see input_update)
        r = touched[i]
        p, n = R[r].prev, R[r].next
        if p >= 0:
            prefetch(R, p)
        if n >= 0:
            prefetch(R, n)
    listed = 0
    for i in range(n_touched):
        r = touched[i]
        if R[r].state < 0:
            continue
        if R[r].prev != NOT_IN_HISTORY:
            _unlink(r, R, meta)
        if R[r].state == 1:
            _push_back(r, R, meta)
        elif R[r].state == 0:
            listed = _remove_from_map(r, R, free, meta, tab, bkeys, bmask, offsets, offset_start, ikeys, icounts, inz,
                                      ifree, out_codes, out_values, listed)
    mask = tab.shape[0] - 1
    while meta[M_HSIZE] > 0 and (meta[M_HSIZE] > n_lim or R[meta[M_HEAD]].last < oldest_allowed):
        r = meta[M_HEAD]
        # the oldest voxels are cold: while this one leaves, the next one's table slot and the
        # record after it are on their way (a linked list: one step ahead)
        nxt = R[r].next
        if nxt >= 0:
            prefetch(tab, _slot(R[nxt].code, mask))
            if R[nxt].next >= 0:
                prefetch(R, R[nxt].next)
        listed = _remove_from_map(r, R, free, meta, tab, bkeys, bmask, offsets, offset_start, ikeys, icounts, inz,
                                  ifree, out_codes, out_values, listed)
    return listed


@njit(cache=True)
def lookup(tab, R, codes, out):
    """Log-odds of each voxel the occupancy map holds, NaN elsewhere."""
    for i in range(codes.shape[0]):
        r = find(tab, R, codes[i])
        out[i] = R[r].l if r >= 0 else np.nan


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
    """Snapshot load: every stored voxel back into the occupancy map (its inflation is rebuilt
    by reinflate)."""
    for i in range(codes.shape[0]):
        x = values[i]
        r = _new_record(codes[i], x, R, free, meta, tab)
        R[r].state = 1 if x > l_occ else (0 if x < l_free else 2)
        _mark_present(codes[i], bkeys, bmask, meta)


@njit(cache=True)
def restore(last, hits, misses, history, R, meta):
    """After load_records (same order as the stored voxels): per-voxel stamps and counts, and
    the history list in its stored order (inflation: reinflate)."""
    for r in range(last.shape[0]):
        R[r].hits = hits[r]
        R[r].misses = misses[r]
        R[r].last = last[r]
    for i in range(history.shape[0]):
        _push_back(history[i], R, meta)


@njit(cache=True)
def reinflate(radius, start, offsets, offset_start, R, meta, ikeys, icounts, inz, ifree):
    """After load_records: record r (r >= start) inflates the sphere of its stored radius[r].
    Returns the record it stopped at for want of room (inflation_room), or radius.shape[0]."""
    for r in range(start, radius.shape[0]):
        if radius[r] >= 0:
            if not inflation_room(ikeys, icounts, meta, bricks_per_sphere(radius[r])):
                return r
            R[r].radius = radius[r]
            sphere_add(R[r].code, radius[r], 1, offsets, offset_start, meta, ikeys, icounts, inz, ifree)
    return radius.shape[0]
