"""One octree map from many Dask workers (`voxtool build SOURCES... -o map.vxm --workers N`).

The map is split into partitions: sets of Morton-prefix shards (voxtool.maps.shards), a shard
going to partition hash(prefix) % P so that the voxels near a sensor spread over every
partition. Ray casting runs as tasks over batches of scans, on any worker; each returns a
batch's voxel updates split by partition, in scan order. Each partition is advanced by a chain
of tasks, one per batch, in batch order; inside a brick the updates keep their order, so every
voxel sees OctoMap's sequence of updates and the map equals the single-process map voxel for
voxel. A lost worker's results are recomputed from the graph (Dask's lineage).

Several sources make one stream, ordered by scan timestamp, then by the source's position on
the command line, then by scan index (sources without timestamps keep their order, one after
the other).
"""

from __future__ import annotations

import os
import time
import uuid
from dataclasses import dataclass, replace

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.kernels import octree as K
from voxtool.maps.shards import DEFAULT_SHARD_DEPTH, ShardedOctree
from voxtool.sources import SourceOptions, open_source
from voxtool.sources.scan import add_drop_counts

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
COUNTERS = ("scans", "points", "points_dropped", "points_dropped_nonfinite", "points_dropped_at_origin",
            "points_dropped_ego_box", "points_dropped_min_range", "raw_bytes",
            "voxel_updates", "ray_steps", "rays", "merged_rays")


def partition_of(codes: np.ndarray, shard_depth: int, partitions: int) -> np.ndarray:
    """The partition of each finest-level Morton code: Fibonacci hash of its shard prefix
    (formats/sharded.md)."""
    prefix = (codes >> np.int64(3 * (16 - shard_depth))).astype(np.uint64)
    with np.errstate(over="ignore"):
        mixed = (prefix * _GOLDEN) >> np.uint64(32)
    return (mixed % np.uint64(partitions)).astype(np.int64)


def _slice(options: SourceOptions, first: int, last: int) -> SourceOptions:
    """Options selecting positions first..last of `options`' selection."""
    start = options.start + first * options.every
    return replace(options, start=start, stop=options.start + last * options.every + 1)


def scan_stamps(source: str, options: SourceOptions) -> np.ndarray:
    """The timestamps (ns) of a source's selected scans (a planning task)."""
    return np.array([s.stamp_ns for s in open_source(source, options).scans], dtype=np.int64)


def order_scans(stamps: list[np.ndarray]) -> list[tuple[int, int]]:
    """(source, position) of every scan of several sources in map order: timestamp, then the
    source's position, then the scan's."""
    src = np.concatenate([np.full(s.shape[0], i, np.int64) for i, s in enumerate(stamps)])
    pos = np.concatenate([np.arange(s.shape[0], dtype=np.int64) for s in stamps])
    order = np.lexsort((pos, src, np.concatenate(stamps)))
    return list(zip(src[order].tolist(), pos[order].tolist()))


def cast_batch(sources: list[str], options: SourceOptions, params: MapParams, picks: list[tuple[int, int]],
               partitions: int, shard_depth: int, threads: int = 1) -> tuple:
    """Ray casting of a batch of scans ((source, position) in map order): per partition, the
    batch's updates (code << 1 | occupied) in scan order; and the batch's counters. A scan's
    updates are expanded partition by partition, so its pieces are slices of one array (a kaist03
    scan at 0.1 m is 5.7 million updates: a split by copy, or by a sort, held them twice or more)."""
    from voxtool.kernels.raycast import BRICK_BITS
    from voxtool.maps.octree import scan_bricks_updates
    from voxtool.parallel import one_blas_thread

    def group_of(codes: np.ndarray) -> np.ndarray:
        return partition_of(codes, shard_depth, partitions)

    wanted: dict[int, list[int]] = {}
    for s, p in picks:
        wanted.setdefault(s, []).append(p)
    by_pick: dict[tuple[int, int], list[np.ndarray]] = {}
    counts = dict.fromkeys(COUNTERS, 0)
    stamps = []
    t0 = time.perf_counter()
    blas = one_blas_thread()
    try:
        for s, positions in wanted.items():
            first, last = min(positions), max(positions)
            keep = set(positions)
            stream = open_source(sources[s], _slice(options, first, last))
            for offset, scan in enumerate(stream.scans):
                if first + offset not in keep:
                    continue
                # the updates come out partition by partition (Morton order inside each): a piece is a slice
                packed, steps, merged, runs = scan_bricks_updates(scan, params, threads, group_of)
                cuts = np.zeros(partitions + 1, np.int64)  # a scan without points: empty pieces
                if runs is not None:
                    bricks, starts = runs
                    cuts = starts[np.searchsorted(group_of(bricks << np.int64(BRICK_BITS)), np.arange(partitions + 1))]
                # one scan: the slices are the pieces; several: copies, so each scan's array is freed now
                # and the pieces are joined below without holding the batch twice
                own = len(picks) > 1
                by_pick[(s, first + offset)] = [packed[a:b].copy() if own else packed[a:b]
                                                for a, b in zip(cuts[:-1], cuts[1:])]
                stamps.append(scan.stamp_ns)
                counts["scans"] += 1
                counts["points"] += scan.points_read
                add_drop_counts(counts, scan)
                counts["raw_bytes"] += scan.raw_bytes
                counts["voxel_updates"] += int(packed.shape[0])
                counts["ray_steps"] += steps
                counts["rays"] += int(scan.points.shape[0])
                counts["merged_rays"] += merged
                del packed
    finally:
        blas.restore_original_limits()
    missing = [pk for pk in picks if pk not in by_pick]
    if missing:
        raise RuntimeError(f"scan {missing[0]} was not read (the source changed while the map was built?)")
    pieces = []
    for p in range(partitions):  # scan order inside each partition: the picks' order
        parts = [by_pick[pk][p] for pk in picks]
        pieces.append(parts[0] if len(parts) == 1 else np.concatenate(parts) if parts else np.zeros(0, np.int64))
        for pk in picks:
            by_pick[pk][p] = None  # a copy is freed as its partition's piece is made
    counts["raycast_s"] = time.perf_counter() - t0
    counts["stamps"] = (min(stamps), max(stamps)) if stamps else None
    return (*pieces, counts)


