"""The `hashmap` backend: task-agnostic hash-table voxel map with dynamic voxel management and
map sharing (seed: voxel-mapping-hash-map-sharing.md, Alg. 1-3, Sec. V). See docs/backends.md."""

from __future__ import annotations

import math
import os
import threading
import time
from dataclasses import replace
from typing import Any

import numba
import numpy as np

from voxtool.config import MapParams, SensorModel, logodds
from voxtool.errors import FormatError, ParameterError
from voxtool.kernels import hashmap as K
from voxtool.kernels.ball import ball_offsets
from voxtool.kernels.raycast import balanced_cuts
from voxtool.keys import coords_to_keys
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.maps.octree import SMALL_SCAN, OctreeMap, merge_rays, miss_scan
from voxtool.parallel import resolve_threads
from voxtool.sources.scan import Scan

# at least this many rays per thread of the ray casting. The region's workers are woken at
# once, so a run costs less to hand off than the octree's pool task (RAYS_PER_PART 1,000 there):
# on 16 cores, quick_shack row a cast in up to 14 runs instead of 3 (its scans have ~3,600
# distinct end voxels) and the cast part fell from 2.4-2.6 to 1.9 ms a scan
# (docs/design/backends.md). Two cores cast in two runs either way.
RAYS_PER_PART = 250

SCHEDULABLE = ("p_init", "n_lim", "d_in", "d_inf", "inf_range", "ttl")
# a snapshot stores each voxel's inflation radius; loading re-inflates. A file asking for more
# than this many sphere cells (count updates) is refused rather than run for minutes, and one
# whose spheres would fill more than MAX_LOAD_INFLATION_BYTES of bricks is refused when they
# reach it: a brick takes a row (512 B or 2 KB) for as little as one cell (voxels scattered one
# a brick), where the shared data fill 17-128 cells a row.
MAX_LOAD_INFLATION = 1 << 27
MAX_LOAD_INFLATION_BYTES = 1 << 31
INT64_MAX, INT64_MIN = int(np.iinfo(np.int64).max), int(np.iinfo(np.int64).min)
# numba's fallback threading layer (workqueue, where neither OpenMP nor TBB loads) aborts the
# process when two threads launch parallel kernels at once: maps in several threads take turns
PARALLEL_LAUNCH = threading.Lock()


class _Parallel:
    launched = False  # this process has cast in a parallel region
    usable = True  # False in a child forked after that: GNU OpenMP is not fork-safe, and numba
    # ends such a child when it launches a parallel region; it casts on its calling thread instead


def _after_fork_in_child() -> None:
    if _Parallel.launched:
        _Parallel.usable = False


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def sphere_sizes(max_radius: int) -> np.ndarray:
    """How many integer offsets |o| <= r there are, for r = 0..max_radius (sphere_offsets'
    group sizes), counted column by column without listing them: a snapshot's inflation is
    sized before its offsets are built (a file with every radius up to 64 would list 18 M)."""
    g = np.arange(-max_radius, max_radius + 1)
    xy2 = (g[:, None] ** 2 + g[None, :] ** 2).ravel()
    sizes = np.empty(max_radius + 1, np.int64)
    for r in range(max_radius + 1):
        inside = xy2[xy2 <= r * r]
        sizes[r] = int((2 * np.floor(np.sqrt(r * r - inside)) + 1).sum())  # the z run of each (x, y) column
    return sizes


def sphere_offsets(radii: set[int]) -> tuple[np.ndarray, np.ndarray]:
    """Integer offsets with |o| <= r for each radius r in `radii`, grouped by r = 0..max(radii):
    rows start[r]:start[r+1], empty for a radius no voxel has. int8 (r <= K.MAX_RADIUS): radius
    64 alone is 1.1 M offsets, 3.4 MB (listing every radius up to 64 in int64 took 435 MB)."""
    groups = [ball_offsets(r) if r in radii else np.zeros((0, 3), np.int64) for r in range(max(radii) + 1)]
    start = np.cumsum([0] + [g.shape[0] for g in groups])
    return np.concatenate(groups).astype(np.int8), start.astype(np.int64)


