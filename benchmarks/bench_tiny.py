"""TinyOctoMap vs the octree backend vs OctoMap C++ on the real streams, and ray merging.

    python benchmarks/bench_tiny.py [--data ../shared/data] [--octomap]

Per dataset: occupied-voxel agreement of `tiny` with `octree` (same known voxels; level
quantization flips some), bytes per node and memory of the three (OctoMap's own memoryUsage(),
with --octomap), and ray merging: merge ratio, time with and without, identical maps.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from report import write_report

DATASETS = [("quick_shack", 0.1, 51.2), ("norlab", 0.2, 819.2), ("kaist03", 0.2, 819.2)]


def occupied(leaves):
    from voxtool.keys import expand_leaves

    occ = leaves.values > 0
    return expand_leaves(leaves.codes[occ], leaves.depths[occ]), expand_leaves(leaves.codes, leaves.depths)


def build(source, backend, params, **kw):
    from voxtool.config import SensorModel
    from voxtool.maps import make_backend
    from voxtool.pipeline import build as run
    from voxtool.sources import SourceOptions, open_source

    m = make_backend(backend, params, SensorModel(), **kw)
    report = run(open_source(source, SourceOptions()), m, progress=False)
    return m, report


def main() -> None:
    from voxtool.config import MapParams

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--octomap", action="store_true", help="also build with OctoMap C++ for memoryUsage()")
    ap.add_argument("--out", default="bench-results/tiny.json")
    args = ap.parse_args()
    rows = []
    for name, res, size in DATASETS:
        src = Path(args.data) / name / "pcd"
        if not src.is_dir():
            continue
        octree, rep_o = build(src, "octree", MapParams(res))
        tiny, rep_t = build(src, "tiny", MapParams(res), pool_blocks=1 << 23, map_size=size)
        o_occ, o_all = occupied(octree.leaves())
        t_occ, t_all = occupied(tiny.leaves())
        leaves_o, inner_o = octree.node_counts()
        leaves_t, inner_t = tiny.node_counts()
        ps = tiny.pool_stats()
        row = {"dataset": name, "resolution": res, "octree_occupied": int(o_occ.size), "tiny_occupied": int(t_occ.size),
               "only_octree": int(np.setdiff1d(o_occ, t_occ).size), "only_tiny": int(np.setdiff1d(t_occ, o_occ).size),
               "known_voxels_equal": bool(np.array_equal(o_all, t_all)),
               "octree_nodes": leaves_o + inner_o, "tiny_nodes": leaves_t + inner_t,
               "tiny_slots": 1 + 8 * (ps["pool_blocks_used"] - 1) + 8 * ps["leaf_blocks_used"],
               "tiny_blocks": ps["pool_blocks_used"], "tiny_finest_blocks": ps["leaf_blocks_used"],
               "octree_bytes_used": octree.used_bytes(), "tiny_bytes_used": tiny.used_bytes(),
               "tiny_bytes_per_node": ps["bytes_per_node"],
               "octree_bytes_per_node": round(octree.used_bytes() / max(leaves_o + inner_o, 1), 2),
               "tiny_dropped": ps["dropped_updates"], "tiny_outside": ps["outside_map_updates"],
               "octree_s": rep_o.time_total, "tiny_s": rep_t.time_total}
        if args.octomap:
            import pyoctomap

            from voxtool.sources import SourceOptions, open_source

            tree = pyoctomap.OcTree(res)
            for scan in open_source(src, SourceOptions()).scans:
                tree.insertPointCloud(scan.points.astype(np.float64), scan.origin.astype(np.float64))
            row.update(octomap_nodes=int(tree.size()), octomap_memory_usage=int(tree.memoryUsage()),
                       octomap_bytes_per_node=round(tree.memoryUsage() / tree.size(), 2),
                       tiny_below_octomap_pct=round(100 * (1 - tiny.used_bytes() / tree.memoryUsage()), 2))
        merged, rep_m = build(src, "octree", MapParams(res, merge_rays=True))
        a, b = octree.leaves(), merged.leaves()
        row.update(merge_ratio=round(rep_m.merged_rays / max(rep_m.rays, 1), 4), merged_rays=rep_m.merged_rays,
                   rays=rep_m.rays, merged_s=rep_m.time_total, merged_raycast_s=rep_m.time_raycast,
                   unmerged_raycast_s=rep_o.time_raycast,
                   merged_map_identical=bool(np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)))
        rows.append(row)
        print(json.dumps(row))
    for r in rows:  # the table's figures in MB, and "-" where OctoMap did not run
        r.update(tiny_mb=round(r["tiny_bytes_used"] / 1e6, 2), octree_mb=round(r["octree_bytes_used"] / 1e6, 2),
                 octomap_mb=round(r["octomap_memory_usage"] / 1e6, 2) if "octomap_memory_usage" in r else "-")
        r.setdefault("tiny_below_octomap_pct", "-")
    write_report(rows, ["dataset", "resolution", "tiny_mb", "octree_mb", "octomap_mb", "tiny_below_octomap_pct",
                        "tiny_blocks", "tiny_finest_blocks"], args.out)


if __name__ == "__main__":
    main()
