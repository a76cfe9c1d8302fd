"""The `tiny` backend: TinyOctoMap (seed tinyoctomap-heterogeneous-navs.md, Sec. III-A).

An octree of integer words in a fixed pool of `pool_blocks` blocks of 8 siblings. Occupancy is a
4-bit level instead of float log-odds: level 0 = unknown, a new voxel starts at `prior` (6), a hit
adds `hit` (2), a miss subtracts `miss` (1), clamped to [1, 15]; occupied when level > prior.
One level step is OctoMap's miss (0.405 log-odds), so hit = 0.81 (OctoMap 0.847), clamps = -2.03 /
+3.65 (OctoMap -1.99 / +3.51). Depth follows from the map size: the smallest d with
resolution * 2^d >= map_size, the map centred on the origin.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.kernels import tiny as K
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.maps.octree import OctreeMap, prepare_scan
from voxtool.parallel import resolve_threads
from voxtool.sources.scan import Scan

LEVEL_STEP_LOG = 0.4054651  # log-odds of one level: OctoMap's miss
MAX_BLOCKS = 1 << 28  # 32-bit words hold 28 bits of block index


def _doubled(words: np.ndarray, free: np.ndarray, per_block: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """A pool of `per_block` words a block and its free list, with twice the blocks."""
    blocks = min(2 * free.shape[0], MAX_BLOCKS)
    if blocks == free.shape[0]:
        raise ParameterError(f"tiny map: {what} would need more than {MAX_BLOCKS} blocks")
    more = blocks - free.shape[0]
    return (np.concatenate([words, np.zeros(more * per_block, dtype=words.dtype)]),
            np.concatenate([free, np.zeros(more, dtype=np.int64)]))


class TinyMap:
    name = "tiny"

    def __init__(self, params: MapParams, sensor: SensorModel, pool_blocks: int | None = None,
                 map_size: float | None = None, hit: int = 2, miss: int = 1, prior: int = 6, threads: int = 0) -> None:
        if pool_blocks is not None and not 2 <= pool_blocks <= MAX_BLOCKS:
            raise ParameterError(f"pool_blocks={pool_blocks} must lie in 2..2^28 (or none: grown as the map needs)")
        if not (1 <= prior < 15 and 1 <= hit <= 14 and 1 <= miss <= 14):
            raise ParameterError(f"tiny levels hit={hit} miss={miss} prior={prior} out of range (levels are 1..15)")
        self.params, self.sensor = params, sensor
        self.threads = resolve_threads(threads)  # ray casting (the pool itself is updated by one)
        size = map_size if map_size is not None else params.resolution * 2048
        if not (size > 0 and np.isfinite(size)):
            raise ParameterError(f"map_size={size} must be positive")
        self.map_size = float(size)
        self.depth = max(1, int(np.ceil(np.log2(size / params.resolution))))
        if self.depth > 16:
            raise ParameterError(f"map_size={size} m at {params.resolution} m needs depth {self.depth} > 16")
        self.offset = 32768 - (1 << (self.depth - 1))  # tiny key 0 = OctoMap key offset
        self.hit, self.miss, self.prior = hit, miss, prior
        # a budget (the paper's fixed pool: updates that need more are dropped and counted), or
        # none: the pool grows as the map needs (32-bit words)
        self.budget = pool_blocks
        blocks = pool_blocks if pool_blocks is not None else 256  # a grown pool doubles as it fills
        dtype = np.uint16 if pool_blocks is not None and pool_blocks <= 4096 else np.uint32  # 12 index bits: 16-bit words
        self.pool = np.zeros(blocks * 8, dtype=dtype)
        self.free = np.zeros(blocks, dtype=np.int64)
        # 32-bit words pack the finest level, 8 voxels a uint32 (kernels.tiny), in a second pool of
        # as many blocks; the paper's 16-bit pool keeps its words throughout
        self.pack = dtype == np.uint32
        leaf_blocks = blocks if self.pack else 0
        self.finest = np.zeros(leaf_blocks, dtype=np.uint32)
        self.finest_free = np.zeros(leaf_blocks, dtype=np.int64)
        self.meta = np.array([0, 1, blocks, 0, 0, 0, 1, leaf_blocks], dtype=np.int64)

    @property
    def pool_blocks(self) -> int:
        return int(self.meta[K.T_BLOCKS])

    def _grow(self) -> None:
        """Double whichever pool is full (the kernel stopped for want of a block)."""
        if self.pack and self.meta[K.T_LEAF_FREE_TOP] == 0 and self.meta[K.T_LEAF_NEXT] >= self.meta[K.T_LEAF_BLOCKS]:
            self.finest, self.finest_free = _doubled(self.finest, self.finest_free, 1, "the finest level")
            self.meta[K.T_LEAF_BLOCKS] = self.finest_free.shape[0]
        else:
            self.pool, self.free = _doubled(self.pool, self.free, 8, "the pool")
            self.meta[K.T_BLOCKS] = self.free.shape[0]

    # -- MapBackend -------------------------------------------------------------------------
    def warm_up(self) -> None:
        OctreeMap(self.params, self.sensor, threads=1).warm_up()
        probe = TinyMap(MapParams(resolution=0.5), self.sensor, pool_blocks=self.budget, map_size=8.0, threads=1)
        probe.integrate(Scan(np.array([[1.0, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32)))
        probe.leaves()

    def prepare(self, scan: Scan) -> PreparedScan:
        return prepare_scan(scan, self.params, self.threads)

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        t0 = time.perf_counter()
        start, n = 0, prepared.packed.shape[0]
        while True:
            start = K.tiny_apply(self.pool, self.free, self.finest, self.finest_free, self.meta, prepared.packed,
                                 self.offset, self.depth, self.hit, self.miss, self.prior, 1, 15, start,
                                 self.budget is None, self.pack)
            if start >= n:
                break
            self._grow()
        return IntegrateTiming(raycast=prepared.seconds, update=time.perf_counter() - t0,
                               voxel_updates=int(prepared.packed.shape[0]), ray_steps=prepared.steps,
                               rays=prepared.rays, merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def level_leaves(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = (self.blocks_used() + self.leaf_blocks_used()) * 8 + 8
        codes = np.empty(n, dtype=np.int64)
        depths = np.empty(n, dtype=np.uint8)
        levels = np.empty(n, dtype=np.int64)
        k = K.tiny_leaves(self.pool, self.finest, self.pack, self.offset, self.depth, codes, depths, levels)
        return codes[:k], depths[:k], levels[:k]

    def leaves(self) -> Leaves:
        codes, depths, levels = self.level_leaves()
        values = ((levels - self.prior) * LEVEL_STEP_LOG).astype(np.float32)
        return Leaves(codes, depths, values)

    def query(self, codes: np.ndarray) -> np.ndarray:
        lv = self.leaves()
        from voxtool.keys import leaf_span

        ends = lv.codes + leaf_span(lv.depths)
        idx = np.searchsorted(lv.codes, codes, side="right") - 1
        out = np.full(codes.shape[0], np.nan, dtype=np.float32)
        ok = (idx >= 0) & (codes < ends[np.clip(idx, 0, None)]) if lv.codes.shape[0] else np.zeros(codes.shape[0], bool)
        out[ok] = lv.values[idx[ok]]
        return out

    def blocks_used(self) -> int:
        return int(self.meta[K.T_NEXT] - self.meta[K.T_FREE_TOP])

    def leaf_blocks_used(self) -> int:
        """Packed finest-level blocks in use (leaf block 0 is never used)."""
        return int(max(self.meta[K.T_LEAF_NEXT] - 1 - self.meta[K.T_LEAF_FREE_TOP], 0)) if self.pack else 0

    def node_counts(self) -> tuple[int, int]:
        codes, _, _ = self.level_leaves()
        inner = self.blocks_used() - 1 + self.leaf_blocks_used()  # one parent per allocated block
        return int(codes.shape[0]), int(inner)

    def memory_bytes(self) -> int:
        return int(self.pool.nbytes + self.finest.nbytes)

    def used_bytes(self) -> int:
        return int(self.blocks_used() * 8 * self.pool.itemsize + self.leaf_blocks_used() * self.finest.itemsize)

    def extra_stats(self) -> dict[str, Any]:
        return self.pool_stats()

    def pool_stats(self) -> dict:
        used = self.blocks_used()
        return {"pool_blocks": self.pool_blocks, "pool_budget": self.budget, "pool_blocks_used": used,
                "pool_usage": round(used / self.pool_blocks, 6),
                "bytes_per_node": int(self.pool.itemsize), "finest_level_packed": self.pack,
                "leaf_blocks": int(self.finest.shape[0]), "leaf_blocks_used": self.leaf_blocks_used(),
                "dropped_updates": int(self.meta[K.T_DROPPED]),
                "outside_map_updates": int(self.meta[K.T_OUTSIDE]), "depth": self.depth, "map_size_m": self.map_size}

    def state_arrays(self) -> dict[str, np.ndarray]:
        lv = self.leaves()
        return {"leaf_codes": lv.codes, "leaf_depths": lv.depths, "leaf_values": lv.values,
                "tiny_pool": self.pool.astype(np.uint32), "tiny_free": self.free, "tiny_meta": self.meta,
                "tiny_leaves": self.finest, "tiny_leaf_free": self.finest_free}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """The pools of a snapshot. One written before the finest level was packed (meta of 5,
        no `tiny_leaves`) loads unpacked, as it was built."""
        from voxtool.errors import FormatError

        pool, free, meta = arrays.get("tiny_pool"), arrays.get("tiny_free"), arrays.get("tiny_meta")
        leaves, leaf_free = arrays.get("tiny_leaves"), arrays.get("tiny_leaf_free")
        if pool is None or free is None or meta is None or meta.shape[0] not in (5, K.META_SIZE):
            raise FormatError("tiny snapshot: pool arrays missing")
        if meta.shape[0] == 5:
            meta = np.concatenate([meta, [0, 1, 0]])
            leaves, leaf_free = np.zeros(0, dtype=np.uint32), np.zeros(0, dtype=np.int64)
        if leaves is None or leaf_free is None:
            raise FormatError("tiny snapshot: pool arrays missing")
        blocks, leaf_blocks = pool.shape[0] // 8, leaves.shape[0]
        pack = leaf_blocks > 0
        if pool.shape[0] % 8 or free.shape[0] != blocks or blocks > MAX_BLOCKS or meta[K.T_BLOCKS] != blocks \
                or leaf_free.shape[0] != leaf_blocks or leaf_blocks > MAX_BLOCKS or meta[K.T_LEAF_BLOCKS] != leaf_blocks \
                or (self.budget is not None and blocks != self.budget):
            raise FormatError("tiny snapshot: pool arrays of the wrong size")
        if np.any((pool >> 4) >= max(blocks, leaf_blocks)) or np.any(free < 0) or np.any(free >= blocks) \
                or np.any(leaf_free < 0) or np.any(leaf_free >= max(leaf_blocks, 1)):
            raise FormatError("tiny snapshot: a child index points outside the pool")
        self.pool = pool.astype(self.pool.dtype)
        self.free = free.astype(np.int64)
        self.finest = leaves.astype(np.uint32)
        self.finest_free = leaf_free.astype(np.int64)
        self.meta = meta.astype(np.int64)
        self.pack = pack

    def extra_meta(self) -> dict[str, Any]:
        return {"pool_blocks": self.budget, "map_size": self.map_size, "hit": self.hit, "miss": self.miss,
                "prior": self.prior}
