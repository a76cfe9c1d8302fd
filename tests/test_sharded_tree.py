"""A sharded map's tree joined from its parts (io.sharded_tree) against the tree of the whole
map: random trees with pruned leaves above, at and below the shard depth, cut into parts the
way a sharded build cuts them."""

from __future__ import annotations

import io

import numpy as np
import pytest

from voxtool.distbuild import partition_of
from voxtool.io.bt import tree_stream
from voxtool.io.sharded_tree import Units, add_part, join, write_pieces
from voxtool.maps.base import Leaves
from voxtool.maps.tree import collapse, node_counts

SHARD_DEPTH = 8


def random_tree(rng, max_depth=10) -> Leaves:
    """Canonical leaves of a random tree below a few depth-3 nodes: nodes split with a chance
    that falls with depth; leaf values from a small set, so that siblings often prune. The
    draws come from Python's random, seeded by `rng`: numpy's scalar draws took most of the time."""
    import random

    draw = random.Random(int(rng.integers(1 << 32)))
    codes, depths, values = [], [], []

    def grow(code, depth):
        if depth < max_depth and (depth < 4 or draw.random() < (0.8 if depth < SHARD_DEPTH else 0.3)):
            step = 1 << (3 * (15 - depth))
            for j in range(8):
                if draw.random() < 0.85:
                    grow(code + j * step, depth + 1)
            return
        codes.append(code)
        depths.append(depth)
        values.append(draw.choice((-2.0, 0.5, 3.5)))

    for top in rng.choice(8 ** 3, size=1, replace=False):
        grow(int(top) << (3 * 13), 3)
    order = np.argsort(codes)
    leaves = Leaves(np.array(codes, np.int64)[order], np.array(depths, np.uint8)[order],
                    np.array(values, np.float32)[order])
    return collapse(leaves)


def parts_of(leaves: Leaves, partitions: int) -> list[Leaves]:
    """Leaves split by the partition of their shard (a leaf above the shard depth goes where
    its first shard goes), each part pruned on its own, as a part snapshot holds it."""
    part = partition_of(leaves.codes, SHARD_DEPTH, partitions)
    return [collapse(Leaves(leaves.codes[part == p], leaves.depths[part == p], leaves.values[part == p]))
            for p in range(partitions)]


@pytest.mark.parametrize("seed", range(6))
def test_joined_tree_equals_the_whole_tree(seed):
    rng = np.random.default_rng(seed)
    whole = random_tree(rng)
    assert (whole.depths < SHARD_DEPTH).any() and (whole.depths > SHARD_DEPTH).any()
    ml = Leaves(whole.codes, whole.depths, np.where(whole.values > 0, 1.0, -1.0).astype(np.float32))
    expected_bytes, ml_leaves, ml_inner = tree_stream(whole, 0.0)
    for partitions in (1, 3, 7):
        logodds, maxlike = Units(), Units()
        spool = io.BytesIO()
        for piece in parts_of(whole, partitions):
            add_part(logodds, piece, SHARD_DEPTH)
        for piece in parts_of(collapse(ml), partitions):
            add_part(maxlike, piece, SHARD_DEPTH, spool)
        assert join(logodds.arrays())[:2] == node_counts(whole)
        table = maxlike.arrays()
        leaves_n, inner_n, pieces = join(table)
        assert (leaves_n, inner_n) == (ml_leaves, ml_inner)
        out = io.BytesIO()
        write_pieces(out, pieces, table, spool)
        assert out.getvalue() == expected_bytes


def test_eight_equal_shards_in_different_parts_prune_above_them():
    """Eight sibling shards, each one leaf of one value, in different parts: the join makes
    them one leaf, as the whole map's pruning does."""
    span = 1 << (3 * (16 - SHARD_DEPTH))
    first = (5 << (3 * 13))
    whole = Leaves(first + span * np.arange(8, dtype=np.int64), np.full(8, SHARD_DEPTH, np.uint8),
                   np.full(8, 3.5, np.float32))
    units = Units()
    for p in range(8):
        add_part(units, Leaves(whole.codes[p:p + 1], whole.depths[p:p + 1], whole.values[p:p + 1]), SHARD_DEPTH)
    assert join(units.arrays())[:2] == node_counts(collapse(whole)) == (1, SHARD_DEPTH - 1)


