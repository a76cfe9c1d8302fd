"""`voxtool clean`: a static point map from a scan sequence, by void regions (DUFOMap's idea).

A voxel is *void* once any ray of any scan has passed through it farther than `sensor_noise`
from every point of that scan (range noise and porous surfaces such as foliage, seen through
between the hits of one scan, give no void evidence), each ray stopping where it comes within
`sensor_noise` of the end of any ray of the scan (DUFOMap's inflated hits). A point is dynamic
when its voxel and every voxel within `pose_error` voxels of it are void: something else was seen through that space at another
time. Everything else is static. The void map holds a bit per voxel that the exact OctoMap ray
casting (voxtool.maps.octree's caster) crossed; docs/cleaning.md says how to tune it and
docs/design/clean.md why it was chosen and what it was measured against.
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
    pose_error: int = 1  # d_p: voxels around a point's voxel that must be void too
    max_range: float = -1.0  # rays are cut here (no void beyond); < 0 unlimited

    def __post_init__(self) -> None:
        MapParams(resolution=self.resolution, max_range=self.max_range)  # the same checks as a map's
        if not (np.isfinite(self.sensor_noise) and 0.0 <= self.sensor_noise <= 100 * self.resolution):
            raise ParameterError(f"sensor_noise={self.sensor_noise} must lie in [0, 100 voxels] metres")
        if not 0 <= self.pose_error <= 5:
            raise ParameterError(f"pose_error={self.pose_error} must lie in 0..5 voxels")


class VoidMap:
    """The void map: a bit per voxel that some ray crossed, in a hash table of 8 x 8 x 8-voxel
    bricks (a brick's 512 bits as 8 words, Morton order inside), shaped as a map backend so
    voxtool.pipeline.build streams scans into it. A scan's map-independent part (reading, keying
    its hits, marking the voxels near them) runs on the read-ahead thread while the previous
    scan's rays are cast and ORed into the table on the calling thread's pool."""

    name = "void"

    def __init__(self, params: CleanParams, threads: int = 0) -> None:
        from voxtool.kernels.clean import BALL_TABLE_RADIUS, NO_BALL_TABLE, ball_brick_masks, ball_offsets

        self.clean = params
        self.params = MapParams(resolution=params.resolution, max_range=params.max_range)
        self.sensor = SensorModel()
        self.threads = resolve_threads(threads)
        self.keys = np.full(1 << 12, -1, dtype=np.int64)  # brick codes, -1 empty (a power of two)
        self.bits = np.zeros((1 << 12, 8), dtype=np.int64)
        self.bricks = 0
        radius = int(np.ceil(params.sensor_noise / params.resolution - 1e-9))
        self.near_hit = ball_offsets(radius)
        self.ball_table = ball_brick_masks(self.near_hit) if radius <= BALL_TABLE_RADIUS else NO_BALL_TABLE

    def warm_up(self) -> None:
        from voxtool.kernels.clean import rehash_bricks

        self.apply(self.prepare(Scan(np.array([[1.0, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32))))
        dynamic_points(self, np.zeros((1, 3), dtype=np.float32))
        rehash_bricks(self.keys, self.bits, self.keys.copy(), self.bits.copy())  # the table's growth
        self.keys[:] = -1
        self.bits[:] = 0
        self.bricks = 0

    def prepare(self, scan: Scan) -> PreparedScan:
        """What a scan's rays respect (kernels.clean.near_hits_table): each ray stops at the last
        sensor_noise metres of any ray of the scan and is silent within sensor_noise of any of
        its hits. Map-independent: runs on the read-ahead thread."""
        from voxtool.kernels.clean import near_hits_table
        from voxtool.keys import coords_to_keys, morton_encode, unique_codes

        t0 = time.perf_counter()
        points = scan.points
        coords_to_keys(scan.origin[None, :], self.params.resolution, what=f"{scan.source}: sensor origin of scan")
        keys = coords_to_keys(points, self.params.resolution, what=f"{scan.source}: point")  # every ray's end
        if self.params.max_range >= 0:  # a ray cut at max range hits nothing
            kept = np.linalg.norm(points.astype(np.float64) - scan.origin, axis=1) <= self.params.max_range
            points, keys = points[kept], keys[kept]
        hits = unique_codes(morton_encode(keys))
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
        """The scan's void evidence: per run of rays, (brick codes, their 512-bit masks of the
        voxels the rays crossed, DDA steps), cast on the map's threads."""
        from voxtool.maps.octree import trace_scan

        return trace_scan(prepared.scan, self.params, self.threads, prepared.near_hits)

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        t0 = time.perf_counter()
        parts = self.evidence(prepared) if prepared.scan.points.shape[0] else []
        t1 = time.perf_counter()
        voxels = sum(self.add_bricks(bricks, masks) for bricks, masks, _, _ in parts)
        return IntegrateTiming(raycast=prepared.seconds + (t1 - t0), update=time.perf_counter() - t1,
                               voxel_updates=voxels, ray_steps=sum(p[3] for p in parts), rays=prepared.rays)

    def add_bricks(self, bricks: np.ndarray, masks: np.ndarray) -> int:
        """Make the voxels of 512-bit brick masks void; returns the bits the masks hold."""
        from voxtool.kernels.clean import or_bricks, rehash_bricks

        while (self.bricks + bricks.shape[0]) * 2 > self.keys.shape[0]:  # at most half full
            size = 2 * self.keys.shape[0]
            keys, bits = np.full(size, -1, dtype=np.int64), np.zeros((size, 8), dtype=np.int64)
            rehash_bricks(self.keys, self.bits, keys, bits)
            self.keys, self.bits = keys, bits
        added, voxels = or_bricks(self.keys, self.bits, bricks, masks)
        self.bricks += added
        return voxels

    def add_void(self, codes: np.ndarray) -> None:
        """Make voxels (finest-level Morton codes) void."""
        codes = np.unique(np.asarray(codes, dtype=np.int64))
        bricks, brick_of = np.unique(codes >> 9, return_inverse=True)
        masks = np.zeros((bricks.shape[0], 8), dtype=np.int64)
        np.bitwise_or.at(masks, (brick_of, (codes & 511) >> 6), np.left_shift(np.int64(1), codes & 63))
        self.add_bricks(bricks, masks)

    def void(self, codes: np.ndarray) -> np.ndarray:
        """Whether each finest-level voxel (Morton code >= 0) is void."""
        from voxtool.kernels.clean import bricks_hold

        out = np.empty(codes.shape[0], dtype=bool)
        bricks_hold(self.keys, self.bits, codes, out)
        return out

    def used_bytes(self) -> int:
        return int(self.keys.nbytes + self.bits.nbytes)


