"""The `octree` backend: OctoMap 1.10's OcTree semantics, as Morton-prefix shards updated in
parallel (voxtool.maps.shards)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError, SourceError
from voxtool.io.snapshot import ChunkedArrays
from voxtool.kernels import octree as K
from voxtool.kernels.raycast import (
    BRICK_BITS,
    NO_NEAR_HITS,
    BrickBuffers,
    balanced_cuts,
    brick_voxels,
    expand_bricks,
    ray_signatures,
    scan_bricks,
    scan_bricks_to_near_hits,
)
from voxtool.keys import coords_to_keys
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.maps.shards import DEFAULT_SHARD_DEPTH, ShardedOctree
from voxtool.parallel import resolve_threads, run_parts
from voxtool.sources.scan import Scan

FORGET_BELOW = 0.01  # log-odds: a decaying voxel nearer than this to unknown (p within 0.0025 of 0.5) is forgotten
SMALL_SCAN = 2_000  # points; below this one thread traces the whole scan
RAYS_PER_PART = 1_000  # at least this many rays per thread: a hand-off costs ~0.1 ms
BRICKS_PER_PART = 2_048  # likewise, bricks per thread when expanding them to voxel updates
_BUFFERS = threading.local()


def _trace_part(scan: Scan, params: MapParams, lo: int, hi: int, near_hits=None) -> tuple:
    """Trace rays lo..hi into this thread's brick buffers; returns copies of the used part,
    sorted by brick code. near_hits: a near-hit table (kernels.clean.near_hits_table) at which
    rays stop, marking no endpoints (clean's void evidence)."""
    buf = getattr(_BUFFERS, "bricks", None) or BrickBuffers()
    trace = scan_bricks if near_hits is None else scan_bricks_to_near_hits
    near_keys, near_bits = NO_NEAR_HITS if near_hits is None else near_hits
    while True:
        n, steps = trace(scan.points[lo:hi], scan.origin, params.resolution, params.max_range,
                         buf.tab, buf.touched, buf.occ, buf.bricks, near_keys, near_bits)
        if n >= 0:
            break
        buf = BrickBuffers(2 * buf.bricks.shape[0])
    _BUFFERS.bricks = buf
    # sorted here, on the tracing thread: expanding them later then reads the masks in order
    # (through a permutation, each brick's two rows cost two cache misses: 11 ms a kaist03 scan)
    order = np.argsort(buf.bricks[:n], kind="stable")
    out = (buf.bricks[order], buf.touched[order], buf.occ[order], steps)
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
    return replace(scan, points=scan.points[keep])


def ray_parts(scan: Scan, threads: int) -> list[tuple[int, int]]:
    """Runs of a scan's rays of about equal work, one per thread (one for a small scan)."""
    n = scan.points.shape[0]
    parts = 1 if n < SMALL_SCAN else max(1, min(threads, n // RAYS_PER_PART))
    if parts == 1:
        return [(0, n)]
    cuts = balanced_cuts(scan.points, scan.origin, parts)
    return [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


@dataclass
class ScanBricks:
    """A scan's updated voxels as bricks (kernels.raycast.scan_bricks), merged: the distinct brick
    codes in order, and per distinct brick k its rows order[firsts[k]:firsts[k + 1]] of the
    touched and endpoint masks (a brick several ray runs filled has several rows, OR-ed)."""

    distinct: np.ndarray
    touched: np.ndarray
    occ: np.ndarray
    order: np.ndarray
    firsts: np.ndarray

    @classmethod
    def merge(cls, bricks: np.ndarray, touched: np.ndarray, occ: np.ndarray, group_of=None) -> ScanBricks:
        """group_of (voxel codes -> small ints): the bricks ordered by group first, then Morton."""
        key = bricks
        if group_of is not None:  # brick codes have 39 bits: the group goes above them
            key = (group_of(bricks << BRICK_BITS).astype(np.int64) << np.int64(40)) | bricks
        order = np.argsort(key, kind="stable")
        firsts = np.flatnonzero(np.diff(key[order], prepend=np.int64(-1)))  # a brick several threads filled: once
        return cls(bricks[order][firsts], touched, occ, order, np.append(firsts, key.shape[0]))

    def runs(self, threads: int) -> list[tuple[int, int]]:
        """Runs of distinct bricks, one per thread (one for few bricks)."""
        n = self.distinct.shape[0]
        parts = max(1, min(threads, n // BRICKS_PER_PART))
        return [(n * k // parts, n * (k + 1) // parts) for k in range(parts)]

    def updates(self, threads: int) -> tuple[np.ndarray, np.ndarray]:
        """(Morton-sorted voxel updates code << 1 | occupied, where each distinct brick's start),
        expanded on `threads` threads, each a run of bricks into its own part of the output."""
        n = self.distinct.shape[0]
        runs = self.runs(threads)
        counts = np.empty(n, dtype=np.int64)
        run_parts(threads, lambda r: brick_voxels(self.touched, self.order, self.firsts, r[0], r[1], counts), runs)
        starts = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(counts, out=starts[1:])
        out = np.empty(int(starts[-1]), dtype=np.int64)
        run_parts(threads, lambda r: expand_bricks(self.distinct, self.touched, self.occ, self.order, self.firsts,
                                                   r[0], r[1], starts, out), runs)
        return out, starts


def miss_scan(scan: Scan, params: MapParams) -> tuple[Scan, MapParams] | None:
    """A scan's no-return beams (Scan.misses) as a scan of their own, with the parameters that
    cut each ray at the beam's range (or the map's max range when nearer) and mark no hit, as
    OctoMap's insertPointCloud does with a point beyond maxrange; None when it has none."""
    if scan.misses is None or scan.misses.shape[0] == 0 or scan.miss_range <= 0:
        return None
    cut = scan.miss_range if params.max_range < 0 else min(scan.miss_range, params.max_range)
    coords_to_keys(scan.misses, params.resolution, what=f"{scan.source}: no-return beam end")
    return Scan(scan.misses, scan.origin, scan.index, scan.stamp_ns, scan.source), replace(params, max_range=cut)


def trace_scan(scan: Scan, params: MapParams, threads: int = 1, near_hits=None) -> list:
    """A scan's rays traced on `threads` threads, in runs of equal work: per run, (brick codes
    sorted, touched masks, endpoint masks, DDA steps) (_trace_part; near_hits: clean's stops).
    The points and the origin must lie in key range."""
    return run_parts(threads, lambda run: _trace_part(scan, params, *run, near_hits), ray_parts(scan, threads))


def hit_bricks(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(brick codes, touched masks, endpoint masks) of the voxels at `keys` (N, 3), each voxel
    once: a scan without rays (Scan.hits_only) as the caster's bricks."""
    from voxtool.keys import morton_encode, unique_codes

    codes = unique_codes(morton_encode(keys))
    bricks = unique_codes(codes >> BRICK_BITS)
    bit = codes & ((1 << BRICK_BITS) - 1)
    masks = np.zeros((bricks.shape[0], 8), dtype=np.int64)
    np.bitwise_or.at(masks, (np.searchsorted(bricks, codes >> BRICK_BITS), bit >> 6), np.left_shift(np.int64(1), bit & 63))
    return bricks, masks, masks.copy()


def cast_scan(scan: Scan, params: MapParams, threads: int = 1, group_of=None) -> tuple[ScanBricks | None, int, int]:
    """(the voxels one scan updates as merged bricks, None for no points; its DDA step count;
    rays merged into others, 0 unless params.merge_rays). group_of: ScanBricks.merge."""
    n = scan.points.shape[0]
    if scan.hits_only:
        if n == 0:
            return None, 0, 0
        keys = coords_to_keys(scan.points, params.resolution, what=f"{scan.source}: point")
        return ScanBricks.merge(*hit_bricks(keys), group_of), 0, 0
    misses = miss_scan(scan, params)
    if n == 0 and misses is None:
        return None, 0, 0
    coords_to_keys(scan.origin[None, :], params.resolution, what=f"{scan.source}: sensor origin of scan")
    coords_to_keys(scan.points, params.resolution, what=f"{scan.source}: point")
    merged = 0
    if params.merge_rays and n:
        scan = merge_rays(scan, params)
        merged = n - scan.points.shape[0]
    parts = trace_scan(scan, params, threads) if n else []
    if misses is not None:  # no-return beams: cut at their range, so they clear and hit nothing
        parts += trace_scan(*misses, threads)
    if len(parts) == 1:
        bricks, touched, occ, steps = parts[0]
    else:
        bricks = np.concatenate([p[0] for p in parts])
        touched = np.concatenate([p[1] for p in parts])
        occ = np.concatenate([p[2] for p in parts])
        steps = sum(p[3] for p in parts)
    return ScanBricks.merge(bricks, touched, occ, group_of), int(steps), merged


def scan_bricks_updates(scan: Scan, params: MapParams, threads: int = 1, group_of=None) -> tuple:
    """(Morton-sorted code << 1 | occupied updates of one scan, its DDA step count, rays merged
    into others (0 unless params.merge_rays), (distinct brick codes, their update starts)).
    group_of: sorted by group first (ScanBricks.merge)."""
    merged_bricks, steps, merged = cast_scan(scan, params, threads, group_of)
    if merged_bricks is None:
        return np.empty(0, dtype=np.int64), 0, 0, None
    packed, starts = merged_bricks.updates(threads)
    return packed, steps, merged, (merged_bricks.distinct, starts)


def scan_updates(scan: Scan, params: MapParams, threads: int = 1) -> tuple[np.ndarray, int, int]:
    """Morton-sorted (code << 1 | occupied) voxel updates of one scan, its DDA step count, and
    how many rays were merged into others (0 unless params.merge_rays)."""
    return scan_bricks_updates(scan, params, threads)[:3]


def prepare_scan(scan: Scan, params: MapParams, threads: int = 1) -> PreparedScan:
    """A scan's voxel updates, timed, with the ray-merging count when it is enabled."""
    t0 = time.perf_counter()
    packed, steps, merged, runs = scan_bricks_updates(scan, params, threads)
    return PreparedScan(packed, steps, time.perf_counter() - t0, int(scan.points.shape[0]), merged, brick_runs=runs)


def prepare_scan_bricks(scan: Scan, params: MapParams, threads: int = 1) -> PreparedScan:
    """prepare_scan, its updates kept as bricks (`bricks`; PreparedScan.updates() expands them):
    the octree applies them from the masks, without a list of per-voxel updates."""
    t0 = time.perf_counter()
    merged_bricks, steps, merged = cast_scan(scan, params, threads)
    packed = np.empty(0, dtype=np.int64) if merged_bricks is None else None
    return PreparedScan(packed, steps, time.perf_counter() - t0, int(scan.points.shape[0]), merged,
                        bricks=merged_bricks, threads=threads)


def warm_up_kernels(merging: bool = False) -> None:
    """Load (or compile, first time on a machine) the kernels a build runs on a tiny scan, so
    the JIT cost is reported apart from the first scan's latency (each costs ~5-10 ms)."""
    scan = Scan(np.array([[1.0, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32))
    params = MapParams(resolution=0.5, merge_rays=merging)
    tree = ShardedOctree()
    tree.apply(scan_updates(scan, params)[0], K.ADD, hit=0.85, miss=-0.4, cmin=-2.0, cmax=3.5)
    tree.apply_masks(cast_scan(scan, params)[0], hit=0.85, miss=-0.4, cmin=-2.0, cmax=3.5)
    balanced_cuts(scan.points, scan.origin, 2)
    tree.leaves()


class OctreeMap:
    """OctoMap-exact occupancy octree (see docs/backends.md). With decay_half_life (seconds of
    scan time) every known voxel's log-odds halve towards unknown over that time before each
    scan's updates, and voxels that come within FORGET_BELOW of unknown are forgotten
    (docs/decay.md); without it (the default) the map is OctoMap's."""

    name = "octree"

    def __init__(self, params: MapParams, sensor: SensorModel, threads: int = 0,
                 shard_depth: int = DEFAULT_SHARD_DEPTH, decay_half_life: float | None = None) -> None:
        if decay_half_life is not None and not decay_half_life > 0:
            raise ParameterError(f"decay half-life must be a positive number of seconds, not {decay_half_life}")
        self.params = params
        self.sensor = sensor
        self.threads = resolve_threads(threads)
        self.shard_depth = shard_depth
        self.decay_half_life = decay_half_life
        self.clock: tuple[int, int] | None = None  # (stamp_ns, index) of the last scan applied, when decaying
        self.tree = ShardedOctree(shard_depth, self.threads)

    def warm_up(self) -> None:
        warm_up_kernels(self.params.merge_rays)
        if self.decay_half_life is not None:
            tree = ShardedOctree()
            tree.apply(np.array([3], dtype=np.int64), K.ADD, hit=0.85, miss=-0.4, cmin=-2.0, cmax=3.5)
            tree.fade(0.5, FORGET_BELOW)
            tree.apply(np.array([3], dtype=np.int64), K.ADD, hit=0.85, miss=-0.4, cmin=-2.0, cmax=3.5)
            tree.settle()

    def prepare(self, scan: Scan) -> PreparedScan:
        """Ray casting: independent of the map, so it may run ahead on another thread."""
        prepared = prepare_scan_bricks(scan, self.params, self.threads)
        prepared.stamp_ns, prepared.index, prepared.source = scan.stamp_ns, scan.index, scan.source
        return prepared

    def decay_to(self, stamp_ns: int, index: int = -1, source: str = "") -> None:
        """Let the map fade from the last scan's time to `stamp_ns`: every log-odds times
        2^(-dt / half-life), and voxels within FORGET_BELOW of unknown are forgotten."""
        last = self.clock
        self.clock = (stamp_ns, index)
        if last is None:  # the first scan: nothing to fade yet
            return
        if stamp_ns <= last[0]:
            raise SourceError(f"{source or 'scan'}: scan {index} has time {stamp_ns * 1e-9:.9f} s, not after scan "
                              f"{last[1]}'s {last[0] * 1e-9:.9f} s; decay needs increasing scan times (a PCD directory "
                              "takes them from the poses.txt beside its scans, or --poses: docs/sources.md)")
        self.tree.fade(2.0 ** (-(stamp_ns - last[0]) * 1e-9 / self.decay_half_life), FORGET_BELOW)

    def apply_updates(self, items: np.ndarray, mode: int = K.ADD, values: np.ndarray | None = None,
                      brick_runs: tuple | None = None) -> None:
        """Fold Morton-sorted updates into the tree: `code << 1 | occupied` (ADD), or codes
        with their new log-odds (SET); `brick_runs` as scan_bricks_updates gives them, if known."""
        s = self.sensor
        extra = {} if values is None else {"values": np.ascontiguousarray(values, dtype=np.float32)}
        self.tree.apply(items, mode, hit=s.hit_log, miss=s.miss_log, cmin=s.clamp_min_log, cmax=s.clamp_max_log,
                        runs=brick_runs, **extra)

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        """Tree update; prepared scans must be applied in scan order."""
        t0 = time.perf_counter()
        if self.decay_half_life is not None:
            self.decay_to(prepared.stamp_ns, prepared.index, prepared.source)
        if prepared.packed is None:  # straight from the brick masks (no per-voxel list: 8 bytes a voxel)
            s = self.sensor
            updated = self.tree.apply_masks(prepared.bricks, hit=s.hit_log, miss=s.miss_log, cmin=s.clamp_min_log,
                                            cmax=s.clamp_max_log)
        else:
            self.apply_updates(prepared.packed, brick_runs=prepared.brick_runs)
            updated = int(prepared.packed.shape[0])
        return IntegrateTiming(raycast=prepared.seconds, update=time.perf_counter() - t0,
                               voxel_updates=updated, ray_steps=prepared.steps,
                               rays=prepared.rays, merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def query(self, codes: np.ndarray) -> np.ndarray:
        return self.tree.values(codes)

    def query_depth(self, codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log-odds, depth of the answering leaf) at finest-level codes; NaN / -1 unknown."""
        return self.tree.query(codes)

    def leaves(self) -> Leaves:
        return self.tree.leaves()

    def leaf_chunks(self):
        """leaves() in consecutive chunks, without holding them all (ShardedOctree.leaf_chunks)."""
        return self.tree.leaf_chunks()

    def node_counts(self) -> tuple[int, int]:
        return self.tree.node_counts()

    canonical_leaves = True  # leaves() is OctoMap's pruned tree (voxtool.maps.tree)

    def memory_bytes(self) -> int:
        return self.tree.memory_bytes()

    def used_bytes(self) -> int:
        return self.tree.used_bytes()

    def state_arrays(self) -> dict[str, ChunkedArrays]:
        """The leaves, for a snapshot written a chunk at a time (its bytes are those of leaves())."""
        tree = self.tree
        leaves = ChunkedArrays(("leaf_codes", "leaf_depths", "leaf_values"), ("int64", "uint8", "float32"),
                               tree.leaf_count(), lambda: ((c.codes, c.depths, c.values) for c in tree.leaf_chunks()))
        return dict.fromkeys(leaves.names, leaves)

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        self.tree = ShardedOctree(self.shard_depth, self.threads)
        self.tree.load(Leaves(arrays["leaf_codes"], arrays["leaf_depths"], arrays["leaf_values"]))

    def extra_meta(self) -> dict[str, Any]:
        # threads and shard depth change how fast a map is built, never what it holds
        return {} if self.decay_half_life is None else {"decay_half_life": self.decay_half_life}

    def extra_stats(self) -> dict[str, Any]:
        out = {"pool_bricks": self.tree.n_bricks, "pool_shards": self.tree.n_rows, "shard_depth": self.tree.depth}
        if self.decay_half_life is not None:
            out["decay_half_life_s"] = self.decay_half_life
        return out
