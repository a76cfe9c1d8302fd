"""The `octocache` backend: OctoCache (seed octocache.md) in front of the octree backend.

A cache of w buckets (w a power of two, bucket = Morton code mod w) holds voxels with their
accumulated log-odds. A scan's updates go to the cache (a miss is seeded from the octree, so the
cache always holds what the octree would); afterwards every bucket above `tau` cells evicts its
oldest cells, which are written back to the octree in the chosen order. Queries look in the cache
first, then the octree, so every answer equals the plain octree's. With overlap=1 (the paper's
two threads) the write-back runs on its own thread while the next scan is ray-cast; cache
insertion waits for it, because a cache miss reads the octree. `threads` is the wrapped octree's
(ray casting and shard updates), as for the `octree` backend.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.kernels import cache as C
from voxtool.kernels import octree as K
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.maps.octree import OctreeMap
from voxtool.sources.scan import Scan

ORDERS = ("morton", "xyz", "random", "bucket")


@dataclass
class CacheCounters:
    """What the cache did, per scan and in total (seconds are thread-1 unless noted)."""

    hits: list[int] = field(default_factory=list)
    updates: list[int] = field(default_factory=list)
    written_to_octree: int = 0
    raycast: float = 0.0
    insert: float = 0.0
    evict: float = 0.0
    octree_update: float = 0.0  # on the write-back thread when overlap == 1
    wait: float = 0.0  # thread 1 waiting for thread 2


class OctoCacheMap:
    """Cache layer wrapping an OctreeMap (composition, not inheritance)."""

    name = "octocache"

    def __init__(self, params: MapParams, sensor: SensorModel, buckets: int | None = None, tau: int = 4,
                 overlap: int = 0, order: str = "morton", seed: int = 0, threads: int = 0) -> None:
        if buckets is not None and (buckets < 1 or buckets & (buckets - 1)):
            raise ParameterError(f"buckets={buckets} must be a power of two")
        if not 1 <= tau <= 64:
            raise ParameterError(f"tau={tau} must lie in 1..64")
        if overlap not in (0, 1):
            raise ParameterError(f"overlap={overlap} must be 0 (write-back on the calling thread) or 1 (on its own)")
        if order not in ORDERS:
            raise ParameterError(f"order '{order}' is not one of {', '.join(ORDERS)}")
        self.params, self.sensor = params, sensor
        self.tree = OctreeMap(params, sensor, threads=threads)
        self.threads = self.tree.threads
        self.tau, self.overlap, self.order = tau, overlap, order
        self.slots = 2 * tau  # cells per bucket; widened when a batch overflows a bucket
        self.buckets = buckets
        self.count: np.ndarray | None = None
        self.counters = CacheCounters()
        self._rng = np.random.default_rng(seed)
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="voxtool-octree") if overlap else None
        self._pending: Future | None = None
        self._lock = threading.Lock()
        if buckets is not None:
            self._allocate(buckets)

    def _allocate(self, buckets: int) -> None:
        self.buckets = buckets
        self.count = np.zeros(buckets, dtype=np.int32)
        self.cell_code = np.zeros(buckets * self.slots, dtype=np.int64)
        self.cell_val = np.zeros(buckets * self.slots, dtype=np.float32)

    def _widen(self) -> None:
        """Double the cells per bucket (a bucket overflowed during a batch); cells keep their order."""
        w, old = self.count.shape[0], self.slots
        self.slots = 2 * old
        for name in ("cell_code", "cell_val"):
            arr = getattr(self, name)
            wide = np.zeros((w, self.slots), dtype=arr.dtype)
            wide[:, :old] = arr.reshape(w, old)
            setattr(self, name, wide.reshape(-1))

    def _sizing_rule(self, distinct: int) -> int:
        """Paper's rule: cache capacity (tau * w cells) about 3-4x a batch's distinct voxels."""
        target = max(1, int(round(3.5 * distinct / self.tau)))
        return 1 << max(10, int(round(np.log2(target))))

    # -- write-back ---------------------------------------------------------------------
    def _ordered(self, codes: np.ndarray, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.order == "morton":
            idx = np.argsort(codes, kind="stable")
        elif self.order == "xyz":
            from voxtool.keys import morton_decode

            k = morton_decode(codes).astype(np.int64)
            idx = np.argsort((k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2], kind="stable")
        elif self.order == "random":
            idx = self._rng.permutation(codes.shape[0])
        else:  # bucket: the paper's literal sweep, buckets in index order
            return codes, vals
        return codes[idx], vals[idx]

    def _write_back(self, codes: np.ndarray, vals: np.ndarray) -> float:
        t0 = time.perf_counter()
        if codes.shape[0]:
            with self._lock:
                self.tree.apply_updates(codes, K.SET, vals)
        self.counters.written_to_octree += int(codes.shape[0])
        return time.perf_counter() - t0

    def _wait(self) -> None:
        if self._pending is not None:
            t0 = time.perf_counter()
            self.counters.octree_update += self._pending.result()
            self.counters.wait += time.perf_counter() - t0
            self._pending = None

    # -- MapBackend -----------------------------------------------------------------------
    def warm_up(self) -> None:
        """Load the octree and cache kernels on a throwaway instance (JIT cost kept out of timings)."""
        self.tree.warm_up()
        probe = OctoCacheMap(MapParams(resolution=0.5), self.sensor, buckets=1024, tau=1, order=self.order, threads=1)
        probe.integrate(Scan(np.array([[1.0, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32)))
        probe.query(np.zeros(1, dtype=np.int64))
        probe.flush()

    def prepare(self, scan: Scan) -> PreparedScan:
        prepared = self.tree.prepare(scan)
        prepared.updates()  # the cache takes per-voxel updates: expanded here, on the read-ahead thread
        return prepared

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        packed = prepared.updates()
        s = self.sensor
        t0 = time.perf_counter()
        self._wait()  # a cache miss reads the octree: thread 2 must be done writing
        t1 = time.perf_counter()
        if self.count is None:
            self._allocate(self._sizing_rule(packed.shape[0]))
        seed = self.tree.query(packed >> 1)  # what a miss starts from: the octree's value (NaN: unknown)
        hits, start = 0, 0
        while True:
            h, start = C.cache_insert(packed, start, self.count, self.cell_code, self.cell_val, self.slots, seed,
                                      np.float32(s.hit_log), np.float32(s.miss_log),
                                      np.float32(s.clamp_min_log), np.float32(s.clamp_max_log))
            hits += h
            if start >= packed.shape[0]:
                break
            self._widen()
        t2 = time.perf_counter()
        n_cached = int(self.count.sum())
        ev_code = np.empty(n_cached, dtype=np.int64)
        ev_val = np.empty(n_cached, dtype=np.float32)
        n_ev = C.cache_evict(self.count, self.cell_code, self.cell_val, self.slots, self.tau, ev_code, ev_val, 0)
        codes, vals = self._ordered(ev_code[:n_ev], ev_val[:n_ev])
        t3 = time.perf_counter()
        c = self.counters
        c.hits.append(int(hits))
        c.updates.append(int(packed.shape[0]))
        c.raycast += prepared.seconds
        c.insert += t2 - t1
        c.evict += t3 - t2
        update = 0.0
        if self._worker is not None:
            self._pending = self._worker.submit(self._write_back, codes, vals)
        else:
            update = self._write_back(codes, vals)
            c.octree_update += update
        return IntegrateTiming(raycast=prepared.seconds, update=(t3 - t0) + update,
                               voxel_updates=int(packed.shape[0]), ray_steps=prepared.steps,
                               rays=prepared.rays, merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def flush(self) -> None:
        """Write every cached voxel back to the octree (before snapshot/export/statistics)."""
        self._wait()
        if self.count is None:
            return
        n = int(self.count.sum())
        ev_code = np.empty(n, dtype=np.int64)
        ev_val = np.empty(n, dtype=np.float32)
        C.cache_drain(self.count, self.cell_code, self.cell_val, self.slots, ev_code, ev_val)
        codes, vals = self._ordered(ev_code, ev_val)
        self.counters.octree_update += self._write_back(codes, vals)

    def query(self, codes: np.ndarray) -> np.ndarray:
        codes = np.ascontiguousarray(codes, dtype=np.int64)
        self._wait()
        out = self.tree.query(codes)
        if self.count is not None:
            found = np.zeros(codes.shape[0], dtype=np.uint8)
            C.cache_lookup(self.count, self.cell_code, self.cell_val, self.slots, codes, out, found)
        return out

    def leaves(self) -> Leaves:
        self.flush()
        return self.tree.leaves()

    def node_counts(self) -> tuple[int, int]:
        self.flush()
        return self.tree.node_counts()

    def cache_bytes(self) -> int:
        if self.count is None:
            return 0
        return int(self.count.nbytes + self.cell_code.nbytes + self.cell_val.nbytes)

    canonical_leaves = True

    def memory_bytes(self) -> int:
        return self.tree.memory_bytes() + self.cache_bytes()

    def used_bytes(self) -> int:
        cells = int(self.count.sum()) if self.count is not None else 0
        return self.tree.used_bytes() + cells * (8 + 4)

    def state_arrays(self) -> dict[str, np.ndarray]:
        self.flush()
        return self.tree.state_arrays()

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        self.tree.load_state(arrays)

    def extra_meta(self) -> dict[str, Any]:
        return {"buckets": self.buckets, "tau": self.tau, "overlap": self.overlap, "order": self.order}

    def extra_stats(self) -> dict[str, Any]:
        c = self.counters
        return {"cache_bytes": self.cache_bytes(), "buckets": self.buckets, "tau": self.tau,
                "hit_ratio": round(sum(c.hits) / max(1, sum(c.updates)), 6), "written_to_octree": c.written_to_octree}

    def close(self) -> None:
        self._wait()
        if self._worker is not None:
            self._worker.shutdown(wait=True)