def test_pruned_tree_counts_equal_the_pruned_trees_node_counts():
    """The one-pass count (kernels.octree.pruned_tree_counts, what `stats` reports) against
    pruning the leaves and counting the pruned tree's nodes, on random trees, for the log-odds
    tree and for the max-likelihood tree at thresholds that split the leaf values differently."""
    from voxtool.kernels.octree import pruned_tree_counts
    from voxtool.maps.tree import max_likelihood

    rng = np.random.default_rng(7)
    for _ in range(20):
        leaves = random_tree(rng)
        got = pruned_tree_counts(leaves.codes, leaves.depths, leaves.values, np.float32(0.0), False)
        assert tuple(int(n) for n in got) == node_counts(collapse(leaves))
        for threshold in (0.0, 1.0, 3.0):
            got = pruned_tree_counts(leaves.codes, leaves.depths, leaves.values, np.float32(threshold), True)
            assert tuple(int(n) for n in got) == node_counts(max_likelihood(leaves, threshold))
    # a single root leaf, eight equal children of the root, and no leaves
    one = np.zeros(1, np.int64), np.zeros(1, np.uint8), np.ones(1, np.float32)
    assert tuple(pruned_tree_counts(*one, np.float32(0), True)) == (1, 0)
    eight = np.arange(8, dtype=np.int64) << 45, np.ones(8, np.uint8), np.full(8, 2.0, np.float32)
    assert tuple(pruned_tree_counts(*eight, np.float32(0), False)) == (1, 0)
    assert tuple(pruned_tree_counts(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.float32),
                                    np.float32(0), True)) == (0, 0)


def test_tree_stats_in_chunks_equal_the_whole_leaves_figures():
    """A build counts its tree while the snapshot writes the leaves a chunk at a time
    (stats.TreeStats): every figure equals tree_stats of all the leaves at once, with chunks cut
    anywhere (one leaf, a few, uneven), for canonical and unpruned leaves."""
    from voxtool.stats import tree_stats

    def split_some(leaves):  # some leaves as their 8 equal children: a tree that still prunes
        codes, depths, values = [], [], []
        for c, d, v in zip(leaves.codes.tolist(), leaves.depths.tolist(), leaves.values.tolist()):
            if d < 16 and rng.random() < 0.3:
                step = 1 << (3 * (15 - d))
                codes += [c + j * step for j in range(8)]
                depths += [d + 1] * 8
                values += [v] * 8
            else:
                codes.append(c)
                depths.append(d)
                values.append(v)
        return Leaves(np.array(codes, np.int64), np.array(depths, np.uint8), np.array(values, np.float32))

    rng = np.random.default_rng(11)
    for _ in range(6):
        canonical = random_tree(rng, max_depth=9)
        unpruned = split_some(canonical)
        for leaves, is_canonical in ((canonical, True), (unpruned, False)):
            whole = tree_stats(leaves, 0.2, 1.0, is_canonical)
            n = len(leaves)
            for cuts in ([1] * min(n, 40), rng.integers(1, 500, size=n // 100 + 1), [n // 3 + 1] * 3):
                bounds = np.minimum(np.cumsum(np.concatenate([[0], cuts])), n)
                if bounds[-1] < n:
                    bounds = np.append(bounds, n)
                chunks = [Leaves(leaves.codes[a:b], leaves.depths[a:b], leaves.values[a:b])
                          for a, b in zip(bounds[:-1], bounds[1:])]
                assert tree_stats(iter(chunks), 0.2, 1.0, is_canonical) == whole
