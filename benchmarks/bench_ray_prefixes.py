"""How much of a scan's ray casting repeats a neighbour's voxels in the same order: the most that
casting shared first voxels once (near the sensor, where most steps repeat) could save, for any
exact method.

    python benchmarks/bench_ray_prefixes.py [--data ../shared/data] [--dataset kaist03]
                                            [--scan 10] [--rays 3000] [--whole-scan]
                                            [--out bench-results/ray_prefixes.json]

For runs of consecutive rays (the sensor's own point order, three places in the scan) at two
resolutions, each ray's voxel sequence as OctoMap casts it (tests/reference.py's DDA, written
apart from voxtool's kernels): the share of all steps that lie in the longest common prefix with
the ray before, and with the best of the 128 rays before; the distinct voxels per step (what
OctoMap's key set keeps); and the steps into a 4x4x4 block whose voxels earlier steps had all
marked (what skipping saturated blocks could save). --whole-scan adds the last two over every
ray of the scan. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from report import write_report  # noqa: E402

from tests.reference import ray_keys  # noqa: E402


def common_prefix(a: list, b: list) -> int:
    n = min(len(a), len(b))
    k = 0
    while k < n and a[k] == b[k]:
        k += 1
    return k


def shares(points, origin, resolution: float, start: int, rays: int, window: int = 128) -> dict:
    paths = [ray_keys(origin, points[i], resolution) for i in range(start, start + rays)]
    counts = repeats(paths)
    before = sum(common_prefix(paths[i], paths[i - 1]) for i in range(1, len(paths)))
    best = sum(max(common_prefix(paths[i], paths[j]) for j in range(max(0, i - window), i))
               for i in range(1, len(paths)))
    return {"start": start, "rays": len(paths), "resolution": resolution, "steps": counts["steps"],
            "shared_with_previous": round(before / counts["steps"], 4),
            f"shared_with_best_of_{window}": round(best / counts["steps"], 4), **counts}


def whole_scan(points, origin, resolution: float, window: int = 128) -> dict:
    """Every ray of the scan: its repeated steps, and those in a block already full (the shared
    prefixes are for runs of rays only: comparing every pair would take hours)."""
    paths = [ray_keys(origin, points[i], resolution) for i in range(points.shape[0])]
    counts = repeats(paths)
    return {"start": 0, "rays": len(paths), "resolution": resolution, "steps": counts["steps"],
            "shared_with_previous": None, f"shared_with_best_of_{window}": None, **counts}


def repeats(paths: list) -> dict:
    """The rays' steps; distinct voxels per step (what OctoMap's key set keeps); and the share of
    steps into a 4x4x4 block (one 64-bit word of a brick's mask) whose 64 voxels earlier steps
    had all marked already: what a ray could skip without stepping, if skipping cost nothing."""
    seen, per_block, full, steps = set(), {}, 0, 0
    for path in paths:
        steps += len(path)
        for k in path:
            block = (k[0] >> 2, k[1] >> 2, k[2] >> 2)
            filled = per_block.get(block, 0)
            full += filled == 64
            if k not in seen:
                seen.add(k)
                per_block[block] = filled + 1
    return {"steps": steps, "distinct_voxels_per_step": round(len(seen) / steps, 4),
            "in_full_block": round(full / steps, 4)}


def main() -> None:
    from voxtool.sources import SourceOptions, open_source

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--dataset", default="kaist03")
    ap.add_argument("--scan", type=int, default=10)
    ap.add_argument("--rays", type=int, default=3000)
    ap.add_argument("--whole-scan", action="store_true",
                    help="also every ray of the scan (pure Python: about 10 s a resolution)")
    ap.add_argument("--out", default="bench-results/ray_prefixes.json")
    args = ap.parse_args()
    source = Path(args.data) / args.dataset / "pcd"
    if not source.is_dir():
        sys.exit(f"{source}: not found (--data names the shared datasets' folder)")
    scan = next(s for i, s in enumerate(open_source(source, SourceOptions()).scans) if i == args.scan)
    n = scan.points.shape[0]
    rows = []
    for resolution in (0.2, 0.1):
        for start in (0, n // 3, 2 * n // 3):
            start = min(start, max(n - args.rays, 0))
            rows.append(shares(scan.points, scan.origin, resolution, start, min(args.rays, n)))
            print(json.dumps(rows[-1]), file=sys.stderr)
        if args.whole_scan:
            rows.append(whole_scan(scan.points, scan.origin, resolution))
            print(json.dumps(rows[-1]), file=sys.stderr)
    print(f"wrote {write_report(rows, list(rows[0]), args.out, dataset=args.dataset, scan=args.scan)}")


if __name__ == "__main__":
    main()
