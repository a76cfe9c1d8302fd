"""Ground models against SemanticKITTI's labels: which points are ground, per scan.

    python benchmarks/bench_ground.py [--kitti .fetched/mini_kitti/sequences] [--resolution 0.2]

For each sequence (frames 0-9 of 00 and 05, scripts/fetch_samples.py kitti), every point is
ground or not by:
- the map's ground (voxtool.ground, what `export --above-ground` uses): the sequence built into a
  map, its ground found, a point ground when it lies within --band metres of the ground under it;
- Patchwork++ (PyPI `pypatchworkpp`, a benchmark extra), scan by scan in the sensor frame.
Truth: SemanticKITTI's road, parking, sidewalk, other-ground, lane-marking and terrain classes
(40, 44, 48, 49, 60, 72). Prints precision, recall and time per scan; writes bench-results/ground.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
OUT = Path("bench-results")


def scores(predicted: np.ndarray, truth: np.ndarray) -> dict:
    tp = int((predicted & truth).sum())
    precision = tp / max(int(predicted.sum()), 1)
    recall = tp / max(int(truth.sum()), 1)
    return {"precision": round(100 * precision, 2), "recall": round(100 * recall, 2),
            "f1": round(200 * precision * recall / max(precision + recall, 1e-12), 2)}


def map_ground(sequence: Path, resolution: float, band: float) -> tuple[np.ndarray, float]:
    """(ground flag per point of every scan, seconds) by the ground of the sequence's map."""
    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.ground import ground_of, occupied_keys
    from voxtool.io.mapfile import load_map
    from voxtool.keys import TREE_MAX_VAL
    from voxtool.sources import SourceOptions, open_source

    out = OUT / f"ground_{sequence.name}.vxm"
    OUT.mkdir(exist_ok=True)
    build_map(sequence, SourceOptions(), MapParams(resolution=resolution), SensorModel(), "octree", out, False)
    backend, _ = load_map(out)
    t0 = time.perf_counter()
    ground = ground_of(occupied_keys(backend.leaves(), backend.sensor.threshold_log), resolution)
    flags = []
    for scan in open_source(sequence, SourceOptions()).scans:
        keys = np.floor(scan.points.astype(np.float64) / resolution).astype(np.int64) + TREE_MAX_VAL
        height = ground.under(keys[:, 0], keys[:, 1])
        flags.append(np.abs(scan.points[:, 2] - height) <= band)  # NaN (no ground known) is never ground
    return np.concatenate(flags), time.perf_counter() - t0


def patchwork_ground(sequence: Path) -> tuple[np.ndarray, float]:
    import pypatchworkpp

    pw = pypatchworkpp.patchworkpp(pypatchworkpp.Parameters())
    flags, seconds = [], 0.0
    for f in sorted((sequence / "velodyne").glob("*.bin")):
        points = np.fromfile(f, dtype="<f4").reshape(-1, 4).astype(np.float64)
        t0 = time.perf_counter()
        pw.estimateGround(points)
        seconds += time.perf_counter() - t0
        flag = np.zeros(len(points), bool)
        flag[np.asarray(pw.getGroundIndices(), dtype=np.int64)] = True
        flags.append(flag)
    return np.concatenate(flags), seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitti", default=str(Path(__file__).resolve().parents[1] / ".fetched" / "mini_kitti" / "sequences"))
    ap.add_argument("--resolution", type=float, default=0.2)
    ap.add_argument("--band", type=float, default=0.3, help="map ground: metres from the ground that count as ground")
    args = ap.parse_args()
    rows = []
    for sequence in sorted(p for p in Path(args.kitti).iterdir() if (p / "labels").is_dir()):
        labels = np.concatenate([np.fromfile(f, dtype="<u4") & 0xFFFF for f in sorted((sequence / "labels").glob("*.label"))])
        truth = np.isin(labels, GROUND_CLASSES)
        scans = len(list((sequence / "labels").glob("*.label")))
        for model, (predicted, seconds) in (("map ground", map_ground(sequence, args.resolution, args.band)),
                                            ("Patchwork++", patchwork_ground(sequence))):
            rows.append({"sequence": sequence.name, "model": model, "points": int(len(truth)),
                         "ground_share": round(100 * float(truth.mean()), 2), **scores(predicted, truth),
                         "ms_per_scan": round(1000 * seconds / scans, 1)})
    print(f"{'seq':<4} {'model':<12} {'points':>10} {'ground %':>9} {'precision':>10} {'recall':>8} {'F1':>7} {'ms/scan':>8}")
    for r in rows:
        print(f"{r['sequence']:<4} {r['model']:<12} {r['points']:>10,} {r['ground_share']:>9} {r['precision']:>10} "
              f"{r['recall']:>8} {r['f1']:>7} {r['ms_per_scan']:>8}")
    OUT.mkdir(exist_ok=True)
    (OUT / "ground.json").write_text(json.dumps({"rows": rows, "args": vars(args)}, indent=2))


if __name__ == "__main__":
    main()
