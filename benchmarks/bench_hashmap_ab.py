"""Before against after for the hash map, scan by scan: another revision and this checkout each
build the same map (setup a of bench_hashmap.py unless told: 0.1 m, d_inf 0.2 m, n_lim 50,000,
inflation range 8 m), in two processes that take each scan in turn, which goes first
alternating. A difference between whole runs on this machine is mostly its drift (20-30 %
between minutes); paired per scan, both sides meet the same minute, and the median of the
paired differences is the change.

    python benchmarks/bench_hashmap_ab.py --base REV [--data ../shared/data] [--dataset quick_shack]
                                         [--rounds 3] [--out bench-results/hashmap_ab.json]

Each side is a `python -c STEPPER` process with PYTHONPATH on its own tree (the other
revision as a git worktree), reading the scans once, then integrating scan i when asked and
answering with that scan's t_tot / t_occ / t_inf / t_m. Every round starts both maps empty;
after each round the two maps must hold the same occupied voxels and inflation counts. Prints,
per part: each side's median and p95, the median of the paired differences (this checkout
minus the base: negative is faster) and how often this checkout was faster; writes JSON.

The medians themselves sit above bench_hashmap.py's (quick_shack row a: 3.4-3.5 against 2.8-3.0
ms in one sitting): each side finds its map evicted from the caches by the other side's scan,
and its second ray-casting thread asleep. Read the paired difference; the goals are
bench_hashmap.py's figures.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from report import write_report
from worktree import ROOT, check_imports, revision

PARTS = ("t_tot_ms", "t_occ_ms", "t_inf_ms", "t_m_ms")

# what each side runs (the APIs it calls have been stable since the hash map's count bricks)
STEPPER = """import hashlib, json, sys
from pathlib import Path
from voxtool.config import MapParams, SensorModel
from voxtool.maps.hashmap import HashVoxelMap
from voxtool.sources import SourceOptions, open_source
src, res, n_lim, d_inf, inf_range = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
scans = list(open_source(Path(src), SourceOptions()).scans)
m = None
print(len(scans), flush=True)
for line in sys.stdin:
    if line.strip() == "new":
        m = HashVoxelMap(MapParams(res), SensorModel(), n_lim=n_lim, d_inf=d_inf, inf_range=inf_range)
        m.warm_up()
        print("{}", flush=True)
    elif line.strip() == "digest":
        h = hashlib.sha256(m.occupied_codes().tobytes())
        h.update(json.dumps(sorted(m.inflation_counts().items())).encode())
        print(json.dumps({"digest": h.hexdigest(), "memory_bytes": m.memory_bytes()}), flush=True)
    else:
        m.integrate(scans[int(line)])
        print(json.dumps({k: m.scan_metrics[-1][k] for k in PARTS}), flush=True)
""".replace("PARTS", repr(PARTS))


class Side:
    """One revision's stepper process."""

    def __init__(self, tree: Path, args: list[str], cwd: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", STEPPER, *args], cwd=cwd, text=True, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(tree)})
        self.scans = int(self._line())

    def _line(self) -> str:
        line = self.proc.stdout.readline()
        if not line:
            sys.exit(f"a stepper ended early (exit code {self.proc.wait()})")
        return line

    def ask(self, what: str) -> dict:
        self.proc.stdin.write(what + "\n")
        self.proc.stdin.flush()
        return json.loads(self._line())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", required=True, help="the revision to compare this checkout with (a commit, tag, branch)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--dataset", default="quick_shack", help="a folder of --data with a pcd/ of scans")
    ap.add_argument("--resolution", type=float, default=0.1)
    ap.add_argument("--n-lim", type=int, default=50_000, help="-1: unlimited")
    ap.add_argument("--d-inf", type=float, default=0.2)
    ap.add_argument("--inf-range", type=float, default=8.0, help="-1: unlimited")
    ap.add_argument("--rounds", type=int, default=3, help="passes over the scans, each from an empty map")
    ap.add_argument("--out", default="bench-results/hashmap_ab.json")
    args = ap.parse_args()
    source = Path(args.data) / args.dataset / "pcd"
    if not source.is_dir():
        sys.exit(f"{source}: not found (--data names the shared datasets' folder)")
    setup = [str(source), str(args.resolution), str(args.n_lim), str(args.d_inf), str(args.inf_range)]
    with tempfile.TemporaryDirectory(prefix="voxtool-hashmap-ab-") as tmp, revision(args.base, Path(tmp)) as base:
        trees = {args.base: base, "this checkout": ROOT}
        for tree in trees.values():
            check_imports(tree, Path(tmp))
        sides = {name: Side(tree, setup, Path(tmp)) for name, tree in trees.items()}
        try:
            got = {name: {k: [] for k in PARTS} for name in sides}
            memory = {}
            for _ in range(args.rounds):
                for side in sides.values():
                    side.ask("new")
                for i in range(sides[args.base].scans):
                    order = list(sides) if i % 2 == 0 else list(sides)[::-1]
                    for name in order:
                        for k, v in sides[name].ask(str(i)).items():
                            got[name][k].append(v)
                digests = {name: side.ask("digest") for name, side in sides.items()}
                if len({d["digest"] for d in digests.values()}) != 1:
                    sys.exit("the two sides built different maps (occupied voxels or inflation counts)")
                memory = {name: d["memory_bytes"] for name, d in digests.items()}
        finally:
            for side in sides.values():
                side.close()
    rows = []
    for k in PARTS:
        a, b = (np.array(got[name][k]) for name in sides)
        rows.append({"part": k, "base_median": round(float(np.median(a)), 3), "median": round(float(np.median(b)), 3),
                     "base_p95": round(float(np.percentile(a, 95)), 3), "p95": round(float(np.percentile(b, 95)), 3),
                     "paired_median_diff": round(float(np.median(b - a)), 3),
                     "faster_in": f"{100 * np.mean(b < a):.0f}%"})
    print(f"{args.dataset} at {args.resolution} m, n_lim {args.n_lim}, d_inf {args.d_inf}, inf_range {args.inf_range}: "
          f"{len(got[args.base]['t_tot_ms'])} scans a side ({args.rounds} rounds); memory at the end "
          + ", ".join(f"{name} {m / 1e6:.1f} MB" for name, m in memory.items()))
    print(f"wrote {write_report(rows, list(rows[0]), args.out, base=args.base, rounds=args.rounds, setup=setup)}")


if __name__ == "__main__":
    main()
