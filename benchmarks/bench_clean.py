"""`voxtool clean` against DUFOMap (PyPI `dufomap`, a benchmark extra) in one run.

    pip install -e '.[bench]'
    python benchmarks/bench_clean.py [--data ../shared/data] [--repeat 2] [--out bench-results/clean.json]
                                     [--only real-movers]

Real scans with known movers (first): the shared datasets' real returns with moving boxes
ray-traced into them (voxtool.synthetic.traffic and insert_movers: two cars, one oncoming at
10 m/s and one overtaking, a cyclist and three pedestrians, standing on the ground; every real
ray kept, and stopped at a box lying in front of its return: those points are the dynamic
truth), all scans, keyframe-like variants (every 3rd scan; scans voxel-downsampled to 0.2 m) and
the same scans without movers (false removals alone); and dense 64-beam car frames (KITTI
sequences 00 and 05, frames 0-9, with SemanticKITTI's moving points as truth too; fetched by
scripts/fetch_samples.py, skipped without them) whose poses carry survey-grade error
(voxtool.synthetic.PoseError). SA / DA / AA of both tools and a picture per scene (removed red
over kept; bench-results/clean_real_<scene>.png). Then the ground table: voxtool judging the
ground as any other surface (--ground-band -1) against its default, and the cost a scan.

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
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REAL = [("kaist03", 80.0), ("quick_shack", None), ("norlab", 60.0)]  # name, picture extent (m)


def _score(value, width: int) -> str:
    """A score as the tables print it; n/a where there was nothing of its kind (accuracy gives None)."""
    return f"{'n/a':>{width}}" if value is None else f"{value:{width}.2f}"


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


@dataclass(frozen=True)
class RealScene:
    name: str
    dataset: str  # a folder of ../shared/data with pcd/, or kitti/NN: .fetched/mini_kitti/sequences/NN
    movers: bool = True
    every: int = 1  # every n-th scan
    voxel: float | None = None  # one point per voxel of this size (a keyframe dump)
    pose_error: bool = False  # synthetic.PoseError on every scan (after the movers are traced)
    drift: bool = False  # ... and the drift of a real INS (PoseError.drifting: the same way for seconds)
    odometry: bool = False  # the scans posed by `voxtool odometry` (a driver's dump without poses)


REAL_SCENES = [
    RealScene("kaist03 + movers", "kaist03"),
    RealScene("kaist03 + movers, every 3rd scan", "kaist03", every=3),
    RealScene("kaist03 + movers, 0.2 m keyframes", "kaist03", voxel=0.2),
    RealScene("kaist03, no movers", "kaist03", movers=False),
    RealScene("norlab + movers", "norlab"),
    RealScene("norlab, no movers", "norlab", movers=False),
    RealScene("quick_shack + movers", "quick_shack"),
    RealScene("quick_shack, no movers", "quick_shack", movers=False),
    # dense 64-beam car frames (KITTI, with their real movers labelled by SemanticKITTI) whose poses
    # carry survey-grade error: rays graze the road another scan saw a few centimetres higher
    RealScene("KITTI 00 + movers, pose error", "kitti/00", pose_error=True),
    RealScene("KITTI 05 + movers, pose error", "kitti/05", pose_error=True),
    RealScene("KITTI 00, pose error", "kitti/00", movers=False, pose_error=True),
    RealScene("KITTI 05, pose error", "kitti/05", movers=False, pose_error=True),
    RealScene("KITTI 05 + movers, exact poses", "kitti/05"),
    # the error of a real INS: it drifts the same way for seconds (35 cm and 0.4 degrees in 6 s)
    RealScene("KITTI 00 + movers, drifting poses", "kitti/00", pose_error=True, drift=True),
    RealScene("KITTI 05 + movers, drifting poses", "kitti/05", pose_error=True, drift=True),
    RealScene("KITTI 05, drifting poses", "kitti/05", movers=False, pose_error=True, drift=True),
    # the same KITTI frames posed by voxtool odometry instead of the survey (their real movers labelled)
    RealScene("KITTI 00 + movers, odometry", "kitti/00", odometry=True),
    RealScene("KITTI 05 + movers, odometry", "kitti/05", odometry=True),
    RealScene("KITTI 05, odometry", "kitti/05", movers=False, odometry=True),
    # a KITTI raw PCD dump as drivers write it (no poses; one (0, 0, 0) "no return" a scan; returns
    # metres under the road), posed by voxtool odometry. Its real traffic is not labelled (a vehicle
    # 2-3 m to the left drives along with the car): what clean removes of it counts against SA
    RealScene("Udacity dump + movers, odometry", "udacity", odometry=True),
    RealScene("Udacity dump, odometry (traffic)", "udacity", movers=False, odometry=True),
]
KITTI = Path(__file__).resolve().parents[1] / ".fetched" / "mini_kitti" / "sequences"  # scripts/fetch_samples.py


def scene_source(data: Path, scene: RealScene) -> tuple[Path, Path | None]:
    """The scans of a scene and the folder of its SemanticKITTI labels (None: no real movers)."""
    if scene.dataset.startswith("kitti/"):
        seq = KITTI / scene.dataset.split("/")[1]
        return seq, seq / "labels"
    if scene.dataset == "udacity":
        return KITTI.parents[1] / "udacity_data_1", None
    return data / scene.dataset / "pcd", None


def real_scene(src: Path, out: Path, scene: RealScene, labels: Path | None = None) -> np.ndarray:
    """A real dataset's scans (every `every`-th; one point per `voxel` cube if given) with the
    moving boxes of synthetic.traffic ray-traced into their real returns, then (pose_error) each
    scan placed by a pose with survey-grade error, written as a PCD directory (points relative
    to the sensor origin, VIEWPOINT the origin, poses.txt the times); returns every point's
    dynamic truth (on a box, or a moving class of `labels`), in read order."""
    from voxtool.io.export import pcd_header, pcd_rows
    from voxtool.sources import SourceOptions, open_source
    from voxtool.synthetic import PoseError, ground_height, insert_movers, traffic

    poses = None
    if scene.odometry:
        from voxtool.odometry import OdometryParams, estimate_poses, write_pose_file

        result = estimate_poses(src, SourceOptions(), OdometryParams(), progress=False)
        poses = str(out.parent / f"{out.name}_odometry.txt")
        write_pose_file(poses, result["poses"], result["stamps_ns"])
    options = SourceOptions(every=scene.every, truth=str(labels) if labels else None, poses=poses)
    scans = list(open_source(src, options).scans)
    stamps = np.array([s.stamp_ns for s in scans], dtype=np.float64) / 1e9
    times = stamps - stamps[0] if np.any(stamps) else np.arange(len(scans)) * scene.every / 10.0
    origins = np.array([s.origin for s in scans], dtype=np.float64)
    boxes = traffic(origins, times, ground_height(scans[0].points, origins[0])) if scene.movers else []
    rng = np.random.default_rng(7)
    error = PoseError.drifting() if scene.drift else PoseError()
    out.mkdir(parents=True, exist_ok=True)
    truths, poses = [], []
    for i, scan in enumerate(scans):
        points, real = scan.points, scan.extra.get("truth", np.zeros(scan.points.shape[0], dtype=bool))
        if scene.voxel is not None:  # a keyframe dump: one point per voxel, the first the scan holds
            keys = np.floor(points / scene.voxel).astype(np.int64)
            _, first = np.unique(keys, axis=0, return_index=True)
            points, real = points[np.sort(first)], real[np.sort(first)]
        points, dynamic = insert_movers(points, scan.origin, float(times[i]), boxes)
        origin = origins[i]
        if scene.pose_error:
            points, origin = error.apply(points, origin, rng, float(times[i]))
        local = (points.astype(np.float64) - origin).astype(np.float32)
        (out / f"{i:06d}.pcd").write_bytes(pcd_header(len(local), False, viewpoint=(*origin, 1.0, 0.0, 0.0, 0.0))
                                           + pcd_rows(local, None))
        poses.append(f"{times[i]:.6f} {origin[0]:.9f} {origin[1]:.9f} {origin[2]:.9f} 0 0 0 1\n")
        truths.append(dynamic | real)
    (out / "poses.txt").write_text("".join(poses))
    return np.concatenate(truths)


def real_movers(data: Path, tmp: Path, out: Path, params, repeat: int,
                words: list[str] | None = None) -> tuple[list[dict], list[dict]]:
    """REAL_SCENES: both tools at their defaults, scored against the ray-traced truth; then the
    ground table: voxtool with the ground judged as any surface (--ground-band -1) against the
    default, and what judging the ground costs a scan."""
    import dataclasses

    from voxtool.clean import accuracy
    from voxtool.plots import clean_figure, write_plot

    rows, ground_rows = [], []
    print(f"{'real scans, movers ray-traced':36} {'points':>9} {'dynamic':>8} | {'voxtool SA / DA / AA':>22} "
          f"{'time':>7} | {'DUFOMap SA / DA / AA':>22} {'time':>7}")
    no_ground = dataclasses.replace(params, ground_band=-1.0)
    for scene in REAL_SCENES:
        if words and not any(w in scene.name for w in words):
            continue
        src, labels = scene_source(data, scene)
        if not src.is_dir():
            continue
        folder = tmp / scene.name.replace(" ", "_").replace(",", "").replace("+", "with")
        truth = real_scene(src, folder, scene, labels)
        (vox, vox_s, cleaned), (duf, duf_s) = best_of(repeat, lambda s=folder: run_voxtool(s, params),
                                                     lambda s=folder: run_dufomap(s, params))
        off, _, off_cleaned = min((run_voxtool(folder, no_ground) for _ in range(repeat)), key=lambda r: r[1])
        v, d, g = accuracy(vox, truth), accuracy(duf, truth), accuracy(off, truth)
        picture = out.parent / f"clean_real_{folder.name}.png"
        write_plot(clean_figure(cleaned.points, vox, f"voxtool clean, {scene.name} (0.1 m)", 80.0)[0], picture)
        rows.append({"input": scene.name, "points": int(truth.size), "dynamic_points": int(truth.sum()),
                     "removed_share": {"voxtool": round(float(vox.mean()), 5), "dufomap": round(float(duf.mean()), 5)},
                     "voxtool": {**v, "seconds": vox_s}, "dufomap": {**d, "seconds": duf_s}, "picture": str(picture)})
        scans = cleaned.figures["scans"]
        extra = (cleaned.figures["timings_s"]["classify"] - off_cleaned.figures["timings_s"]["classify"]) / scans
        ground_rows.append({"input": scene.name, "ground_points": cleaned.figures["ground_points"],
                            "ground_judged": {**v, "removed_share": round(float(vox.mean()), 5)},
                            "ground_as_any_surface": {**g, "removed_share": round(float(off.mean()), 5)},
                            "ground_ms_per_scan": round(1000 * extra, 2)})
        print(f"{scene.name:36} {truth.size:>9,} {int(truth.sum()):>8,} | {_score(v['SA'], 6)} {_score(v['DA'], 6)} {_score(v['AA'], 6)} "
              f"{vox_s:6.2f}s | {_score(d['SA'], 6)} {_score(d['DA'], 6)} {_score(d['AA'], 6)} {duf_s:6.2f}s", flush=True)
    print(f"\n{'the ground (voxtool)':36} {'ground':>9} | {'--ground-band -1: SA / DA / AA':>31} {'removed':>8} | "
          f"{'default (0.3 m): SA / DA / AA':>30} {'removed':>8} | {'cost a scan':>11}")
    for r in ground_rows:
        g, v = r["ground_as_any_surface"], r["ground_judged"]
        print(f"{r['input']:36} {r['ground_points']:>9,} | {_score(g['SA'], 13)} {_score(g['DA'], 6)} {_score(g['AA'], 6)} "
              f"{100 * g['removed_share']:7.2f}% | {_score(v['SA'], 12)} {_score(v['DA'], 6)} {_score(v['AA'], 6)} "
              f"{100 * v['removed_share']:7.2f}% | {r['ground_ms_per_scan']:8.1f} ms")
    return rows, ground_rows


def main() -> None:
    from voxtool.clean import CleanParams, accuracy
    from voxtool.synthetic import write_pcd_scans

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--repeat", type=int, default=2, help="runs of each tool per input (alternating); best time kept")
    ap.add_argument("--out", default="bench-results/clean.json")
    ap.add_argument("--only", choices=["real-movers"], help="only the real scans with ray-traced movers")
    ap.add_argument("--scenes", nargs="*", default=None, metavar="WORD",
                    help="only the real scenes whose names hold one of these words (e.g. drifting Udacity)")
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
        real_rows, ground_rows = real_movers(Path(args.data), Path(tmp), out, params, args.repeat, args.scenes)
        rows += real_rows
        if args.only == "real-movers":
            out.write_text(json.dumps({"params": params.__dict__, "rows": rows, "ground": ground_rows}, indent=2))
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
            print(f"{name:32} {truth.size:>9,} {int(truth.sum()):>8,} | {_score(v['SA'], 6)} {_score(v['DA'], 6)} {_score(v['AA'], 6)} "
                  f"{vox_s:6.2f}s | {_score(d['SA'], 6)} {_score(d['DA'], 6)} {_score(d['AA'], 6)} {duf_s:6.2f}s")
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
    out.write_text(json.dumps({"params": params.__dict__, "rows": rows, "ground": ground_rows}, indent=2))
    print(f"\nwritten {out}")


if __name__ == "__main__":
    main()
