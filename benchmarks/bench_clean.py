"""`voxtool clean` against DUFOMap (PyPI `dufomap`, a benchmark extra) in one run.

    pip install -e '.[bench]'
    python benchmarks/bench_clean.py [--data ../shared/data] [--repeat 2] [--out bench-results/clean.json]
                                     [--only real-movers]

Real scans with known movers (first): the shared datasets' real returns with moving boxes
ray-traced into them (voxtool.synthetic.traffic and insert_movers: two cars, one oncoming at
10 m/s and one overtaking, a cyclist and three pedestrians, standing on the ground; every real
ray kept, and stopped at a box lying in front of its return: those points are the dynamic
truth), all scans, keyframe-like variants (every 3rd scan; scans voxel-downsampled to 0.2 m) and
the same scans without movers (false removals alone). SA / DA / AA of both tools and a picture
per scene (removed red over kept; bench-results/clean_real_<scene>.png).

Generated street scenes with ground truth (voxtool.synthetic: buildings, poles, parked cars; two
cars, a cyclist and pedestrians moving; a 32- or 64-beam spinning LiDAR with range noise):
the DynamicMap benchmark's SA / DA / AA per point, and the time of each tool from reading the
scans to every point's label, in this process, alternating which runs first. Then the shared
real datasets (no labels): points removed by each, times, and a before/after PNG of voxtool's
result per dataset (bench-results/clean_<name>.png).
"""

from __future__ import annotations

import os

# one BLAS thread, as the voxtool command sets it (before numpy loads): OpenBLAS threads left
# spinning after a scan's transform would take cores from either tool
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REAL = [("kaist03", 80.0), ("quick_shack", None), ("norlab", 60.0)]  # name, picture extent (m)


def scenes():
    from voxtool.synthetic import Lidar, street

    return [("street, 32 beams", street(30, seed=1)),
            ("street, 64 beams", street(30, seed=2, lidar=Lidar(beams=64, columns=1024))),
            ("street, 32 beams, slow sensor", street(40, seed=3))]


def run_voxtool(source, params):
    from voxtool.clean import clean_stream
    from voxtool.sources import open_source

    t0 = time.perf_counter()
    cleaned = clean_stream(open_source(source), params, progress=False)
    return cleaned.dynamic, time.perf_counter() - t0, cleaned


def run_dufomap(source, params):
    """DUFOMap with the same resolution, d_s and d_p, fed the scans voxtool reads (world frame,
    the sensor origin as the pose), as its own examples run it."""
    from dufomap import dufomap

    from voxtool.sources import open_source

    t0 = time.perf_counter()
    scans = list(open_source(source).scans)
    mapper = dufomap(params.resolution, params.sensor_noise, params.pose_error, num_threads=0)
    poses = [[float(s.origin[0]), float(s.origin[1]), float(s.origin[2]), 1.0, 0.0, 0.0, 0.0] for s in scans]
    for scan, pose in zip(scans, poses):
        mapper.run(scan.points, pose, cloud_transform=False)
    mapper.oncePropagateCluster(if_propagate=True, if_cluster=False)
    labels = [mapper.segment(scan.points, pose, cloud_transform=False) for scan, pose in zip(scans, poses)]
    dynamic = np.concatenate(labels).astype(bool) if labels else np.zeros(0, bool)
    return dynamic, time.perf_counter() - t0


def best_of(repeat, first, second):
    """Alternate the two tools `repeat` times (the machine drifts between minutes); the fastest of each."""
    a, b = [], []
    for k in range(repeat):
        for fn, out in ((first, a), (second, b)) if k % 2 == 0 else ((second, b), (first, a)):
            out.append(fn())
    return min(a, key=lambda r: r[1]), min(b, key=lambda r: r[1])


