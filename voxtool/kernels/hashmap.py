"""Kernels of the `hashmap` backend (seed: voxel-mapping-hash-map-sharing.md, Alg. 1-3).

Voxel records live in flat arrays indexed by record number (the paper's pointers); an
open-addressing table maps Morton code -> record. The history buffer is a doubly linked list
through rec_prev / rec_next. States: 0 free, 1 occupied, 2 unknown.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16, morton3

EMPTY = -1
TOMB = -2
NOT_IN_HISTORY = -2
# meta fields
M_HEAD, M_TAIL, M_HSIZE, M_FREE_TOP, M_LIVE, M_TOMBS, M_NEXT = 0, 1, 2, 3, 4, 5, 6
_MULT = np.int64(-7046029254386353131)


@njit(cache=True, inline="always")
def _slot(code, mask):
    return ((code * _MULT) >> 20) & mask


@njit(cache=True)
def find(tab_key, tab_val, code):
    mask = tab_key.shape[0] - 1
    s = _slot(code, mask)
    while True:
        k = tab_key[s]
        if k == EMPTY:
            return -1
        if k == code:
            return tab_val[s]
        s = (s + 1) & mask


@njit(cache=True)
def _insert(tab_key, tab_val, code, rec, meta):
    mask = tab_key.shape[0] - 1
    s = _slot(code, mask)
    while tab_key[s] != EMPTY and tab_key[s] != TOMB:
        s = (s + 1) & mask
    if tab_key[s] == TOMB:
        meta[M_TOMBS] -= 1
    tab_key[s] = code
    tab_val[s] = rec


@njit(cache=True)
def _erase(tab_key, code, meta):
    mask = tab_key.shape[0] - 1
    s = _slot(code, mask)
    while tab_key[s] != code:
        s = (s + 1) & mask
    tab_key[s] = TOMB
    meta[M_TOMBS] += 1


@njit(cache=True)
def _new_record(code, R, free, meta, tab_key, tab_val):
    rec_code, rec_l, rec_state, rec_in_occ, rec_inf, rec_radius, rec_prev, rec_next, rec_hits, rec_misses, rec_last = R
    if meta[M_FREE_TOP] > 0:
        meta[M_FREE_TOP] -= 1
        r = free[meta[M_FREE_TOP]]
    else:
        r = meta[M_NEXT]
        meta[M_NEXT] += 1
    rec_code[r] = code
    rec_l[r] = 0.0
    rec_state[r] = 2
    rec_in_occ[r] = 0
    rec_inf[r] = 0
    rec_radius[r] = -1
    rec_prev[r] = NOT_IN_HISTORY
    rec_next[r] = NOT_IN_HISTORY
    rec_hits[r] = 0
    rec_misses[r] = 0
    rec_last[r] = 0
    meta[M_LIVE] += 1
    _insert(tab_key, tab_val, code, r, meta)
    return r


@njit(cache=True)
def _drop_record(r, R, free, meta, tab_key):
    R[2][r] = -1  # state: slot unused
    _erase(tab_key, R[0][r], meta)
    free[meta[M_FREE_TOP]] = r
    meta[M_FREE_TOP] += 1
    meta[M_LIVE] -= 1


PRESENCE_BITS = 1 << 24  # 2 MiB bitmap: "a record may exist for this code" (no false negatives)


@njit(cache=True, inline="always")
def _presence_bit(code):
    return ((code * _MULT) >> 32) & (PRESENCE_BITS - 1)


@njit(cache=True)
def input_update(packed, stamp, l_init, l_hit, l_miss, l_min, l_max, l_occ, l_free, R, free, meta, tab_key, tab_val,
                 presence, out_touched, out_new, out_changed):
    """Alg. 1 + occupancy check. Hits create voxels (prior l_init); misses update only voxels the
    occupancy map holds (known-free space is never stored): most misses fall in empty space, so a
    presence bitmap (set when a voxel enters the occupancy map, never cleared) skips their look-up.
    Returns (n touched, n occ-changed)."""
    rec_code, rec_l, rec_state, rec_in_occ, rec_inf, rec_radius, rec_prev, rec_next, rec_hits, rec_misses, rec_last = R
    nt = 0
    nc = 0
    for i in range(packed.shape[0]):
        code = packed[i] >> 1
        hit = (packed[i] & 1) == 1
        bit = _presence_bit(code)
        if not hit and (presence[bit >> 6] >> (bit & 63)) & 1 == 0:
            continue
        r = find(tab_key, tab_val, code)
        is_new = False
        if hit:
            if r < 0:
                r = _new_record(code, R, free, meta, tab_key, tab_val)
            if rec_in_occ[r] == 0:
                # entering the occupancy map (new, or until now only inflated): misses apply from now on
                presence[bit >> 6] |= np.int64(1) << (bit & 63)
                rec_in_occ[r] = 1
                rec_l[r] = l_init
                rec_state[r] = 2
                is_new = True
            v = rec_l[r] + l_hit
            rec_hits[r] += 1
        else:
            if r < 0 or rec_in_occ[r] == 0:
                continue
            v = rec_l[r] + l_miss
            rec_misses[r] += 1
        if v < l_min:
            v = l_min
        elif v > l_max:
            v = l_max
        rec_l[r] = v
        was_occ = rec_state[r] == 1 and not is_new
        rec_state[r] = 1 if v > l_occ else (0 if v < l_free else 2)
        rec_last[r] = stamp
        out_touched[nt] = r
        out_new[nt] = is_new
        nt += 1
        if was_occ != (rec_state[r] == 1):
            out_changed[nc] = r
            nc += 1
    return nt, nc


@njit(cache=True)
def _inflate_one(r, sign, radius, offsets, offset_start, R, free, meta, tab_key, tab_val):
    """Add (sign=1) or remove (sign=-1) r's inflation over the sphere of `radius` voxels."""
    rec_in_occ, rec_inf = R[3], R[4]
    code = R[0][r]
    x = compact16(code)
    y = compact16(code >> 1)
    z = compact16(code >> 2)
    for j in range(offset_start[radius], offset_start[radius + 1]):
        nx = x + offsets[j, 0]
        ny = y + offsets[j, 1]
        nz = z + offsets[j, 2]
        if nx < 0 or ny < 0 or nz < 0 or nx > 65535 or ny > 65535 or nz > 65535:
            continue
        c = morton3(nx, ny, nz)
        t = find(tab_key, tab_val, c)
        if sign > 0:
            if t < 0:
                t = _new_record(c, R, free, meta, tab_key, tab_val)
            rec_inf[t] += 1
        else:
            rec_inf[t] -= 1
            if rec_inf[t] == 0 and rec_in_occ[t] == 0:
                _drop_record(t, R, free, meta, tab_key)


