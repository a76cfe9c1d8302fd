"""The build pipeline: stream scans from a source through a map backend, timing every phase."""

from __future__ import annotations

import gc
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from voxtool.maps.base import MapBackend
from voxtool.parallel import usable_cores
from voxtool.sources import ScanStream


@dataclass
class BuildReport:
    scans: int = 0
    points: int = 0
    points_dropped: int = 0
    points_dropped_nonfinite: int = 0
    points_dropped_at_origin: int = 0
    points_dropped_ego_box: int = 0
    points_dropped_min_range: int = 0
    no_returns: int = 0  # beams that saw nothing (LaserScan range_max / +Inf): free space only
    raw_bytes: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    time_read: float = 0.0
    time_raycast: float = 0.0
    time_update: float = 0.0
    time_total: float = 0.0
    time_jit: float = 0.0
    voxel_updates: int = 0
    ray_steps: int = 0
    rays: int = 0
    merged_rays: int = 0
    scan_latency: list[float] = field(default_factory=list)
    scan_stamps_ns: list[int] = field(default_factory=list)
    map_bytes: list[int] = field(default_factory=list)  # the map's used bytes after each scan
    skipped: list[dict] = field(default_factory=list)  # scans the source could not read (--bad-scans skip)
    scans_unposed: int = 0  # scans before the first transform or after the last, left out as tf does

    def per_scan(self) -> dict:
        """The series `build --plot` draws (not in to_dict: a long run has many scans)."""
        return {"latency_ms": [round(s * 1e3, 4) for s in self.scan_latency], "stamps_ns": self.scan_stamps_ns,
                "map_bytes": self.map_bytes}

    def to_dict(self) -> dict:
        lat = np.array(self.scan_latency) * 1e3 if self.scan_latency else np.zeros(1)
        return {
            "scans": self.scans,
            "scans_skipped": len(self.skipped),
            "skipped_scans": self.skipped[:100],  # index and reason of the first 100
            "points": self.points,
            "points_dropped": self.points_dropped,
            "points_dropped_nonfinite": self.points_dropped_nonfinite,
            "points_dropped_at_origin": self.points_dropped_at_origin,
            "points_dropped_ego_box": self.points_dropped_ego_box,
            "points_dropped_min_range": self.points_dropped_min_range,
            "no_returns": self.no_returns,
            "scans_unposed": self.scans_unposed,
            "raw_bytes": self.raw_bytes,
            "voxel_updates": self.voxel_updates,
            "ray_steps": self.ray_steps,
            "rays": self.rays,
            "merged_rays": self.merged_rays,
            "merge_ratio": round(self.merged_rays / max(self.rays, 1), 6),
            "timings_s": {
                "total": round(self.time_total, 6),
                "jit": round(self.time_jit, 6),
                "read": round(self.time_read, 6),
                "raycast": round(self.time_raycast, 6),
                "update": round(self.time_update, 6),
            },
            "scan_latency_ms": {
                "mean": round(float(lat.mean()), 4),
                "p50": round(float(np.percentile(lat, 50)), 4),
                "p95": round(float(np.percentile(lat, 95)), 4),
                "p99": round(float(np.percentile(lat, 99)), 4),
                "max": round(float(lat.max()), 4),
            },
        }


def read_ahead(backend: MapBackend) -> bool:
    """Whether build() reads scan i+1 on a helper thread while scan i updates the map. A
    backend that casts its rays itself on its threads (update_codes: the hash map) keeps them
    busy-waiting between scans (OpenMP's wait policy, for a prompt start of the next cast), so a
    reader would be one thread more than its cores: measured on quick_shack with two threads on
    two cores, it slowed the map update by more than reading ahead saved (docs/design/backends.md).
    It reads ahead when a core is free beyond the backend's threads."""
    return not hasattr(backend, "update_codes") or usable_cores() > getattr(backend, "threads", 1)


def build(stream: ScanStream, backend: MapBackend, progress: bool | None = None, on_scan=None) -> BuildReport:
    """Integrate every scan of `stream` into `backend`.

    Reading and ray casting of scan i+1 run on a helper thread while scan i updates the map (both
    release the GIL), so `raycast` + `update` can exceed `total`, which is wall-clock time without
    the JIT warm-up (reported apart). A scan's latency is its ray casting plus its map update.
    A backend that casts its rays itself on two threads (the hash map) reads ahead only when a
    third core is free (see read_ahead()).
    """
    from tqdm import tqdm

    from voxtool.parallel import one_blas_thread

    if progress is None:
        progress = sys.stderr.isatty()
    report = BuildReport()
    t_jit = time.perf_counter()
    backend.warm_up()
    t_start = time.perf_counter()
    report.time_jit = t_start - t_jit
    scans = iter(stream.scans)

    def read_and_prepare():
        t0 = time.perf_counter()
        scan = next(scans, None)
        t1 = time.perf_counter()
        return (scan, backend.prepare(scan) if scan is not None else None, t1 - t0)

    bar = tqdm(total=stream.count, unit="scan", disable=not progress, file=sys.stderr, desc="build")
    # The cyclic garbage collector would stop a scan now and then to re-scan every object of the
    # compiled kernels (perf: ~7 % of a hash-map build); a scan loop creates almost no cycles,
    # so it is paused until the loop ends.
    gc_was_enabled = gc.isenabled()
    gc.disable()
    ahead = ThreadPoolExecutor(max_workers=1, thread_name_prefix="voxtool-prepare") if read_ahead(backend) else None
    blas = one_blas_thread()
    try:
        future = ahead.submit(read_and_prepare) if ahead else None
        while True:
            scan, prepared, read_s = future.result() if future else read_and_prepare()
            if scan is None:
                break
            if hasattr(backend, "update_codes"):
                # a backend that casts rays against its own map (the hash map) does so now, on
                # both cores, before the next scan's reading takes one of them
                backend.update_codes(prepared)
            if ahead:
                future = ahead.submit(read_and_prepare)
            timing = backend.apply(prepared)
            if on_scan is not None:
                on_scan(scan, backend)
            report.time_read += read_s
            report.scan_latency.append(timing.raycast + timing.update)
            report.scan_stamps_ns.append(scan.stamp_ns)
            report.map_bytes.append(backend.used_bytes())
            report.time_raycast += timing.raycast
            report.time_update += timing.update
            report.voxel_updates += timing.voxel_updates
            report.ray_steps += timing.ray_steps
            report.rays += timing.rays
            report.merged_rays += timing.merged_rays
            report.scans += 1
            report.points += scan.points_read
            for key, n in scan.drop_counts().items():
                setattr(report, key, getattr(report, key) + n)
            report.no_returns += scan.no_returns
            report.raw_bytes += scan.raw_bytes
            if report.first_stamp_ns is None:
                report.first_stamp_ns = scan.stamp_ns
            report.last_stamp_ns = scan.stamp_ns
            bar.update(1)
    finally:
        if gc_was_enabled:
            gc.enable()
        if ahead:
            ahead.shutdown(wait=True, cancel_futures=True)
        blas.restore_original_limits()
        bar.close()
    report.time_total = time.perf_counter() - t_start
    report.skipped = stream.bad.skipped
    report.scans_unposed = stream.bad.unposed
    return report
