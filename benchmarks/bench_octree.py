"""voxtool's octree backend against OctoMap C++ (pyoctomap) on the same scans, in one run.

Per dataset: OctoMap 1.10 inserts every scan (its insertion time, as OctoMap users time it);
then the whole `voxtool build SCANS --resolution R -o map.vxm` command runs, timed from start to
exit as a user waits for it, at each thread count asked for. Every process's peak resident
memory is its own (os.wait4). The maps must be identical: voxtool's snapshot and OctoMap's .bt
are compared voxel by voxel (occupied and free sets at the finest resolution). Prints a table
and writes JSON.

    python benchmarks/bench_octree.py [--data ../shared/data] [--only kaist03] [--threads 1 2]
                                      [--repeat 2] [--octomap-repeat 1] [--out bench-results/octree.json]
    python benchmarks/bench_octree.py --scale [--octomap-limit 60] [--out bench-results/octree_scale.json]

--scale: how cost grows with the work. Per dataset, the whole command against the number of
scans (a quarter, half, three quarters, all, at the reference resolution) and against the
resolution (all scans, coarser and finer), with where its time goes (build --json's phases), ray
steps, leaves and peak memory; OctoMap's insertion where its time, predicted from the row before
by ray steps, stays under --octomap-limit seconds. A table, JSON and a plot (time against ray
steps, memory against leaves).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from report import write_report

DATASETS = [("kaist03", 0.2), ("quick_shack", 0.1), ("norlab", 0.2)]
SCALE_RESOLUTIONS = {"kaist03": (0.4, 0.2, 0.1), "quick_shack": (0.2, 0.1, 0.05), "norlab": (0.4, 0.2, 0.1)}


def octomap_worker(source: str, res: float, out: str, stop: int = -1) -> None:
    """OctoMap's insertion of every scan (reading not timed; before scan `stop` when >= 0);
    writes its .bt and a JSON."""
    import pyoctomap

    from voxtool.sources import SourceOptions, open_source

    tree = pyoctomap.OcTree(res)
    insert = 0.0
    for scan in open_source(source, SourceOptions(stop=stop if stop >= 0 else None)).scans:
        pts = scan.points.astype(np.float64)
        origin = scan.origin.astype(np.float64)
        t0 = time.perf_counter()
        tree.insertPointCloud(pts, origin)
        insert += time.perf_counter() - t0
    tree.writeBinary(out)
    Path(out + ".json").write_text(json.dumps({"insert_s": insert, "memory_bytes": int(tree.memoryUsage())}))


# A small launcher between this process and the timed command: a child's peak RSS (ru_maxrss)
# starts from its parent's at fork, and this process holds hundreds of MB of voxel sets.
_LAUNCH = """import json, os, sys, time
t0 = time.perf_counter()
pid = os.fork()
if pid == 0:
    os.execvp(sys.argv[1], sys.argv[1:])
