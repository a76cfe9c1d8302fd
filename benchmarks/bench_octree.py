"""voxtool's octree backend vs OctoMap C++ (pyoctomap) on the same scans, in one run.

For each dataset: build with voxtool and with OctoMap 1.10 (each in its own process so peak
memory is that process's max RSS), print the speed ratio, peak memory of both and the voxel
agreement (occupied and free voxel sets at the finest resolution). Writes a JSON file too.

    python benchmarks/bench_octree.py [--data ../shared/data] [--only kaist03] [--out bench-results/octree.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

DATASETS = [("kaist03", 0.2), ("quick_shack", 0.1), ("norlab", 0.2)]


def worker(engine: str, source: str, res: float, out: str) -> None:
    from voxtool.sources import SourceOptions, open_source

    result: dict = {}
    if engine == "voxtool":
        from voxtool.config import MapParams, SensorModel
        from voxtool.io.bt import write_bt
        from voxtool.maps import make_backend
        from voxtool.pipeline import build

        m = make_backend("octree", MapParams(resolution=res), SensorModel())
        report = build(open_source(source, SourceOptions()), m, progress=False)
        # reading overlaps ray casting on a helper thread, so wall time includes it; it is small
        result["peak_rss_bytes"] = _vm_hwm()  # before the .bt export, which builds a second tree
        result.update(insert_s=report.time_total, read_s=report.time_read, jit_s=report.time_jit,
                      raycast_s=report.time_raycast, update_s=report.time_update, ray_steps=report.ray_steps,
                      voxel_updates=report.voxel_updates, memory_bytes=m.memory_bytes())
        write_bt(out, m.leaves(), res, m.sensor.threshold_log)
    else:
        import pyoctomap

        tree = pyoctomap.OcTree(res)
        insert = read = 0.0
        t_read = time.perf_counter()
        for scan in open_source(source, SourceOptions()).scans:
            pts = scan.points.astype(np.float64)
            origin = scan.origin.astype(np.float64)
            t0 = time.perf_counter()
            read += t0 - t_read
            tree.insertPointCloud(pts, origin)
            t_read = time.perf_counter()
            insert += t_read - t0
        result["peak_rss_bytes"] = _vm_hwm()
        result.update(insert_s=insert, read_s=read, memory_bytes=int(tree.memoryUsage()))
        tree.writeBinary(out)
    Path(out + ".json").write_text(json.dumps(result))


def _vm_hwm() -> int:
    """Peak resident memory of this process since exec (VmHWM); ru_maxrss would include the
    parent's footprint inherited at fork."""
    status = Path("/proc/self/status").read_text()
    return int(next(ln.split()[1] for ln in status.splitlines() if ln.startswith("VmHWM"))) * 1024


def run_worker(engine: str, source: Path, res: float, out: Path) -> dict:
    cmd = [sys.executable, __file__, "--worker", engine, str(source), str(res), str(out)]
    if subprocess.run(cmd).returncode != 0:
        raise SystemExit(f"{engine} worker failed on {source}")
    return json.loads(Path(str(out) + ".json").read_text())


def voxel_sets(bt: Path):
    from voxtool.io.bt import read_bt
    from voxtool.keys import expand_leaves

    t = read_bt(bt)
    return (expand_leaves(t.codes[t.occupied], t.depths[t.occupied]),
            expand_leaves(t.codes[~t.occupied], t.depths[~t.occupied]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--only", nargs="*", help="dataset names to run")
    ap.add_argument("--out", default="bench-results/octree.json")
    ap.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker[0], args.worker[1], float(args.worker[2]), args.worker[3])
        return
    out_dir = Path(args.out).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, res in DATASETS:
        if args.only and name not in args.only:
            continue
        source = Path(args.data) / name / "pcd"
        if not source.is_dir():
            print(f"skip {name}: {source} absent", file=sys.stderr)
            continue
        vt = run_worker("voxtool", source, res, out_dir / f"{name}_voxtool.bt")
        om = run_worker("octomap", source, res, out_dir / f"{name}_octomap.bt")
        a_occ, a_free = voxel_sets(out_dir / f"{name}_voxtool.bt")
        b_occ, b_free = voxel_sets(out_dir / f"{name}_octomap.bt")
        row = {
            "dataset": name, "resolution": res,
            "voxtool_insert_s": round(vt["insert_s"], 3), "voxtool_jit_s": round(vt["jit_s"], 3),
            "voxtool_raycast_s": round(vt["raycast_s"], 3), "voxtool_update_s": round(vt["update_s"], 3),
            "octomap_insert_s": round(om["insert_s"], 3),
            "speedup": round(om["insert_s"] / vt["insert_s"], 2),
            "voxtool_peak_rss_mib": round(vt["peak_rss_bytes"] / 2**20, 1),
            "octomap_peak_rss_mib": round(om["peak_rss_bytes"] / 2**20, 1),
            "voxtool_map_mib": round(vt["memory_bytes"] / 2**20, 1),
            "octomap_map_mib": round(om["memory_bytes"] / 2**20, 1),
            "ray_steps_per_s": round(vt["ray_steps"] / max(vt["raycast_s"], 1e-9)),
            "occupied_voxels": int(a_occ.size), "free_voxels": int(a_free.size),
            "occupied_differ": int(np.setxor1d(a_occ, b_occ).size),
            "free_differ": int(np.setxor1d(a_free, b_free).size),
        }
        rows.append(row)
    cols = ["dataset", "resolution", "octomap_insert_s", "voxtool_insert_s", "speedup", "voxtool_raycast_s",
            "voxtool_update_s", "voxtool_jit_s", "octomap_peak_rss_mib", "voxtool_peak_rss_mib",
            "occupied_voxels", "occupied_differ", "free_voxels", "free_differ"]
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r[c]) for c in cols))
    Path(args.out).write_text(json.dumps({"machine": os.uname().nodename, "cpus": os.cpu_count(), "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