@njit(cache=True)
def inflate(changed, n_changed, sx, sy, sz, inf_range, resolution, radius_now, offsets, offset_start,
            R, free, meta, tab_key, tab_val):
    """Alg. 2: occupancy-changed voxels within inf_range of the sensor (re)inflate: a voxel that
    became occupied inflates the sphere of the current radius (remembered per voxel), one that
    stopped being occupied removes exactly the sphere it added. Returns voxels processed."""
    rec_state, rec_radius = R[2], R[5]
    done = 0
    for i in range(n_changed):
        r = changed[i]
        if rec_state[r] < 0:
            continue
        code = R[0][r]
        px = (np.float64(compact16(code)) - 32768 + 0.5) * resolution - sx
        py = (np.float64(compact16(code >> 1)) - 32768 + 0.5) * resolution - sy
        pz = (np.float64(compact16(code >> 2)) - 32768 + 0.5) * resolution - sz
        if inf_range >= 0 and px * px + py * py + pz * pz > inf_range * inf_range:
            continue
        if rec_state[r] == 1 and rec_radius[r] < 0:
            rec_radius[r] = radius_now
            _inflate_one(r, 1, radius_now, offsets, offset_start, R, free, meta, tab_key, tab_val)
            done += 1
        elif rec_state[r] != 1 and rec_radius[r] >= 0:
            _inflate_one(r, -1, rec_radius[r], offsets, offset_start, R, free, meta, tab_key, tab_val)
            rec_radius[r] = -1
            done += 1
    return done


@njit(cache=True)
def _unlink(r, R, meta):
    rec_prev, rec_next = R[6], R[7]
    p, n = rec_prev[r], rec_next[r]
    if p >= 0:
        rec_next[p] = n
    else:
        meta[M_HEAD] = n
    if n >= 0:
        rec_prev[n] = p
    else:
        meta[M_TAIL] = p
    rec_prev[r] = NOT_IN_HISTORY
    rec_next[r] = NOT_IN_HISTORY
    meta[M_HSIZE] -= 1


