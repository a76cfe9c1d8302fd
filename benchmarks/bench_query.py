"""Point queries: `VoxelMap.query` (vectorized) against OctoMap's own `search` (the real OctoMap
1.10 library through pyoctomap, one call per point), on maps built from the shared datasets.
Every voxtool answer is checked against OctoMap's on the points OctoMap answers. Prints a table,
writes bench-results/query.json.

    python benchmarks/bench_query.py [--data ../shared/data] [--points 1000000] [--octomap-points 20000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from report import write_report

DATASETS = [("kaist03", 0.2), ("quick_shack", 0.1), ("norlab", 0.2)]


def octomap_states(tree, pts: np.ndarray) -> np.ndarray:
    """0 unknown, 1 free, 2 occupied, as OctoMap answers them (its API has no batch search)."""
    out = np.zeros(len(pts), np.uint8)
    for i, p in enumerate(pts):
        node = tree.search(p)
        if node is not None:
            out[i] = 2 if tree.isNodeOccupied(node) else 1
    return out


def main() -> None:
    import voxtool

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--octomap-points", type=int, default=20_000)
    ap.add_argument("--out", default="bench-results/query.json")
    args = ap.parse_args()
    try:
        import pyoctomap
    except ImportError:
        pyoctomap = None
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, res in DATASETS:
            src = Path(args.data) / name / "pcd"
            if not src.is_dir():
                continue
            out = Path(tmp) / f"{name}.vxm"
            voxtool.build(src, out, resolution=res, progress=False)
            m = voxtool.load(out)
            lo, hi = (np.array(m.stats()["occupied_bbox"][k]) for k in ("min", "max"))
            pts = np.random.default_rng(0).uniform(lo - 5, hi + 5, size=(args.points, 3))
            t0 = time.perf_counter()
            states = m.query(pts)["state"]
            ours_s = time.perf_counter() - t0
            row = {"dataset": name, "resolution": res, "points": args.points, "voxtool_s": round(ours_s, 4),
                   "voxtool_points_per_s": round(args.points / ours_s),
                   **{k: int(v) for k, v in zip(("unknown", "free", "occupied"), np.bincount(states, minlength=3))}}
            if pyoctomap is not None:
                m.export(Path(tmp) / f"{name}.bt")
                tree = pyoctomap.OcTree(res)
                assert tree.readBinary(str(Path(tmp) / f"{name}.bt"))
                few = pts[: args.octomap_points]
                t0 = time.perf_counter()
                theirs = octomap_states(tree, few)
                octo_s = time.perf_counter() - t0
                row.update(octomap_points=len(few), octomap_s=round(octo_s, 4),
                           octomap_points_per_s=round(len(few) / octo_s),
                           differing_answers=int((theirs != states[: len(few)]).sum()))
            rows.append(row)
    for r in rows:
        octo = r.get("octomap_points_per_s")
        r["speed_up"] = round(r["voxtool_points_per_s"] / octo, 1) if octo else "-"
        r.setdefault("octomap_points_per_s", "-")
        r.setdefault("differing_answers", "-")
    write_report(rows, ["dataset", "points", "voxtool_s", "voxtool_points_per_s", "octomap_points_per_s", "speed_up",
                        "differing_answers"], args.out)


if __name__ == "__main__":
    main()