def cube_offsets(radius: int) -> np.ndarray:
    """(n, 3) offsets of the (2r+1)^3 cube around a voxel, itself excluded."""
    r = np.arange(-radius, radius + 1)
    cube = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int64)
    return cube[np.any(cube != 0, axis=1)]


CLASSIFY_CHUNK = 131_072  # points a thread judges at a time


def dynamic_points(void_map: VoidMap, points: np.ndarray) -> np.ndarray:
    """Which world points are dynamic: their voxel and its pose_error cube all void (chunks of
    points on the map's threads)."""
    from voxtool.parallel import run_parts

    n = points.shape[0]
    chunks = [(a, min(a + CLASSIFY_CHUNK, n)) for a in range(0, n, CLASSIFY_CHUNK)]
    out = np.empty(n, dtype=bool)

    def judge(chunk):
        out[chunk[0]:chunk[1]] = _dynamic_chunk(void_map, points[chunk[0]:chunk[1]])

    run_parts(void_map.threads, judge, chunks)
    return out


def _dynamic_chunk(void_map: VoidMap, points: np.ndarray) -> np.ndarray:
    from voxtool.kernels.clean import neighbour_codes
    from voxtool.keys import coords_to_keys, morton_encode

    codes = morton_encode(coords_to_keys(points, void_map.params.resolution))
    dynamic = void_map.void(codes)
    offsets = cube_offsets(void_map.clean.pose_error)
    candidates = np.flatnonzero(dynamic)
    if candidates.shape[0] and offsets.shape[0]:
        near = np.empty((candidates.shape[0], offsets.shape[0]), dtype=np.int64)
        neighbour_codes(codes[candidates], offsets, near)
        inside = near >= 0
        ok = np.zeros(near.shape, dtype=bool)
        ok[inside] = void_map.void(near[inside])
        dynamic[candidates] = ok.all(axis=1)
    return dynamic


@dataclass
class Cleaned:
    """A cleaned scan sequence: every kept point (world frame, scan order), which are dynamic,
    where each scan's points start, and the figures of the run."""

    points: np.ndarray  # (N, 3) float32
    dynamic: np.ndarray  # (N,) bool
    scan_starts: np.ndarray  # (scans + 1,) int64
    figures: dict = field(default_factory=dict)


def clean_stream(stream: ScanStream, params: CleanParams, threads: int = 0, progress: bool | None = None) -> Cleaned:
    """Two passes over the points, one over the rays: build the void map from every scan while
    keeping the scans' points, then judge every point against the finished map."""
    from voxtool.pipeline import build

    void_map = VoidMap(params, threads)
    clouds: list[np.ndarray] = []
    report = build(stream, void_map, progress, on_scan=lambda scan, _: clouds.append(scan.points))
    t0 = time.perf_counter()
    points = np.concatenate(clouds) if clouds else np.empty((0, 3), dtype=np.float32)
    dynamic = dynamic_points(void_map, points)
    t_classify = time.perf_counter() - t0
    starts = np.zeros(len(clouds) + 1, dtype=np.int64)
    np.cumsum([c.shape[0] for c in clouds], out=starts[1:])
    built = report.to_dict()
    figures = {
        "scans": built["scans"], "points_read": built["points"], "points_dropped": built["points_dropped"],
        "points_in": int(points.shape[0]), "points_kept": int(points.shape[0] - dynamic.sum()),
        "points_removed": int(dynamic.sum()), "void_map_bytes": void_map.used_bytes(),
        "threads": void_map.threads, "params": asdict(params),
        "timings_s": {"jit": built["timings_s"]["jit"], "read": built["timings_s"]["read"],
                      "raycast": built["timings_s"]["raycast"], "void_update": built["timings_s"]["update"],
                      "scans_total": built["timings_s"]["total"], "classify": round(t_classify, 6)},
    }
    return Cleaned(points, dynamic, starts, figures)


