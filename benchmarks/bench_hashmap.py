"""Hash-map backend on quick_shack/pcd (Livox Avia, the sensor of the seed's Urban set) at 0.1 m with
a 0.2 m inflation radius: a Table-I style row per setting, and the relayed map built only from
the shared frames. Rows: n_lim 50,000 or unlimited, inflation range (the paper's Table I `d_inf`
column, `inf_range` here) 8 m as in the paper's rows a-c, or unlimited.

    python benchmarks/bench_hashmap.py [--data ../shared/data] [--out bench-results/hashmap.json] [--repeat 3]
    python benchmarks/bench_hashmap.py --scaling 1 2 4 8 16 [--repeat 3]   # row a against threads only

Last, row a runs as whole `voxtool build` commands idle and beside one busy process, with the
default threads and with --threads 1 (under_load): the default must not be the slower.

--repeat N runs the scan-by-scan measurement N times per row and prints the median of the N
medians with their range: on a shared VM a single run can land in a slow minute. Each row also
times two fixed reference workloads (compute, memory latency; see reference()) just before its
scan-by-scan runs, so that a slow sitting shows as a slow reference rather than passing for a
slower voxtool. The second ray-casting thread spins only briefly between scans
(GOMP_SPINCOUNT=1000, voxtool.parallel), so each scan pays for waking it.

Where the time goes: each row's t_occ (ray casting + input update), t_inf (inflation) and t_m
(history), and for row a the same parts over its slowest 5 % of scans, which set the p95. Then
empty_prefix_bound(): the most that skipping the first, empty part of each ray could save, and
cast_floor(): row a with a ray casting that cost only its DDA steps, the most a faster miss
detection could save while the rest of the update runs on one thread.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from report import write_report

from voxtool.parallel import usable_cores

SETUPS = [(50_000, 8.0), (50_000, -1.0), (-1, 8.0), (-1, -1.0)]


def run(src: Path, n_lim: int, inf_range: float, share: Path) -> dict:
    from voxtool.api import build_map
    from voxtool.codec.logstats import log_stats
    from voxtool.config import MapParams, SensorModel
    from voxtool.sources import SourceOptions

    r = build_map(src, SourceOptions(), MapParams(0.1), SensorModel(), "hashmap", None, False,
                  {"n_lim": n_lim, "d_inf": 0.2, "inf_range": inf_range}, share)
    st = log_stats(share)["robots"]["r1"]
    return {"n_lim": n_lim if n_lim >= 0 else "inf", "inf_range_m": inf_range if inf_range >= 0 else "inf",
            "d_inf_m": 0.2, "points_per_scan": round(r["points"] / r["scans"]), "n_occ": r["n_occ"],
            "n_inf_mean": round(r["per_scan_n_inf"]["mean"]), "t_tot_ms": r["per_scan_t_tot_ms"],
            "t_occ_ms": r["per_scan_t_occ_ms"]["mean"], "t_inf_ms": r["per_scan_t_inf_ms"]["mean"],
            "t_m_ms": r["per_scan_t_m_ms"]["mean"], "memory_max_mb": round(r["per_scan_memory_bytes"]["max"] / 1e6, 1),
            "shared_avg_Bps": st["avg_Bps"], "raw_sensor_Bps": st["raw_sensor_Bps"],
            "bandwidth_reduction": round(1 - st["avg_Bps"] / st["raw_sensor_Bps"], 5)}


def reference() -> dict:
    """How fast the machine runs right now, by two fixed workloads independent of voxtool's code
    (each the best of three): `compute_ms`, 20,000 rays x 500 DDA steps with the axis choice a
    branch, as in the hash map's ray casting (L1-resident); `memory_ns`, one dependent load
    through a random cycle over 16 MB, twice the hash map's memory in row a (8 MB: records,
    tables, bricks), so a sitting whose cache is crowded by other tenants shows up here."""
    import time

    import numpy as np
    from numba import njit

    @njit(cache=True)
    def dda(dirs, nsteps):
        acc = 0
        for i in range(dirs.shape[0]):
            ux, uy, uz = 0.1 / abs(dirs[i, 0]), 0.1 / abs(dirs[i, 1]), 0.1 / abs(dirs[i, 2])
            tx, ty, tz = 0.5 * ux, 0.3 * uy, 0.7 * uz
            for _ in range(nsteps):
                if tx < ty and tx < tz:
                    tx += ux
                    acc += 1
                elif ty < tz:
                    ty += uy
                    acc += 3
                else:
                    tz += uz
                    acc += 7
        return acc

    @njit(cache=True)
    def chase(nxt, hops):
        i = 0
        for _ in range(hops):
            i = nxt[i]
        return i

    d = np.random.default_rng(1).normal(size=(20_000, 3))
    perm = np.random.default_rng(2).permutation(1 << 22).astype(np.int32)
    nxt = np.empty(perm.shape[0], np.int32)
    nxt[perm] = np.roll(perm, -1)  # one cycle through every slot
    dda(d[:2], 2)
    chase(nxt, 2)
    compute = memory = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        dda(d, 500)
        t1 = time.perf_counter()
        chase(nxt, 1_000_000)
        t2 = time.perf_counter()
        compute, memory = min(compute, t1 - t0), min(memory, (t2 - t1) / 1e6)
    return {"compute_ms": round(1e3 * compute, 2), "memory_ns": round(1e9 * memory, 1)}


def scan_by_scan(scans: list, n_lim: int, inf_range: float, threads: int = 0) -> dict:
    """Per-scan latency as a real-time node sees it: each scan already in memory, nothing else
    running (`voxtool build` also reads each scan from disk and, with --share, writes the shared
    frames after it). `threads` as --threads (0: the usable cores)."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps.hashmap import HashVoxelMap

    m = HashVoxelMap(MapParams(0.1), SensorModel(), n_lim=n_lim, d_inf=0.2, inf_range=inf_range, threads=threads)
    m.warm_up()
    for scan in scans:
        m.integrate(scan)
    st = m.extra_stats()
    # the slowest 5 % of scans (those that set the p95), part by part: what a p95 goal must cut.
    # Medians: the mean of so few scans follows the one or two that grew the map's arrays
    parts = {k: np.array([sm[k] for sm in m.scan_metrics]) for k in ("t_tot_ms", "t_occ_ms", "t_inf_ms", "t_m_ms")}
    slow = parts["t_tot_ms"] >= np.percentile(parts["t_tot_ms"], 95)
    return {"t_tot_ms": st["per_scan_t_tot_ms"], "t_occ_ms": st["per_scan_t_occ_ms"]["mean"],
            "t_inf_ms": st["per_scan_t_inf_ms"]["mean"], "t_m_ms": st["per_scan_t_m_ms"]["mean"],
            "slowest_5pct_median_ms": {k: round(float(np.median(v[slow])), 3) for k, v in parts.items()}}