def real_scene(src: Path, out: Path, movers: bool, every: int = 1, voxel: float | None = None) -> np.ndarray:
    """A shared dataset's scans (every `every`-th; one point per `voxel` cube if given) with the
    moving boxes of synthetic.traffic ray-traced into their real returns, written as a PCD
    directory (points relative to the sensor origin, VIEWPOINT the origin, poses.txt the
    times); returns every point's dynamic truth, in read order."""
    from voxtool.io.export import pcd_header, pcd_rows
    from voxtool.sources import SourceOptions, open_source
    from voxtool.synthetic import ground_height, insert_movers, traffic

    scans = list(open_source(src, SourceOptions(every=every)).scans)
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.float64) / 1e9
    times = stamps - stamps[0] if np.any(stamps) else np.arange(len(scans)) * every / 10.0
    origins = np.array([s.origin for s in scans], dtype=np.float64)
    boxes = traffic(origins, times, ground_height(scans[0].points, origins[0])) if movers else []
    out.mkdir(parents=True, exist_ok=True)
    labels, poses = [], []
    for i, scan in enumerate(scans):
        points = scan.points
        if voxel is not None:  # a keyframe dump: one point per voxel, the first the scan holds
            keys = np.floor(points / voxel).astype(np.int64)
            _, first = np.unique(keys, axis=0, return_index=True)
            points = points[np.sort(first)]
        points, dynamic = insert_movers(points, scan.origin, float(times[i]), boxes)
        local = (points.astype(np.float64) - origins[i]).astype(np.float32)
        (out / f"{i:06d}.pcd").write_bytes(pcd_header(len(local), False, viewpoint=(*origins[i], 1.0, 0.0, 0.0, 0.0))
                                           + pcd_rows(local, None))
        poses.append(f"{times[i]:.6f} {origins[i][0]:.9f} {origins[i][1]:.9f} {origins[i][2]:.9f} 0 0 0 1\n")
        labels.append(dynamic)
    (out / "poses.txt").write_text("".join(poses))
    return np.concatenate(labels)


REAL_SCENES = [  # name, dataset, movers, every n-th scan, voxel size of a keyframe dump
    ("kaist03 + movers", "kaist03", True, 1, None),
    ("kaist03 + movers, every 3rd scan", "kaist03", True, 3, None),
    ("kaist03 + movers, 0.2 m keyframes", "kaist03", True, 1, 0.2),
    ("kaist03, no movers", "kaist03", False, 1, None),
    ("norlab + movers", "norlab", True, 1, None),
    ("norlab, no movers", "norlab", False, 1, None),
    ("quick_shack + movers", "quick_shack", True, 1, None),
    ("quick_shack, no movers", "quick_shack", False, 1, None),
]


def real_movers(data: Path, tmp: Path, out: Path, params, repeat: int) -> list[dict]:
    """REAL_SCENES: both tools at their defaults, scored against the ray-traced truth."""
    from voxtool.clean import accuracy
    from voxtool.plots import clean_figure, write_plot

    rows = []
    print(f"{'real scans, movers ray-traced':36} {'points':>9} {'dynamic':>8} | {'voxtool SA / DA / AA':>22} "
          f"{'time':>7} | {'DUFOMap SA / DA / AA':>22} {'time':>7}")
    for name, dataset, movers, every, voxel in REAL_SCENES:
        src = data / dataset / "pcd"
        if not src.is_dir():
            continue
        scene = tmp / name.replace(" ", "_").replace(",", "").replace("+", "with")
        truth = real_scene(src, scene, movers, every, voxel)
        (vox, vox_s, cleaned), (duf, duf_s) = best_of(repeat, lambda s=scene: run_voxtool(s, params),
                                                     lambda s=scene: run_dufomap(s, params))
        v, d = accuracy(vox, truth), accuracy(duf, truth)
        picture = out.parent / f"clean_real_{scene.name}.png"
        write_plot(clean_figure(cleaned.points, vox, f"voxtool clean, {name} (0.1 m)", 80.0)[0], picture)
        rows.append({"input": name, "points": int(truth.size), "dynamic_points": int(truth.sum()),
                     "removed_share": {"voxtool": round(float(vox.mean()), 5), "dufomap": round(float(duf.mean()), 5)},
                     "voxtool": {**v, "seconds": vox_s}, "dufomap": {**d, "seconds": duf_s}, "picture": str(picture)})
        print(f"{name:36} {truth.size:>9,} {int(truth.sum()):>8,} | {v['SA']:6.2f} {v['DA']:6.2f} {v['AA']:6.2f} "
              f"{vox_s:6.2f}s | {d['SA']:6.2f} {d['DA']:6.2f} {d['AA']:6.2f} {duf_s:6.2f}s", flush=True)
    return rows


