"""`voxtool odometry` on 2D LaserScan logs against a simulator's truth: the grid matcher (the default
for 2D scans) and KISS-ICP on the same scans, in one run.

    python benchmarks/bench_odometry_2d.py [LOG ...] [--out bench-results/odometry_2d.json]

LOG: ROS 2 bag folders of a simulated TurtleBot3 whose /tf odom -> base_footprint is the
simulator's model pose (Gazebo's diff-drive plugin at its default, WORLD). Default: the Gazebo logs
scripts/fetch_samples.py lays out in .fetched/gazebo_tb3/ (driving, hall, teleop, localization).
For each: the truth's path, ATE RMSE after one rigid fit (the odometry's frame is the first
scan's) for each matcher, whether the run was flagged (plausibility) and the time a scan.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

FETCHED = Path(__file__).resolve().parents[1] / ".fetched" / "gazebo_tb3"
MOVING = ("driving", "hall", "teleop", "localization")


def measure(log: Path) -> dict:
    from voxtool.errors import VoxtoolWarning
    from voxtool.odometry import OdometryParams, ate_rmse, estimate_poses
    from voxtool.sources import SourceOptions, open_source

    truth = np.array([s.origin for s in open_source(log, SourceOptions(world_frame="odom")).scans], np.float64)
    row = {"log": log.name, "scans": len(truth),
           "path_m": round(float(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1).sum()), 2)}
    for matcher in ("grid", "kiss-icp"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", VoxtoolWarning)
            t0 = time.perf_counter()
            result = estimate_poses(log, SourceOptions(), OdometryParams(matcher=matcher), progress=False)
            seconds = time.perf_counter() - t0
        check = result["figures"]["plausibility"]
        row[matcher] = {"ate_m": round(ate_rmse(result["poses"][:, :3, 3], truth), 4), "flagged": bool(check["suspect"]),
                        "one_direction_scans": check.get("one_direction_scans"),
                        "ms_a_scan": round(1000 * seconds / len(truth), 2)}
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="*", type=Path)
    parser.add_argument("--out", type=Path, default=Path("bench-results/odometry_2d.json"))
    args = parser.parse_args()
    logs = args.logs or [FETCHED / name for name in MOVING if (FETCHED / name / "metadata.yaml").is_file()]
    if not logs:
        raise SystemExit("no log: lay out the Gazebo logs (scripts/fetch_samples.py gazebo, gazebo-hall, "
                         "gazebo-teleop, gazebo-localization) or name bag folders")
    rows = [measure(log) for log in logs]
    print(f"{'log':<44} {'scans':>6} {'path m':>7} {'grid ATE m':>11} {'flagged':>8} {'KISS-ICP ATE m':>15} "
          f"{'flagged':>8} {'grid ms/scan':>13} {'KISS ms/scan':>13}")
    for r in rows:
        g, k = r["grid"], r["kiss-icp"]
        print(f"{r['log']:<44} {r['scans']:>6} {r['path_m']:>7.2f} {g['ate_m']:>11.3f} {str(g['flagged']):>8} "
              f"{k['ate_m']:>15.3f} {str(k['flagged']):>8} {g['ms_a_scan']:>13.2f} {k['ms_a_scan']:>13.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
