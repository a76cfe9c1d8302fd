"""The tree of a sharded map, joined from its parts without holding them together.

A part holds whole shards (the Morton-prefix subtrees at the shard depth). Its pruned leaves
are cut into units: a shard's subtree, or a leaf at or above the shard depth (a part is pruned
inside itself, so 8 sibling shards of one part can already be one coarser leaf). The units of
every part, in Morton order, are then joined by the nodes above them, pruned where 8 children
are leaves of one value, as OctoMap prunes. Memory: one part, plus a few numbers per unit; a
.bt's unit streams wait in a spool file until the join writes them in order.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from voxtool.maps.base import Leaves

LEAF, INNER = 1, 3  # a unit is a leaf, or a subtree whose stream is spooled


@dataclass
class Units:
    """Subtrees of a sharded map, one row each: first finest-level code, depth, value (when a
    leaf), its own leaf and inner nodes (when a subtree), its stream in the spool."""

    code: list = field(default_factory=list)
    depth: list = field(default_factory=list)
    kind: list = field(default_factory=list)
    value: list = field(default_factory=list)
    leaves: list = field(default_factory=list)
    inner: list = field(default_factory=list)
    offset: list = field(default_factory=list)
    length: list = field(default_factory=list)

    def arrays(self) -> dict[str, np.ndarray]:
        order = np.argsort(np.asarray(self.code, np.int64), kind="stable")
        return {k: np.asarray(getattr(self, k))[order] for k in
                ("code", "depth", "kind", "value", "leaves", "inner", "offset", "length")}


def unit_bounds(leaves: Leaves, shard_depth: int) -> np.ndarray:
    """Start of every unit in Morton-ordered leaves, and the end (len(leaves))."""
    depth = np.minimum(leaves.depths.astype(np.int64), shard_depth)
    unit = leaves.codes >> (3 * (16 - depth))
    new = np.ones(len(leaves), bool)
    new[1:] = (unit[1:] != unit[:-1]) | (depth[1:] != depth[:-1])
    return np.append(np.flatnonzero(new), len(leaves))


def add_part(units: Units, leaves: Leaves, shard_depth: int, spool=None) -> None:
    """Cut a part's canonical (pruned) leaves into units. With `spool` (a binary file) every
    subtree unit's OctoMap stream is appended to it (for the .bt of max-likelihood leaves)."""
    from voxtool.kernels import octree as K
    from voxtool.kernels.bt import serialize_bt

    bounds = unit_bounds(leaves, shard_depth)
    for a, b in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        d = min(int(leaves.depths[a]), shard_depth)
        code = int(leaves.codes[a]) >> (3 * (16 - d)) << (3 * (16 - d))
        units.code.append(code)
        units.depth.append(d)
        if b - a == 1 and int(leaves.depths[a]) == d:
            units.kind.append(LEAF)
            units.value.append(float(leaves.values[a]))
            units.leaves.append(0)
            units.inner.append(0)
            units.offset.append(0)
            units.length.append(0)
            continue
        units.kind.append(INNER)
        units.value.append(np.nan)
        units.leaves.append(b - a)
        codes, depths = leaves.codes[a:b], leaves.depths[a:b]
        if spool is None:
            units.inner.append(int(K.inner_nodes(codes, depths, 0, -1)) - d)
            units.offset.append(0)
            units.length.append(0)
            continue
        occupied = leaves.values[a:b] > 0
        data = np.zeros(serialize_bt(codes, depths, occupied, np.zeros(0, np.uint8)), np.uint8)
        serialize_bt(codes, depths, occupied, data)
        # the stream from the root: one word per ancestor above the unit, then the unit's own
        units.inner.append(data.shape[0] // 2 - d)
        units.offset.append(spool.tell())
        units.length.append(data.shape[0] - 2 * d)
        spool.write(data[2 * d:].tobytes())


def join(units: dict[str, np.ndarray]) -> tuple[int, int, list]:
    """(leaf nodes, inner nodes, pieces) of the whole tree: pieces in OctoMap's stream order,
    each a 16-bit word (int) or a unit index (its spooled stream)."""
    code, depth, kind, value = units["code"], units["depth"], units["kind"], units["value"]

    def node(first: int, d: int, lo: int, hi: int):
        # (LEAF, value) | (INNER, unit index) | (0, children)
        if hi - lo == 1 and depth[lo] == d:
            return (LEAF, float(value[lo])) if kind[lo] == LEAF else (INNER, lo)
        step = 1 << (3 * (15 - d))
        cuts = [lo, *(np.searchsorted(code[lo:hi], first + step * np.arange(1, 8)) + lo).tolist(), hi]
        children = [node(first + j * step, d + 1, cuts[j], cuts[j + 1]) if cuts[j + 1] > cuts[j] else None
                    for j in range(8)]
        if all(c is not None and c[0] == LEAF for c in children) and len({c[1] for c in children}) == 1:
            return children[0]
        return (0, children)

    if len(code) == 0:
        return 0, 0, []
    root = node(0, 0, 0, len(code))  # units lie below the root: it is split, or pruned to one leaf
    if root[0] == LEAF:
        return 1, 0, []
    counts = [0, 0]  # leaves, inner nodes above the units
    pieces: list = []

    def emit(children) -> None:
        counts[1] += 1
        word = 0
        for j, c in enumerate(children):
            if c is None:
                continue
            if c[0] == LEAF:
                word |= (2 if c[1] > 0 else 1) << (2 * j)
                counts[0] += 1
            else:
                word |= 3 << (2 * j)
        pieces.append(word)
        for c in children:
            if c is not None and c[0] == INNER:
                pieces.append(("unit", c[1]))
            elif c is not None and c[0] == 0:
                emit(c[1])

    emit(root[1])
    inner_units = units["kind"] == INNER
    return (counts[0] + int(units["leaves"][inner_units].sum()),
            counts[1] + int(units["inner"][inner_units].sum()), pieces)


def join_counts(ml: Units, lo: Units) -> dict:
    """Node counts of a sharded map's two trees from its parts' units, as `stats` gives them for
    a snapshot: the max-likelihood (.bt) tree's and the log-odds octree's."""
    ml_leaves, ml_inner, _ = join(ml.arrays())
    lo_leaves, lo_inner, _ = join(lo.arrays())
    return {"bt_leaf_nodes": ml_leaves, "bt_inner_nodes": ml_inner, "logodds_leaf_nodes": lo_leaves,
            "logodds_inner_nodes": lo_inner}


def write_pieces(handle, pieces: list, units: dict[str, np.ndarray], spool) -> None:
    """Write a join's pieces: words as little-endian uint16, units copied from the spool."""
    words: list[int] = []
    for piece in pieces:
        if isinstance(piece, int):
            words.append(piece)
            continue
        if words:
            handle.write(struct.pack(f"<{len(words)}H", *words))
            words = []
        spool.seek(int(units["offset"][piece[1]]))
        handle.write(spool.read(int(units["length"][piece[1]])))
    if words:
        handle.write(struct.pack(f"<{len(words)}H", *words))
