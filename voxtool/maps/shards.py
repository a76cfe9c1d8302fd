"""OctoMap's OcTree as voxel bricks in Morton-prefix shards (kernels.octree).

The voxel values live in bricks of 8x8x8 voxels (a depth-13 subtree each). Bricks are grouped
into shards, the subtrees below depth `shard_depth` (8..13): a shard's row in `directory` maps
each brick position inside it to the brick's slot in the arena (-1: none). Shards share nothing,
so a set of shards plus its slices of a batch's updates is enough to advance it (the unit of
distribution); inside one process, threads split a batch's bricks into runs of equal work.

A batch of Morton-sorted updates is applied brick by brick, so every voxel sees OctoMap's
sequence of updates and the map equals OctoMap's whatever the threads or the shard depth. The
tree is derived when asked for (`leaves`, `node_counts`, `query` depths): pruning inside each
brick, then across bricks and shards (8 sibling bricks that are equal leaves become one leaf).
A loaded map may hold leaves coarser than a brick; they stay so (`coarse`) until an update
reaches into one, which then splits along the way, as OctoMap expands a pruned node.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass

import numpy as np

from voxtool.errors import ParameterError
from voxtool.kernels import octree as K
from voxtool.maps.base import Leaves
from voxtool.maps.tree import collapse, node_counts
from voxtool.parallel import run_parts

DEFAULT_SHARD_DEPTH = 10  # shards of 64^3 voxels, 512 bricks: a 2 KiB directory row each
MIN_SHARD_DEPTH = 8  # a directory row holds 8^(13 - depth) entries: 128 KiB at depth 8
SMALL_BATCH = 20_000  # updates; below this one thread applies a batch (a hand-off costs more)
RESETTLE_BELOW = 2.0**-40  # a decaying map's pending scale: below it, stored log-odds near float32's range
_NONE_F32 = np.zeros(0, dtype=np.float32)
LEAF_CHUNK = 1 << 20  # leaves a chunk of leaf_chunks: 13 MiB, big enough that a chunk's hand-offs cost nothing
_EMPTY = Leaves(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.float32))


def check_shard_depth(depth: int) -> int:
    if not MIN_SHARD_DEPTH <= depth <= K.BRICK_DEPTH:
        raise ParameterError(f"shard_depth={depth} must lie in {MIN_SHARD_DEPTH}..{K.BRICK_DEPTH}")
    return int(depth)


def leaf_spans(depths: np.ndarray) -> np.ndarray:
    return np.int64(1) << (3 * (16 - depths.astype(np.int64)))


def balanced_runs(starts: np.ndarray, parts: int) -> list[tuple[int, int]]:
    """Runs of bricks (starts[k]: a brick's first item) holding about equal numbers of items."""
    n = starts.shape[0] - 1
    cuts = np.searchsorted(starts, np.linspace(0, starts[-1], parts + 1)[1:-1]).tolist()
    bounds = [0] + cuts + [n]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


class Arena:
    """Brick storage in an anonymous memory map: page-aligned; grown in place by the OS (mremap)
    rather than copied (growing a 100 MB map by copies cost 0.3 s of a kaist03 build); with 2 MiB
    pages where the OS gives them (a scattered access then misses the TLB far less); untouched
    pages cost no memory."""

    def __init__(self, bricks: int) -> None:
        # private: a shared anonymous map cannot grow (its pages past the first size fault)
        self._map = mmap.mmap(-1, bricks * K.BRICK * 4, flags=mmap.MAP_PRIVATE)
        self._views()

    def _views(self) -> None:
        if hasattr(mmap, "MADV_HUGEPAGE"):
            self._map.madvise(mmap.MADV_HUGEPAGE)
        self.vals = np.frombuffer(self._map, dtype=np.float32)

    @property
    def bricks(self) -> int:
        return self.vals.shape[0] // K.BRICK

    def grow(self, bricks: int) -> None:
        """Room for `bricks` bricks (only while no kernel runs: the view is replaced)."""
        size = bricks * K.BRICK * 4
        del self.vals
        try:
            self._map.resize(size)
        except (BufferError, OSError, SystemError, ValueError):  # no mremap (not Linux), or a view held
            old = self._map
            self._map = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE)
            self._map[: len(old)] = old
        self._views()


