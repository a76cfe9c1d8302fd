"""Ground models against SemanticKITTI's labels: which points are ground, per scan.

    python benchmarks/bench_ground.py [--kitti .fetched/mini_kitti/sequences] [--resolution 0.2]

For each sequence (frames 0-9 of 00 and 05, scripts/fetch_samples.py kitti), every point is
ground or not by:
- the map's ground (voxtool.ground, what `export --above-ground` uses): the sequence built into a
  map, its ground found, a point ground when it lies within --band metres of the ground under it;
- Patchwork++ (PyPI `pypatchworkpp`, a benchmark extra), scan by scan in the sensor frame.
Truth: SemanticKITTI's road, parking, sidewalk, other-ground, lane-marking and terrain classes
(40, 44, 48, 49, 60, 72). Prints precision, recall and time per scan; writes bench-results/ground.json.

The grid table (`export --above-ground 0.3,2` of each sequence's map, what a planner drives on):
- road free: the share of cells holding road, parking, sidewalk or other-ground points (40, 44, 48,
  49) and no object point that the grid marks free;
- objects occupied: the share of cells holding at least two labelled object points (classes 10-99
  but the ground's) 0.3-2 m above the labelled ground under them (the median height of the ground
  points within 1 m) that it marks occupied;
- path free: the share of cells within 2 m of the driven path (the sensor's positions, joined)
  that it marks free; `--pcd DIR --poses FILE` adds an unlabelled dump (path free only);
- path free, cleaned: the same of the grid of `clean --map` at the same resolution (the map of
  the points `clean` keeps: vehicles that drive alongside are no obstacle in it);
- clean --grid: road free, objects occupied and path free of the grid `clean --grid` writes at
  the same resolution (the kept points' map, and their returns that map has not cleared).
`--obstacle-log-odds T`: the grids with voxels over log-odds T as obstacles (the ground as before);
`--step-everywhere`: the ground with clean's 0.3 m step at every window, as the grid had it before;
`--kitti-odometry`: the KITTI sequences posed by `voxtool odometry` instead of the survey.
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
    from voxtool.ground import ground_of, occupied_voxels
    from voxtool.io.mapfile import load_map
    from voxtool.keys import TREE_MAX_VAL
    from voxtool.sources import SourceOptions, open_source

    out = OUT / f"ground_{sequence.name}.vxm"
    OUT.mkdir(exist_ok=True)
    build_map(sequence, SourceOptions(), MapParams(resolution=resolution), SensorModel(), "octree", out, False)
    backend, _ = load_map(out)
    t0 = time.perf_counter()
    keys, hits = occupied_voxels(backend.leaves(), backend.sensor.threshold_log)
    ground = ground_of(keys, resolution, weights=hits)
    flags = []
    for scan in open_source(sequence, SourceOptions()).scans:
        keys = np.floor(scan.points.astype(np.float64) / resolution).astype(np.int64) + TREE_MAX_VAL
        height = ground.under(keys[:, 0], keys[:, 1])
        flags.append(np.abs(scan.points[:, 2] - height) <= band)  # NaN (no ground known) is never ground
    return np.concatenate(flags), time.perf_counter() - t0


ROAD_CLASSES = (40, 44, 48, 49)
BAND = (0.3, 2.0)


def _cells(grid, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of world (x, y) in the grid, and whether they fall inside it."""
    col = np.floor((xy[:, 0] - grid.origin[0]) / grid.resolution).astype(np.int64)
    row = np.floor((xy[:, 1] - grid.origin[1]) / grid.resolution).astype(np.int64)
    inside = (row >= 0) & (row < grid.cells.shape[0]) & (col >= 0) & (col < grid.cells.shape[1])
    return np.stack([row, col], 1), inside


