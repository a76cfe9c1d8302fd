"""The octree's map update alone: a dataset's scans cast once, then applied to a fresh map again
and again, timed apart from the ray casting.

    python benchmarks/bench_update.py [--data ../shared/data] [--datasets kaist03 quick_shack norlab]
                                      [--threads 1] [--repeat 5] [--out bench-results/update.json]

Per dataset at its reference resolution: the scans' merged brick masks (maps.octree.cast_scan)
are kept in memory; each repeat applies all of them to an empty ShardedOctree straight from the
masks (`apply_masks`, what `build` does) and, from the same scans' per-voxel lists, with
`apply(..., ADD)` (what OctoCache and Dask partitions use). Reports the best time and ns a voxel
update, and checks that both give the same map. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from report import write_report  # noqa: E402

REFERENCE_RESOLUTION = {"kaist03": 0.2, "quick_shack": 0.1, "norlab": 0.2}


def cast_all(source: Path, resolution: float) -> list:
    from voxtool.config import MapParams
    from voxtool.maps.octree import cast_scan
    from voxtool.sources import SourceOptions, open_source

    params = MapParams(resolution=resolution)
    return [b for b in (cast_scan(scan, params, 1)[0] for scan in open_source(source, SourceOptions()).scans)
            if b is not None]


def replay(scans: list, threads: int, lists: bool):
    from voxtool.config import SensorModel
    from voxtool.kernels import octree as K
    from voxtool.maps.shards import ShardedOctree

    s = SensorModel()  # OctoMap's defaults
    clamped = {"hit": s.hit_log, "miss": s.miss_log, "cmin": s.clamp_min_log, "cmax": s.clamp_max_log}
    tree = ShardedOctree(threads=threads)
    updates = [b.updates(1)[0] for b in scans] if lists else None
    t0 = time.perf_counter()
    n = 0
    for i, bricks in enumerate(scans):
        if lists:
            tree.apply(updates[i], K.ADD, **clamped)
            n += updates[i].shape[0]
        else:
            n += tree.apply_masks(bricks, **clamped)
    return time.perf_counter() - t0, n, tree


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--datasets", nargs="*", default=list(REFERENCE_RESOLUTION))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default="bench-results/update.json")
    args = ap.parse_args()
    rows = []
    for name in args.datasets:
        resolution = REFERENCE_RESOLUTION[name]
        scans = cast_all(Path(args.data) / name / "pcd", resolution)
        best = {}
        maps = {}
        for _ in range(args.repeat + 1):  # the first of each warms the kernels and the allocator
            for lists in (False, True):
                t, n, tree = replay(scans, args.threads, lists)
                key = "lists" if lists else "masks"
                best[key] = min(best.get(key, float("inf")), t)
                maps[key] = tree
        a, b = maps["masks"].leaves(), maps["lists"].leaves()
        same = all(np.array_equal(getattr(a, f), getattr(b, f)) for f in ("codes", "depths", "values"))
        rows.append({"dataset": name, "resolution": resolution, "scans": len(scans), "voxel_updates": n,
                     "threads": args.threads, "masks_s": round(best["masks"], 4),
                     "masks_ns_per_update": round(best["masks"] / n * 1e9, 2), "lists_s": round(best["lists"], 4),
                     "lists_ns_per_update": round(best["lists"] / n * 1e9, 2), "same_map": same})
        if not same:
            raise SystemExit(f"{name}: apply_masks and apply(ADD) gave different maps")
    out = write_report(rows, ["dataset", "resolution", "scans", "voxel_updates", "threads", "masks_s",
                              "masks_ns_per_update", "lists_s", "lists_ns_per_update", "same_map"], args.out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
