"""`build --decay`: how much of the movers' trails a half-life forgets, what it costs the static
map, and what it costs in time, in one run.

    python benchmarks/bench_decay.py [--data ../shared/data] [--out bench-results/decay.json]

A generated street (voxtool.synthetic, 32-beam LiDAR, 10 Hz, the sensor driving at 3 m/s) is
built without decay (OctoMap's map) and with several half-lives. Each occupied voxel of a map is
judged from the scene: static when its centre lies on a static box or the ground (within a
voxel), current when it lies in a mover at the last scan's time, else trail (a mover that left).
"static near" counts static voxels within 20 m of the sensor at the end: what a robot plans in.
Then the shared kaist03 bag (scan times from the bag): occupied voxels and time per half-life.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

HALF_LIVES = [None, 20.0, 5.0, 2.0, 1.0]
NEAR_M = 20.0


def build(source, half_life, resolution, poses=None):
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps.octree import OctreeMap
    from voxtool.pipeline import build as run
    from voxtool.sources import SourceOptions, open_source

    backend = OctreeMap(MapParams(resolution=resolution), SensorModel(), decay_half_life=half_life)
    report = run(open_source(source, SourceOptions(poses=poses)), backend, progress=False)
    return backend, report


def judge(backend, scene, resolution: float) -> dict:
    """Occupied voxels of the map split into static, current (in a mover now) and trail."""
    from voxtool.io.export import voxel_centres

    leaves = backend.leaves()
    occupied = leaves.values > np.float32(backend.sensor.threshold_log)
    centres = voxel_centres(leaves, occupied, resolution)
    t_end = (scene.n_scans - 1) / scene.rate_hz
    pad = resolution

    def inside(box, t):
        shift = np.asarray(box.velocity) * t
        lo, hi = np.asarray(box.lo) + shift - pad, np.asarray(box.hi) + shift + pad
        return np.all((centres >= lo) & (centres <= hi), axis=1)

    static = centres[:, 2] < pad
    current = np.zeros(centres.shape[0], dtype=bool)
    for box in scene.boxes:
        if box.moving:
            current |= inside(box, t_end)
        else:
            static |= inside(box, 0.0)
    current &= ~static
    sensor = np.asarray(scene.sensor_start) + t_end * np.asarray(scene.sensor_velocity)
    near = np.linalg.norm(centres - sensor, axis=1) <= NEAR_M
    return {"occupied": int(centres.shape[0]), "static": int(static.sum()), "static_near": int((static & near).sum()),
            "current": int(current.sum()), "trail": int((~static & ~current).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data")
    ap.add_argument("--out", type=Path, default=Path("bench-results/decay.json"))
    ap.add_argument("--scans", type=int, default=100)
    args = ap.parse_args()
    from voxtool.synthetic import street, write_pcd_scans

    results = {"street": [], "kaist03": []}
    scene = street(args.scans, seed=4)
    with tempfile.TemporaryDirectory() as tmp:
        write_pcd_scans(scene, tmp)
        build(tmp, 1.0, 0.2, Path(tmp) / "poses.txt")  # compile
        print(f"street, 32 beams, {args.scans} scans at 10 Hz, 0.2 m voxels")
        print(f"{'half-life':>10} {'occupied':>9} {'static':>8} {'near':>7} {'current':>8} {'trail':>7} "
              f"{'update s':>9}")
        for h in HALF_LIVES:
            backend, report = build(tmp, h, 0.2, Path(tmp) / "poses.txt")
            row = {"half_life_s": h, **judge(backend, scene, 0.2),
                   "update_s": round(report.time_update, 3), "total_s": round(report.time_total, 3)}
            results["street"].append(row)
            print(f"{'none' if h is None else f'{h:g} s':>10} {row['occupied']:>9,} {row['static']:>8,} "
                  f"{row['static_near']:>7,} {row['current']:>8,} {row['trail']:>7,} "
                  f"{row['update_s']:>9.3f}")
    bag = args.data / "kaist03" / "kaist03_21scans.mcap"
    if bag.exists():
        print(f"\n{bag.name}, 0.1 m voxels")
        print(f"{'half-life':>10} {'occupied':>9} {'update s':>9} {'total s':>8}")
        for h in HALF_LIVES:
            t0 = time.perf_counter()
            backend, report = build(bag, h, 0.1)
            leaves = backend.leaves()
            row = {"half_life_s": h, "occupied": int((leaves.values > 0).sum()),
                   "update_s": round(report.time_update, 3), "total_s": round(time.perf_counter() - t0, 3)}
            results["kaist03"].append(row)
            print(f"{'none' if h is None else f'{h:g} s':>10} {row['occupied']:>9,} "
                  f"{row['update_s']:>9.3f} {row['total_s']:>8.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
