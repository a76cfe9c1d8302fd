"""`voxtool clean`: a static point map from a scan sequence, by void regions (DUFOMap's idea).

Each scan's rays cross voxels on their way to its points, each ray stopping where it comes
within `sensor_noise` of the end of any ray of the scan (DUFOMap's inflated hits) and silent
within `sensor_noise` of any of its points (porous surfaces such as foliage, seen through
between the hits of one scan). A crossed voxel is *void* when the same scan also knew every
voxel within `pose_error` of it (crossed it, or stopped in it): space the scan saw through
whole, not a ray grazing a surface or passing between sparse beams.

A point is dynamic by its group: the points of its scan in voxels some ray crossed, within
GROUP_STEPS voxel steps of a point in a void voxel, joined as 26-connected voxels; a group is
dynamic when at least MIN_VOID_POINTS and `group_share` of its points lie in void voxels. So
an object another scan saw through goes whole, the parts no scan saw through whole (its bottom
near the ground, its edges) included, while a lone void voxel in a surface that rays grazed
keeps its points. Everything else is static.

The ground is apart (`ground_band`): points at most that high above the ground under all the
scans' points (voxtool.ground) seed no group, since under pose error rays graze the road that
another scan saw a few centimetres higher; a ground point goes with a moving group standing
right above it (_moving_groups_over_ground).

The maps hold a bit per voxel of what the exact OctoMap ray casting (voxtool.maps.octree's
caster) crossed; docs/cleaning.md says how to tune it and docs/design/clean.md why it was
chosen and what it was measured against.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.maps.base import IntegrateTiming, PreparedScan
from voxtool.parallel import resolve_threads
from voxtool.sources import ScanStream, SourceOptions, open_source
from voxtool.sources.scan import Scan

CLOUD_SUFFIXES = (".pcd", ".ply")


@dataclass(frozen=True)
class CleanParams:
    """How `clean` judges a point (docs/cleaning.md)."""

    resolution: float = 0.1  # voxel edge, metres
    sensor_noise: float = 0.2  # d_s: no void evidence within d_s of a point of the same scan
    pose_error: int = 1  # d_p: voxels around a crossed voxel that one scan must know for it to be void
    max_range: float = -1.0  # rays are cut here (no void beyond); < 0 unlimited
    group_share: float = 0.15  # share of a group's points in void voxels that makes it dynamic
    ground_band: float = 0.3  # metres above the scans' ground that are no evidence of a mover (< 0: none)

    def __post_init__(self) -> None:
        MapParams(resolution=self.resolution, max_range=self.max_range)  # the same checks as a map's
        if not (np.isfinite(self.sensor_noise) and 0.0 <= self.sensor_noise <= 100 * self.resolution):
            raise ParameterError(f"sensor_noise={self.sensor_noise} must lie in [0, 100 voxels] metres")
        if not 0 <= self.pose_error <= 5:
            raise ParameterError(f"pose_error={self.pose_error} must lie in 0..5 voxels")
        if not (np.isfinite(self.ground_band) and self.ground_band <= 10.0):
            raise ParameterError(f"ground_band={self.ground_band} must be at most 10 metres (< 0: off)")
        if not 0.0 <= self.group_share <= 1.0:
            raise ParameterError(f"group_share={self.group_share} must lie in [0, 1]")


MIN_VOID_POINTS = 3  # a group with fewer points in void voxels stays: one stray ray is no mover
SPLIT_SCAN = 10_000  # points: a smaller scan's rays are cast on one thread
GROUND_COLUMN_M = 0.2  # the ground's columns (metres): coarser than 0.1 m voxels costs 4x less, 2 cm on a 10 % slope
GRID_BAND = (0.3, 2.0)  # --grid: what stands this high over the ground (metres) is an obstacle
GROUND_CELLS = 1 << 20  # at most this many ground columns: coarser over a larger area (its cost: 0.1 s a million)
GROUP_STEPS = 4  # voxels a group reaches beyond its void points (a mover's unseen bottom and edges)
LEVEL_TOLERANCE = 1e-3  # metres: a scan whose points all lie this close to its sensor's height is a level 2D scan


class BrickSet:
    """A set of voxels: a hash table of 8 x 8 x 8-voxel bricks, a brick's 512 bits as 8 words
    (Morton order inside), grown as it fills (at most half full)."""

    def __init__(self, bricks: int = 2048) -> None:
        size = 1 << max(12, int(bricks).bit_length() + 1)  # room for `bricks` at most half full
        self.keys = np.full(size, -1, dtype=np.int64)  # brick codes, -1 empty (a power of two)
        self.bits = np.zeros((size, 8), dtype=np.int64)
        self.bricks = 0

    def add(self, bricks: np.ndarray, masks: np.ndarray) -> int:
        """Add the voxels of 512-bit brick masks; returns the bits the masks hold."""
        from voxtool.kernels.clean import or_bricks

        while (self.bricks + bricks.shape[0]) * 2 > self.keys.shape[0]:
            self.grow()
        added, voxels = or_bricks(self.keys, self.bits, bricks, masks)
        self.bricks += added
        return voxels

    def grow(self) -> None:
        """Twice the rows, the bricks rehashed."""
        from voxtool.kernels.clean import rehash_bricks

        size = 2 * self.keys.shape[0]
        keys, bits = np.full(size, -1, dtype=np.int64), np.zeros((size, 8), dtype=np.int64)
        rehash_bricks(self.keys, self.bits, keys, bits)
        self.keys, self.bits = keys, bits

    def add_codes(self, codes: np.ndarray) -> None:
        """Add voxels given as finest-level Morton codes (in any order)."""
        from voxtool.kernels.clean import or_codes

        codes = np.asarray(codes, dtype=np.int64)
        while (bricks := or_codes(self.keys, self.bits, self.bricks, codes)) < 0:
            self.grow()
        self.bricks = bricks

    def holds(self, codes: np.ndarray) -> np.ndarray:
        """Whether each finest-level voxel (Morton code >= 0) is in the set."""
        from voxtool.kernels.clean import bricks_hold

        out = np.empty(codes.shape[0], dtype=bool)
        bricks_hold(self.keys, self.bits, codes, out)
        return out

    def clear(self) -> None:
        self.keys[:] = -1
        self.bits[:] = 0
        self.bricks = 0

    def nbytes(self) -> int:
        return int(self.keys.nbytes + self.bits.nbytes)


class VoidMap:
    """The evidence of every scan: `crossed`, the voxels some ray crossed (away from its scan's
    hits), and `void`, those that one scan saw through whole (kernels.clean.seen_whole); shaped
    as a map backend so voxtool.pipeline.build streams scans into it. A scan's map-independent
    part (reading, keying its hits, marking the voxels near them) runs on the read-ahead thread
    while the previous scan's rays are cast and judged on the calling thread's pool."""

    name = "void"

    def __init__(self, params: CleanParams, threads: int = 0) -> None:
        from voxtool.kernels.ball import ball_offsets
        from voxtool.kernels.clean import (
            BALL_TABLE_RADIUS,
            NO_BALL_TABLE,
            ball_brick_masks,
            cube_brick_table,
        )

        self.clean = params
        self.params = MapParams(resolution=params.resolution, max_range=params.max_range)
        self.sensor = SensorModel()
        self.threads = resolve_threads(threads)
        self.crossed = BrickSet()
        self.void = BrickSet()
        radius = int(np.ceil(params.sensor_noise / params.resolution - 1e-9))
        self.near_hit = ball_offsets(radius)
        self.ball_table = ball_brick_masks(self.near_hit) if radius <= BALL_TABLE_RADIUS else NO_BALL_TABLE
        self.cube = cube_brick_table(params.pose_error)
        self.points = BrickSet()  # the voxels holding points of any scan: the only ones judged

    def warm_up(self) -> None:
        from voxtool.kernels.clean import rehash_bricks, voxel_groups, within_steps

        self.apply(self.prepare(Scan(np.array([[1.0, 0.5, 0.25], [1.1, 0.5, 0.25]], dtype=np.float32),
                                     np.zeros(3, dtype=np.float32))))
        dynamic_points(self, np.zeros((1, 3), dtype=np.float32))
        voxel_groups(np.arange(2, dtype=np.int64))
        within_steps(np.arange(2, dtype=np.int64), np.ones(2, dtype=bool), GROUP_STEPS)
        BrickSet().add_codes(np.arange(2, dtype=np.int64))
        for cells in (self.crossed, self.void):
            rehash_bricks(cells.keys, cells.bits, cells.keys.copy(), cells.bits.copy())  # the tables' growth
            cells.clear()

    def prepare(self, scan: Scan) -> PreparedScan:
        """What a scan's rays respect (kernels.clean.near_hits_table): each ray stops at the last
        sensor_noise metres of any ray of the scan and is silent within sensor_noise of any of
        its hits. Map-independent: runs on the read-ahead thread."""
        from voxtool.kernels.clean import near_hits_table
        from voxtool.keys import coords_to_keys, point_codes, unique_codes

        t0 = time.perf_counter()
        points = scan.points
        coords_to_keys(scan.origin[None, :], self.params.resolution, what=f"{scan.source}: sensor origin of scan")
        codes = point_codes(points, self.params.resolution, what=f"{scan.source}: point")  # every ray's end
        if self.params.max_range >= 0:  # a ray cut at max range hits nothing
            kept = np.linalg.norm(points.astype(np.float64) - scan.origin, axis=1) <= self.params.max_range
            points, codes = points[kept], codes[kept]
        hits = unique_codes(codes)
        size = 1 << max(10, int(hits.shape[0]).bit_length() + 1)  # bricks near hits: ~hits / 2
        while True:
            table = (np.full(size, -1, dtype=np.int64), np.zeros((size, 16), dtype=np.int64))
            if near_hits_table(points, hits, scan.origin, self.params.resolution, self.clean.sensor_noise,
                               self.near_hit, *self.ball_table, *table):
                break
            size *= 2
        return PreparedScan(np.empty(0, dtype=np.int64), 0, time.perf_counter() - t0, int(scan.points.shape[0]),
                            scan=scan, near_hits=table)

    def evidence(self, prepared: PreparedScan) -> list:
        """The scan's crossed voxels: per run of rays, (brick codes, their 512-bit masks of the
        voxels the rays crossed, endpoint masks, DDA steps), cast on the map's threads."""
        from voxtool.maps.octree import trace_scan

        # a small scan on one thread: the read-ahead thread marks the next scan's near hits
        # meanwhile, and a hand-off would cost more than it saves (quick_shack, 4,800 points a
        # scan on two cores: 0.54-0.60 s against 0.64-1.06 s split in two)
        threads = self.threads if prepared.scan.points.shape[0] >= SPLIT_SCAN else 1
        return trace_scan(prepared.scan, self.params, threads, prepared.near_hits)

    def seen_whole(self, bricks: np.ndarray, masks: np.ndarray, near_hits) -> tuple[np.ndarray, np.ndarray]:
        """The voxels of one scan's crossed bricks/masks that hold points (self.points) and
        that it saw through whole, with every voxel of their pose_error cube crossed or stopped
        at (kernels.clean.seen_whole), on the map's threads; returns (bricks, masks)."""
        from voxtool.kernels.clean import seen_whole
        from voxtool.parallel import run_parts

        crossed = BrickSet(bricks.shape[0])
        crossed.add(bricks, masks)
        size = crossed.keys.shape[0]
        out = np.zeros((size, 8), dtype=np.int64)
        step = -(-size // max(1, 4 * self.threads)) if size > 1 << 15 else size  # a small scan: one part
        run_parts(self.threads, lambda a: seen_whole(crossed.keys, crossed.bits, self.points.keys, self.points.bits,
                                                     *near_hits, self.cube, a, min(a + step, size), out),
                  list(range(0, size, step)))
        rows = np.flatnonzero(out.any(axis=1))
        return crossed.keys[rows], out[rows]

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        """Cast the scan's rays; its void voxels, then its crossed ones, into the maps."""
        t0 = time.perf_counter()
        parts = self.evidence(prepared) if prepared.scan.points.shape[0] else []
        if not parts:
            return IntegrateTiming(raycast=prepared.seconds, update=0.0, voxel_updates=0, ray_steps=0,
                                   rays=prepared.rays)
        bricks = np.concatenate([p[0] for p in parts])
        masks = np.concatenate([p[1] for p in parts])
        self.void.add(*self.seen_whole(bricks, masks, prepared.near_hits))
        t1 = time.perf_counter()
        voxels = self.crossed.add(bricks, masks)
        return IntegrateTiming(raycast=prepared.seconds + (t1 - t0), update=time.perf_counter() - t1,
                               voxel_updates=voxels, ray_steps=sum(p[3] for p in parts), rays=prepared.rays)

    def used_bytes(self) -> int:
        return self.crossed.nbytes() + self.void.nbytes() + self.points.nbytes()


CLASSIFY_CHUNK = 131_072  # points a thread looks up at a time
GROUND_CHUNK = 1 << 21  # points whose keys are made at a time for the ground


def ground_points(points: np.ndarray, resolution: float, band: float) -> np.ndarray:
    """Which points lie at most `band` metres above the ground under them (voxtool.ground: the
    lowest surface of all the scans' points, objects filtered out, in columns of
    GROUND_COLUMN_M). The points' keys are made GROUND_CHUNK at a time: 18.7 M points' keys at
    once took 0.45 GB, their codes and sort as much again."""
    from voxtool.ground import ground_from_codes, unique_codes, voxel_codes
    from voxtool.keys import coords_to_keys

    def chunks():
        for a in range(0, points.shape[0], GROUND_CHUNK):
            yield a, coords_to_keys(points[a:a + GROUND_CHUNK], resolution).astype(np.int64)

    pieces = [unique_codes(voxel_codes(keys)) for _, keys in chunks()]
    codes, hits = unique_codes(np.concatenate([c for c, _ in pieces]), np.concatenate([h for _, h in pieces]))
    del pieces
    kx, ky = codes >> 32, (codes >> 16) & 0xFFFF
    extent = np.array([kx.max() - kx.min() + 1, ky.max() - ky.min() + 1], dtype=np.float64)
    column = max(1, int(round(GROUND_COLUMN_M / resolution)),
                 int(np.ceil(np.sqrt(extent[0] * extent[1] / GROUND_CELLS))))  # a long drive: coarser columns
    ground = ground_from_codes(codes, hits, resolution, column=column)
    is_ground = np.empty(points.shape[0], dtype=bool)
    for a, keys in chunks():
        # NaN (no ground known): not ground
        is_ground[a:a + keys.shape[0]] = points[a:a + keys.shape[0], 2] - ground.under(keys[:, 0], keys[:, 1]) <= band
    return is_ground


def point_columns(points: np.ndarray, resolution: float) -> np.ndarray:
    """Each point's voxel column (key x << 16 | key y)."""
    from voxtool.keys import coords_to_keys

    keys = coords_to_keys(points, resolution).astype(np.int64)
    return keys[:, 0] << 16 | keys[:, 1]


def point_evidence(void_map: VoidMap, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(whether each world point's voxel is void, whether some ray crossed it or it is void):
    every point looked up in both maps, in chunks on the map's threads."""
    from voxtool.parallel import run_parts

    n = points.shape[0]
    void = np.empty(n, dtype=bool)
    seen = np.empty(n, dtype=bool)

    def look_up(a):
        b = min(a + CLASSIFY_CHUNK, n)
        codes = _voxel_codes(void_map, points[a:b])  # a scan's points in sensor order: few bricks in a row
        void[a:b] = void_map.void.holds(codes)
        seen[a:b] = void_map.crossed.holds(codes) | void[a:b]

    run_parts(void_map.threads, look_up, list(range(0, n, CLASSIFY_CHUNK)))
    return void, seen


def dynamic_points(void_map: VoidMap, points: np.ndarray, scan_starts: np.ndarray | None = None,
                   ground: np.ndarray | None = None, evidence: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> np.ndarray:
    """Which world points are dynamic (the module's rule): every point's voxel looked up in
    both maps (point_evidence, or `evidence` where already found), then the groups of each scan
    that has points in void voxels (`scan_starts`: where each scan's points start, and their
    count last; one scan if None). `ground`: ground_points() of the points, or None to judge the
    ground as any other surface."""
    from voxtool.parallel import run_parts

    n = points.shape[0]
    starts = np.array([0, n], dtype=np.int64) if scan_starts is None else np.asarray(scan_starts, dtype=np.int64)
    void, seen = point_evidence(void_map, points) if evidence is None else evidence
    dynamic = np.zeros(n, dtype=bool)
    voids_before = np.concatenate([[0], np.cumsum(void)])
    scans_with_void = np.flatnonzero(voids_before[starts[1:]] > voids_before[starts[:-1]])

    def judge(i):
        a, b = int(starts[i]), int(starts[i + 1])
        if b > a:
            if ground is None:
                dynamic[a:b] = _moving_groups(void_map, points[a:b], void[a:b], seen[a:b])
            else:
                dynamic[a:b] = _moving_groups_over_ground(void_map, points[a:b], void[a:b], seen[a:b], ground[a:b],
                                                          point_columns(points[a:b], void_map.params.resolution))

    run_parts(void_map.threads, judge, scans_with_void.tolist())
    return dynamic


def _voxel_codes(void_map: VoidMap, points: np.ndarray) -> np.ndarray:
    from voxtool.keys import point_codes

    return point_codes(points, void_map.params.resolution)


def _moving_groups(void_map: VoidMap, points: np.ndarray, void: np.ndarray, seen: np.ndarray,
                   seeds_from: np.ndarray | None = None) -> np.ndarray:
    """One scan's points: those in crossed voxels at most GROUP_STEPS voxel steps (through
    such voxels) from a point in a void voxel (of the points `seeds_from` allows, all if None),
    in groups of 26-connected voxels; dynamic where enough of a group's points lie in void
    voxels."""
    from voxtool.kernels.clean import voxel_groups, within_steps

    members = np.flatnonzero(seen)
    voxels, voxel_of = np.unique(_voxel_codes(void_map, points[members]), return_inverse=True)
    seeds = np.zeros(voxels.shape[0], dtype=bool)
    seeds[voxel_of[(void if seeds_from is None else void & seeds_from)[members]]] = True
    reached = within_steps(voxels, seeds, GROUP_STEPS)
    voxels = voxels[reached]
    kept = reached[voxel_of]
    members = members[kept]
    voxel_of = (np.cumsum(reached) - 1)[voxel_of[kept]]  # indices into the reached voxels
    group = voxel_groups(voxels)[voxel_of]
    in_void = np.bincount(group, weights=void[members], minlength=voxels.shape[0])
    size = np.bincount(group, minlength=voxels.shape[0])
    moving = (in_void >= MIN_VOID_POINTS) & (in_void >= void_map.clean.group_share * size)
    dynamic = np.zeros(points.shape[0], dtype=bool)
    dynamic[members] = moving[group]
    return dynamic


NEAR_COLUMNS = [0] + [(dx << 16) + dy for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]  # 0: its own


def _moving_groups_over_ground(void_map: VoidMap, points: np.ndarray, void: np.ndarray, seen: np.ndarray,
                               ground: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """One scan's points judged with the ground apart. A ground point in a void voxel seeds no
    group (under pose error rays graze the road another scan saw a few centimetres higher), but
    ground points still join the groups the points above the ground seed and count in their
    share (_moving_groups). Then a ground point goes with a moving group whose lowest point above
    the ground, in its voxel column (or the 8 around, where the ground point is void itself),
    stands at most ground_band and a voxel above it: the wheels and feet beyond the group's
    GROUP_STEPS."""
    dynamic = _moving_groups(void_map, points, void, seen, seeds_from=~ground)
    moving = np.flatnonzero(dynamic & ~ground)
    if moving.shape[0] == 0:
        return dynamic
    order = np.lexsort((points[moving, 2], columns[moving]))  # by column, then height
    moving_columns, first = np.unique(columns[moving[order]], return_index=True)
    lowest = points[moving[order[first]], 2]  # each such column's lowest moving point
    low = np.flatnonzero(ground)
    reach = void_map.clean.ground_band + void_map.params.resolution
    for offset in NEAR_COLUMNS:
        pick = low if offset == 0 else low[void[low]]
        at = np.minimum(np.searchsorted(moving_columns, columns[pick] + offset), moving_columns.shape[0] - 1)
        dynamic[pick] |= (moving_columns[at] == columns[pick] + offset) & (lowest[at] - points[pick, 2] <= reach)
    return dynamic


@dataclass
class Cleaned:
    """A cleaned scan sequence: every kept point (world frame, scan order), which are dynamic,
    where each scan's points start, and the figures of the run."""

    points: np.ndarray  # (N, 3) float32
    dynamic: np.ndarray  # (N,) bool
    scan_starts: np.ndarray  # (scans + 1,) int64
    figures: dict = field(default_factory=dict)
    # each scan as read, less its points (its origin, stamp, no-return beams): what a map of the
    # kept points casts its rays from (static_map)
    shells: list = field(default_factory=list)
    stream: ScanStream | None = None  # the source read (kind, path), its scans consumed
    void: np.ndarray | None = None  # (N,) bool: the point's voxel is void (another scan saw through it)


def clean_stream(stream: ScanStream, params: CleanParams, threads: int = 0, progress: bool | None = None) -> Cleaned:
    """Three passes over the points, one over the rays: read every scan and note the voxels its
    points lie in (the only voxels ever judged), build the void map from every scan, then judge
    every point against the finished map."""
    import dataclasses

    from voxtool.keys import point_codes
    from voxtool.pipeline import build
    from voxtool.progress import track

    void_map = VoidMap(params, threads)
    t0 = time.perf_counter()
    scans = []
    level = True  # every scan a level 2D one: its points at its sensor's height
    for scan in track(stream.scans, stream.count, "read", progress, unit="scan"):
        if scan.hits_only:
            raise ParameterError(f"{scan.source}: has no sensor origin: clean judges points by the rays that "
                                 "crossed them, and it has none")
        void_map.points.add_codes(point_codes(scan.points, params.resolution, what=f"{scan.source}: point"))
        level = level and (scan.points.shape[0] == 0
                           or float(np.abs(scan.points[:, 2] - scan.origin[2]).max()) <= LEVEL_TOLERANCE)
        scans.append(scan)
    t_read = time.perf_counter() - t0
    planar = level and bool(scans)
    if planar:
        # a 2D scanner's rays stay in its layer: the pose-error cube would ask the layers above
        # and below to be crossed, which never happens, and the scan plane is no ground
        from voxtool.kernels.clean import cube_brick_table

        void_map.cube = cube_brick_table(params.pose_error, True)
    report = build(dataclasses.replace(stream, scans=iter(scans)), void_map, progress)
    clouds = [scan.points for scan in scans]  # as read: build casts each scan unchanged
    truths = [scan.extra.get("truth") for scan in scans]  # ground truth per point (--truth), where given
    shells = [dataclasses.replace(scan, points=clouds[0][:0], extra={}) for scan in scans]
    del scans
    t0 = time.perf_counter()
    points = np.concatenate(clouds) if clouds else np.empty((0, 3), dtype=np.float32)
    starts = np.zeros(len(clouds) + 1, dtype=np.int64)
    np.cumsum([c.shape[0] for c in clouds], out=starts[1:])
    del clouds  # the scans' own arrays: every point was held twice from here on
    judge_ground = params.ground_band >= 0 and points.shape[0] > 0 and not planar
    ground = ground_points(points, params.resolution, params.ground_band) if judge_ground else None
    void, seen = point_evidence(void_map, points)
    dynamic = dynamic_points(void_map, points, starts, ground, (void, seen))
    del seen
    t_classify = time.perf_counter() - t0
    built = report.to_dict()
    figures = {
        "scans": built["scans"], "scans_skipped": built["scans_skipped"], "skipped_scans": built["skipped_scans"],
        "points_read": built["points"], "points_dropped": built["points_dropped"],
        "points_in": int(points.shape[0]), "points_kept": int(points.shape[0] - dynamic.sum()),
        "points_removed": int(dynamic.sum()), "void_map_bytes": void_map.used_bytes(),
        "ground_points": int(ground.sum()) if ground is not None else None, "planar": planar,
        "threads": void_map.threads, "params": asdict(params),
        "timings_s": {"jit": built["timings_s"]["jit"], "read": round(t_read + built["timings_s"]["read"], 6),
                      "raycast": built["timings_s"]["raycast"], "void_update": built["timings_s"]["update"],
                      "scans_total": built["timings_s"]["total"], "classify": round(t_classify, 6)},
    }
    if truths and all(t is not None for t in truths):
        truth = np.concatenate(truths)
        figures["accuracy"] = accuracy_figures(dynamic, truth)
    return Cleaned(points, dynamic, starts, figures, shells, stream, void)


def static_map(cleaned: Cleaned, params: CleanParams, threads: int = 0, progress: bool | None = None):
    """The occupancy map of the kept points (octree, OctoMap's sensor model, clean's resolution and
    max range): each scan's rays cast from its origin to its kept points, its no-return beams as
    read; a removed point marks nothing and its ray is not cast. Returns (backend, build report).
    A planner's grid of it (export --above-ground) has no movers in it."""
    import dataclasses

    from voxtool.config import MapParams, SensorModel
    from voxtool.maps import make_backend
    from voxtool.pipeline import build

    starts, keep = cleaned.scan_starts, ~cleaned.dynamic
    scans = (dataclasses.replace(shell, points=np.ascontiguousarray(cleaned.points[a:b][keep[a:b]]))
             for shell, a, b in zip(cleaned.shells, starts[:-1], starts[1:]))
    backend = make_backend("octree", MapParams(resolution=params.resolution, max_range=params.max_range), SensorModel(),
                           threads=threads)
    report = build(dataclasses.replace(cleaned.stream, scans=scans), backend, progress)
    return backend, report


def check_outputs(output: str | os.PathLike | None, labels: str | os.PathLike | None,
                  dynamic: str | os.PathLike | None = None, png: str | os.PathLike | None = None,
                  map_output: str | os.PathLike | None = None, grid: str | os.PathLike | None = None) -> None:
    """Refuse outputs that cannot be written before any work."""
    from voxtool.atomic import check_writable

    if all(p is None for p in (output, labels, dynamic, png, map_output, grid)):
        raise ParameterError("clean writes its result: give -o STATIC.pcd/.ply, --map STATIC.vxm, --grid GRID.pgm, "
                             "--labels LABELS.npy, --dynamic REMOVED.pcd/.ply or --png OUT.png")
    if grid is not None:
        from voxtool.io.export import check_grid_writable

        suffix = Path(grid).suffix.lower()
        if suffix not in (".pgm", ".mcap"):
            raise ParameterError(f"{grid}: --grid writes a planner's grid as a .pgm (and its .yaml beside it, as nav2 "
                                 "reads it) or a .mcap (a nav_msgs/OccupancyGrid)")
        if suffix == ".pgm":
            check_grid_writable(Path(grid))
        else:
            check_writable(grid)
    if map_output is not None:
        if Path(map_output).suffix.lower() != ".vxm":
            raise ParameterError(f"{map_output}: --map writes a map snapshot, a .vxm (`voxtool export` makes .bt, .pgm, "
                                 "... of it)")
        check_writable(map_output)
    for path, what in ((output, "the static points are"), (dynamic, "--dynamic: the removed points are")):
        if path is not None:
            if Path(path).suffix.lower() not in CLOUD_SUFFIXES:
                raise ParameterError(f"{path}: {what} written as .pcd or .ply")
            check_writable(path)
    if png is not None:
        from voxtool.plots import check_png

        check_png(png, "--png")
    if labels is not None:
        if Path(labels).suffix.lower() != ".npy":
            raise ParameterError(f"{labels}: labels are written as .npy (uint8 per point: 0 static, 1 dynamic)")
        check_writable(labels)


WRITE_CHUNK = 1 << 21  # points moved and written at a time


def write_cloud_points(path: str | os.PathLike, points: np.ndarray, origin=None, resolution: float = 1.0,
                       keep: np.ndarray | None = None) -> None:
    """The points (`keep`: those flagged) as a binary .pcd or .ply (the export writers' layout),
    atomically, WRITE_CHUNK at a time (no copy of them all); moved back to the scans' frame by the
    local origin (--origin), in float64 where float32 would blur them."""
    from voxtool.atomic import atomic_writer
    from voxtool.io.export import CLOUD_FORMATS, needs_double

    header, rows = CLOUD_FORMATS[Path(path).suffix.lower().lstrip(".")]
    keep = np.ones(points.shape[0], dtype=bool) if keep is None else keep
    chunks = range(0, points.shape[0], WRITE_CHUNK)
    shift = None if origin is None or not np.any(origin) else np.asarray(origin, dtype=np.float64)
    double = False
    if shift is not None:
        largest = max((float(np.abs(points[a:a + WRITE_CHUNK][keep[a:a + WRITE_CHUNK]] + shift).max(initial=0.0))
                       for a in chunks), default=0.0)
        double = needs_double(largest, resolution)
    with atomic_writer(path) as handle:
        handle.write(header(int(keep.sum()), False, double))
        for a in chunks:
            part = points[a:a + WRITE_CHUNK][keep[a:a + WRITE_CHUNK]]
            if shift is not None:
                part = part.astype(np.float64) + shift
                part = part if double else part.astype(np.float32)
            handle.write(rows(part, None))


def write_labels(path: str | os.PathLike, dynamic: np.ndarray) -> None:
    from voxtool.atomic import atomic_writer

    with atomic_writer(path) as handle:
        np.save(handle, dynamic.astype(np.uint8))


def clean_source(source: str | os.PathLike, options: SourceOptions, params: CleanParams,
                 output: str | os.PathLike | None = None, labels: str | os.PathLike | None = None,
                 threads: int = 0, progress: bool | None = None, dynamic: str | os.PathLike | None = None,
                 png: str | os.PathLike | None = None, view: str = "top",
                 truth_npy: str | os.PathLike | None = None, above_ground: tuple | None = None,
                 map_output: str | os.PathLike | None = None, grid: str | os.PathLike | None = None,
                 grid_band: tuple[float, float] = GRID_BAND) -> dict[str, Any]:
    """`voxtool clean`: judge every point of `source`; write the static points (`output`), the
    labels, the removed points (`dynamic`), a picture of what was removed (`png`: the removed
    points in red over the kept ones, seen from `view`; `above_ground`: coloured by height over
    the ground on that scale), the map of the kept points (`map_output`, a .vxm: static_map)
    and/or a planner's grid of what stands `grid_band` metres over the ground (`grid`, a .pgm or
    .mcap: static_grid)."""
    from voxtool.sources import resolve_origin

    check_outputs(output, labels, dynamic, png, map_output, grid)
    truth = None if truth_npy is None else read_truth_npy(truth_npy)  # a bad file fails before the work
    options = resolve_origin(source, options, params.resolution)
    cleaned = clean_stream(open_source(source, options), params, threads, progress)
    if truth is not None:
        if truth.shape[0] != cleaned.dynamic.shape[0]:
            raise ParameterError(f"{truth_npy}: {truth.shape[0]:,} labels for the {cleaned.dynamic.shape[0]:,} points "
                                 "judged (one per point, in scan order, as --labels writes them)")
        cleaned.figures["accuracy"] = accuracy_figures(cleaned.dynamic, truth)
    if grid is not None and cleaned.figures["planar"]:  # refused before anything is written
        raise ParameterError(f"{grid}: --grid: a 2D scanner's scans have no ground to measure height from; write "
                             "--map and export it without --above-ground for their grid")
    if map_output is not None or grid is not None:
        backend, report = static_map(cleaned, params, threads, progress)
    if grid is not None:  # made before anything is written: a grid that cannot be made leaves no file
        try:
            planner_grid, grid_figures = static_grid(cleaned, backend, grid_band)
        except ParameterError as err:
            raise ParameterError(f"{grid}: --grid: {err}") from None
    t0 = time.perf_counter()
    if output is not None:
        write_cloud_points(output, cleaned.points, options.origin, params.resolution, keep=~cleaned.dynamic)
    if labels is not None:
        write_labels(labels, cleaned.dynamic)
    if grid is not None:
        stamp_ns = cleaned.shells[-1].stamp_ns if cleaned.shells else 0
        cleaned.figures["grid"] = write_static_grid(Path(grid), planner_grid, grid_figures, grid_band, stamp_ns,
                                                    options.origin)
    if map_output is not None:
        from voxtool.api import backend_stats, save_counted, snapshot_info

        info = {**snapshot_info(source, cleaned.stream.kind, options, report),
                "cleaned": {"points_removed": int(cleaned.dynamic.sum()), "params": asdict(params)}}
        tree, _, _ = save_counted(map_output, backend, info)
        stats = backend_stats(backend, tree)
        cleaned.figures["map"] = {"written": str(map_output), "occupied_voxels": stats["occupied_voxels"],
                                  "free_voxels": stats["free_voxels"]}
    if dynamic is not None:
        write_cloud_points(dynamic, cleaned.points, options.origin, params.resolution, keep=cleaned.dynamic)
    if png is not None:
        from voxtool.plots import clean_figure, write_plot

        fig, roof = clean_figure(cleaned.points, cleaned.dynamic, f"voxtool clean {Path(source).name}", None, view,
                                 above_ground=above_ground, resolution=params.resolution)
        cleaned.figures["png"] = write_plot(fig, png)
        if roof is not None:
            cleaned.figures["png"]["below_roof_m"] = round(roof, 6)
    figures = cleaned.figures
    figures["timings_s"]["write"] = round(time.perf_counter() - t0, 6)
    figures["source"] = str(source)
    figures["origin"] = list(options.origin) if options.origin is not None else [0.0, 0.0, 0.0]
    return figures


def static_grid(cleaned: Cleaned, backend, band: tuple[float, float]):
    """`clean --grid`: the grid of what the kept points and their map (static_map) show standing
    `band` metres over the ground (voxtool.ground.project_returns_above_ground); (grid, figures)."""
    from voxtool.ground import project_returns_above_ground

    origins = np.array([shell.origin for shell in cleaned.shells], dtype=np.float64).reshape(-1, 3)
    return project_returns_above_ground(cleaned.points, cleaned.scan_starts, origins, backend, band,
                                        keep=~cleaned.dynamic, evidence=~cleaned.void)


def write_static_grid(path: Path, grid, figures: dict, band: tuple[float, float], stamp_ns: int = 0,
                      origin=None) -> dict:
    """static_grid's grid as nav2's .pgm and .yaml, or as a .mcap's OccupancyGrid at `stamp_ns`."""
    from voxtool.io.export import write_grid_pgm
    from voxtool.io.viewer_mcap import write_grid_mcap

    if path.suffix.lower() == ".mcap":
        written = write_grid_mcap(path, grid, stamp_ns, origin)
    else:
        written = write_grid_pgm(path, grid, origin)
    return {"written": str(path), **written, "above_ground": list(band), "resolution": grid.resolution, **figures}


def read_truth_npy(path: str | os.PathLike) -> np.ndarray:
    """Ground-truth labels of a .npy (one per judged point; non-zero: dynamic)."""
    try:
        labels = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise ParameterError(f"{path}: cannot be read as a .npy of labels ({err})") from err
    if labels.ndim != 1 or labels.dtype.kind not in "biu":
        raise ParameterError(f"{path}: labels must be one integer or bool per point, not {labels.dtype} {labels.shape}")
    return labels.astype(bool)


def accuracy(dynamic: np.ndarray, truth: np.ndarray) -> dict[str, float | None]:
    """The DynamicMap benchmark's scores of per-point labels against ground truth: static
    accuracy SA (static points kept), dynamic accuracy DA (dynamic points removed) and their
    geometric mean AA, in percent. A score with nothing of its kind to judge is None (no moving
    point: DA and AA are not known, and a 100 there would read as a cleaner that found every mover)."""
    dynamic = np.asarray(dynamic, dtype=bool)
    truth = np.asarray(truth, dtype=bool)
    if dynamic.shape != truth.shape:
        raise ParameterError(f"labels of {dynamic.shape[0]} points against a ground truth of {truth.shape[0]}")
    static = ~truth
    sa = 100.0 * float(np.count_nonzero(~dynamic & static)) / int(static.sum()) if static.any() else None
    da = 100.0 * float(np.count_nonzero(dynamic & truth)) / int(truth.sum()) if truth.any() else None
    return {"SA": sa, "DA": da, "AA": None if sa is None or da is None else float(np.sqrt(sa * da))}


def accuracy_figures(dynamic: np.ndarray, truth: np.ndarray) -> dict:
    """accuracy() rounded as `clean --json` reports it, with the counts of each kind."""
    scores = {k: None if v is None else round(v, 4) for k, v in accuracy(dynamic, truth).items()}
    return {**scores, "dynamic_points": int(truth.sum()), "static_points": int((~truth).sum())}
