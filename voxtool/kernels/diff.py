"""Kernels of `voxtool diff`: two maps' leaves compared as runs of Morton codes, never voxel by
voxel. A leaf covers the codes [code, code + 8^(16 - depth)); walking both leaf lists at once,
every run between two consecutive leaf edges has one state in each map, so counts are sums of
run lengths and a coarse free leaf costs as much as a single voxel."""

from __future__ import annotations

import numpy as np
from numba import njit

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
SAME_STATE_NEW_VALUE = 9  # counts[9]: known in both, same state, other log-odds


@njit(cache=True, inline="always")
def _probability(log_odds):
    return 1.0 - 1.0 / (1.0 + np.exp(np.float64(log_odds)))  # OctoMap's probability()


@njit(cache=True, inline="always")
def _kld(p1, p2):
    """compare_octrees' Kullback-Leibler divergence of one voxel, KL(p1 || p2), with its branches."""
    if p1 < 0.0001:
        return np.log((1 - p1) / (1 - p2)) * (1 - p1)
    if p1 > 0.9999:
        return np.log(p1 / p2) * p1
    return np.log(p1 / p2) * p1 + np.log((1 - p1) / (1 - p2)) * (1 - p1)


@njit(cache=True, inline="always")
def _span(depth):
    return np.int64(1) << np.int64(3 * (16 - np.int64(depth)))


@njit(cache=True, inline="always")
def _state(known, value, threshold):
    if not known:
        return UNKNOWN
    return OCCUPIED if value > threshold else FREE


@njit(cache=True, nogil=True)
def compare_runs(ac, ad, av, at, bc, bd, bv, bt, counts, starts, ends, kinds):
    """Walk leaves A (first codes ac, depths ad, log-odds av, threshold at) and B together.
    counts[3 * state_a + state_b] += voxels; counts[SAME_STATE_NEW_VALUE] likewise. Runs whose
    state differs go to starts/ends/kinds (kind 3 * state_a + state_b; neighbours of one kind
    joined) while they have room; all are counted. Returns (changed runs, KL divergence summed
    over voxels known in both, those voxels): more runs than room means run it again with more."""
    na, nb = ac.shape[0], bc.shape[0]
    room = starts.shape[0]
    record = True
    # KL of recent (A, B) value pairs: a map holds few distinct log-odds, so few distinct pairs
    memo_a = np.full(4096, np.nan, dtype=np.float32)
    memo_b = np.full(4096, np.nan, dtype=np.float32)
    memo_kl = np.zeros(4096, dtype=np.float64)
    far = np.int64(1) << np.int64(62)
    i = j = 0
    pos = np.int64(-1)
    n = 0
    kl = 0.0
    common = np.int64(0)
    last_end, last_kind = np.int64(-1), -1
    end_a = ac[0] + _span(ad[0]) if na else far
    end_b = bc[0] + _span(bd[0]) if nb else far
    while True:
        while i < na and end_a <= pos:
            i += 1
            end_a = ac[i] + _span(ad[i]) if i < na else far
        while j < nb and end_b <= pos:
            j += 1
            end_b = bc[j] + _span(bd[j]) if j < nb else far
        if i >= na and j >= nb:
            break
        in_a = i < na and ac[i] <= pos
        in_b = j < nb and bc[j] <= pos
        next_a = end_a if in_a else (ac[i] if i < na else far)
        next_b = end_b if in_b else (bc[j] if j < nb else far)
        nxt = min(next_a, next_b)
        if not in_a and not in_b:
            pos = nxt
            continue
        length = nxt - pos
        sa = _state(in_a, av[i] if in_a else 0.0, at)
        sb = _state(in_b, bv[j] if in_b else 0.0, bt)
        kind = 3 * sa + sb
        counts[kind] += length
        if in_a and in_b and av[i] != bv[j]:  # equal values add 0 to the divergence
            va, vb = av[i], bv[j]
            h = (np.int64(np.float32(va * 7919.0)) * 31 + np.int64(np.float32(vb * 104729.0))) & 4095
            if memo_a[h] != va or memo_b[h] != vb:
                memo_a[h], memo_b[h] = va, vb
                memo_kl[h] = _kld(_probability(va), _probability(vb))
            kl += length * memo_kl[h]
            if sa == sb:
                counts[SAME_STATE_NEW_VALUE] += length
        if in_a and in_b:
            common += length
        if sa != sb:
            if n > 0 and last_end == pos and last_kind == kind:
                pass  # the same change goes on
            else:
                n += 1
                record = n <= room
            if record:
                if last_end != pos or last_kind != kind:
                    starts[n - 1] = pos
                kinds[n - 1] = kind
                ends[n - 1] = nxt
            last_end, last_kind = nxt, kind
        pos = nxt
    return n, kl, common


@njit(cache=True, nogil=True)
def run_blocks(starts, ends, kinds, codes, depths, block_kinds, record):
    """Cut each run [start, end) into the fewest aligned octree nodes (code, depth): what a leaf
    list holds, so runs can be drawn, bounded and expanded like leaves. Returns how many there
    are; written only with `record` (a first pass sizes the arrays)."""
    n = 0
    for r in range(starts.shape[0]):
        pos = starts[r]
        while pos < ends[r]:
            level = 0  # the node covers 8^level codes
            while level < 16:
                span = np.int64(1) << np.int64(3 * (level + 1))
                if pos % span != 0 or pos + span > ends[r]:
                    break
                level += 1
            if record:
                codes[n] = pos
                depths[n] = 16 - level
                block_kinds[n] = kinds[r]
            n += 1
            pos += np.int64(1) << np.int64(3 * level)
    return n
