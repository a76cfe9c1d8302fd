"""The `octree` backend: OctoMap 1.10's OcTree semantics in flat arrays, updated in Morton order."""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.kernels import octree as K
from voxtool.kernels.raycast import BrickBuffers, bricks_to_packed, ray_signatures, scan_bricks
from voxtool.keys import coords_to_keys
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.sources.scan import Scan

BYTES_PER_SLOT = 4 + 1 + 4  # child int32, mask uint8, value float32
_NO_VALUES = np.zeros(0, dtype=np.float32)


class OctreePool:
    """Node pool plus the resumable batch-update protocol of `voxtool.kernels.octree`."""

    def __init__(self, capacity_slots: int = 1 << 16) -> None:
        self.child, self.mask, self.value, self.free, self.meta = K.new_pool(capacity_slots)
        self.path = np.zeros(17, dtype=np.int64)
        self.pstate = np.array([-1, 0], dtype=np.int64)

    def _grow(self) -> None:
        old = self.child.shape[0]
        new = (old * 3 // 2) // 8 * 8 + 8 * 4096  # 1.5x (+4096 blocks): less idle capacity than doubling
        self.child = np.concatenate([self.child, np.full(new - old, -1, dtype=np.int32)])
        self.mask = np.concatenate([self.mask, np.zeros(new - old, dtype=np.uint8)])
        self.value = np.concatenate([self.value, np.zeros(new - old, dtype=np.float32)])
        self.free = np.concatenate([self.free, np.zeros(new // 8 + 1 - self.free.shape[0], dtype=np.int32)])

    def _run(self, items: np.ndarray, values: np.ndarray, mode: int, sensor: SensorModel) -> None:
        hit, miss = np.float32(sensor.hit_log), np.float32(sensor.miss_log)
        cmin, cmax = np.float32(sensor.clamp_min_log), np.float32(sensor.clamp_max_log)
        start = 0
        while True:
            start = K.apply_updates(
                self.child, self.mask, self.value, self.free, self.meta, self.path, self.pstate,
                items, values, mode, start, hit, miss, cmin, cmax,
            )
            if start >= items.shape[0]:
                return
            self._grow()

    def apply(self, packed: np.ndarray, sensor: SensorModel) -> None:
        """Apply updates (code << 1 | occupied) with OctoMap's rule; Morton order is fastest."""
        self._run(packed, _NO_VALUES, K.ADD, sensor)

    def set_values(self, codes: np.ndarray, values: np.ndarray, sensor: SensorModel) -> None:
        """Overwrite finest-level voxels with log-odds `values` (cache write-back)."""
        self._run(codes, np.ascontiguousarray(values, dtype=np.float32), K.SET, sensor)

    def load(self, leaves: Leaves) -> None:
        start = 0
        while True:
            start = K.insert_leaves(
                self.child, self.mask, self.value, self.free, self.meta, self.path, self.pstate,
                leaves.codes, leaves.depths, leaves.values, start,
            )
            if start >= len(leaves):
                return
            self._grow()

    def query(self, codes: np.ndarray) -> np.ndarray:
        codes = np.ascontiguousarray(codes, dtype=np.int64)
        out = np.empty(codes.shape[0], dtype=np.float32)
        depth = np.empty(codes.shape[0], dtype=np.int64)
        K.lookup(self.child, self.mask, self.value, self.meta, codes, out, depth)
        return out

    def node_counts(self) -> tuple[int, int]:
        leaves, inner = K.count_nodes(self.child, self.mask, self.meta)
        return int(leaves), int(inner)

    def leaves(self) -> Leaves:
        n_leaves, _ = self.node_counts()
        codes, depths, values = K.extract_leaves(self.child, self.mask, self.value, self.meta, n_leaves)
        return Leaves(codes, depths, values)

    def used_slots(self) -> int:
        return int(self.meta[K.META_TOP] - 8 * self.meta[K.META_NFREE])

    def memory_bytes(self) -> int:
        """Bytes of the allocated pool arrays (what the process holds for the tree)."""
        return int(self.child.nbytes + self.mask.nbytes + self.value.nbytes + self.free.nbytes)


RAY_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="voxtool-raycast")


def _new_ray_pool_in_child() -> None:
    # a forked child inherits the pool but none of its threads: work submitted to it would wait
    # forever (a multiprocessing worker casting rays hung). The child gets a pool of its own.
    global RAY_POOL
    RAY_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="voxtool-raycast")


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_ray_pool_in_child)
_SPLITS = 2  # this machine class has 2 cores; each thread traces half of the rays
SMALL_SCAN = 2_000  # points; below this one thread traces the whole scan
_BUFFERS = threading.local()


def _trace_part(scan: Scan, params: MapParams, lo: int, hi: int) -> tuple:
    """Trace rays lo..hi into this thread's brick buffers; returns copies of the used part."""
    buf = getattr(_BUFFERS, "bricks", None) or BrickBuffers()
    while True:
        n, steps = scan_bricks(scan.points[lo:hi], scan.origin, params.resolution, params.max_range,
                               buf.tab, buf.touched, buf.occ, buf.bricks)
        if n >= 0:
            break
        buf = BrickBuffers(2 * buf.bricks.shape[0])
    _BUFFERS.bricks = buf
    out = (buf.bricks[:n].copy(), buf.touched[:n].copy(), buf.occ[:n].copy(), steps)
    buf.reset(n)
    return out


def merge_rays(scan: Scan, params: MapParams) -> Scan:
    """Keep one representative of every group of rays with identical voxel paths.

    Rays are identical when they end in the same voxel (and both hit or both were cut at max
    range) and their DDA visits the same voxels in the same order (64-bit path signature).
    Under OctoMap's one-update-per-voxel-per-scan model the map is unchanged."""
    n = scan.points.shape[0]
    ends = np.empty(n, dtype=np.int64)
    sigs = np.empty(n, dtype=np.int64)
    ray_signatures(scan.points, scan.origin, params.resolution, params.max_range, ends, sigs)
    order = np.lexsort((sigs, ends))
    first = np.ones(n, dtype=bool)
    first[1:] = (ends[order][1:] != ends[order][:-1]) | (sigs[order][1:] != sigs[order][:-1])
    keep = np.sort(order[first])
    return Scan(scan.points[keep], scan.origin, scan.index, scan.stamp_ns, scan.source)


def scan_updates(scan: Scan, params: MapParams) -> tuple[np.ndarray, int, int]:
    """Morton-sorted (code << 1 | occupied) voxel updates of one scan, its DDA step count, and
    how many rays were merged into others (0 unless params.merge_rays)."""
    n = scan.points.shape[0]
    if n == 0:
        return np.empty(0, dtype=np.int64), 0, 0
    coords_to_keys(scan.origin[None, :], params.resolution, what=f"{scan.source}: sensor origin of scan")
    coords_to_keys(scan.points, params.resolution, what=f"{scan.source}: point")
    merged = 0
    if params.merge_rays:
        scan = merge_rays(scan, params)
        merged = n - scan.points.shape[0]
        n = scan.points.shape[0]
    if n < SMALL_SCAN:  # thread hand-off costs more than it saves on small scans
        parts = [_trace_part(scan, params, 0, n)]
    else:
        cuts = np.linspace(0, n, _SPLITS + 1).astype(int)
        parts = list(RAY_POOL.map(lambda k: _trace_part(scan, params, cuts[k], cuts[k + 1]), range(_SPLITS)))
    bricks = np.concatenate([p[0] for p in parts])
    touched = np.concatenate([p[1] for p in parts])
    occ = np.concatenate([p[2] for p in parts])
    order = np.argsort(bricks, kind="stable")
    return bricks_to_packed(bricks, touched, occ, order), int(sum(p[3] for p in parts)), merged


def prepare_scan(scan: Scan, params: MapParams) -> PreparedScan:
    """A scan's voxel updates, timed, with the ray-merging count when it is enabled."""
    t0 = time.perf_counter()
    packed, steps, merged = scan_updates(scan, params)
    return PreparedScan(packed, steps, time.perf_counter() - t0, int(scan.points.shape[0]), merged)


def warm_up_kernels() -> None:
    """Load (or compile, first time on a machine) the kernels on a tiny scan, so the JIT cost is
    reported apart from the first scan's latency."""
    scan = Scan(np.array([[1.0, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32))
    pool = OctreePool(64)
    pool.apply(scan_updates(scan, MapParams(resolution=0.5))[0], SensorModel())
    merge_rays(scan, MapParams(resolution=0.5))
    pool.leaves()
    pool.query(np.zeros(1, dtype=np.int64))


class OctreeMap:
    """OctoMap-exact occupancy octree (see docs/backends.md)."""

    name = "octree"

    def __init__(self, params: MapParams, sensor: SensorModel) -> None:
        self.params = params
        self.sensor = sensor
        self.pool = OctreePool()

    def warm_up(self) -> None:
        warm_up_kernels()

    def prepare(self, scan: Scan) -> PreparedScan:
        """Ray casting: independent of the map, so it may run ahead on another thread."""
        return prepare_scan(scan, self.params)

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        """Tree update; prepared scans must be applied in scan order."""
        t0 = time.perf_counter()
        self.pool.apply(prepared.packed, self.sensor)
        return IntegrateTiming(raycast=prepared.seconds, update=time.perf_counter() - t0,
                               voxel_updates=int(prepared.packed.shape[0]), ray_steps=prepared.steps,
                               rays=prepared.rays, merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def query(self, codes: np.ndarray) -> np.ndarray:
        return self.pool.query(codes)

    def leaves(self) -> Leaves:
        return self.pool.leaves()

    def node_counts(self) -> tuple[int, int]:
        return self.pool.node_counts()

    def memory_bytes(self) -> int:
        return self.pool.memory_bytes()

    def state_arrays(self) -> dict[str, np.ndarray]:
        leaves = self.leaves()
        return {"leaf_codes": leaves.codes, "leaf_depths": leaves.depths, "leaf_values": leaves.values}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        self.pool = OctreePool(max(1 << 16, 2 * arrays["leaf_codes"].shape[0]))
        self.pool.load(Leaves(arrays["leaf_codes"], arrays["leaf_depths"], arrays["leaf_values"]))

    def extra_meta(self) -> dict[str, Any]:
        return {}

    def extra_stats(self) -> dict[str, Any]:
        return {"bytes_per_node": BYTES_PER_SLOT, "pool_slots_used": self.pool.used_slots()}
