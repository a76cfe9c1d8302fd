"""`voxtool diff` of two maps against building one, whole commands, in one run (the issue's
target: a diff of two kaist03 maps takes less time than building one). Prints a table, writes
bench-results/diff.json.

    python benchmarks/bench_diff.py [--data ../shared/data] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

DATASETS = [("kaist03", "kaist03_21scans.mcap", 0.1, 18), ("quick_shack", "quick_shack.mcap", 0.1, None)]


def timed(*args) -> float:
    """Seconds of one whole voxtool command in a child process."""
    t0 = time.perf_counter()
    subprocess.run(["voxtool", *map(str, args)], check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("bench-results/diff.json"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, bag, res, fewer in DATASETS:
            src = args.data / name / bag
            if not src.exists():
                continue
            a, b = Path(tmp) / f"{name}-a.vxm", Path(tmp) / f"{name}-b.vxm"
            stop = ["--stop", fewer] if fewer else ["--every", 2]
            timed("build", src, "--resolution", res, "-o", a, *stop)
            build_s, diff_s = [], []
            for _ in range(args.repeat):  # alternating, best of each
                build_s.append(timed("build", src, "--resolution", res, "-o", b))
                diff_s.append(timed("diff", a, b, "--json"))
            report = json.loads(subprocess.run(["voxtool", "diff", a, b, "--json"], check=True, capture_output=True,
                                               text=True).stdout)
            row = {"dataset": name, "resolution": res, "map_a": " ".join(map(str, stop)), "build_s": round(min(build_s), 2),
                   "diff_s": round(min(diff_s), 2), "changed_voxels": report["changed_voxels"],
                   "common_known_voxels": report["common_known_voxels"]}
            rows.append(row)
    print(f"{'dataset':<12} {'map A':<10} {'build s':>8} {'diff s':>7} {'changed':>11} {'known in both':>14}")
    for r in rows:
        print(f"{r['dataset']:<12} {r['map_a']:<10} {r['build_s']:>8.2f} {r['diff_s']:>7.2f} {r['changed_voxels']:>11,} "
              f"{r['common_known_voxels']:>14,}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