@dataclass
class _Derived:
    """The tree above the voxel values, derived on demand (kept until the next change)."""

    slots: np.ndarray  # bricks in Morton order: their arena slots
    codes: np.ndarray  # ... their brick codes
    rank: np.ndarray  # slot -> index in that order
    l15: np.ndarray
    l14: np.ndarray
    root_leaf: np.ndarray
    counts: np.ndarray  # (leaf, inner) nodes inside each brick
    top: Leaves  # leaves at depth <= 13: bricks that are one leaf, coarse leaves; pruned across
    leaves: Leaves | None = None  # all leaves, once extracted


class ShardedOctree:
    """OctoMap's OcTree as voxel bricks in shards; see the module docstring."""

    def __init__(self, shard_depth: int = DEFAULT_SHARD_DEPTH, threads: int = 1) -> None:
        self.depth = check_shard_depth(shard_depth)
        self.threads = threads
        self.shift = 3 * (K.BRICK_DEPTH - self.depth)  # brick code >> shift = shard prefix
        self.per_shard = 1 << self.shift  # bricks a shard can hold
        self.arena = Arena(64)
        self.n_bricks = 0
        self.brick_code = np.zeros(64, dtype=np.int64)  # the brick code of each slot
        self.directory = np.full((16, self.per_shard), -1, dtype=np.int32)
        self.n_rows = 0
        self.prefixes = np.zeros(0, dtype=np.int64)  # sorted prefixes of the shards
        self.prefix_rows = np.zeros(0, dtype=np.int64)  # the directory row of each
        self.coarse = _EMPTY  # leaves coarser than a brick (a loaded map's), Morton order
        self.scale = 1.0  # a decaying map's stored log-odds times this are its log-odds (fade)
        self.forget = 0.0  # ... and a voxel whose |log-odds| is below this is unknown
        self._unsettled = False  # decay steps or updates since the last settle (decaying maps only)
        self._derived: _Derived | None = None

    # -- moving between processes -----------------------------------------------------------
    def bricks(self) -> tuple[np.ndarray, np.ndarray]:
        """(brick codes, their 512 log-odds each) in slot order: the map's whole content with
        `coarse` (what a Dask worker sends, or what put_bricks takes)."""
        self.settle()
        n = self.n_bricks
        return self.brick_code[:n].copy(), self.arena.vals[: n * K.BRICK].reshape(n, K.BRICK).copy()

    def put_bricks(self, codes: np.ndarray, values: np.ndarray) -> None:
        """Add bricks this map does not hold yet (another part of the same map)."""
        if codes.shape[0] == 0:
            return
        self.settle()
        self._derived = None
        order = np.argsort(codes, kind="stable")
        slots, fresh, _ = self._slots_for(codes[order])
        if not fresh.all():
            raise ValueError("put_bricks: a brick is already present")
        self.arena.vals.reshape(-1, K.BRICK)[slots] = values[order]

    def __getstate__(self) -> dict:
        codes, values = self.bricks()
        return {"depth": self.depth, "threads": self.threads, "codes": codes, "values": values, "coarse": self.coarse}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["depth"], state["threads"])
        self.coarse = state["coarse"]
        self.put_bricks(state["codes"], state["values"])

    # -- bricks ------------------------------------------------------------------------------
    def _rows_for(self, prefixes: np.ndarray) -> np.ndarray:
        """Directory rows of the shards with these (sorted, distinct) prefixes, made where missing."""
        idx = np.minimum(np.searchsorted(self.prefixes, prefixes), max(self.prefixes.shape[0] - 1, 0))
        found = self.prefixes[idx] == prefixes if self.prefixes.shape[0] else np.zeros(prefixes.shape[0], bool)
        rows = np.empty(prefixes.shape[0], dtype=np.int64)
        rows[found] = self.prefix_rows[idx[found]]
        new = np.flatnonzero(~found)
        if new.shape[0]:
            while self.n_rows + new.shape[0] > self.directory.shape[0]:
                grown = np.full((2 * self.directory.shape[0], self.per_shard), -1, dtype=np.int32)
                grown[: self.n_rows] = self.directory[: self.n_rows]
                self.directory = grown
            rows[new] = np.arange(self.n_rows, self.n_rows + new.shape[0])
            self.n_rows += new.shape[0]
            merged = np.concatenate([self.prefixes, prefixes[new]])
            order = np.argsort(merged, kind="stable")
            self.prefixes = merged[order]
            self.prefix_rows = np.concatenate([self.prefix_rows, rows[new]])[order]
        return rows

    def _slots_for(self, bricks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arena slots of these (sorted, distinct) bricks, made where missing: (slots, fresh,
        init), a fresh brick to be filled with init (NaN, or the coarse leaf it lies in)."""
        pre = bricks >> self.shift
        first = np.concatenate([[0], np.flatnonzero(np.diff(pre)) + 1])
        rows = np.repeat(self._rows_for(pre[first]), np.diff(np.append(first, pre.shape[0])))
        local = bricks & (self.per_shard - 1)
        slots = self.directory[rows, local].astype(np.int64)
        fresh = slots < 0
        init = np.full(bricks.shape[0], np.nan, dtype=np.float32)
        new = np.flatnonzero(fresh)
        if new.shape[0]:
            need = self.n_bricks + new.shape[0]
            if need > self.arena.bricks:
                self.arena.grow(max(need, 2 * self.arena.bricks))
            if need > self.brick_code.shape[0]:
                self.brick_code = np.concatenate([self.brick_code, np.zeros(max(need, self.brick_code.shape[0]), np.int64)])
            slots[new] = np.arange(self.n_bricks, need)
            self.n_bricks = need
            self.directory[rows[new], local[new]] = slots[new]
            self.brick_code[slots[new]] = bricks[new]
            if self.coarse.codes.shape[0]:
                init[new] = self._split_coarse(bricks[new])
        return slots, fresh, init

    def _split_coarse(self, bricks: np.ndarray) -> np.ndarray:
        """Values for new bricks (NaN where none): a brick inside a coarse leaf takes its value,
        and the leaf splits down to the brick, its other parts staying coarse leaves."""
        out = np.full(bricks.shape[0], np.nan, dtype=np.float32)
        for i, brick in enumerate(bricks.tolist()):
            c = self.coarse
            code = brick << K.BRICK_BITS
            k = int(np.searchsorted(c.codes, code, side="right")) - 1
            if k < 0 or code >= c.codes[k] + int(leaf_spans(c.depths[k: k + 1])[0]):
                continue
            out[i] = value = c.values[k]
            parts = []  # the 7 siblings of the path to the brick, at each level below the leaf
            for d in range(int(c.depths[k]) + 1, K.BRICK_DEPTH + 1):
                parent = (code >> (3 * (17 - d))) << (3 * (17 - d))
                mine = (code >> (3 * (16 - d))) & 7
                parts += [(parent | (j << (3 * (16 - d))), d) for j in range(8) if j != mine]
            codes = np.concatenate([np.delete(c.codes, k), np.array([p for p, _ in parts], dtype=np.int64)])
            depths = np.concatenate([np.delete(c.depths, k), np.array([d for _, d in parts], dtype=np.uint8)])
            values = np.concatenate([np.delete(c.values, k), np.full(len(parts), value, dtype=np.float32)])
            order = np.argsort(codes, kind="stable")
            self.coarse = Leaves(codes[order], depths[order], values[order])
        return out

    # -- updates ---------------------------------------------------------------------------
    def apply(self, items: np.ndarray, mode: int = K.ADD, values: np.ndarray = _NONE_F32,
              hit=0.0, miss=0.0, cmin=0.0, cmax=0.0, runs: tuple | None = None) -> None:
        """Apply updates (kernels.octree.apply_bricks' modes) brick by brick, on `threads`
        threads. Morton order is fastest; other orders are grouped by brick, keeping their order
        inside each (the order of updates to distinct voxels does not change the map). `runs`:
        the items' distinct bricks and where each one's items start, when the caller knows them."""
        n = items.shape[0]
        if n == 0:
            return
        self._derived = None
        shift = K.BRICK_BITS + (1 if mode == K.ADD else 0)
        bricks, starts, ordered = runs + (True,) if runs is not None else K.brick_runs(items, shift)
        if not ordered:
            by_brick = np.argsort(items >> shift, kind="stable")
            items = items[by_brick]
            values = values[by_brick] if values.shape[0] else values
            bricks, starts, _ = K.brick_runs(items, shift)
        if mode != K.ADD:
            self.settle()
        slots, fresh, init = self._slots_for(bricks)
        consts = self._update_consts(hit, miss, cmin, cmax)
        runs = balanced_runs(starts, 1 if n < SMALL_BATCH else self.threads)
        vals = self.arena.vals
        run_parts(self.threads, lambda r: K.apply_bricks(vals, slots, fresh, init, starts, r[0], r[1], items, values,
                                                         mode, *consts), runs)

    def _update_consts(self, hit: float, miss: float, cmin: float, cmax: float) -> tuple:
        """The kernels' (hit, miss, cmin, cmax, forget) for the updates about to be applied: a
        decaying map's, in its stored units (fade); an update may leave a voxel below forget."""
        s = self.scale
        self._unsettled |= self.forget > 0
        return (np.float32(hit / s), np.float32(miss / s), np.float32(cmin / s), np.float32(cmax / s),
                np.float32(self.forget / s))

    def apply_masks(self, bricks, hit=0.0, miss=0.0, cmin=0.0, cmax=0.0) -> int:
        """apply(mode ADD) of one scan's updates kept as merged brick masks (maps.octree.ScanBricks),
        straight from the masks; returns how many voxels were updated."""
        n = bricks.distinct.shape[0]
        if n == 0:
            return 0
        self._derived = None
        slots, fresh, init = self._slots_for(bricks.distinct)
        consts = self._update_consts(hit, miss, cmin, cmax)
        vals = self.arena.vals
        return sum(run_parts(self.threads, lambda r: K.apply_masks(vals, slots, fresh, init, bricks.touched, bricks.occ,
                                                                   bricks.order, bricks.firsts, r[0], r[1], *consts),
                             bricks.runs(self.threads)))

    def fade(self, factor: float, forget: float) -> None:
        """A decay step: every log-odds times `factor`, then a voxel whose |log-odds| is below
        `forget` is forgotten (unknown); reading the map is a step of factor 1. Lazily: the
        bricks hold log-odds / scale and updates are scaled to match (one division per update,
        not a pass over the map per scan); an update treats a stored value below forget / scale
        as unknown (the step before it forgot it); the bricks are settled (scaled and forgotten
        for real) before anything reads them, and when the scale nears float32's range."""
        self._derived = None
        self.scale *= factor
        self.forget = float(forget)
        self._unsettled = True
        if self.scale < RESETTLE_BELOW:
            self.settle()

    def settle(self) -> None:
        """Apply the pending decay to every brick and coarse leaf (fade)."""
        if not self._unsettled:
            return
        self._derived = None
        factor, forget = np.float32(self.scale), np.float32(self.forget)
        self.scale, self._unsettled = 1.0, False
        if self.coarse.codes.shape[0]:
            values = self.coarse.values * factor
            keep = np.abs(values) >= forget
            self.coarse = Leaves(self.coarse.codes[keep], self.coarse.depths[keep], values[keep])
        n = self.n_bricks
        vals = self.arena.vals
        run_parts(self.threads, lambda r: K.decay_bricks(vals, r[0], r[1], factor, forget),
                  balanced_runs(np.arange(n + 1), 1 if n * K.BRICK < SMALL_BATCH else self.threads))

    def load(self, leaves: Leaves) -> None:
        """Rebuild from Morton-ordered, non-overlapping leaves (a snapshot, a .bt file)."""
        self.settle()
        self._derived = None
        coarse = leaves.depths < K.BRICK_DEPTH
        if coarse.any():
            self.coarse = Leaves(leaves.codes[coarse], leaves.depths[coarse], leaves.values[coarse])
            leaves = Leaves(leaves.codes[~coarse], leaves.depths[~coarse], leaves.values[~coarse])
        if len(leaves) == 0:
            return
        bricks, starts, _ = K.brick_runs(leaves.codes, K.BRICK_BITS)
        slots, fresh, init = self._slots_for(bricks)
        vals = self.arena.vals
        K.apply_bricks(vals, slots, fresh, init, np.zeros(bricks.shape[0] + 1, np.int64), 0, bricks.shape[0],
                       leaves.codes, _NONE_F32, K.ADD, *[np.float32(0)] * 5)
        K.fill_leaves(vals, np.repeat(slots, np.diff(starts)), leaves.codes, leaves.depths,
                      np.ascontiguousarray(leaves.values, dtype=np.float32))

    # -- reading ---------------------------------------------------------------------------
    def _lookup(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log-odds, brick slot) at finest-level codes: NaN / -1 where no brick holds one."""
        self.settle()
        codes = np.ascontiguousarray(codes, dtype=np.int64)
        value = np.empty(codes.shape[0], dtype=np.float32)
        slot = np.empty(codes.shape[0], dtype=np.int64)
        K.voxel_values(codes, self.prefixes, self.prefix_rows, self.directory, self.arena.vals, self.shift, value, slot)
        return value, slot

    def values(self, codes: np.ndarray) -> np.ndarray:
        """Log-odds at finest-level Morton codes; NaN where unknown."""
        codes = np.asarray(codes, dtype=np.int64)
        out, slots = self._lookup(codes)
        if self.coarse.codes.shape[0]:
            outside = slots < 0
            if outside.any():
                out[outside] = self._in_leaves(self.coarse, codes[outside])[0]
        return out

    @staticmethod
    def _in_leaves(leaves: Leaves, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(value, depth) of the leaf of `leaves` holding each code; NaN / -1 where none."""
        value = np.full(codes.shape[0], np.nan, dtype=np.float32)
        depth = np.full(codes.shape[0], -1, dtype=np.int64)
        k = np.searchsorted(leaves.codes, codes, side="right") - 1
        ok = k >= 0
        ok[ok] = codes[ok] < leaves.codes[k[ok]] + leaf_spans(leaves.depths[k[ok]])
        value[ok] = leaves.values[k[ok]]
        depth[ok] = leaves.depths[k[ok]]
        return value, depth

    def query(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log-odds, depth of the leaf that answered) at finest-level Morton codes; NaN / -1
        where unknown."""
        codes = np.ascontiguousarray(codes, dtype=np.int64)
        d = self._derive()
        value, slots = self._lookup(codes)
        depth = np.full(codes.shape[0], -1, dtype=np.int64)
        index = np.where(slots >= 0, d.rank[np.maximum(slots, 0)], -1)
        index[np.isnan(value) & (slots >= 0)] = -1
        K.leaf_depths(codes, index, d.l15, d.l14, d.root_leaf, depth)
        above = (depth == K.BRICK_DEPTH) | (slots < 0)  # the leaf may be coarser than a brick
        if above.any():
            value[above], depth[above] = self._in_leaves(d.top, codes[above])
        return value, depth

    def _derive(self) -> _Derived:
        self.settle()
        if self._derived is not None:
            return self._derived
        slots = np.argsort(self.brick_code[: self.n_bricks], kind="stable")
        codes = self.brick_code[slots]
        rank = np.empty(self.n_bricks, dtype=np.int64)
        rank[slots] = np.arange(self.n_bricks)
        n = self.n_bricks
        l15 = np.zeros(n, np.int64)
        l14 = np.zeros(n, np.int64)
        root_leaf = np.zeros(n, np.bool_)
        counts = np.zeros((n, 2), np.int64)
        vals = self.arena.vals
        run_parts(self.threads, lambda r: K.summarize(vals, slots, r[0], r[1], l15, l14, root_leaf, counts),
                  balanced_runs(np.arange(n + 1), self.threads))
        leafs = np.flatnonzero(root_leaf)
        top = Leaves(np.concatenate([codes[leafs] << K.BRICK_BITS, self.coarse.codes]),
                     np.concatenate([np.full(leafs.shape[0], K.BRICK_DEPTH, np.uint8), self.coarse.depths]),
                     np.concatenate([vals[slots[leafs] * K.BRICK], self.coarse.values]))
        order = np.argsort(top.codes, kind="stable")
        top = collapse(Leaves(top.codes[order], top.depths[order], top.values[order]), K.BRICK_DEPTH)
        self._derived = _Derived(slots, codes, rank, l15, l14, root_leaf, counts, top)
        return self._derived

    def node_counts(self) -> tuple[int, int]:
        """(leaf nodes, inner nodes) of the tree, as OctoMap counts them."""
        return node_counts(self.leaves())

    def leaves(self) -> Leaves:
        """All leaves of the tree in Morton order (kept until the next change)."""
        d = self._derive()
        if d.leaves is None:
            d.leaves = next(iter(self.leaf_chunks(None)), _EMPTY)
        return d.leaves

    def leaf_count(self) -> int:
        """len(leaves()), without extracting them."""
        d = self._derive()
        if d.leaves is not None:
            return len(d.leaves)
        return int(d.counts[~d.root_leaf, 0].sum()) + len(d.top)

    def leaf_chunks(self, max_leaves: int | None = LEAF_CHUNK):
        """The leaves of `leaves()` as consecutive chunks of at most `max_leaves` (None: one
        chunk), or of one brick's leaves where a brick holds more. A chunk is a view of buffers
        the next chunk reuses: read it before asking for the next. A build's snapshot and
        statistics go through the leaves this way, never holding all of them (13 bytes a leaf)."""
        d = self._derive()
        if d.leaves is not None:
            yield d.leaves
            return
        inner = np.flatnonzero(~d.root_leaf)  # bricks whose own leaves are the tree's
        first = d.codes[inner] << K.BRICK_BITS
        per = d.counts[inner, 0]
        # a brick's leaves start after the leaves of the bricks and top leaves before it
        before = np.concatenate([[0], np.cumsum(per)]).astype(np.int64)
        offsets = before[:-1] + np.searchsorted(d.top.codes, first)
        total = int(before[-1]) + len(d.top)
        at_top = np.arange(len(d.top)) + before[np.searchsorted(first, d.top.codes)]
        step = total if max_leaves is None else max(int(max_leaves), 1)
        size = min(max(step, K.BRICK), total)
        codes = np.empty(size, dtype=np.int64)
        depths = np.empty(size, dtype=np.uint8)
        values = np.empty(size, dtype=np.float32)
        slots, l15, l14, bcodes = d.slots[inner], d.l15[inner], d.l14[inner], d.codes[inner]
        vals = self.arena.vals
        lo = 0
        while lo < total:
            # `step` leaves, or up to the brick holding the end (a brick's leaves come out of one
            # kernel call), or that whole brick when it starts the chunk
            hi = min(lo + step, total)
            k = int(np.searchsorted(offsets, hi, side="right")) - 1
            if k >= 0 and offsets[k] < hi < offsets[k] + per[k]:
                hi = int(offsets[k]) if offsets[k] > lo else int(offsets[k] + per[k])
            a, b = np.searchsorted(offsets, [lo, hi]).tolist()  # the chunk's bricks
            tops = slice(*np.searchsorted(at_top, [lo, hi]).tolist())
            put = at_top[tops] - lo
            codes[put], depths[put], values[put] = d.top.codes[tops], d.top.depths[tops], d.top.values[tops]
            local = offsets - lo  # the chunk's bricks write from their place in it
            runs = [(a + r0, a + r1) for r0, r1 in balanced_runs(np.append(local[a:b], hi - lo), self.threads)]
            run_parts(self.threads, lambda r, local=local: K.brick_leaves(vals, slots, bcodes, r[0], r[1], l15, l14,
                                                                          local, codes, depths, values), runs)
            yield Leaves(codes[: hi - lo], depths[: hi - lo], values[: hi - lo])
            lo = hi

    def used_bytes(self) -> int:
        """Bytes holding the map's content: its bricks, directory rows and coarse leaves (as
        many for a map loaded from a snapshot as for the one that wrote it)."""
        return int(self.n_bricks * K.BRICK * 4 + self.n_rows * self.per_shard * 4 + self.n_bricks * 8
                   + self.coarse.codes.shape[0] * 13)

    def memory_bytes(self) -> int:
        """Bytes of the arrays holding the map (allocated capacity)."""
        return int(self.arena.vals.nbytes + self.directory.nbytes + self.brick_code.nbytes + self.prefixes.nbytes
                   + self.prefix_rows.nbytes + self.coarse.codes.nbytes * 2)