def path_cells(grid, origins: np.ndarray, radius: float = 2.0) -> np.ndarray:
    """(row, col) of the grid cells whose centres lie within `radius` of the polyline of sensor positions."""
    found = []
    for a, b in zip(origins[:-1, :2], origins[1:, :2]):
        lo, hi = np.minimum(a, b) - radius, np.maximum(a, b) + radius  # the segment's box: only its cells
        c0, c1 = np.floor((np.array([lo, hi]) - grid.origin) / grid.resolution).astype(np.int64)  # (x, y) cells
        rows, cols = np.meshgrid(np.arange(max(c0[1], 0), min(c1[1] + 1, grid.cells.shape[0])),
                                 np.arange(max(c0[0], 0), min(c1[0] + 1, grid.cells.shape[1])), indexing="ij")
        centres = np.stack([grid.origin[0] + (cols.ravel() + 0.5) * grid.resolution,
                            grid.origin[1] + (rows.ravel() + 0.5) * grid.resolution], 1)
        ab = b - a
        t = np.clip(((centres - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        near = np.linalg.norm(centres - (a + t[:, None] * ab), axis=1) <= radius
        found.append(np.stack([rows.ravel()[near], cols.ravel()[near]], 1))
    return np.unique(np.concatenate(found), axis=0) if found else np.zeros((0, 2), np.int64)


def _share(grid, cells: np.ndarray, state: int) -> float:
    if len(cells) == 0:
        return float("nan")
    return round(100 * float((grid.cells[cells[:, 0], cells[:, 1]] == state).mean()), 2)


def labelled_cells(grid, points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(road cells, object cells) of the grid by the labelled points (world frame)."""
    ground = np.isin(labels, GROUND_CLASSES)
    road = np.isin(labels, ROAD_CLASSES)
    objects = (labels >= 10) & (labels <= 99) & ~ground
    # the labelled ground's height: the median of the ground points in each 1 m square
    squares = np.floor(points[:, :2]).astype(np.int64)
    key = squares[:, 0] << 32 | (squares[:, 1] & 0xFFFFFFFF)
    order = np.argsort(key[ground], kind="stable")
    gkey, gz = key[ground][order], points[ground, 2][order]
    starts = np.flatnonzero(np.r_[True, gkey[1:] != gkey[:-1]])
    medians = np.array([np.median(z) for z in np.split(gz, starts[1:])]) if len(gz) else np.zeros(0)
    where = np.searchsorted(gkey[starts], key[objects]) if len(gz) else np.zeros(int(objects.sum()), np.int64)
    where = np.minimum(where, max(len(starts) - 1, 0))
    found = len(gz) > 0 and (gkey[starts][where] == key[objects])
    under = np.where(found, medians[where] if len(gz) else np.nan, np.nan)
    height = points[objects, 2] - under
    standing = (height >= BAND[0]) & (height <= BAND[1])
    obj_cells, inside = _cells(grid, points[objects][standing, :2])
    obj_cells, counts = np.unique(obj_cells[inside], axis=0, return_counts=True)
    obj_cells = obj_cells[counts >= 2]
    any_object, inside_o = _cells(grid, points[objects, :2])
    any_object = {tuple(c) for c in any_object[inside_o]}
    road_cells, inside = _cells(grid, points[road, :2])
    road_cells = np.unique(road_cells[inside], axis=0)
    road_cells = np.array([c for c in road_cells if tuple(c) not in any_object]).reshape(-1, 2)
    return road_cells, obj_cells


def grid_of(source: Path, resolution: float, poses: str | None = None, choice: dict | None = None):
    """The --above-ground grid of the source's map, the scans (world points) and the sensor positions.
    `choice`: project_above_ground's keywords (obstacle_log, params), if not its defaults."""
    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.ground import project_above_ground
    from voxtool.io.mapfile import load_map
    from voxtool.sources import SourceOptions, open_source

    options = SourceOptions(poses=poses)
    out = OUT / f"grid_{source.name}.vxm"
    OUT.mkdir(exist_ok=True)
    build_map(source, options, MapParams(resolution=resolution), SensorModel(), "octree", out, False)
    backend, _ = load_map(out)
    t0 = time.perf_counter()
    grid = project_above_ground(backend.leaves(), resolution, backend.sensor.threshold_log, BAND, **(choice or {}))
    seconds = time.perf_counter() - t0
    scans = list(open_source(source, options).scans)
    return grid, scans, np.array([s.origin for s in scans], np.float64), seconds


def cleaned_grids(source: Path, resolution: float, origins: np.ndarray, poses: str | None = None,
                  choice: dict | None = None):
    """(the path-free share of the --above-ground grid of `clean --map`'s map, the grid `clean
    --grid` writes) of the source, cleaned once at the same resolution."""
    from voxtool.clean import CleanParams, clean_stream, static_grid, static_map
    from voxtool.ground import project_above_ground
    from voxtool.sources import SourceOptions, open_source

    params = CleanParams(resolution=resolution)
    cleaned = clean_stream(open_source(source, SourceOptions(poses=poses)), params, progress=False)
    backend, _ = static_map(cleaned, params)
    exported = project_above_ground(backend.leaves(), resolution, backend.sensor.threshold_log, BAND, **(choice or {}))
    grid, _ = static_grid(cleaned, backend, BAND)
    return _share(exported, path_cells(exported, origins), 0), grid


def grid_rows(kitti: Path, resolution: float, pcd: list[tuple[Path, str]], choice: dict | None = None,
              kitti_poses: dict | None = None) -> list[dict]:
    """`kitti_poses`: a pose file per sequence name, to use instead of the survey's."""
    rows = []
    for sequence in sorted(p for p in kitti.iterdir() if (p / "labels").is_dir()):
        poses = (kitti_poses or {}).get(sequence.name)
        grid, scans, origins, seconds = grid_of(sequence, resolution, poses, choice)
        labels = np.concatenate([np.fromfile(f, dtype="<u4") & 0xFFFF for f in sorted((sequence / "labels").glob("*.label"))])
        points = np.concatenate([s.points for s in scans]).astype(np.float64)
        assert len(points) == len(labels), "a scan lost points on reading: labels no longer line up"
        road, objects = labelled_cells(grid, points, labels)
        cleaned_path, returns = cleaned_grids(sequence, resolution, origins, poses, choice)
        road_r, objects_r = labelled_cells(returns, points, labels)
        rows.append({"input": f"KITTI {sequence.name}", "road_cells": len(road), "road_free": _share(grid, road, 0),
                     "object_cells": len(objects), "objects_occupied": _share(grid, objects, 100),
                     "path_free": _share(grid, path_cells(grid, origins), 0), "path_free_cleaned": cleaned_path,
                     "grid_road_free": _share(returns, road_r, 0), "grid_objects_occupied": _share(returns, objects_r, 100),
                     "grid_path_free": _share(returns, path_cells(returns, origins), 0),
                     "ground_s": round(seconds, 3)})
    for folder, poses in pcd:
        grid, _, origins, seconds = grid_of(folder, resolution, poses, choice)
        cleaned_path, returns = cleaned_grids(folder, resolution, origins, poses, choice)
        rows.append({"input": folder.name, "road_cells": None, "road_free": None, "object_cells": None,
                     "objects_occupied": None, "path_free": _share(grid, path_cells(grid, origins), 0),
                     "path_free_cleaned": cleaned_path, "grid_road_free": None, "grid_objects_occupied": None,
                     "grid_path_free": _share(returns, path_cells(returns, origins), 0), "ground_s": round(seconds, 3)})
    return rows


def odometry_poses(kitti: Path) -> dict:
    """Each labelled sequence posed by `voxtool odometry` (the first scan's frame), as pose files."""
    from voxtool.odometry import OdometryParams, estimate_poses, write_pose_file
    from voxtool.sources import SourceOptions

    found = {}
    OUT.mkdir(exist_ok=True)
    for sequence in sorted(p for p in kitti.iterdir() if (p / "labels").is_dir()):
        poses = estimate_poses(sequence, SourceOptions(), OdometryParams(), progress=False)
        found[sequence.name] = str(OUT / f"odometry_{sequence.name}.txt")
        write_pose_file(found[sequence.name], poses["poses"], poses["stamps_ns"])
    return found


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
    ap.add_argument("--pcd", nargs=2, action="append", default=[], metavar=("DIR", "POSES"),
                    help="an unlabelled PCD dump and its pose file: its path-free share in the grid table")
    ap.add_argument("--grid-only", action="store_true", help="only the grid table")
    ap.add_argument("--kitti-odometry", action="store_true",
                    help="grid table: the KITTI sequences posed by `voxtool odometry` instead of their survey poses")
    ap.add_argument("--obstacle-log-odds", type=float, default=None,
                    help="grid table: a voxel over this log-odds in the band is an obstacle (default: the map's "
                         "occupancy threshold, what `export --above-ground` uses)")
    ap.add_argument("--step-everywhere", action="store_true",
                    help="grid table: the ground with the 0.3 m step at every window (clean's; before the grid's "
                         "narrow steps, docs/design/ground.md section 3)")
    args = ap.parse_args()
    choice = {"obstacle_log": args.obstacle_log_odds}
    if args.step_everywhere:
        from voxtool.ground import GroundParams

        choice["params"] = GroundParams()
    kitti_poses = odometry_poses(Path(args.kitti)) if args.kitti_odometry else None
    grid = grid_rows(Path(args.kitti), args.resolution, [(Path(d), p) for d, p in args.pcd], choice, kitti_poses)

    def cell(v):
        return "-" if v is None else v

    print(f"{'':<16} {'export --above-ground':^68} {'clean --grid':^27}")
    print(f"{'input':<16} {'road cells':>10} {'road free %':>12} {'object cells':>13} {'objects occ. %':>15} "
          f"{'path free %':>12} {'cleaned %':>10} {'road %':>8} {'objects %':>10} {'path %':>7} {'ground s':>9}")
    for r in grid:
        print(f"{r['input']:<16} {cell(r['road_cells']):>10} {cell(r['road_free']):>12} {cell(r['object_cells']):>13} "
              f"{cell(r['objects_occupied']):>15} {r['path_free']:>12} {r['path_free_cleaned']:>10} "
              f"{cell(r['grid_road_free']):>8} {cell(r['grid_objects_occupied']):>10} {r['grid_path_free']:>7} "
              f"{r['ground_s']:>9}", flush=True)
    OUT.mkdir(exist_ok=True)
    (OUT / "ground_grid.json").write_text(json.dumps({"rows": grid, "args": vars(args)}, indent=2))
    if args.grid_only:
        return
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
