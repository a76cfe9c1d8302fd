"""What Dask costs and gives: one map (single process vs --workers N) and a fleet of the shared
datasets (one after the other vs --workers N), whole commands timed as a user runs them, with
peak memory of the command and of its worker processes. Prints a table, writes
bench-results/dask.json.

    python benchmarks/bench_dask.py [--workers 1 2 4 8] [--sharded] [--large] [--data ../shared/data]

worker/first: a worker's peak RSS against the single process's (the memory target: 1/4 at 8
workers). Worker counts above the core count measure memory, not speed.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

DATASETS = [("kaist03", "kaist03/pcd", 0.2), ("quick_shack", "quick_shack/pcd", 0.1), ("norlab", "norlab/pcd", 0.2)]
# one map: a folder of scans, and a ROS 2 bag (cast tasks start reading at their batch's chunk)
ONE_MAP = [DATASETS[0], ("quick_shack.mcap", "quick_shack/quick_shack.mcap", 0.1)]


def run(cmd: list[str]) -> dict:
    """Wall time of a command, its peak RSS and the largest peak RSS of any child (a Dask worker)."""
    t0 = time.perf_counter()
    proc = psutil.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peaks: dict[int, int] = {}
    done = threading.Event()

    def watch():
        while not done.is_set():
            try:
                for p in [proc, *proc.children(recursive=True)]:
                    peaks[p.pid] = max(peaks.get(p.pid, 0), p.memory_info().rss)
            except psutil.Error:
                pass
            time.sleep(0.02)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    out, err = proc.communicate()
    done.set()
    watcher.join()
    wall = time.perf_counter() - t0
    if proc.returncode not in (0,):
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-400:]}")
    children = [v for k, v in peaks.items() if k != proc.pid]
    return {"wall_s": round(wall, 3), "peak_rss_mb": round(peaks.get(proc.pid, 0) / 2**20, 1),
            "worker_peak_rss_mb": round(max(children) / 2**20, 1) if children else None,
            "result": json.loads(out) if out.strip().startswith("{") else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=[2])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--sharded", action="store_true",
                    help="also each one-map run with --sharded (workers write their parts; nothing gathered)")
    ap.add_argument("--large", action="store_true",
                    help="also kaist03 at 0.1 m (a 0.9 GB map: where per-worker memory is mostly map, not runtime)")
    args = ap.parse_args()
    data = Path(args.data).resolve()  # the fleet links to its datasets from a temporary folder
    voxtool = [sys.executable, "-m", "voxtool.cli"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, rel, res in ONE_MAP + ([("kaist03 0.1 m", "kaist03/pcd", 0.1)] if args.large else []):
            base = run(voxtool + ["build", str(data / rel), "-o", f"{tmp}/single.vxm", "--resolution", str(res),
                                  "--json"])
            rows.append({"job": f"one map {name}", "mode": "single process", **base})
            for n in args.workers:
                r = run(voxtool + ["build", str(data / rel), "-o", f"{tmp}/w{n}.vxm", "--resolution", str(res),
                                   "--workers", str(n), "--json"])
                assert r["result"]["occupied_voxels"] == base["result"]["occupied_voxels"]
                rows.append({"job": f"one map {name}", "mode": f"--workers {n}", **r})
                if args.sharded:
                    r = run(voxtool + ["build", str(data / rel), "-o", f"{tmp}/w{n}-sharded", "--resolution", str(res),
                                       "--workers", str(n), "--sharded", "--json"])
                    assert r["result"]["occupied_voxels"] == base["result"]["occupied_voxels"]
                    rows.append({"job": f"one map {name}", "mode": f"--workers {n} --sharded", **r})
        runs = Path(tmp) / "runs"
        runs.mkdir()
        for name, rel, _ in DATASETS:
            (runs / name).symlink_to(data / rel)
        sources = [str(runs / name) for name, _, _ in DATASETS]
        fleet = run(voxtool + ["build", *sources, "-o", f"{tmp}/fleet/", "--resolution", "0.2", "--json"])
        rows.append({"job": "fleet of 3", "mode": "one after the other", **fleet})
        for n in args.workers:
            r = run(voxtool + ["build", *sources, "-o", f"{tmp}/fleet{n}/", "--resolution", "0.2", "--workers", str(n),
                               "--json"])
            rows.append({"job": "fleet of 3", "mode": f"--workers {n}", **r})
    print(f"{'job':<25} {'mode':<24} {'wall s':>8} {'vs first':>9} {'peak RSS MB':>12} {'worker peak MB':>15} "
          f"{'worker/first':>13}")
    for r in rows:
        first = next(x for x in rows if x["job"] == r["job"])
        r["worker_peak_vs_first"] = round(r["worker_peak_rss_mb"] / first["peak_rss_mb"], 3) if r["worker_peak_rss_mb"] else None
        print(f"{r['job']:<25} {r['mode']:<24} {r['wall_s']:>8.2f} {r['wall_s'] / first['wall_s']:>8.2f}x "
              f"{r['peak_rss_mb']:>12.0f} {r['worker_peak_rss_mb'] or 0:>15.0f} {r['worker_peak_vs_first'] or 0:>13.2f}")
    for r in rows:
        r.pop("result")
    out = Path("bench-results")
    out.mkdir(exist_ok=True)
    (out / "dask.json").write_text(json.dumps({"cores": psutil.cpu_count(), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
