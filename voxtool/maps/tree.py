"""OctoMap's tree as it follows from a map's leaves: pruning and node counts.

A tree is canonical when every node whose 8 children are leaves of one value is itself a leaf,
as OctoMap keeps it (voxtool.kernels.octree explains why the octree backend's tree always is).
"""

from __future__ import annotations

import numpy as np

from voxtool.kernels import octree as K
from voxtool.maps.base import Leaves, join_leaves


def collapse(leaves: Leaves, deepest: int = 16) -> Leaves:
    """OctoMap's pruning of Morton-ordered leaves: 8 equal sibling leaves at depth <= deepest
    become their parent, repeatedly (on copies)."""
    codes, depths, values = leaves.codes.copy(), leaves.depths.copy(), leaves.values.copy()
    n = K.collapse_leaves(codes, depths, values, deepest)
    return Leaves(codes[:n], depths[:n], values[:n])


def node_counts(leaves: Leaves) -> tuple[int, int]:
    """(leaf nodes, inner nodes) of the tree of canonical leaves, as OctoMap counts them
    (OcTree::getNumLeafNodes(), size() - that)."""
    return len(leaves), int(K.inner_nodes(leaves.codes, leaves.depths, 0, -1))


def max_likelihood(leaves: Leaves, threshold_log: float) -> Leaves:
    """The tree OctoMap writes to a .bt file: every leaf occupied (+1) or free (-1) by the
    threshold, then pruned (toMaxLikelihood + prune). voxtool prunes fully; OctoMap's own prune
    loop stops at the first level where nothing pruned, so its file can hold more nodes for the
    same voxels."""
    ml = np.where(leaves.values > np.float32(threshold_log), np.float32(1.0), np.float32(-1.0)).astype(np.float32)
    return collapse(Leaves(leaves.codes, leaves.depths, ml))


def crop(leaves: Leaves, lo_key: np.ndarray, hi_key: np.ndarray) -> Leaves:
    """The voxels of `leaves` whose keys lie in the box lo_key..hi_key (inclusive, per axis), as
    leaves: a leaf inside is kept whole, one outside dropped, one across the box's faces split
    into its 8 children until each is inside or outside (the tree stays canonical, since a
    split leaf never keeps all 8 children)."""
    from voxtool.keys import leaf_edge, morton_decode

    lo_key, hi_key = np.asarray(lo_key, np.int64), np.asarray(hi_key, np.int64)
    kept = []
    codes, depths, values = leaves.codes, leaves.depths, leaves.values
    while codes.shape[0]:
        first = morton_decode(codes).astype(np.int64)
        last = first + leaf_edge(depths)[:, None].astype(np.int64) - 1
        inside = np.all((first >= lo_key) & (last <= hi_key), axis=1)
        touches = np.all((last >= lo_key) & (first <= hi_key), axis=1)
        kept.append(Leaves(codes[inside], depths[inside], values[inside]))
        across = touches & ~inside  # never a single voxel: it is inside or outside
        children = np.int64(1) << (3 * (15 - depths[across].astype(np.int64)))
        codes = (codes[across][:, None] + np.arange(8, dtype=np.int64) * children[:, None]).ravel()
        depths = np.repeat(depths[across] + np.uint8(1), 8)
        values = np.repeat(values[across], 8)
    return join_leaves(kept)