def main() -> None:
    from voxtool.clean import CleanParams, accuracy
    from voxtool.synthetic import write_pcd_scans

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--repeat", type=int, default=2, help="runs of each tool per input (alternating); best time kept")
    ap.add_argument("--out", default="bench-results/clean.json")
    ap.add_argument("--only", choices=["real-movers"], help="only the real scans with ray-traced movers")
    args = ap.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    params = CleanParams()  # DUFOMap's published defaults: 0.1 m, d_s 0.2 m, d_p 1 voxel
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # warm both (numba's kernels load, DUFOMap's library) on a small scene, untimed
        from voxtool.synthetic import street

        write_pcd_scans(street(2), Path(tmp) / "warm")
        run_voxtool(Path(tmp) / "warm", params)
        run_dufomap(Path(tmp) / "warm", params)
        rows += real_movers(Path(args.data), Path(tmp), out, params, args.repeat)
        if args.only == "real-movers":
            out.write_text(json.dumps({"params": params.__dict__, "rows": rows}, indent=2))
            print(f"\nwritten {out}")
            return
        print()
        print(f"{'input':32} {'points':>9} {'dynamic':>8} | {'voxtool SA / DA / AA':>22} {'time':>7} | "
              f"{'DUFOMap SA / DA / AA':>22} {'time':>7}")
        for name, scene in scenes():
            src = Path(tmp) / name.replace(" ", "_").replace(",", "")
            truth = write_pcd_scans(scene, src)
            (vox, vox_s, _), (duf, duf_s) = best_of(args.repeat, lambda s=src: run_voxtool(s, params),
                                                   lambda s=src: run_dufomap(s, params))
            v, d = accuracy(vox, truth), accuracy(duf, truth)
            rows.append({"input": name, "points": int(truth.size), "dynamic_points": int(truth.sum()),
                         "voxtool": {**v, "seconds": vox_s}, "dufomap": {**d, "seconds": duf_s}})
            print(f"{name:32} {truth.size:>9,} {int(truth.sum()):>8,} | {v['SA']:6.2f} {v['DA']:6.2f} {v['AA']:6.2f} "
                  f"{vox_s:6.2f}s | {d['SA']:6.2f} {d['DA']:6.2f} {d['AA']:6.2f} {duf_s:6.2f}s")
    print()
    print(f"{'real data (no labels)':32} {'points':>9} | {'voxtool removed':>16} {'time':>7} | "
          f"{'DUFOMap removed':>16} {'time':>7} | picture")
    for name, extent in REAL:
        src = Path(args.data) / name / "pcd"
        if not src.is_dir():
            continue
        (vox, vox_s, cleaned), (duf, duf_s) = best_of(args.repeat, lambda s=src: run_voxtool(s, params),
                                                     lambda s=src: run_dufomap(s, params))
        picture = out.parent / f"clean_{name}.png"
        from voxtool.plots import clean_figure, write_plot

        write_plot(clean_figure(cleaned.points, vox, f"voxtool clean {name} (0.1 m)", extent)[0], picture)
        both = int((vox & duf).sum())
        rows.append({"input": name, "points": int(vox.size), "voxtool": {"removed": int(vox.sum()), "seconds": vox_s},
                     "dufomap": {"removed": int(duf.sum()), "seconds": duf_s}, "removed_by_both": both,
                     "picture": str(picture)})
        print(f"{name:32} {vox.size:>9,} | {int(vox.sum()):>16,} {vox_s:6.2f}s | {int(duf.sum()):>16,} {duf_s:6.2f}s | "
              f"{picture} ({both:,} removed by both)")
    out.write_text(json.dumps({"params": params.__dict__, "rows": rows}, indent=2))
    print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
