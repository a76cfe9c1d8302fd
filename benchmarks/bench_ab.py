"""Before against after, in one run: whole `voxtool build` commands of another revision (a git
worktree of it) and of this checkout, alternated, on the shared datasets. The machine drifts
20-30 % between minutes, so only figures from the same run compare.

    python benchmarks/bench_ab.py --base REV [--data ../shared/data] [--runs 4]
                                  [--only kaist03:0.2 quick_shack:0.1 norlab:0.2]
                                  [--out bench-results/ab.json]

Each side runs as `python -m voxtool.cli build PCD_DIR --resolution R -o map.vxm --json` with
PYTHONPATH on its own tree (numba caches its kernels per tree: one warm-up run each first). Per
dataset and side: the best and median wall time, the largest peak RSS (os.wait4), the snapshot's
size, and the medians of build --json's start-up, statistics + snapshot, and scan loop. The two
snapshots of every round must hold the same arrays (the same bytes, unless the storage changed).
Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from report import write_report
from worktree import ROOT, check_imports, revision

SAME_ARRAYS = """import sys
import numpy as np
from voxtool.io.snapshot import read_snapshot
x, y = (read_snapshot(p).arrays for p in sys.argv[1:])
sys.exit(0 if x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x) else 1)
"""


def same_arrays(a: Path, b: Path) -> bool:
    """Whether two snapshots hold the same arrays, however they are stored (a codec change
    changes the bytes, not the map). In a process of its own: reading them here would raise this
    process's peak memory, which the builds it starts then report as theirs (ru_maxrss)."""
    return subprocess.run([sys.executable, "-c", SAME_ARRAYS, str(a), str(b)], cwd=a.parent).returncode == 0


def timed_build(tree: Path, source: Path, resolution: float, out: Path) -> dict:
    """One whole build command of `tree`: wall time, its own peak RSS (wait4), build --json's parts."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "voxtool.cli", "build", str(source), "--resolution", str(resolution),
                             "-o", str(out), "--json", "--no-progress"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, cwd=out.parent)  # not a checkout: `python -m` imports from there
    stdout = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"{tree}: build of {source} at {resolution} m failed")
    t = json.loads(stdout)["timings_s"]
    return {"wall_s": wall, "peak_rss_mib": usage.ru_maxrss / 1024, "startup_s": t["startup"],
            "stats_write_s": t["stats"] + t["write"], "loop_s": t["total"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the revision to compare this checkout with (a commit, tag, branch)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--runs", type=int, default=4, help="alternated runs per side and dataset")
    ap.add_argument("--only", nargs="*", default=["kaist03:0.2", "quick_shack:0.1", "norlab:0.2"],
                    help="DATASET:RESOLUTION pairs")
    ap.add_argument("--out", default="bench-results/ab.json")
    args = ap.parse_args()
    cases = []
    for item in args.only:
        name, _, res = item.partition(":")
        source = Path(args.data) / name / "pcd"
        if not source.is_dir():
            sys.exit(f"{source}: not found (--data names the shared datasets' folder)")
        cases.append((name, float(res or 0.2), source))
    with tempfile.TemporaryDirectory(prefix="voxtool-ab-") as tmp, revision(args.base, Path(tmp)) as base:
        sides = {args.base: base, "this checkout": ROOT}
        rows = []
        for tree in sides.values():
            check_imports(tree, Path(tmp))
        for name, res, source in cases:
            for tree in sides.values():  # numba compiles (or loads) each tree's kernels once
                timed_build(tree, source, res, Path(tmp) / "warm.vxm")
            runs: dict[str, list] = {side: [] for side in sides}
            for _ in range(args.runs):
                outs = []
                for side, tree in sides.items():
                    out = Path(tmp) / f"{len(outs)}.vxm"
                    runs[side].append({**timed_build(tree, source, res, out), "bytes": out.stat().st_size})
                    outs.append(out)
                if outs[0].read_bytes() != outs[1].read_bytes() and not same_arrays(*outs):
                    sys.exit(f"{name} at {res} m: the two sides wrote different maps")
            for side, got in runs.items():
                walls = [r["wall_s"] for r in got]
                rows.append({"dataset": name, "resolution": res, "side": side, "wall_best_s": round(min(walls), 3),
                             "wall_median_s": round(statistics.median(walls), 3),
                             "peak_rss_mib": round(max(r["peak_rss_mib"] for r in got), 1),
                             "snapshot_mib": round(got[-1]["bytes"] / 2**20, 2),
                             **{k: round(statistics.median(r[k] for r in got), 3)
                                for k in ("startup_s", "stats_write_s", "loop_s")}})
                print(json.dumps(rows[-1]), file=sys.stderr)
    print(f"wrote {write_report(rows, list(rows[0]), args.out, base=args.base, runs=args.runs)}")


if __name__ == "__main__":
    main()