@dataclass
class Partition:
    """The shards of one partition and the sensor model that advances them."""

    tree: ShardedOctree
    sensor: SensorModel


def new_partition(shard_depth: int, sensor: SensorModel) -> Partition:
    return Partition(ShardedOctree(shard_depth, 1), sensor)


def advance(part: Partition, updates: np.ndarray) -> Partition:
    """Apply one batch's updates (scan order) to a partition. The partition is changed in place
    and returned: a chain's previous state is never read again (a lost one is recomputed from
    the start of its chain)."""
    s = part.sensor
    part.tree.apply(updates, K.ADD, hit=s.hit_log, miss=s.miss_log, cmin=s.clamp_min_log, cmax=s.clamp_max_log)
    return part


def partition_bricks(part: Partition) -> tuple[np.ndarray, np.ndarray]:
    return part.tree.bricks()


def batches_of(order: list, workers: int) -> list[list]:
    """Batches of about 4 per worker (cast tasks to balance), at most 8 scans each."""
    n = len(order)
    size = max(1, min(8, -(-n // (4 * max(workers, 1)))))
    return [order[i: i + size] for i in range(0, n, size)]


def distributed_build(client, sources: list[str], options: SourceOptions, params: MapParams, sensor: SensorModel,
                      partitions: int | None = None, shard_depth: int = DEFAULT_SHARD_DEPTH,
                      progress: bool | None = None, sharded_dir: str | os.PathLike | None = None,
                      info: dict | None = None):
    """Build one octree map on a Dask cluster. Returns (OctreeMap or None when written sharded,
    report dict)."""
    from operator import getitem

    from voxtool.cluster import gather_all
    from voxtool.maps.octree import OctreeMap

    t0 = time.perf_counter()
    tag = f"voxtool-{uuid.uuid4().hex[:8]}"  # keys unique to this build (a client may run several)
    addresses = sorted(client.scheduler_info(n_workers=-1)["workers"])
    workers = max(1, len(addresses))
    partitions = partitions or 2 * workers
    streams = [open_source(s, options) for s in sources]  # checks every source before any task
    if len(sources) == 1 and streams[0].count is not None:
        order = [(0, p) for p in range(streams[0].count)]
    else:
        stamp_futures = [client.submit(scan_stamps, s, options, pure=False) for s in sources]
        order = order_scans(gather_all(client, stamp_futures, "plan", progress))
    batches = batches_of(order, workers)
    # each partition's chain prefers one worker, so its growing state stays put and only the small
    # pieces travel (a loose preference: Dask still moves or recomputes it when that worker is gone)
    home = [{"workers": [addresses[p % len(addresses)]], "allow_other_workers": True} if addresses else {}
            for p in range(partitions)]
    state = [client.submit(new_partition, shard_depth, sensor, key=f"{tag}-partition-0-{p}", **home[p])
             for p in range(partitions)]
    casts = []
    for b, picks in enumerate(batches):
        cast = client.submit(cast_batch, sources, options, params, picks, partitions, shard_depth,
                             key=f"{tag}-cast-{b}")
        casts.append(cast)
        for p in range(partitions):
            # consuming a cast's pieces comes before the next cast (higher priority): pieces do not
            # pile up in workers' memory while the chains fall behind
            piece = client.submit(getitem, cast, p, key=f"{tag}-piece-{b}-{p}", priority=1)
            state[p] = client.submit(advance, state[p], piece, key=f"{tag}-partition-{b + 1}-{p}", priority=1,
                                     **home[p])
    counters = [client.submit(getitem, c, partitions, key=f"{tag}-counts-{i}") for i, c in enumerate(casts)]
    del casts  # the pieces hold what the chains need; the casts' results are freed once split
    if sharded_dir is not None:
        from voxtool.io.sharded import write_part

        finals = [client.submit(write_part, state[p], str(sharded_dir), p, params, info, key=f"{tag}-write-{p}")
                  for p in range(partitions)]
    else:
        finals = [client.submit(partition_bricks, state[p], key=f"{tag}-bricks-{p}") for p in range(partitions)]
    results = gather_all(client, counters + finals, "build", progress)
    counts, finals = results[: len(counters)], results[len(counters):]
    report = dict.fromkeys(COUNTERS, 0)
    for c in counts:
        for k in COUNTERS:
            report[k] += c[k]
    report["timings_s"] = {"raycast_task_sum": round(sum(c["raycast_s"] for c in counts), 6)}
    stamps = [c["stamps"] for c in counts if c["stamps"] is not None]
    report["first_stamp_ns"] = min(s[0] for s in stamps) if stamps else None
    report["last_stamp_ns"] = max(s[1] for s in stamps) if stamps else None
    report.update(workers=workers, partitions=partitions, batches=len(batches))
    if sharded_dir is not None:
        report["timings_s"]["total"] = round(time.perf_counter() - t0, 6)
        return finals, report
    backend = OctreeMap(params, sensor, threads=0, shard_depth=shard_depth)
    for codes, values in finals:
        backend.tree.put_bricks(codes, values)
    report["timings_s"]["total"] = round(time.perf_counter() - t0, 6)
    return backend, report