class HashVoxelMap:
    name = "hashmap"

    def __init__(self, params: MapParams, sensor: SensorModel, p_init: float = 0.5, n_lim: int = -1,
                 d_in: float = -1.0, d_inf: float = 0.2, inf_range: float = -1.0, ttl: float = -1.0,
                 p_free: float = 0.4, schedule: list | None = None, rate_hz: float = 10.0,
                 discretize: int = 1, threads: int = 0) -> None:
        self.params, self.sensor = params, sensor
        self.threads = resolve_threads(threads)  # ray casting: a run of rays per thread
        if discretize not in (0, 1):
            raise ParameterError(f"discretize={discretize} must be 1 (one ray per end voxel, to its centre: the "
                                 "paper, OctoMap's discretize) or 0 (one ray per point, OctoMap's default)")
        self.discretize = discretize
        if not 0 < p_free < sensor.occupancy_threshold:
            raise ParameterError(f"p_free={p_free} must lie between 0 and the occupancy threshold "
                                 f"{sensor.occupancy_threshold}")
        if not 0 < rate_hz < math.inf:
            raise ParameterError(f"rate_hz={rate_hz} must be a positive number")
        self.p_free = p_free
        self.values: dict[str, float] = {}
        self.icounts: np.ndarray | None = None  # the inflation map's counts (below), widened by set_params
        self.sphere_radii: set[int] = set()  # the radii voxels inflate with: their offsets are built
        self.set_params(p_init=p_init, n_lim=n_lim, d_in=d_in, d_inf=d_inf, inf_range=inf_range, ttl=ttl)
        self.schedule = sorted((int(i), str(k), self._checked(str(k), v)) for i, k, v in (schedule or []))
        self.period_ns = int(1e9 / rate_hz)
        self.rec = K.new_records(1024)
        self.free = np.zeros(1024, dtype=np.int64)
        self.tab = K.new_table(4096)
        self.meta = np.zeros(K.META_FIELDS, dtype=np.int64)
        self.meta[[K.M_HEAD, K.M_TAIL]] = -1
        self.bkeys, self.bmask = K.new_bricks(1024)
        self.ikeys, self.icounts, self.inz, self.ifree = K.new_inflation(1024, 64, K.count_dtype(self.radius_vox))
        self.scan_metrics: list[dict] = []
        self.removed: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros(0, np.float32))
        self._set_size = 1 << 13  # de-duplicating sets of the ray casting, one per run of rays
        self._bufs: tuple[np.ndarray, ...] | None = None
        self._update_bufs: tuple[np.ndarray, ...] | None = None
        self._cell_set: tuple[np.ndarray, np.ndarray] | None = None  # discretize's set and its scratch
        self.newly_occupied: np.ndarray = np.zeros(0, np.int64)

    # -- parameters ----------------------------------------------------------------------------
    def _checked(self, key: str, value) -> float:
        """A value `key` may take (all of them, so that a schedule is checked before the first scan)."""
        if key not in SCHEDULABLE:
            raise ParameterError(f"hashmap has no parameter '{key}' (one of {', '.join(SCHEDULABLE)})")
        x = float(value)
        if not math.isfinite(x):
            unlimited = " (a negative one means unlimited)" if key in ("n_lim", "d_in", "inf_range", "ttl") else ""
            raise ParameterError(f"{key}={value} must be a finite number{unlimited}")
        if key == "p_init" and not 0 < x < 1:
            raise ParameterError(f"p_init={x} must lie in (0, 1)")
        if key == "d_inf" and not 0 <= x <= K.MAX_RADIUS * self.params.resolution:
            raise ParameterError(f"d_inf={x} must lie in [0, {K.MAX_RADIUS} voxels]")
        return x

    def set_params(self, **kw) -> None:
        """Change p_init, n_lim, d_in, d_inf, inf_range, ttl; they take effect from the next scan."""
        checked = {k: self._checked(k, v) for k, v in kw.items()}  # all or nothing
        self.values.update(checked)
        if "d_in" in checked:
            self._d_in_ahead = checked["d_in"]
        v = self.values
        self.radius_vox = int(math.floor(v["d_inf"] / self.params.resolution + 1e-9))
        sm = self.sensor  # the input update's float32 constants, converted once per change
        self._model = tuple(np.float32(x) for x in (logodds(v["p_init"]), sm.hit_log, sm.miss_log, sm.clamp_min_log,
                                                    sm.clamp_max_log, sm.threshold_log, logodds(self.p_free)))
        self._build_spheres({self.radius_vox})
        self._widen_counts(self.radius_vox)

    def _build_spheres(self, radii: set[int]) -> None:
        """Offsets for spheres of these radii too (voxels keep the radius they inflated with)."""
        if not radii <= self.sphere_radii:
            self.sphere_radii |= radii
            self.offsets, self.offset_start = sphere_offsets(self.sphere_radii)

    def _widen_counts(self, radius: int) -> None:
        """Inflation counts wide enough for spheres of `radius` (never narrowed: voxels keep the
        radius they inflated with)."""
        wide = K.count_dtype(radius)
        if self.icounts is not None and wide.itemsize > self.icounts.dtype.itemsize:
            self.icounts = self.icounts.astype(wide)

    def _schedule_for(self, index: int) -> None:
        for i, k, value in self.schedule:
            if i == index:
                self.set_params(**{k: value})

    # -- storage -------------------------------------------------------------------------------
    def _reserve(self, new_records: int, new_bricks: int = 0) -> None:
        """Room for new_records more records and new_bricks more bricks of the brick table."""
        need = int(self.meta[K.M_NEXT]) + new_records
        if need > K.MAX_RECORDS:
            raise ParameterError(f"hashmap: {need} voxel records exceed the {K.MAX_RECORDS} the table addresses; "
                                 "lower n_lim")
        cap = self.rec.shape[0]
        if need > cap:
            new_cap = max(need, 2 * cap)
            grown = K.new_records(new_cap)
            grown.view(np.uint8)[: self.rec.nbytes] = self.rec.view(np.uint8)  # bytes: 10x a field-wise copy
            self.rec = grown
            f = np.zeros(new_cap, dtype=np.int64)
            f[: self.free.shape[0]] = self.free
            self.free = f
        live = int(self.meta[K.M_LIVE]) + new_records
        size = self.tab.shape[0]
        if K.RECORD_TABLE_LOAD * (live + int(self.meta[K.M_TOMBS])) > size:
            while 2 * K.RECORD_TABLE_LOAD * live > size:  # grown to half the bound: room to fill
                size *= 2
            self.tab = K.new_table(size)
            K.rehash(self.tab, self.rec, int(self.meta[K.M_NEXT]))
            self.meta[K.M_TOMBS] = 0
        bricks = int(self.meta[K.M_BRICKS]) + new_bricks
        size = self.bkeys.shape[0]
        # kept sparse (at most 1/4 full, 1/8 after growing): every ray crossing into a brick looks
        # it up, and short probe chains keep those look-ups predictable (measured ~7 % of the ray
        # casting against 1/2 full); 1,600 bricks take 1.2 MB
        if K.BRICK_TABLE_LOAD * (bricks + int(self.meta[K.M_BTOMBS])) > size:
            while 2 * K.BRICK_TABLE_LOAD * bricks > size:
                size *= 2
            bkeys, bmask = K.new_bricks(size)
            K.brick_rehash(self.bkeys, self.bmask, bkeys, bmask)
            self.bkeys, self.bmask = bkeys, bmask
            self.meta[K.M_BTOMBS] = 0

    def _inflation_room(self, bricks: int, max_bytes: int = -1) -> None:
        """Room in the inflation map for `bricks` more bricks: rows of counts (doubling) and its
        table within K.BRICK_TABLE_LOAD (half that after growing), as the brick table above. A
        snapshot load passes max_bytes: counts that would grow past it are the file's error."""
        rows = self.icounts.shape[0]
        free_rows = rows - int(self.meta[K.M_INEXT]) + int(self.meta[K.M_IFREE_TOP])
        if free_rows < bricks:
            grown = max(2 * rows, rows + bricks)
            if 0 <= max_bytes < grown * self.icounts[0].nbytes:
                raise FormatError(f"hashmap snapshot: rebuilding its inflation would take more than "
                                  f"{max_bytes:,} bytes of inflation counts ({grown:,} bricks)")
            if grown > K.ROW_MASK + 1:
                raise ParameterError(f"hashmap: the inflation map would need {grown} bricks, more than the "
                                     f"{K.ROW_MASK + 1} its table addresses; lower d_inf or inf_range")
            counts = np.zeros((grown, 512), self.icounts.dtype)  # the rows beyond are all zero: handed out as they are
            counts[:rows] = self.icounts
            nz, free = np.zeros(grown, np.int32), np.zeros(grown, np.int32)
            nz[:rows], free[:rows] = self.inz, self.ifree
            self.icounts, self.inz, self.ifree = counts, nz, free
        live = int(self.meta[K.M_IBRICKS]) + bricks
        size = self.ikeys.shape[0]
        if K.BRICK_TABLE_LOAD * (live + int(self.meta[K.M_ITOMBS])) > size:
            while 2 * K.BRICK_TABLE_LOAD * live > size:
                size *= 2
            ikeys = np.full(size, K.EMPTY, np.int64)
            K.ibrick_rehash(self.ikeys, ikeys)
            self.ikeys = ikeys
            self.meta[K.M_ITOMBS] = 0

    def _inflation_args(self) -> tuple:
        return (self.offsets, self.offset_start, self.rec, self.meta, self.ikeys, self.icounts, self.inz, self.ifree)

    # -- MapBackend ------------------------------------------------------------------------------
    def warm_up(self) -> None:
        OctreeMap(self.params, self.sensor, threads=1).warm_up()
        probe = HashVoxelMap(MapParams(resolution=0.5), self.sensor, n_lim=1, d_inf=0.5, threads=self.threads)
        for wide in (False, True):  # the update's kernels for one-byte counts, then for int32 ones
            if wide:
                probe._widen_counts(K.MAX_RADIUS)
            for x in (1.0, 3.0):
                probe.integrate(Scan(np.array([[x, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32)))
            K.reinflate(np.zeros(0, np.int32), 0, *probe._inflation_args())
        # the table rebuilds run only when a table grows: load them now, not in a timed scan
        K.count_hits(np.zeros(1, np.int64))
        K.rehash(probe.tab, probe.rec, int(probe.meta[K.M_NEXT]))
        K.ibrick_rehash(probe.ikeys, np.full(probe.ikeys.shape[0], K.EMPTY, np.int64))
        probe.query(np.zeros(1, np.int64))
        probe.discretize = 0  # SMALL_SCAN rays (to one voxel): the parallel path
        probe._trace(Scan(np.tile(np.array([[1.0, 0.5, 0.25]], np.float32), (SMALL_SCAN, 1)), np.zeros(3, np.float32)))
        K.brick_rehash(probe.bkeys, probe.bmask, *K.new_bricks(probe.bkeys.shape[0]))

    def prepare(self, scan: Scan) -> PreparedScan:
        """Input range and key checks only: which misses matter depends on the map, so the rays
        are cast later, against the map as it is then (by update_codes() or apply())."""
        if scan.hits_only:
            raise ParameterError(f"{scan.source}: has no sensor origin, so no rays: its occupied voxels are built by "
                                 "the octree, octocache and tiny backends, not by the hash map's ray casting")
        # prepare() may run ahead on another thread while apply() folds the previous scan in:
        # it follows the schedule's d_in on its own and leaves the map's parameters to apply()
        for i, k, value in self.schedule:
            if i == scan.index and k == "d_in":
                self._d_in_ahead = value
        d_in = self._d_in_ahead
        if d_in >= 0 and scan.points.shape[0]:
            d = np.linalg.norm(scan.points.astype(np.float64) - scan.origin.astype(np.float64), axis=1)
            scan = replace(scan, points=scan.points[d <= d_in])
        merged = 0
        if scan.points.shape[0]:
            coords_to_keys(scan.origin[None, :], self.params.resolution, what=f"{scan.source}: sensor origin of scan")
            coords_to_keys(scan.points, self.params.resolution, what=f"{scan.source}: point")
            if self.params.merge_rays:
                n = scan.points.shape[0]
                scan = merge_rays(scan, self.params)
                merged = n - scan.points.shape[0]
        stamp = scan.stamp_ns if scan.stamp_ns else scan.index * self.period_ns
        return PreparedScan(np.empty(0, np.int64), 0, 0.0, int(scan.points.shape[0]), merged, stamp_ns=stamp,
                            origin=scan.origin, scan=scan, index=scan.index)

    def _discretized(self, scan: Scan) -> Scan:
        """The scan with one point per distinct end voxel, at its centre (OctoMap's
        computeDiscreteUpdate; the paper casts one ray per voxel of the input)."""
        n = scan.points.shape[0]
        size = 1 << max(4, int(4 * n - 1).bit_length())  # room for 2 x points: the set never fills
        if self._cell_set is None or self._cell_set[0].shape[0] < size:
            # kept between scans (the kernel leaves it all EMPTY): no per-scan fill of a new set
            self._cell_set = (np.full(size, K.EMPTY, np.int64), np.empty(size // 2 + 1, np.int64))
        centres = np.empty((n, 3), np.float32)
        k = K.discretize(scan.points, self.params.resolution, *self._cell_set, centres)
        return Scan(centres[:k], scan.origin, scan.index, scan.stamp_ns, scan.source)

    def _cast_buffers(self, parts: int, size: int) -> tuple:
        """The ray casting's de-duplicating sets (all EMPTY; the kernels leave them so) and
        scratch, one row per run of rays, kept from scan to scan."""
        if self._bufs is None or self._bufs[0].shape != (parts, size):
            run = K.set_limit(size) + 1
            self._bufs = (np.full((parts, size), K.EMPTY, dtype=np.int64), np.empty((parts, run), np.int64),
                          np.empty((parts, run), np.int64), np.zeros((parts, 2), np.int64),
                          np.empty(parts * run, np.int64), np.empty(parts * run, np.int64))
        return self._bufs

    def _update_buffers(self, updates: int, leaving: int) -> tuple[np.ndarray, ...]:
        """apply()'s lists, kept from scan to scan: records touched and changed and codes that
        became occupied (one per update), and the codes and log-odds of voxels that leave the map
        (room for every voxel touched and in the history)."""
        if self._update_bufs is None or self._update_bufs[0].shape[0] < updates \
                or self._update_bufs[3].shape[0] < leaving:
            updates, leaving = 2 * updates, 2 * leaving  # grown ahead: a busier scan soon after reuses them
            self._update_bufs = (np.empty(updates, np.int64), np.empty(updates, np.int64),
                                 np.empty(updates, np.int64), np.empty(leaving, np.int64),
                                 np.empty(leaving, np.float32))
        return self._update_bufs

    def cast_parts(self, rays: int) -> int:
        """Runs (one a thread) that a scan of `rays` distinct end voxels is cast in."""
        if rays < SMALL_SCAN or not _Parallel.usable:  # one thread (a small scan: a launch costs more than it saves)
            return 1
        return min(self.threads, numba.config.NUMBA_NUM_THREADS, max(1, rays // RAYS_PER_PART))

    def _trace(self, scan: Scan) -> tuple[np.ndarray, int]:
        """The scan's Morton-sorted (code << 1 | hit) updates that can change this map: every
        endpoint voxel, and the passed-through voxels that may be in the occupancy map; each
        voxel once, a hit winning over a miss (the one-update-per-voxel rule of OctoMap). With
        `discretize`, the rays go to the centres of the distinct end voxels."""
        misses = miss_scan(scan, self.params)
        if misses is not None:  # no-return beams: cut at their range, so they clear and hit nothing
            packed, steps = self._trace_points(scan)
            free, free_steps = self._trace_points(*misses)
            both = np.sort(np.concatenate([packed, free]))
            last = np.append((both[1:] >> 1) != (both[:-1] >> 1), True)  # per voxel its last: a hit wins
            return both[last], steps + free_steps
        return self._trace_points(scan)

    def _trace_points(self, scan: Scan, params: MapParams | None = None) -> tuple[np.ndarray, int]:
        """_trace of the scan's points alone, their rays cut at params.max_range (the map's by default)."""
        params = params or self.params
        if self.discretize and scan.points.shape[0]:
            scan = self._discretized(scan)
        n = scan.points.shape[0]
        if n == 0:
            return np.empty(0, np.int64), 0
        while True:
            size = self._set_size
            parts = self.cast_parts(n)
            seen, slots, out, counts, merged, spare = self._cast_buffers(parts, size)
            if parts == 1:
                k, steps = K.trace_present(scan.points, scan.origin, params.resolution, params.max_range,
                                           self.bkeys, self.bmask, seen[0], slots[0], out[0])
                if k >= 0:
                    return out[0, :k].copy(), steps
            else:
                cuts = balanced_cuts(scan.points, scan.origin, parts)
                with PARALLEL_LAUNCH:
                    _Parallel.launched = True
                    numba.set_num_threads(parts)  # a thread a run
                    k = K.trace_parts(scan.points, cuts, scan.origin, params.resolution, params.max_range,
                                      self.bkeys, self.bmask, seen, slots, out, counts, merged, spare)
                if k >= 0:
                    return merged[:k].copy(), int(counts[:, 1].sum())
            self._set_size *= 2  # rare: the sets grow to the busiest scan seen

    def _cast(self, prepared: PreparedScan) -> None:
        """Cast the prepared scan's rays against the map as it is now, once: the updates go
        into prepared.packed and the time into prepared.seconds."""
        if prepared.scan is not None:
            t0 = time.perf_counter()
            prepared.packed, prepared.steps = self._trace(prepared.scan)
            prepared.seconds += time.perf_counter() - t0
            prepared.scan = None

    def update_codes(self, prepared: PreparedScan) -> np.ndarray:
        """The Morton codes whose state the next apply(prepared) updates (casting its rays now;
        apply() reuses them)."""
        self._cast(prepared)
        return prepared.packed >> 1

    def removed_voxels(self) -> tuple[np.ndarray, np.ndarray]:
        """Voxels the last apply() took out of the occupancy map (known free, over n_lim, past
        the TTL): Morton codes and their log-odds before they left."""
        return self.removed

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        if prepared.index >= 0:
            self._schedule_for(prepared.index)
        v = self.values
        stamp = prepared.stamp_ns
        origin = (prepared.origin if prepared.origin is not None else np.zeros(3, np.float32)).astype(np.float64)
        self._cast(prepared)
        packed, steps = prepared.packed, prepared.steps
        t_cast = time.perf_counter()
        touched, changed, occupied, gone_codes, gone_values = self._update_buffers(
            packed.shape[0], packed.shape[0] + int(self.meta[K.M_HSIZE]))
        counts = np.zeros(3, np.int64)
        done = 0
        while (done := K.input_update(packed, done, counts, stamp, *self._model, self.rec, self.free, self.meta,
                                      self.tab, self.bkeys, self.bmask, touched, changed, occupied)) < packed.shape[0]:
            self._reserve(*K.count_hits(packed[done:]))  # the map grows (by doubling): rare
        nt, nc, no = (int(c) for c in counts)
        self.newly_occupied = occupied[:no].copy()
        t1 = time.perf_counter()
        while K.inflate(changed, nc, origin[0], origin[1], origin[2], v["inf_range"], self.params.resolution,
                        self.radius_vox, *self._inflation_args()) < 0:
            self._inflation_room(K.bricks_per_sphere(self.radius_vox))  # rare: the map grows by doubling
        t2 = time.perf_counter()
        n_lim = int(v["n_lim"]) if v["n_lim"] >= 0 else INT64_MAX
        oldest = stamp - int(v["ttl"] * 1e9) if v["ttl"] >= 0 else INT64_MIN
        n_gone = K.manage(touched, nt, n_lim, oldest, self.rec, self.free, self.meta, self.tab, self.bkeys,
                          self.bmask, self.offsets, self.offset_start, self.ikeys, self.icounts, self.inz, self.ifree,
                          gone_codes, gone_values)
        self.removed = (gone_codes[:n_gone].copy(), gone_values[:n_gone].copy())
        t3 = time.perf_counter()
        self.scan_metrics.append({"n_occ": int(self.meta[K.M_HSIZE]), "n_inf": int(self.meta[K.M_NINF]),
                                  "t_tot_ms": 1e3 * (prepared.seconds + t3 - t_cast),
                                  "t_occ_ms": 1e3 * (prepared.seconds + t1 - t_cast),
                                  "t_inf_ms": 1e3 * (t2 - t1), "t_m_ms": 1e3 * (t3 - t2), "memory_bytes": self.memory_bytes()})
        return IntegrateTiming(raycast=prepared.seconds, update=t3 - t_cast,
                               voxel_updates=int(packed.shape[0]), ray_steps=steps, rays=prepared.rays,
                               merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def integrate_shared(self, keys: np.ndarray, stamp_ns: int, index: int) -> None:
        """Integrate shared newly-occupied voxels like sensor hits, without ray casting."""
        from voxtool.keys import morton_encode

        codes = np.unique(morton_encode(np.asarray(keys, dtype=np.int64).reshape(-1, 3)))
        self.apply(PreparedScan((codes << 1) | 1, 0, 0.0, stamp_ns=stamp_ns, origin=np.zeros(3, np.float32),
                                index=index))

    # -- views ---------------------------------------------------------------------------------
    def _occupancy_map(self) -> np.ndarray:
        """Records of the occupancy map (occupied and undecided voxels) in Morton order."""
        live = self.rec[: int(self.meta[K.M_NEXT])]
        live = live[live["state"] >= 0]
        return live[np.argsort(live["code"])]

    def occupied_codes(self) -> np.ndarray:
        occ = self._occupancy_map()
        return occ["code"][occ["state"] == 1]

    def inflation_counts(self) -> dict[int, int]:
        """The inflation map: Morton code -> inflation count of every voxel inflated."""
        from voxtool.keys import morton_encode

        keys = self.ikeys[self.ikeys >= 0]
        counts = self.icounts[keys & K.ROW_MASK]
        at, cell = np.nonzero(counts)
        codes = morton_encode(K.brick_cell_keys((keys >> K.ROW_BITS)[at], cell))
        return dict(zip(codes.tolist(), counts[at, cell].tolist()))

    def n_inflated(self) -> int:
        return int(self.meta[K.M_NINF])

    def leaves(self) -> Leaves:
        """The occupancy map (occupied and undecided voxels) as one-voxel leaves."""
        occ = self._occupancy_map()
        return Leaves(occ["code"].copy(), np.full(occ.shape[0], 16, np.uint8), occ["l"].copy())

    def query(self, codes: np.ndarray) -> np.ndarray:
        """Log-odds of voxels of the occupancy map, NaN for every other voxel."""
        out = np.empty(codes.shape[0], dtype=np.float32)
        K.lookup(self.tab, self.rec, np.ascontiguousarray(codes, dtype=np.int64), out)
        return out

    def node_counts(self) -> tuple[int, int]:
        return int(self.leaves().codes.shape[0]), 0

    def memory_bytes(self) -> int:
        return int(self.rec.nbytes + self.free.nbytes + self.tab.nbytes + self.bkeys.nbytes + self.bmask.nbytes
                   + self.ikeys.nbytes + self.icounts.nbytes + self.inz.nbytes + self.ifree.nbytes)

    def used_bytes(self) -> int:
        """Live records (64 B) with their table slots (4 B), bricks (8 B id + 64 B mask) and
        inflation bricks (8 B key, 512 counts of 1 or 4 B, 4 B of non-zero cells)."""
        live = int(self.meta[K.M_LIVE])
        brick = 8 + self.icounts[0].nbytes + 4
        return int(live * (64 + 4) + int(self.meta[K.M_BRICKS]) * 72 + int(self.meta[K.M_IBRICKS]) * brick)

    def _history(self) -> np.ndarray:
        """Record indices of the history list, oldest first."""
        out = np.empty(int(self.meta[K.M_HSIZE]), dtype=np.int64)
        r, k = int(self.meta[K.M_HEAD]), 0
        nxt = self.rec["next"]
        while r >= 0 and k < out.shape[0]:  # a snapshot write, not a hot path
            out[k] = r
            r = int(nxt[r])
            k += 1
        return out

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Occupancy-map voxels (Morton order) plus what makes the map resume exactly: each
        voxel's inflation radius, last-update stamp, hit/miss counts, and the history order."""
        n = int(self.meta[K.M_NEXT])
        live = self.rec[:n]
        r = np.flatnonzero(live["state"] >= 0)
        r = r[np.argsort(live["code"][r])]
        occ = live[r]
        position = np.full(n, -1, dtype=np.int64)
        position[r] = np.arange(r.shape[0])
        return {"leaf_codes": occ["code"].copy(), "leaf_depths": np.full(r.shape[0], 16, np.uint8),
                "leaf_values": occ["l"].copy(), "hm_radius": occ["radius"].astype(np.int32),
                "hm_last": occ["last"].copy(), "hm_hits": occ["hits"].copy(),
                "hm_misses": occ["misses"].copy(), "hm_history": position[self._history()]}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        codes, values = arrays["leaf_codes"], arrays["leaf_values"]
        n = codes.shape[0]
        extra = [arrays.get(k) for k in ("hm_radius", "hm_last", "hm_hits", "hm_misses", "hm_history")]
        if any(a is None for a in extra) or any(a.shape[0] != n for a in extra[:4]):
            raise FormatError("hashmap snapshot: per-voxel arrays missing or of the wrong length")
        radius, last, hits, misses, history = extra
        if (np.any(radius > K.MAX_RADIUS) or np.any(history < 0) or np.any(history >= n)
                or np.unique(history).size != history.size):
            raise FormatError("hashmap snapshot: inflation radius or history out of range")
        max_r = int(max(radius.max(initial=0), self.radius_vox))
        cells = int(sphere_sizes(max_r)[radius[radius >= 0]].sum())  # the inflation the file asks to rebuild
        if cells > MAX_LOAD_INFLATION:
            raise FormatError(f"hashmap snapshot: rebuilding its inflation would touch {cells:,} voxels "
                              f"(more than {MAX_LOAD_INFLATION:,})")
        self._build_spheres({int(r) for r in np.unique(radius[radius >= 0])})
        self._widen_counts(max_r)
        self._reserve(n, int(np.unique(codes >> 9).shape[0]))
        K.load_records(codes, values, np.float32(self.sensor.threshold_log), np.float32(logodds(self.p_free)),
                       self.rec, self.free, self.meta, self.tab, self.bkeys, self.bmask)
        K.restore(last.astype(np.int64), hits.astype(np.int32), misses.astype(np.int32), history.astype(np.int64),
                  self.rec, self.meta)
        radius = radius.astype(np.int32)
        done = 0
        while (done := K.reinflate(radius, done, *self._inflation_args())) < n:
            self._inflation_room(K.bricks_per_sphere(int(radius[done])), MAX_LOAD_INFLATION_BYTES)

    def extra_meta(self) -> dict[str, Any]:
        return {k: self.values[k] for k in SCHEDULABLE} | {"p_free": self.p_free, "discretize": self.discretize}

    def extra_stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {"n_occ": int(self.meta[K.M_HSIZE]), "n_inf": self.n_inflated()}
        if self.scan_metrics:
            for key in ("n_occ", "n_inf", "t_tot_ms", "t_occ_ms", "t_inf_ms", "t_m_ms", "memory_bytes"):
                a = np.array([m[key] for m in self.scan_metrics], dtype=np.float64)
                out[f"per_scan_{key}"] = {"mean": round(float(a.mean()), 4), "median": round(float(np.median(a)), 4),
                                          "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}
        return out

    def close(self) -> None:
        pass
