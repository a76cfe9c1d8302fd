"""Kernels of the `octree` backend: OctoMap 1.10's OcTree as voxel bricks under a derived tree.

OctoMap's update is per voxel: a voxel's log-odds start at 0 and each scan adds the hit or miss
log-odds, clamped (its early abort for clamped leaves and its expansion of pruned nodes never
change what a voxel holds). Its tree is then a function of the voxel values: a node exists when
a voxel below it is known, and it is a leaf (pruned) when its 8 children exist and are leaves of
one value. So the values are kept in bricks of 8x8x8 voxels, 512 float32 in Morton order (NaN:
unknown), and the tree is derived where it is needed: leaves, node counts, leaf depths, .bt.

A brick is the subtree of one depth-13 node: its 64 depth-15 nodes cover 8 consecutive values
each, its 8 depth-14 nodes 64. A brick's pruning summary: l15 (bit g: depth-15 node g is a leaf),
l14 (bit h: depth-14 node h is a leaf), and whether the brick's root is a leaf.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.raycast import brick_word, lowest_bit

BRICK = 512  # voxels per brick
BRICK_BITS = 9  # brick code = voxel code >> 9
BRICK_DEPTH = 13  # the depth of a brick's root node

ADD = 0  # items are code << 1 | occupied: add hit/miss log-odds, clamp (OctoMap updateNode)
SET = 1  # items are codes, values[i] the new log-odds (writing back cached voxels)


@njit(cache=True, nogil=True)
def brick_runs(items, shift):
    """Runs of equal brick (items >> shift) in items: (brick codes, starts, sorted), starts[k]
    the first item of run k and starts[-1] = len(items); `sorted` False when a brick code
    decreases somewhere (the runs are then not the bricks: sort the items first)."""
    n = items.shape[0]
    count = 0
    last = np.int64(-1)
    ordered = True
    for i in range(n):
        b = items[i] >> shift
        if b != last:
            if b < last:
                ordered = False
            count += 1
            last = b
    codes = np.empty(count, dtype=np.int64)
    starts = np.empty(count + 1, dtype=np.int64)
    k = 0
    last = np.int64(-1)
    for i in range(n):
        b = items[i] >> shift
        if b != last:
            codes[k] = b
            starts[k] = i
            k += 1
            last = b
    starts[count] = n
    return codes, starts, ordered


@njit(cache=True, nogil=True)
def apply_bricks(vals, slots, fresh, init, starts, lo, hi, items, values, mode, hit, miss, cmin, cmax, forget):
    """Apply the updates of bricks lo..hi (items[starts[k]:starts[k + 1]] go to brick slots[k]).
    A brick with fresh[k] is first filled with init[k] (NaN: unknown, or the value of the coarse
    leaf it was split from). mode ADD: OctoMap's clamped log-odds update, a new voxel starting
    at 0; a decaying map (forget > 0) treats a value below `forget` as unknown, forgotten by an
    earlier decay step (0 for OctoMap's: never). mode SET: the voxel takes values[i]."""
    for k in range(lo, hi):
        base = slots[k] * BRICK
        if fresh[k]:
            for j in range(BRICK):
                vals[base + j] = init[k]
        if mode == ADD and forget > 0:  # a separate loop: OctoMap's own keeps its speed
            for i in range(starts[k], starts[k + 1]):
                item = items[i]
                at = base + ((item >> 1) & (BRICK - 1))
                v = vals[at]
                if v != v or abs(v) < forget:
                    v = np.float32(0.0)
                vals[at] = min(max(v + (hit if (item & 1) else miss), cmin), cmax)
        elif mode == ADD:
            for i in range(starts[k], starts[k + 1]):
                item = items[i]
                at = base + ((item >> 1) & (BRICK - 1))
                v = vals[at]
                if v != v:
                    v = np.float32(0.0)
                vals[at] = min(max(v + (hit if (item & 1) else miss), cmin), cmax)  # no branch on the clamp
        else:
            for i in range(starts[k], starts[k + 1]):
                vals[base + (items[i] & (BRICK - 1))] = values[i]


@njit(cache=True, nogil=True)
def apply_masks(vals, slots, fresh, init, touched, occ, order, firsts, lo, hi, hit, miss, cmin, cmax, forget):
    """apply_bricks' ADD for one scan's merged brick masks (maps.octree.ScanBricks), without a
    list of per-voxel updates: distinct brick k (slot slots[k]) holds the voxels set in the OR of
    its rows order[firsts[k]:firsts[k + 1]] of `touched`, occupied where set in `occ`. Bits are
    visited in order, so each voxel gets the update apply_bricks would give it. Returns how many
    voxels were updated."""
    n = 0
    for k in range(lo, hi):
        base = slots[k] * BRICK
        if fresh[k]:
            for j in range(BRICK):
                vals[base + j] = init[k]
        for w in range(8):
            x, o = brick_word(touched, occ, order, firsts[k], firsts[k + 1], w)
            at0 = base + (w << 6)
            while x != 0:
                bit = lowest_bit(x)
                at = at0 + bit
                v = vals[at]
                if v != v or abs(v) < forget:  # unknown, or forgotten by a decay step (forget 0: never)
                    v = np.float32(0.0)
                # min/max, not branches: a free voxel's update often reaches the clamp, unpredictably
                vals[at] = min(max(v + (hit if (o >> bit) & 1 else miss), cmin), cmax)
                n += 1
                x &= x - 1  # that bit done
    return n


@njit(cache=True, nogil=True)
def fill_leaves(vals, slots, codes, depths, values):
    """Write leaves of depth >= 13 (a snapshot's, a .bt file's) into their bricks: a leaf at
    depth d covers 8^(16 - d) consecutive values of brick slots[i]."""
    for i in range(codes.shape[0]):
        at = slots[i] * BRICK + (codes[i] & (BRICK - 1))
        span = np.int64(1) << (3 * (16 - np.int64(depths[i])))
        for j in range(span):
            vals[at + j] = values[i]


@njit(cache=True, inline="always")
def _all_equal(vals, at, n):
    """The n values from `at` are known and equal."""
    v0 = vals[at]
    if v0 != v0:
        return False
    for j in range(1, n):
        if vals[at + j] != v0:
            return False
    return True


@njit(cache=True, nogil=True)
def summarize(vals, slots, lo, hi, l15, l14, root_leaf, counts):
    """Pruning summaries of bricks lo..hi (see the module docstring) and the (leaf, inner) node
    counts of each brick's subtree (a brick whose root is a leaf counts as one leaf)."""
    for k in range(lo, hi):
        base = slots[k] * BRICK
        m15 = np.int64(0)
        known15 = np.int64(0)
        voxels = 0
        for g in range(64):
            at = base + 8 * g
            n = 0
            for j in range(8):
                if vals[at + j] == vals[at + j]:
                    n += 1
            voxels += n
            if n:
                known15 |= np.int64(1) << g
                if n == 8 and _all_equal(vals, at, 8):
                    m15 |= np.int64(1) << g
        m14 = 0
        for h in range(8):
            if (m15 >> (8 * h)) & 0xFF == 0xFF and _all_equal(vals, base + 64 * h, 64):
                m14 |= 1 << h
        is_leaf = m14 == 0xFF and _all_equal(vals, base, BRICK)
        l15[k] = m15
        l14[k] = m14
        root_leaf[k] = is_leaf
        if is_leaf:
            counts[k, 0] = 1
            counts[k, 1] = 0
            continue
        leaves = 0
        inner = 1  # the brick's root
        for h in range(8):
            if (known15 >> (8 * h)) & 0xFF == 0:
                continue
            if (m14 >> h) & 1:
                leaves += 1
                continue
            inner += 1
            for g in range(8 * h, 8 * h + 8):
                if (known15 >> g) & 1 == 0:
                    continue
                if (m15 >> g) & 1:
                    leaves += 1
                else:
                    inner += 1
                    for j in range(8):
                        if vals[base + 8 * g + j] == vals[base + 8 * g + j]:
                            leaves += 1
        counts[k, 0] = leaves
        counts[k, 1] = inner


@njit(cache=True, nogil=True)
def brick_leaves(vals, slots, brick_codes, lo, hi, l15, l14, offsets, codes, depths, values):
    """The leaves of bricks lo..hi (roots not leaves) in Morton order, from codes[offsets[k]]."""
    for k in range(lo, hi):
        base = slots[k] * BRICK
        first = brick_codes[k] << BRICK_BITS
        n = offsets[k]
        for h in range(8):
            if (l14[k] >> h) & 1:
                codes[n] = first | (h << 6)
                depths[n] = 14
                values[n] = vals[base + 64 * h]
                n += 1
                continue
            for g in range(8 * h, 8 * h + 8):
                if (l15[k] >> g) & 1:
                    codes[n] = first | (g << 3)
                    depths[n] = 15
                    values[n] = vals[base + 8 * g]
                    n += 1
                    continue
                for j in range(8 * g, 8 * g + 8):
                    v = vals[base + j]
                    if v == v:
                        codes[n] = first | j
                        depths[n] = 16
                        values[n] = v
                        n += 1


@njit(cache=True, nogil=True)
def leaf_depths(codes, brick_index, l15, l14, root_leaf, out):
    """Depth of the leaf holding each voxel code inside its brick (brick_index[i] into the
    summaries; -1: no brick, left as is): 16, or 15 / 14 / 13 where the voxel's node is pruned."""
    for i in range(codes.shape[0]):
        k = brick_index[i]
        if k < 0:
            continue
        v = codes[i] & (BRICK - 1)
        if root_leaf[k]:
            out[i] = 13
        elif (l14[k] >> (v >> 6)) & 1:
            out[i] = 14
        elif (l15[k] >> (v >> 3)) & 1:
            out[i] = 15
        else:
            out[i] = 16


@njit(cache=True, nogil=True)
def collapse_leaves(codes, depths, values, deepest):
    """OctoMap's pruning of Morton-ordered, non-overlapping leaves: 8 sibling leaves of one value
    at a depth <= `deepest` become their parent, repeatedly (one pass: the children of a node
    arrive together). Returns the count; the pruned leaves are left in the input's first slots."""
    n = 0
    for i in range(codes.shape[0]):
        codes[n] = codes[i]
        depths[n] = depths[i]
        values[n] = values[i]
        n += 1
        while n >= 8:
            d = np.int64(depths[n - 1])
            if d == 0 or d > deepest:
                break
            shift = 3 * (17 - d)
            top = codes[n - 1] >> shift
            same = True
            for j in range(n - 8, n - 1):
                if depths[j] != d or codes[j] >> shift != top or values[j] != values[n - 1]:
                    same = False
                    break
            if not same:
                break
            n -= 7  # the first of the 8 children starts where its parent does
            depths[n - 1] = d - 1
    return n


@njit(cache=True, inline="always")
def _shared_depth(a, b):
    """Deepest depth at which finest-level codes a and b lie in the same node (16: equal)."""
    x = a ^ b
    if x == 0:
        return 16
    t = 0
    while (x >> (3 * (t + 1))) != 0:
        t += 1
    return 15 - t


@njit(cache=True, nogil=True)
def inner_nodes(codes, depths, prev_code, prev_depth):
    """Inner nodes of the tree whose leaves are these Morton-ordered, non-overlapping leaves: each
    leaf adds its ancestors below the deepest one it shares with the leaf before it (in depth-
    first order every ancestor shared with an earlier leaf is shared with the previous one).
    prev_code / prev_depth: the leaf before the first (leaves counted in chunks), depth -1 none."""
    total = np.int64(0)
    last_code = prev_code
    last_depth = np.int64(prev_depth)
    for i in range(codes.shape[0]):
        d = np.int64(depths[i])
        if last_depth < 0:
            total += d
        else:
            shared = min(_shared_depth(codes[i], last_code), d - 1, last_depth - 1)
            total += d - 1 - shared
        last_code = codes[i]
        last_depth = d
    return total


def pruned_tree_counts(codes, depths, values, threshold, max_likelihood):
    """(leaf nodes, inner nodes) of OctoMap's pruned tree of Morton-ordered, non-overlapping
    leaves (max_likelihood: each value first made +1 / -1 by `threshold`, the tree a .bt holds),
    in one pass and without copies: what node_counts(collapse(...)) gives."""
    state = pruned_tree_state()
    pruned_tree_feed(codes, depths, values, threshold, max_likelihood, *state)
    return pruned_tree_close(*state)


def pruned_tree_state() -> tuple:
    """The open nodes of a pruned-tree count (pruned_tree_feed) before any leaf."""
    return (np.zeros(17, np.int64), np.zeros(17, np.int64), np.zeros(17, np.bool_), np.zeros(17, np.float32),
            np.full(17, -1, np.int64), np.zeros(4, np.int64))


@njit(cache=True, nogil=True)
def pruned_tree_feed(codes, depths, values, threshold, max_likelihood, n_child, n_leaf, same, value, prefix, state):
    """Count the next Morton-ordered leaves into a pruned-tree count (pruned_tree_counts), in as
    many calls as chunks. The nodes on the path to the current leaf are open; a node closes when
    a leaf outside it arrives, and becomes a leaf of its parent when its 8 children are leaves of
    one value. Per depth k: children so far, leaf children not yet counted (the node may still
    prune), whether every child so far is a leaf of value value[k], and the node's code prefix
    (codes >> 3 (16 - k)); state: open depth (nodes 0..it - 1 are open), leaves and inner nodes
    counted, 1 when the root is a leaf."""
    open_depth = state[0]
    leaves = state[1]
    inner = state[2]
    for i in range(codes.shape[0]):
        d = np.int64(depths[i])
        v = values[i]
        if max_likelihood:
            v = np.float32(1.0) if v > threshold else np.float32(-1.0)
        if d == 0:  # the root is a leaf: the whole tree
            state[3] = 1
            return
        c = codes[i]
        # close the open nodes that do not hold this leaf, deepest first, into their parents
        while open_depth > 1 and (c >> (3 * (16 - (open_depth - 1)))) != prefix[open_depth - 1]:
            k = open_depth - 1
            if n_child[k] == 8 and same[k]:
                child_value = value[k]
                is_leaf = True
            else:
                leaves += n_leaf[k]
                inner += 1
                is_leaf = False
            open_depth -= 1
            p = k - 1
            n_child[p] += 1
            if is_leaf:
                n_leaf[p] += 1
                same[p] = (same[p] and value[p] == child_value) if n_child[p] > 1 else True
                value[p] = child_value if n_child[p] == 1 else value[p]
            else:
                same[p] = False
        # open this leaf's ancestors below the deepest open node
        for k in range(open_depth, d):
            prefix[k] = c >> (3 * (16 - k))
            n_child[k] = 0
            n_leaf[k] = 0
            same[k] = True
        open_depth = max(open_depth, d)
        p = d - 1
        n_child[p] += 1
        n_leaf[p] += 1
        same[p] = (same[p] and value[p] == v) if n_child[p] > 1 else True
        value[p] = v if n_child[p] == 1 else value[p]
    state[0] = open_depth
    state[1] = leaves
    state[2] = inner


@njit(cache=True, nogil=True)
def pruned_tree_close(n_child, n_leaf, same, value, prefix, state):
    """(leaf nodes, inner nodes) of a pruned-tree count once every leaf is fed: every open node
    closes, the root last."""
    if state[3]:
        return np.int64(1), np.int64(0)
    open_depth = state[0]
    leaves = state[1]
    inner = state[2]
    while open_depth > 0:
        k = open_depth - 1
        if n_child[k] == 8 and same[k]:
            child_value = value[k]
            is_leaf = True
        else:
            leaves += n_leaf[k]
            inner += 1
            is_leaf = False
        open_depth -= 1
        if k == 0:
            if is_leaf:
                leaves += 1
            break
        p = k - 1
        n_child[p] += 1
        if is_leaf:
            n_leaf[p] += 1
            same[p] = (same[p] and value[p] == child_value) if n_child[p] > 1 else True
            value[p] = child_value if n_child[p] == 1 else value[p]
        else:
            same[p] = False
    return leaves, inner


@njit(cache=True, nogil=True)
def voxel_values(codes, prefixes, prefix_rows, directory, vals, shift, out_value, out_slot):
    """Log-odds at finest-level codes (NaN where no brick holds the voxel) and each code's brick
    slot (-1: none). Sorted codes find their brick once per brick; a shard's row is looked up
    (binary search over the sorted shard prefixes) once per shard."""
    last_brick = np.int64(-1)
    slot = np.int64(-1)
    last_prefix = np.int64(-1)
    row = np.int64(-1)
    per_shard = directory.shape[1]
    for i in range(codes.shape[0]):
        brick = codes[i] >> BRICK_BITS
        if brick != last_brick:
            last_brick = brick
            prefix = brick >> shift
            if prefix != last_prefix:
                last_prefix = prefix
                k = np.searchsorted(prefixes, prefix)
                row = prefix_rows[k] if k < prefixes.shape[0] and prefixes[k] == prefix else -1
            slot = directory[row, brick & (per_shard - 1)] if row >= 0 else -1
        out_slot[i] = slot
        out_value[i] = vals[slot * BRICK + (codes[i] & (BRICK - 1))] if slot >= 0 else np.nan



@njit(cache=True, nogil=True)
def decay_bricks(vals, lo, hi, factor, forget):
    """Scale the log-odds of brick slots lo..hi by `factor` and forget (NaN) those whose
    |log-odds| is then below `forget` (NaN stays NaN)."""
    for k in range(lo, hi):
        base = k * BRICK
        for j in range(BRICK):
            v = vals[base + j] * factor
            vals[base + j] = np.float32(np.nan) if abs(v) < forget else v
