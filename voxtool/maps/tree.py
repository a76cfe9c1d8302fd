"""OctoMap's tree as it follows from a map's leaves: pruning and node counts.

A tree is canonical when every node whose 8 children are leaves of one value is itself a leaf,
as OctoMap keeps it (voxtool.kernels.octree explains why the octree backend's tree always is).
"""

from __future__ import annotations

import numpy as np

from voxtool.kernels import octree as K
from voxtool.maps.base import Leaves


def collapse(leaves: Leaves, deepest: int = 16) -> Leaves:
    """OctoMap's pruning of Morton-ordered leaves: 8 equal sibling leaves at depth <= deepest
    become their parent, repeatedly (on copies)."""
    codes, depths, values = leaves.codes.copy(), leaves.depths.copy(), leaves.values.copy()
    n = K.collapse_leaves(codes, depths, values, deepest)
    return Leaves(codes[:n], depths[:n], values[:n])


def node_counts(leaves: Leaves) -> tuple[int, int]:
    """(leaf nodes, inner nodes) of the tree of canonical leaves, as OctoMap counts them
    (OcTree::getNumLeafNodes(), size() - that)."""
    return len(leaves), int(K.inner_nodes(leaves.codes, leaves.depths))


def max_likelihood(leaves: Leaves, threshold_log: float) -> Leaves:
    """The tree OctoMap writes to a .bt file: every leaf occupied (+1) or free (-1) by the
    threshold, then pruned (toMaxLikelihood + prune). voxtool prunes fully; OctoMap's own prune
    loop stops at the first level where nothing pruned, so its file can hold more nodes for the
    same voxels."""
    ml = np.where(leaves.values > np.float32(threshold_log), np.float32(1.0), np.float32(-1.0)).astype(np.float32)
    return collapse(Leaves(leaves.codes, leaves.depths, ml))