@njit(cache=True)
def _push_back(r, R, meta):
    rec_prev, rec_next = R[6], R[7]
    rec_prev[r] = meta[M_TAIL]
    rec_next[r] = -1
    if meta[M_TAIL] >= 0:
        rec_next[meta[M_TAIL]] = r
    else:
        meta[M_HEAD] = r
    meta[M_TAIL] = r
    meta[M_HSIZE] += 1


@njit(cache=True)
def _remove_from_map(r, offsets, offset_start, R, free, meta, tab_key, tab_val):
    """Take r out of the occupancy map; its inflation goes with it (exact, whatever the range)."""
    if R[5][r] >= 0:
        _inflate_one(r, -1, R[5][r], offsets, offset_start, R, free, meta, tab_key, tab_val)
        R[5][r] = -1
    if R[6][r] != NOT_IN_HISTORY:
        _unlink(r, R, meta)
    R[3][r] = 0
    if R[4][r] == 0:
        _drop_record(r, R, free, meta, tab_key)
    else:
        R[2][r] = 2  # stays only as an inflated voxel of the inflation map


@njit(cache=True)
def manage(touched, n_touched, n_lim, oldest_allowed, offsets, offset_start, R, free, meta, tab_key, tab_val):
    """Alg. 3: touched occupied voxels move to the back of the history, known-free ones leave the
    map, then the oldest leave until at most n_lim remain (and those older than the TTL).
    Returns how many voxels were removed by the limit / TTL."""
    rec_state = R[2]
    for i in range(n_touched):
        r = touched[i]
        if rec_state[r] < 0 or R[3][r] == 0:
            continue
        if R[6][r] != NOT_IN_HISTORY:
            _unlink(r, R, meta)
        if rec_state[r] == 1:
            _push_back(r, R, meta)
        elif rec_state[r] == 0:
            _remove_from_map(r, offsets, offset_start, R, free, meta, tab_key, tab_val)
    removed = 0
    while meta[M_HSIZE] > 0 and (meta[M_HSIZE] > n_lim or R[10][meta[M_HEAD]] < oldest_allowed):
        _remove_from_map(meta[M_HEAD], offsets, offset_start, R, free, meta, tab_key, tab_val)
        removed += 1
    return removed


@njit(cache=True)
def rehash(tab_key, tab_val, rec_code, rec_state, n_records):
    """Rebuild the table from the live records (drops tombstones)."""
    tab_key[:] = EMPTY
    mask = tab_key.shape[0] - 1
    for r in range(n_records):
        if rec_state[r] >= 0:
            s = _slot(rec_code[r], mask)
            while tab_key[s] != EMPTY:
                s = (s + 1) & mask
            tab_key[s] = rec_code[r]
            tab_val[s] = r




@njit(cache=True)
def load_records(codes, values, l_occ, l_free, R, free, meta, tab_key, tab_val, presence):
    """Snapshot load: every stored voxel back into the occupancy map (inflation is rebuilt as
    the map is used again)."""
    for i in range(codes.shape[0]):
        r = _new_record(codes[i], R, free, meta, tab_key, tab_val)
        v = values[i]
        R[1][r] = v
        R[3][r] = 1
        R[2][r] = 1 if v > l_occ else (0 if v < l_free else 2)
        bit = _presence_bit(codes[i])
        presence[bit >> 6] |= np.int64(1) << (bit & 63)


@njit(cache=True)
def restore(radius, last, hits, misses, history, offsets, offset_start, R, free, meta, tab_key, tab_val):
    """After load_records (same order as the stored voxels): per-voxel radius, stamps and counts,
    the inflation map re-derived from the radii, and the history list in its stored order."""
    n = radius.shape[0]
    for r in range(n):
        R[8][r] = hits[r]
        R[9][r] = misses[r]
        R[10][r] = last[r]
        if radius[r] >= 0:
            R[5][r] = radius[r]
            _inflate_one(r, 1, radius[r], offsets, offset_start, R, free, meta, tab_key, tab_val)
    for i in range(history.shape[0]):
        _push_back(history[i], R, meta)
