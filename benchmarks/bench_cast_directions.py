"""How fast the ray-casting kernel steps, by how many axes its rays move along: the cost of the
DDA's axis choice when the branch predictor cannot follow it.

    python benchmarks/bench_cast_directions.py [--rays 20000] [--length 30] [--out bench-results/cast_directions.json]

One thread, one scan of `--rays` generated rays of `--length` metres at 0.2 m from near the
origin, per family: along one axis; one axis with a slope in a second (a step in y every 3-10 in
x); slopes in both others; uniformly random directions (as a spinning LiDAR's, which also touch
many more bricks). Best of five calls of kernels.raycast.scan_bricks. Prints a table and writes
JSON.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from report import write_report  # noqa: E402

RESOLUTION = 0.2


def families(n: int, length: float, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    along = np.zeros((n, 3))
    along[:, 0] = length
    along[:, 1:] = rng.uniform(0.0, 0.19, (n, 2))  # end points spread over the voxel's face, still on the axis
    one_slope = np.stack([np.ones(n), rng.uniform(0.1, 0.3, n), np.zeros(n)], axis=1)
    two_slopes = np.stack([np.ones(n), rng.uniform(0.1, 0.3, n), rng.uniform(0.1, 0.3, n)], axis=1)
    random = rng.normal(size=(n, 3))
    out = {"one axis": along}
    for name, d in (("two axes", one_slope), ("three axes", two_slopes), ("random directions", random)):
        out[name] = d / np.linalg.norm(d, axis=1, keepdims=True) * length
    return {k: v.astype(np.float32) for k, v in out.items()}


def steps_per_second(points: np.ndarray, repeat: int = 5) -> tuple[float, int, int]:
    from voxtool.kernels.raycast import BrickBuffers, scan_bricks

    origin = np.full(3, 0.05, dtype=np.float32)  # inside the first voxel, off its faces
    buffers = BrickBuffers(1 << 16)
    near_keys, near_bits = np.full(2, -1, np.int64), np.zeros((2, 16), np.int64)
    best, steps, bricks = float("inf"), 0, 0
    for _ in range(repeat + 1):  # the first loads the kernel
        t0 = time.perf_counter()
        bricks, steps = scan_bricks(points, origin, RESOLUTION, -1.0, buffers.tab, buffers.touched, buffers.occ,
                                    buffers.bricks, near_keys, near_bits)
        best = min(best, time.perf_counter() - t0)
        if bricks < 0:
            raise SystemExit("brick buffers too small: use fewer --rays")
        buffers.reset(bricks)
    return steps / best, int(steps), int(bricks)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=20000)
    ap.add_argument("--length", type=float, default=30.0)
    ap.add_argument("--out", default="bench-results/cast_directions.json")
    args = ap.parse_args()
    rows = []
    for name, points in families(args.rays, args.length).items():
        rate, steps, bricks = steps_per_second(points)
        rows.append({"rays": name, "steps": steps, "bricks": bricks, "M_steps_per_s": round(rate / 1e6, 1),
                     "ns_per_step": round(1e9 / rate, 2)})
    out = write_report(rows, list(rows[0]), args.out, resolution=RESOLUTION, length_m=args.length)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