def empty_prefix_bound(scans: list, rays: int = 400) -> dict:
    """The most any method that skips a ray's first steps could save in the hash map's ray
    casting: the share of DDA steps (OctoMap's keys, tests/reference.py) that come before the
    ray first passes within r voxels (any axis) of a voxel of the occupancy map. A skip must
    stop that far ahead to stay exact (a coarse grid of blocks needs r of about a block). Over
    `rays` random rays of the scan two thirds into the log, against the map of the scans before."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.reference import ray_keys
    from voxtool.config import MapParams, SensorModel
    from voxtool.keys import morton_decode
    from voxtool.maps.hashmap import HashVoxelMap

    at = 2 * len(scans) // 3
    m = HashVoxelMap(MapParams(0.1), SensorModel(), n_lim=50_000, d_inf=0.2, inf_range=8.0)
    for scan in scans[:at]:
        m.integrate(scan)
    keys = morton_decode(m._occupancy_map()["code"]).astype(np.int64)
    pad = 16
    lo = keys.min(axis=0) - pad
    grid = np.zeros(keys.max(axis=0) - lo + pad + 1, np.int32)
    grid[tuple((keys - lo).T)] = 1
    table = np.pad(grid, ((1, 0), (1, 0), (1, 0))).cumsum(0).cumsum(1).cumsum(2)  # summed-area table
    scan = m._discretized(m.prepare(scans[at]).scan)
    pick = np.random.default_rng(0).choice(scan.points.shape[0], min(rays, scan.points.shape[0]), replace=False)
    paths = [np.array(ray_keys(scan.origin, scan.points[i], 0.1)[:-1], np.int64).reshape(-1, 3) - lo for i in pick]
    out = {}
    for r in (1, 2, 4, 8):
        before = total = 0
        for a in paths:
            a0 = np.clip(a - r, 0, np.array(grid.shape))
            a1 = np.clip(a + r + 1, 0, np.array(grid.shape))
            near = np.zeros(len(a), np.int64)  # map voxels in the cube of side 2r + 1 round each step
            for corner in range(8):
                c = [a1[:, d] if corner >> d & 1 else a0[:, d] for d in range(3)]
                near += (-1) ** (3 - bin(corner).count("1")) * table[c[0], c[1], c[2]]
            hit = np.flatnonzero(near > 0)
            before += hit[0] if hit.size else len(a)
            total += len(a)
        out[f"r{r}"] = round(before / max(total, 1), 4)
    return out


def cast_floor(scans: list) -> dict:
    """What a scan of row a would take if its ray casting cost only the DDA's steps: before each
    scan, the same distinct end voxels (discretized) are cast on the same threads and cuts by a
    kernel that only steps (no brick look-ups, mask tests, sets, sort or merge; the same step
    count, checked), then the map takes the scan as usual. `floor_scan` = the scan's update
    (everything after the cast, on one thread) + that floor cast: no faster miss detection can
    beat it without the update itself running on more threads. Medians and p95 in ms."""
    import time

    import numba
    from numba import njit, prange

    from voxtool.config import MapParams, SensorModel
    from voxtool.kernels.raycast import _coord_key, balanced_cuts, ray_setup
    from voxtool.maps.hashmap import HashVoxelMap

    @njit(cache=True, nogil=True)
    def dda_steps(points, origin, resolution, max_range):
        res_factor = 1.0 / resolution
        okx, oky, okz = (_coord_key(origin[0], res_factor), _coord_key(origin[1], res_factor),
                         _coord_key(origin[2], res_factor))
        steps = 0
        for i in range(points.shape[0]):
            cut, ekx, eky, ekz, tx, ty, tz, ux, uy, uz, sx, sy, sz, length = ray_setup(
                points, i, origin, okx, oky, okz, resolution, max_range)
            if ekx == okx and eky == oky and ekz == okz:
                continue
            kx, ky, kz = okx, oky, okz
            to_end = abs(ekx - okx) + abs(eky - oky) + abs(ekz - okz)
            while True:  # kernels.hashmap.trace_present's loop, less what it does at each voxel
                steps += 1
                if tx < ty:
                    if tx < tz:
                        kx += sx
                        tx += ux
                    else:
                        kz += sz
                        tz += uz
                elif ty < tz:
                    ky += sy
                    ty += uy
                else:
                    kz += sz
                    tz += uz
                to_end -= 1
                if to_end == 0 and kx == ekx and ky == eky and kz == ekz:
                    break
                if min(tx, min(ty, tz)) > length:
                    break
        return steps

    @njit(cache=True, parallel=True, nogil=True)
    def dda_parts(points, cuts, origin, resolution, max_range, steps):
        for w in prange(cuts.shape[0] - 1):
            steps[w] = dda_steps(points[cuts[w]:cuts[w + 1]], origin, resolution, max_range)

    m = HashVoxelMap(MapParams(0.1), SensorModel(), n_lim=50_000, d_inf=0.2, inf_range=8.0)
    m.warm_up()
    steps = np.zeros(numba.config.NUMBA_NUM_THREADS, np.int64)
    first = m._discretized(scans[0])
    dda_parts(first.points, balanced_cuts(first.points, first.origin, 1), first.origin, 0.1, -1.0, steps)  # compile
    cols = {"t_tot": [], "cast": [], "floor_cast": [], "update": []}
    for scan in scans:
        t0 = time.perf_counter()
        rays = m._discretized(scan)
        parts = m.cast_parts(rays.points.shape[0])
        numba.set_num_threads(parts)
        dda_parts(rays.points, balanced_cuts(rays.points, rays.origin, parts), rays.origin, m.params.resolution,
                  m.params.max_range, steps)
        floor = 1e3 * (time.perf_counter() - t0)
        timing = m.integrate(scan)
        if int(steps[:parts].sum()) != timing.ray_steps:
            raise AssertionError("the floor kernel stepped differently from the map's ray casting")
        t_tot = m.scan_metrics[-1]["t_tot_ms"]
        for k, v in zip(cols, (t_tot, 1e3 * timing.raycast, floor, t_tot - 1e3 * timing.raycast)):
            cols[k].append(v)
    a = {k: np.array(v) for k, v in cols.items()}
    a["floor_scan"] = a["update"] + a["floor_cast"]
    return {k: {"median": round(float(np.median(v)), 3), "p95": round(float(np.percentile(v, 95)), 3)}
            for k, v in a.items()}


def relayed(src: Path, share: Path) -> dict:
    """A receiver's hash map from the shared frames only, against the sender's map."""
    from voxtool.codec.share import relay
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps.hashmap import HashVoxelMap
    from voxtool.pipeline import build
    from voxtool.sources import SourceOptions, open_source

    sender = HashVoxelMap(MapParams(0.1), SensorModel(), d_inf=0.2)
    build(open_source(src, SourceOptions()), sender, progress=False)
    receiver = HashVoxelMap(MapParams(0.1), SensorModel(), d_inf=0.2)
    relay(share, receiver)
    a, b = sender.occupied_codes(), receiver.occupied_codes()
    return {"sender_occupied": int(a.size), "relayed_occupied": int(b.size),
            "relayed_holds": round(np.intersect1d(a, b).size / max(a.size, 1), 6)}


def under_load(src: Path, tmp: str) -> list[dict]:
    """Row a (n_lim 50,000, inflation range 8 m) as whole `voxtool build` commands, idle and
    beside one busy process (a Python busy loop, as another node on the robot's cores would be),
    with the default threads and with --threads 1; `GOMP_SPINCOUNT=300000` is OpenMP's own idle
    spin, voxtool's default before it chose a short one (voxtool.parallel)."""
    import os
    import subprocess
    import sys
    import time

    def build(threads: int, env: dict) -> dict:
        out = subprocess.run([sys.executable, "-m", "voxtool.cli", "build", str(src), "--backend", "hashmap",
                              "--resolution", "0.1", "--param", "n_lim=50000", "--param", "d_inf=0.2", "--param",
                              "inf_range=8", "--threads", str(threads), "-o", str(Path(tmp) / "load.vxm"), "--json",
                              "--no-progress"], capture_output=True, text=True, env={**os.environ, **env}, check=True)
        t = json.loads(out.stdout)["per_scan_t_tot_ms"]
        return {"median_ms": t["median"], "p95_ms": t["p95"]}

    cases = [("default", 0, {}), ("--threads 1", 1, {}), ("default, OpenMP's spin", 0, {"GOMP_SPINCOUNT": "300000"})]
    rows = []
    for load in (False, True):
        busy = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if load else None
        try:
            time.sleep(0.3 if load else 0)
            for name, threads, env in cases:
                runs = sorted((build(threads, env) for _ in range(3)), key=lambda r: r["median_ms"])
                rows.append({"load": "one busy process" if load else "idle", "threads": name, **runs[1]})
        finally:
            if busy is not None:
                busy.kill()
    return rows


def median_run(scans: list, n_lim: int, inf_range: float, repeat: int, threads: int = 0) -> tuple[dict, list]:
    """scan_by_scan `repeat` times: the run with the median median, and each run's median, sorted."""
    runs = sorted((scan_by_scan(scans, n_lim, inf_range, threads) for _ in range(max(repeat, 1))),
                  key=lambda r: r["t_tot_ms"]["median"])
    return runs[len(runs) // 2], [r["t_tot_ms"]["median"] for r in runs]


def scaling(scans: list, threads: list[int], repeat: int) -> list[dict]:
    """Row a scan by scan at each thread count (the ray casting splits its rays over them; the
    rest of a scan's update runs on one thread), with the parts of its slowest 5 % of scans."""
    rows = []
    for t in threads:
        mid, medians = median_run(scans, 50_000, 8.0, repeat, t)
        slow = mid["slowest_5pct_median_ms"]
        rows.append({"threads": t, "median_ms": mid["t_tot_ms"]["median"], "p95_ms": mid["t_tot_ms"]["p95"],
                     "t_occ_ms": mid["t_occ_ms"], "t_inf_ms": mid["t_inf_ms"], "t_m_ms": mid["t_m_ms"],
                     **{f"slowest_5pct_{k}": slow[k] for k in ("t_occ_ms", "t_inf_ms", "t_m_ms")},
                     "median_runs_ms": medians})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--out", default="bench-results/hashmap.json")
    ap.add_argument("--repeat", type=int, default=1, help="scan-by-scan runs per row (median and range printed)")
    ap.add_argument("--scaling", type=int, nargs="+", metavar="THREADS",
                    help="only row a, scan by scan, at each of these thread counts")
    ap.add_argument("--rays-per-part", type=int, help="--scaling: the fewest rays a thread casts (a what-if)")
    args = ap.parse_args()
    from voxtool.maps import hashmap

    if args.rays_per_part:
        hashmap.RAYS_PER_PART = args.rays_per_part
    src = Path(args.data) / "quick_shack" / "pcd"
    from voxtool.sources import SourceOptions, open_source

    scans = list(open_source(src, SourceOptions()).scans)
    if args.scaling:
        print(f"row a scan by scan (n_lim 50 k, 8 m), usable cores {usable_cores()}, "
              f"at least {hashmap.RAYS_PER_PART} rays a thread; ms:")
        rows = scaling(scans, args.scaling, args.repeat)
        write_report(rows, list(rows[0]), args.out, usable_cores=usable_cores(), rays_per_part=hashmap.RAYS_PER_PART)
        return
    rows = []
    print("latency ms: 'build' = in the voxtool build pipeline (reading, --share writing between scans), "
          "'scan' = scan by scan, nothing else running; t_occ / t_inf / t_m are scan-by-scan means")
    print(f"{'n_lim':>7} {'inf_range':>9} {'n_occ':>7} {'n_inf':>7} {'build med':>9} {'p95':>6} {'scan med':>8} "
          f"{'p95':>6} {'t_occ':>6} {'t_inf':>6} {'t_m':>6} {'mem MB':>6} {'shared B/s':>10} {'reduction':>9} {'ref ms':>6} {'ref ns':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        for n_lim, inf_range in SETUPS:
            share = Path(tmp) / f"share_{n_lim}_{inf_range}.mcap"
            row = run(src, n_lim, inf_range, share)
            row["reference"] = reference()
            row["scan_by_scan"], medians = median_run(scans, n_lim, inf_range, args.repeat)
            row["scan_median_runs_ms"] = medians
            if n_lim < 0 and inf_range < 0:
                row.update(relayed(src, share))
            rows.append(row)
            t, q = row["t_tot_ms"], row["scan_by_scan"]
            spread = f" ({medians[0]:.2f}-{medians[-1]:.2f})" if len(medians) > 1 else ""
            print(f"{row['n_lim']:>7} {row['inf_range_m']:>9} {row['n_occ']:>7} {row['n_inf_mean']:>7} "
                  f"{t['median']:>9.2f} {t['p95']:>6.2f} {q['t_tot_ms']['median']:>8.2f} {q['t_tot_ms']['p95']:>6.2f} "
                  f"{q['t_occ_ms']:>6.2f} {q['t_inf_ms']:>6.2f} {q['t_m_ms']:>6.2f} {row['memory_max_mb']:>6} "
                  f"{row['shared_avg_Bps']:>10.0f} {row['bandwidth_reduction']:>9.2%} {row['reference']['compute_ms']:>6.1f} "
                  f"{row['reference']['memory_ns']:>6.1f}{spread}")
    print("ref ms / ns: fixed reference workloads (compute; memory latency over 16 MB) timed before the row's "
          "scan-by-scan runs: lower = the machine ran faster")
    slow = rows[0]["scan_by_scan"]["slowest_5pct_median_ms"]
    print(f"row a, the slowest 5 % of scans (they set the p95), medians: t_tot {slow['t_tot_ms']:.2f} ms, t_occ "
          f"{slow['t_occ_ms']:.2f}, t_inf {slow['t_inf_ms']:.2f}, t_m {slow['t_m_ms']:.2f}")
    bound = empty_prefix_bound(scans)
    rows[0]["empty_prefix_bound"] = bound
    print("steps a ray takes before it first passes within r voxels of a map voxel (the most that skipping a ray's "
          "first steps could save): " + ", ".join(f"r {k[1:]}: {v:.1%}" for k, v in bound.items()))
    floor = cast_floor(scans)
    rows[0]["cast_floor"] = floor
    print("row a with a ray casting that cost only its DDA steps (same rays, threads, steps), ms median / p95: "
          + ", ".join(f"{k} {v['median']:.2f} / {v['p95']:.2f}" for k, v in floor.items()))
    with tempfile.TemporaryDirectory() as tmp:
        loaded = under_load(src, tmp)
    print(f"\nrow a as whole commands (median of 3 runs): {'load':<17} {'threads':<23} {'median ms':>9} {'p95 ms':>7}")
    for r in loaded:
        print(f"{'':44}{r['load']:<17} {r['threads']:<23} {r['median_ms']:>9.2f} {r['p95_ms']:>7.2f}")
    rows.append({"under_load": loaded})
    for r in rows:
        if "relayed_holds" not in r:
            continue
        print(f"relayed map holds {r['relayed_holds']:.2%} of the sender's {r['sender_occupied']} occupied voxels")
    Path(args.out).parent.mkdir(exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