def check_outputs(output: str | os.PathLike | None, labels: str | os.PathLike | None,
                  dynamic: str | os.PathLike | None = None, png: str | os.PathLike | None = None) -> None:
    """Refuse outputs that cannot be written before any work."""
    from voxtool.atomic import check_writable

    if output is None and labels is None and dynamic is None and png is None:
        raise ParameterError("clean writes its result: give -o STATIC.pcd/.ply, --labels LABELS.npy, --dynamic "
                             "REMOVED.pcd/.ply or --png OUT.png")
    for path, what in ((output, "the static map is"), (dynamic, "--dynamic: the removed points are")):
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


def write_cloud_points(path: str | os.PathLike, points: np.ndarray, origin=None, resolution: float = 1.0) -> None:
    """Points as a binary .pcd or .ply (the export writers' layout), atomically; moved back to
    the scans' frame by the local origin (--origin), in float64 where float32 would blur them."""
    from voxtool.atomic import atomic_writer
    from voxtool.io.export import CLOUD_FORMATS, in_source_frame

    header, rows = CLOUD_FORMATS[Path(path).suffix.lower().lstrip(".")]
    points = in_source_frame(points, origin, resolution)
    with atomic_writer(path) as handle:
        handle.write(header(len(points), False, points.dtype == np.float64))
        handle.write(rows(points, None))


def write_labels(path: str | os.PathLike, dynamic: np.ndarray) -> None:
    from voxtool.atomic import atomic_writer

    with atomic_writer(path) as handle:
        np.save(handle, dynamic.astype(np.uint8))


def clean_source(source: str | os.PathLike, options: SourceOptions, params: CleanParams,
                 output: str | os.PathLike | None = None, labels: str | os.PathLike | None = None,
                 threads: int = 0, progress: bool | None = None, dynamic: str | os.PathLike | None = None,
                 png: str | os.PathLike | None = None, view: str = "top") -> dict[str, Any]:
    """`voxtool clean`: judge every point of `source`; write the static points (`output`), the
    labels, the removed points (`dynamic`) and/or a picture of what was removed (`png`: the
    removed points in red over the kept ones, seen from `view`)."""
    from voxtool.sources import resolve_origin

    check_outputs(output, labels, dynamic, png)
    options = resolve_origin(source, options, params.resolution)
    cleaned = clean_stream(open_source(source, options), params, threads, progress)
    t0 = time.perf_counter()
    if output is not None:
        write_cloud_points(output, cleaned.points[~cleaned.dynamic], options.origin, params.resolution)
    if labels is not None:
        write_labels(labels, cleaned.dynamic)
    if dynamic is not None:
        write_cloud_points(dynamic, cleaned.points[cleaned.dynamic], options.origin, params.resolution)
    if png is not None:
        from voxtool.plots import clean_figure, write_plot

        cleaned.figures["png"] = write_plot(clean_figure(cleaned.points, cleaned.dynamic,
                                                         f"voxtool clean {Path(source).name}", None, view), png)
    figures = cleaned.figures
    figures["timings_s"]["write"] = round(time.perf_counter() - t0, 6)
    figures["source"] = str(source)
    figures["origin"] = list(options.origin) if options.origin is not None else [0.0, 0.0, 0.0]
    return figures


def accuracy(dynamic: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The DynamicMap benchmark's scores of per-point labels against ground truth: static
    accuracy SA (static points kept), dynamic accuracy DA (dynamic points removed) and their
    geometric mean AA, in percent; SA or DA is 100 where there is nothing of its kind to judge."""
    dynamic = np.asarray(dynamic, dtype=bool)
    truth = np.asarray(truth, dtype=bool)
    if dynamic.shape != truth.shape:
        raise ParameterError(f"labels of {dynamic.shape[0]} points against a ground truth of {truth.shape[0]}")
    static = ~truth
    sa = 100.0 * float(np.count_nonzero(~dynamic & static)) / max(int(static.sum()), 1) if static.any() else 100.0
    da = 100.0 * float(np.count_nonzero(dynamic & truth)) / max(int(truth.sum()), 1) if truth.any() else 100.0
    return {"SA": sa, "DA": da, "AA": float(np.sqrt(sa * da))}
