"""`voxtool cache-bench`: the same scans through the plain octree and through OctoCache settings.

Every configuration runs in its own process (so peak memory is that configuration's), scans one
after another without read-ahead (so the time decomposition adds up to the total), and leaves its
final map in a file the parent compares voxel for voxel with the plain octree's.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from voxtool import errors
from voxtool.errors import VoxtoolError


def run_config(source: str, options: dict, params: dict, sensor: dict, backend: str, cfg: dict, leaves_out: str) -> dict:
    """Build once with one configuration; returns timings and counters (runs in a worker)."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps import make_backend
    from voxtool.sources import SourceOptions, open_source

    m = make_backend(backend, MapParams(**params), SensorModel(**sensor), **cfg)
    m.warm_up()
    scans = list(open_source(source, SourceOptions(**options)).scans)  # read up front: not timed
    raycast = update = 0.0
    t_start = time.perf_counter()
    for scan in scans:
        prepared = m.prepare(scan)
        raycast += prepared.seconds
        timing = m.apply(prepared)
        update += timing.update
    t_flush = time.perf_counter()
    if backend == "octocache":
        before_flush = (m.counters.octree_update, m.counters.wait)
        m.flush()
    t_end = time.perf_counter()
    total = t_end - t_start
    lv = m.leaves()
    np.savez(leaves_out, codes=lv.codes, depths=lv.depths, values=lv.values)
    status = Path("/proc/self/status").read_text() if Path("/proc/self/status").exists() else ""
    hwm = [ln.split()[1] for ln in status.splitlines() if ln.startswith("VmHWM")]
    out = {"backend": backend, **cfg, "scans": len(scans), "total_s": total, "raycast_s": raycast,
           "peak_rss_bytes": int(hwm[0]) * 1024 if hwm else None, "memory_bytes": m.memory_bytes()}
    if backend == "octree":
        out.update(octree_update_s=update, parts_s=raycast + update)
        out["voxel_updates"] = out["written_to_octree"] = None
    else:
        c = m.counters
        flush = t_end - t_flush
        out.update(buckets=m.buckets, insert_s=c.insert, evict_s=c.evict, octree_update_s=c.octree_update,
                   wait_s=c.wait, flush_s=flush, cache_bytes=m.cache_bytes(),
                   hit_ratio=sum(c.hits) / max(1, sum(c.updates)),
                   hit_ratio_per_scan=[round(h / max(1, u), 4) for h, u in zip(c.hits, c.updates)],
                   voxel_updates=sum(c.updates), written_to_octree=c.written_to_octree)
        # thread 1's time: the octree update counts only where thread 1 did it or waited for it;
        # the final flush (drain + ordering + write-back) is all on thread 1
        t1_update = before_flush[1] if m.overlap else before_flush[0]
        out["thread1_update_s"] = t1_update
        out["parts_s"] = raycast + c.insert + c.evict + t1_update + flush
        if m.overlap:
            out["overlapped"] = 1.0 - c.wait / max(c.octree_update - flush, 1e-9)
        m.close()
    return out


def _spawn(source, options, params, sensor, backend, cfg, workdir: Path, tag: str) -> dict:
    leaves = workdir / f"{tag}.npz"
    spec = json.dumps({"source": str(source), "options": options, "params": params, "sensor": sensor,
                       "backend": backend, "cfg": cfg, "leaves_out": str(leaves)})
    proc = subprocess.run([sys.executable, "-m", "voxtool.cachebench", spec], capture_output=True, text=True)
    if proc.returncode != 0:
        lines = proc.stderr.strip().splitlines()
        try:  # a voxtool error in the worker is raised here as itself (its class gives the exit code)
            failure = json.loads(lines[-1])
            raise getattr(errors, failure["error"])(failure["message"])
        except (IndexError, ValueError, KeyError, TypeError, AttributeError):
            pass
        raise VoxtoolError(f"cache-bench worker for {tag} failed: {lines[-1] if lines else proc.returncode}")
    result = json.loads(proc.stdout)
    result["leaves_file"] = str(leaves)
    return result


def cache_bench(source, options: dict, params: dict, sensor: dict, taus: list[int], buckets: list[int | None],
                orders: list[str], overlaps: list[int], threads: int = 0, progress=None) -> dict:
    """Plain octree first, then one OctoCache row per (overlap, tau, buckets, order); every row
    on `threads` threads (0: the usable cores)."""
    with tempfile.TemporaryDirectory(prefix="voxtool-cache-bench-") as tmp:
        work = Path(tmp)
        configs = [("octree", {"threads": threads})] + [
            ("octocache", {"overlap": ov, "tau": tau, "buckets": b, "order": order, "threads": threads})
            for ov in overlaps for tau in taus for b in buckets for order in orders
        ]
        rows = []
        for k, (backend, cfg) in enumerate(configs):
            if progress:
                progress(k, len(configs), backend, cfg)
            rows.append(_spawn(source, options, params, sensor, backend, cfg, work, f"run{k}"))
        base = np.load(rows[0]["leaves_file"])
        for row in rows:
            lv = np.load(row.pop("leaves_file"))
            row["identical_to_octree"] = bool(all(np.array_equal(lv[f], base[f]) for f in ("codes", "depths", "values")))
            row["speedup"] = rows[0]["total_s"] / row["total_s"]
            row["decomposition_error"] = abs(row["parts_s"] - row["total_s"]) / row["total_s"]
    return {"source": str(source), "resolution": params["resolution"], "rows": rows}


if __name__ == "__main__":
    spec = json.loads(sys.argv[1])
    try:
        print(json.dumps(run_config(spec["source"], spec["options"], spec["params"], spec["sensor"], spec["backend"],
                                    spec["cfg"], spec["leaves_out"])))
    except VoxtoolError as err:  # for _spawn to raise as itself
        print(json.dumps({"error": type(err).__name__, "message": str(err)}), file=sys.stderr)
        sys.exit(1)