_, status, usage = os.wait4(pid, 0)
print(json.dumps([time.perf_counter() - t0, usage.ru_maxrss * 1024, os.waitstatus_to_exitcode(status)]), file=sys.stderr)
"""


def run_timed(cmd: list[str]) -> tuple[float, int, str]:
    """(wall seconds from start to exit, peak RSS bytes, stdout) of a command."""
    proc = subprocess.run([sys.executable, "-c", _LAUNCH, *cmd], capture_output=True, text=True)
    lines = proc.stderr.strip().splitlines()
    wall, rss, code = json.loads(lines[-1]) if lines else (0.0, 0, proc.returncode)
    if code != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {lines[-2] if len(lines) > 1 else code}")
    return wall, rss, proc.stdout


def datasets(args):
    """(name, reference resolution, PCD directory) of each dataset asked for that is present."""
    for name, res in DATASETS:
        if args.only and name not in args.only:
            continue
        source = Path(args.data) / name / "pcd"
        if not source.is_dir():
            print(f"skip {name}: {source} absent", file=sys.stderr)
            continue
        yield name, res, source


def fastest_build(args, build_args: list[str]) -> tuple[float, int, dict]:
    """(wall seconds, peak RSS bytes, build --json) of the fastest of --repeat runs of
    `voxtool build BUILD_ARGS --json`."""
    best = None
    for _ in range(args.repeat):
        wall, rss, text = run_timed([*shlex.split(args.voxtool), "build", *build_args, "--json", "--no-progress"])
        if best is None or wall < best[0]:
            best = (wall, rss, json.loads(text))
    return best


def voxel_sets(occupied_codes, occupied_depths, free_codes, free_depths):
    from voxtool.keys import expand_leaves

    return expand_leaves(occupied_codes, occupied_depths), expand_leaves(free_codes, free_depths)


def bt_voxels(path: Path):
    from voxtool.io.bt import read_bt

    t = read_bt(path)
    return voxel_sets(t.codes[t.occupied], t.depths[t.occupied], t.codes[~t.occupied], t.depths[~t.occupied])


def vxm_voxels(path: Path):
    from voxtool.io.mapfile import load_map

    m, _ = load_map(path)
    lv = m.leaves()
    occ = lv.values > np.float32(m.sensor.threshold_log)
    return voxel_sets(lv.codes[occ], lv.depths[occ], lv.codes[~occ], lv.depths[~occ])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--only", nargs="*", help="dataset names to run")
    ap.add_argument("--threads", nargs="*", type=int, default=[0],
                    help="voxtool thread counts (0: all cores; -1: no --threads option, for older voxtools)")
    ap.add_argument("--repeat", type=int, default=2, help="voxtool runs per thread count (the fastest counts)")
    ap.add_argument("--octomap-repeat", type=int, default=1,
                    help="OctoMap insertions per dataset (the fastest counts, as --repeat for voxtool)")
    ap.add_argument("--voxtool", default="voxtool", help="the voxtool command to time (split like a shell line)")
    ap.add_argument("--out", default="bench-results/octree.json")
    ap.add_argument("--scale", action="store_true", help="time and memory against scans and resolution")
    ap.add_argument("--octomap-limit", type=float, default=60.0,
                    help="--scale: run OctoMap where its predicted insertion time is below this (s)")
    ap.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        octomap_worker(args.worker[0], float(args.worker[1]), args.worker[2], int(args.worker[3]))
        return
    if args.scale:
        scale(args)
        return
    out_dir = Path(args.out).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, res, source in datasets(args):
        om_bt = out_dir / f"{name}_octomap.bt"
        om_rss, insert_times = 0, []
        for _ in range(args.octomap_repeat):  # OctoMap's own time varies (quick_shack: 7.5-15.7 s in one day)
            _, rss, _ = run_timed([sys.executable, __file__, "--worker", str(source), str(res), str(om_bt), "-1"])
            om_rss = max(om_rss, rss)
            insert_times.append(json.loads(Path(str(om_bt) + ".json").read_text())["insert_s"])
        om = {"insert_s": min(insert_times)}
        want_occ, want_free = bt_voxels(om_bt)
        for threads in args.threads:
            vxm = out_dir / f"{name}_t{threads}.vxm"
            wall, rss, built = fastest_build(args, [str(source), "--resolution", str(res), "-o", str(vxm),
                                                     *(["--threads", str(threads)] if threads >= 0 else [])])
            got_occ, got_free = vxm_voxels(vxm)
            t = built["timings_s"]
            rows.append({
                "dataset": name, "resolution": res, "threads": built.get("threads", threads),
                "octomap_insert_s": round(om["insert_s"], 3), "octomap_insert_runs_s": [round(x, 3) for x in insert_times],
                "voxtool_command_s": round(wall, 3),
                "speedup": round(om["insert_s"] / wall, 2),
                "voxtool_loop_s": round(t["total"], 3), "voxtool_jit_s": round(t["jit"], 3),
                "ray_steps_per_s": round(built["ray_steps"] / max(t["raycast"], 1e-9)),
                "updates_per_s": round(built["voxel_updates"] / max(t["update"], 1e-9)),
                "voxtool_peak_rss_mib": round(rss / 2**20, 1), "octomap_peak_rss_mib": round(om_rss / 2**20, 1),
                "occupied_voxels": int(got_occ.size), "free_voxels": int(got_free.size),
                "occupied_differ": int(np.setxor1d(got_occ, want_occ).size),
                "free_differ": int(np.setxor1d(got_free, want_free).size),
            })
            print(json.dumps(rows[-1]), file=sys.stderr)
    cols = ["dataset", "threads", "octomap_insert_s", "voxtool_command_s", "speedup", "voxtool_loop_s",
            "ray_steps_per_s", "updates_per_s", "octomap_peak_rss_mib", "voxtool_peak_rss_mib", "occupied_voxels",
            "occupied_differ", "free_voxels", "free_differ"]
    print(f"wrote {write_report(rows, cols, args.out, machine=os.uname().nodename, cpus=os.cpu_count())}")


def scale(args) -> None:
    out_dir = Path(args.out).parent
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, ref, source in datasets(args):
        n = len(list(source.glob("*.pcd")))
        configs = [("scans", ref, max(1, round(n * q / 4))) for q in (1, 2, 3, 4)]
        configs += [("resolution", res, n) for res in SCALE_RESOLUTIONS[name] if res != ref]
        last_om = None  # (insert seconds, ray steps) of OctoMap's last run: predicts the next
        for axis, res, stop in configs:
            vxm = out_dir / f"{name}_scale.vxm"
            wall, rss, built = fastest_build(args, [str(source), "--resolution", str(res), "--stop", str(stop),
                                                     "-o", str(vxm)])
            t = built["timings_s"]
            steps = built["ray_steps"]
            row = {"dataset": name, "axis": axis, "resolution": res, "scans": built["scans"], "ray_steps": steps,
                   "voxel_updates": built["voxel_updates"], "leaves": built["logodds_leaf_nodes"],
                   "command_s": round(wall, 3), "ns_per_step": round(wall / steps * 1e9, 2),
                   "loop_ns_per_step": round(t["total"] / steps * 1e9, 2), "peak_rss_mib": round(rss / 2**20, 1),
                   "bytes_per_leaf": round(rss / max(built["logodds_leaf_nodes"], 1), 1),
                   **{f"{k}_s": t[k] for k in ("startup", "open", "jit", "total", "stats", "write")},
                   # the loop's phases, each summed over the scans (they overlap: read and cast
                   # scan i+1 on a helper thread while scan i updates the map)
                   **{f"loop_{k}_s": t[k] for k in ("read", "raycast", "update")},
                   "octomap_insert_s": None, "octomap_peak_rss_mib": None, "speedup": None}
            row["exit_and_rest_s"] = round(wall - sum(t[k] or 0 for k in ("startup", "open", "jit", "total", "stats",
                                                                            "write")), 3)
            predicted = last_om[0] * steps / last_om[1] if last_om else 0.0
            if predicted <= args.octomap_limit:
                om_bt = out_dir / f"{name}_scale_octomap.bt"
                _, om_rss, _ = run_timed([sys.executable, __file__, "--worker", str(source), str(res), str(om_bt),
                                          str(stop)])
                om = json.loads(Path(str(om_bt) + ".json").read_text())
                last_om = (om["insert_s"], steps)
                row.update(octomap_insert_s=round(om["insert_s"], 3), octomap_peak_rss_mib=round(om_rss / 2**20, 1),
                           speedup=round(om["insert_s"] / wall, 2))
            rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    cols = ["dataset", "resolution", "scans", "ray_steps", "leaves", "command_s", "ns_per_step", "loop_ns_per_step",
            "startup_s", "total_s", "loop_read_s", "loop_raycast_s", "loop_update_s", "stats_s", "write_s",
            "exit_and_rest_s", "peak_rss_mib", "bytes_per_leaf", "octomap_insert_s", "octomap_peak_rss_mib", "speedup"]
    out = write_report(rows, cols, args.out if args.out != "bench-results/octree.json" else "bench-results/octree_scale.json",
                       machine=os.uname().nodename, cpus=os.cpu_count())
    plot_scale(rows, out.with_suffix(".png"))
    print(f"wrote {out} and {out.with_suffix('.png')}")


def plot_scale(rows: list[dict], path: Path) -> None:
    """Whole-command and scan-loop time against ray steps, peak memory against leaves, per dataset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (tim, mem) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, name in enumerate(dict.fromkeys(r["dataset"] for r in rows)):
        mine = sorted((r for r in rows if r["dataset"] == name), key=lambda r: r["ray_steps"])
        colour = f"C{i}"
        steps = [r["ray_steps"] for r in mine]
        tim.plot(steps, [r["command_s"] for r in mine], "o-", color=colour, label=f"{name}: whole command")
        tim.plot(steps, [r["total_s"] for r in mine], "s--", color=colour, label=f"{name}: scan loop")
        om = [(r["ray_steps"], r["octomap_insert_s"]) for r in mine if r["octomap_insert_s"]]
        if om:
            tim.plot(*zip(*om), "x:", color=colour, label=f"{name}: OctoMap insertion")
        by_leaves = sorted(mine, key=lambda r: r["leaves"])
        mem.plot([r["leaves"] for r in by_leaves], [r["peak_rss_mib"] for r in by_leaves], "o-", color=colour,
                 label=name)
    for ax, xlabel, ylabel in ((tim, "ray steps", "seconds"), (mem, "leaves of the map", "peak RSS (MiB)")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    tim.set_title("time against the work (scans and resolution)", fontsize=10)
    mem.set_title("memory against the map", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
