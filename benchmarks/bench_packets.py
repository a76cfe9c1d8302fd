"""Map-change packet bandwidth: the paper's Fig. 5 sweep and real streams, per scheme and codec.

    python benchmarks/bench_packets.py fig5 [--samples 10]        # synthetic OGMs, hilbert vs RACER bytes
    python benchmarks/bench_packets.py streams [--pcd] [--data ../shared/data]  # real streams, bandwidth table
    python benchmarks/bench_packets.py intervals                  # quick_shack: saving vs packet interval t
    python benchmarks/bench_packets.py throughput                 # encode/decode cells per second
    python benchmarks/bench_packets.py split                      # one stream as two robots: fusion, resend
    python benchmarks/bench_packets.py codecs [--runs 2]          # whole `encode`, zstd vs cm: first run and warm
    python benchmarks/bench_packets.py onboard                    # per packet at the paper's setting, vs its Table IV
    python benchmarks/bench_packets.py disk [--log-mb 120] [--base REV] [--repeats 5]  # stats / merge / decode vs build
    python benchmarks/bench_packets.py long [--scans 141] [--base REV] [--repeats 3]  # the same on a 9,000-packet log

Prints tables and writes bench-results/packets_<mode>.json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT = Path("bench-results")


def fig5(samples: int) -> dict:
    """OGM of N voxels (a near-cubic box), a ratio r of voxels changed (half free, half occupied)
    at random positions; hilbert packet bytes (zlib as the paper, and zstd) vs RACER's
    changed x address-bytes (the paper's rule for its baseline)."""
    from voxtool.codec.packet import address_width, encode_packet

    rows = []
    rng = np.random.default_rng(0)
    for n_vox in (10**4, 10**5, 10**6, 10**7):
        side = round(n_vox ** (1 / 3))
        dims = np.array([side, side, max(1, n_vox // (side * side))])
        cells = int(np.prod(dims))
        width = address_width(dims)
        for ratio in (1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 0.5):
            changed = max(1, int(round(ratio * cells)))
            sizes = {("hilbert", "zlib"): [], ("hilbert", "zstd"): [], ("nested", "cm"): []}
            for _ in range(samples):
                idx = rng.choice(cells, changed, replace=False)
                keys = np.stack([idx % dims[0], (idx // dims[0]) % dims[1], idx // (dims[0] * dims[1])], axis=1) + 1000
                states = (rng.random(changed) < 0.5).astype(np.uint8)
                for scheme, codec in sizes:
                    sizes[scheme, codec].append(len(encode_packet("r", 0, 0, scheme, codec, 0.1, keys, states,
                                                                  box=(np.full(3, 1000), dims))))
            racer = changed * width
            rows.append({"ogm_voxels": cells, "changed_ratio": ratio, "changed": changed, "racer_bytes": racer,
                         "hilbert_zlib_bytes": float(np.mean(sizes["hilbert", "zlib"])),
                         "hilbert_zstd_bytes": float(np.mean(sizes["hilbert", "zstd"])),
                         "nested_cm_bytes": float(np.mean(sizes["nested", "cm"])),
                         "racer_over_hilbert_zlib": round(racer / np.mean(sizes["hilbert", "zlib"]), 3)})
    print(f"{'OGM voxels':>10} {'ratio':>7} {'changed':>9} {'RACER B':>10} {'hilbert zlib B':>14} {'hilbert zstd B':>14} "
          f"{'nested cm B':>12} {'RACER/ours':>10}")
    for r in rows:
        print(f"{r['ogm_voxels']:>10} {r['changed_ratio']:>7g} {r['changed']:>9} {r['racer_bytes']:>10} "
              f"{r['hilbert_zlib_bytes']:>14.0f} {r['hilbert_zstd_bytes']:>14.0f} {r['nested_cm_bytes']:>12.0f} "
              f"{r['racer_over_hilbert_zlib']:>10.2f}")
    return {"samples": samples, "rows": rows}


STREAMS = [("quick_shack", "quick_shack/quick_shack.mcap", 0.1), ("kaist03", "kaist03/kaist03_21scans.mcap", 0.2)]
# the same scans as PCD directories (VIEWPOINT poses, no stamps: 10 Hz assumed), `streams --pcd`
PCD_STREAMS = [("quick_shack/pcd", "quick_shack/pcd", 0.1), ("kaist03/pcd", "kaist03/pcd", 0.2)]
# the paper's Table I pairs each resolution with a sensing range: 0.1 m with 7 m, 0.2 m with 20 m
PAPER_RANGE = {0.1: 7.0, 0.2: 20.0}
# RACER's own message (swarm_exploration/plan_env/msg/ChunkData.msg: uint32[] voxel_adrs, uint8[]
# voxel_occ_, 3 int32 + 2 uint32 + 3 float64 fields, ROS 1 array length prefixes): what the
# paper's Table I measured as "Racer". Computed from the racer log's packets (same changes,
# same packet cuts), 5 bytes per changed voxel plus 52 per message.
RACER_CHUNK_FIXED, RACER_CHUNK_PER_VOXEL = 3 * 4 + 2 * 4 + 3 * 8 + 2 * 4, 4 + 1


def racer_chunk_bandwidth(log: Path) -> dict:
    """Average and 1 s maximum bandwidth of RACER's ChunkData messages for a racer-scheme log."""
    from voxtool.codec.log import read_log
    from voxtool.codec.logstats import _bandwidth, _span
    from voxtool.codec.packet import decode_packet

    meta, messages = read_log(log)
    stamps, sizes = [], []
    for _, _, blob in messages:
        p = decode_packet(blob)
        stamps.append(p.stamp_ns)
        sizes.append(RACER_CHUNK_FIXED + RACER_CHUNK_PER_VOXEL * p.count)
    span = _span(next(iter(meta.values()), {}), stamps)
    return _bandwidth(np.array(stamps), np.array(sizes), span)


SETTINGS = [("hilbert", "zstd"), ("hilbert", "zlib"), ("nested", "zstd"), ("nested", "zlib"), ("nested", "cm"),
            ("racer", "none"), ("racer", "zstd"), ("occupied", "zstd")]


def streams(data: Path, pcd: bool = False) -> dict:
    """Each stream with unlimited sensing range and with the range the paper paired with its
    resolution (dataset name@range): long rays make thin, scattered changes across big boxes."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for (name, rel, res), max_range in [(st, r) for st in (PCD_STREAMS if pcd else STREAMS)
                                            for r in (-1.0, PAPER_RANGE[st[2]])]:
            src = data / rel
            if not src.exists():
                print(f"skip {name}: {src} absent", file=sys.stderr)
                continue
            if max_range >= 0:
                name = f"{name}@{max_range:g}m"
            for scheme, codec in SETTINGS:
                log = Path(tmp) / f"{name.replace('/', '_')}_{scheme}_{codec}.mcap"
                cmd = ["voxtool", "encode", str(src), "-o", str(log), "--resolution", str(res), "--scheme", scheme,
                       "--codec", codec, "--max-range", str(max_range), "--json", "--no-progress"]
                enc = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
                st = json.loads(subprocess.run(["voxtool", "stats", str(log), "--json"], check=True,
                                               capture_output=True, text=True).stdout)
                r = st["robots"]["r1"]
                if scheme == "racer" and codec == "none":
                    chunk = racer_chunk_bandwidth(log)
                    rows.append({"dataset": name, "resolution": res, "max_range_m": max_range, "scheme": "racer-chunk", "codec": "none",
                                 "packets": r["packets"], "avg_Bps": chunk["avg_Bps"], "max_Bps": chunk["max_Bps"],
                                 "bytes_per_changed_voxel": None, "ratio_to_raw_sensor": round(
                                     chunk["avg_Bps"] / r["raw_sensor_Bps"], 6), "raw_sensor_Bps": r["raw_sensor_Bps"]})
                rows.append({"dataset": name, "resolution": res, "max_range_m": max_range, "scheme": scheme, "codec": codec,
                             "packets": r["packets"], "bytes": r["bytes"], "avg_Bps": r["avg_Bps"], "max_Bps": r["max_Bps"],
                             "bytes_per_changed_voxel": r["bytes_per_changed_voxel"],
                             "compression_ratio": r["compression_ratio"], "raw_sensor_Bps": r["raw_sensor_Bps"],
                             "ratio_to_raw_sensor": r["ratio_to_raw_sensor"], "encode_cells_per_s": enc["encode_cells_per_s"]})
    print("racer: our racer scheme (min. address bytes for the map box + 2-bit states, issue's Fig. 5 rule); "
          "racer-chunk: RACER's own ChunkData message (the paper's Table I baseline)")
    print(f"{'dataset':<16} {'scheme':<11} {'codec':<5} {'packets':>7} {'avg B/s':>11} {'max B/s':>11} {'B/changed':>9} "
          f"{'x raw':>9} {'racer/this':>15} {'chunk/this':>15}")
    for r in rows:
        for base, tag in (("racer", "racer"), ("racer-chunk", "chunk")):
            b = next(x for x in rows if x["dataset"] == r["dataset"] and x["scheme"] == base and x["codec"] == "none")
            r[f"{tag}_over_this_avg"] = round(b["avg_Bps"] / r["avg_Bps"], 2)
            r[f"{tag}_over_this_max"] = round(b["max_Bps"] / r["max_Bps"], 2)
        per = f"{r['bytes_per_changed_voxel']:>9.3f}" if r["bytes_per_changed_voxel"] is not None else f"{'':>9}"
        print(f"{r['dataset']:<16} {r['scheme']:<11} {r['codec']:<5} {r['packets']:>7} {r['avg_Bps']:>11.0f} {r['max_Bps']:>11.0f} "
              f"{per} {r['ratio_to_raw_sensor']:>9.4f} {r['racer_over_this_avg']:>7.2f}/{r['racer_over_this_max']:<7.2f} "
              f"{r['chunk_over_this_avg']:>7.2f}/{r['chunk_over_this_max']:<7.2f}")
    return {"rows": rows}


def intervals(data: Path) -> dict:
    """quick_shack at 0.1 m, hilbert/zstd against RACER's ChunkData for packet intervals t: the
    longer changes accumulate, the denser the boxes and the larger the saving (the paper: 0.5 s)."""
    src = data / "quick_shack" / "quick_shack.mcap"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for t in (0.5, 1.0, 2.0, 5.0):
            got = {}
            for scheme, codec in (("hilbert", "zstd"), ("nested", "cm"), ("racer", "none")):
                log = Path(tmp) / f"{scheme}_{t}.mcap"
                subprocess.run(["voxtool", "encode", str(src), "-o", str(log), "--resolution", "0.1", "--scheme", scheme,
                                "--codec", codec, "--max-interval", str(t), "--no-progress"], check=True, capture_output=True)
                st = json.loads(subprocess.run(["voxtool", "stats", str(log), "--json"], check=True,
                                               capture_output=True, text=True).stdout)["robots"]["r1"]
                got[scheme] = st
                if scheme == "racer":
                    got["chunk"] = racer_chunk_bandwidth(log)
            h, c = got["hilbert"], got["nested"]
            rows.append({"max_interval_s": t, "hilbert_avg_Bps": h["avg_Bps"], "hilbert_max_Bps": h["max_Bps"],
                         "hilbert_B_per_changed": h["bytes_per_changed_voxel"],
                         "racer_over_hilbert_avg": round(got["racer"]["avg_Bps"] / h["avg_Bps"], 2),
                         "chunk_over_hilbert_avg": round(got["chunk"]["avg_Bps"] / h["avg_Bps"], 2),
                         "chunk_over_hilbert_max": round(got["chunk"]["max_Bps"] / h["max_Bps"], 2),
                         "cm_B_per_changed": c["bytes_per_changed_voxel"],
                         "chunk_over_cm_avg": round(got["chunk"]["avg_Bps"] / c["avg_Bps"], 2),
                         "chunk_over_cm_max": round(got["chunk"]["max_Bps"] / c["max_Bps"], 2)})
            print(json.dumps(rows[-1]))
    return {"rows": rows}


def split(data: Path) -> dict:
    """One real stream split between two robots: fused map vs the single-robot map, and the
    resend simulation under 30 % loss (+ reordering, duplicates) vs the lossless fusion."""
    from voxtool.codec.fusion import fuse
    from voxtool.codec.resend import simulate

    src = data / "quick_shack" / "quick_shack.mcap"
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        logs = {}
        for robot, args in (("a", ["--stop", "120"]), ("b", ["--start", "120"]), ("single", [])):
            logs[robot] = Path(tmp) / f"{robot}.mcap"
            subprocess.run(["voxtool", "encode", str(src), "-o", str(logs[robot]), "--robot", robot, "--resolution", "0.1",
                            "--no-progress", *args], check=True, capture_output=True)
        fused = fuse([logs["a"], logs["b"]])
        single = fuse([logs["single"]])
        union = np.union1d(fused.codes, single.codes)
        fs = dict(zip(fused.codes.tolist(), fused.states.tolist()))
        ss = dict(zip(single.codes.tolist(), single.states.tolist()))
        agree = sum(1 for c in union.tolist() if fs.get(c, 2) == ss.get(c, 2))
        occ_f = set(fused.codes[fused.states == 1].tolist())
        occ_s = set(single.codes[single.states == 1].tolist())
        rows["fused_vs_single"] = {
            "voxels_union": int(union.size), "same_state": agree, "agreement": round(agree / union.size, 6),
            "occupied_single": len(occ_s), "occupied_fused": len(occ_f), "occupied_both": len(occ_s & occ_f),
            "only_single_known": int(np.setdiff1d(single.codes, fused.codes).size),
            "only_fused_known": int(np.setdiff1d(fused.codes, single.codes).size)}
        sims = []
        for seed in range(3):
            sims.append(simulate([logs["a"], logs["b"]], loss=0.3, seed=seed))
        rows["simulations"] = sims
    print(json.dumps(rows, indent=1))
    return rows


def lossless(data: Path) -> dict:
    """Decode every scheme/codec log of the real streams and compare with the robot's own map."""
    from voxtool.codec.encode import EncodeOptions, encode_stream
    from voxtool.codec.fusion import fuse
    from voxtool.config import MapParams, SensorModel
    from voxtool.keys import expand_leaves
    from voxtool.maps import make_backend
    from voxtool.sources import SourceOptions, open_source

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, rel, res in STREAMS:
            src = data / rel
            for scheme in ("hilbert", "nested", "racer"):
                for codec in ("zstd", "zlib", "none") + (("cm",) if scheme == "nested" else ()):
                    backend = make_backend("octree", MapParams(res), SensorModel())
                    log = Path(tmp) / f"{name}_{scheme}_{codec}.mcap"
                    encode_stream(open_source(src, SourceOptions()), backend, log,
                                  EncodeOptions(scheme=scheme, codec=codec), {}, progress=False)
                    lv = backend.leaves()
                    codes = expand_leaves(lv.codes, lv.depths)
                    states = np.repeat((lv.values > 0).astype(np.uint8), np.left_shift(1, 3 * (16 - lv.depths.astype(np.int64))))
                    got = fuse([log])
                    equal = bool(np.array_equal(got.codes, codes) and np.array_equal(got.states, states))
                    rows.append({"dataset": name, "scheme": scheme, "codec": codec, "voxels": int(codes.size),
                                 "decoded_equals_map": equal})
                    print(json.dumps(rows[-1]))
    return {"rows": rows}


def throughput() -> dict:
    """Encode and decode speed in cells of box volume per second: boxes with 1 % of their cells
    changed at random positions (the hardest case for cm: no structure to learn, every changed
    cell costs its full decisions); hilbert with and without its cell order cached."""
    from voxtool.codec.cm import warm_up
    from voxtool.codec.hilbert import box_order
    from voxtool.codec.packet import decode_packet, encode_packet

    rng = np.random.default_rng(1)
    rows = []
    warm_up()
    for dims in ((200, 200, 100), (400, 300, 90), (512, 512, 64)):
        cells = int(np.prod(dims))
        idx = rng.choice(cells, cells // 100, replace=False)
        keys = np.stack([idx % dims[0], (idx // dims[0]) % dims[1], idx // (dims[0] * dims[1])], axis=1)
        states = rng.integers(0, 2, idx.shape[0]).astype(np.uint8)
        box = (np.zeros(3, np.int64), np.array(dims))
        encode_packet("r", 0, 0, "hilbert", "zstd", 0.1, keys, states, box=box)  # JIT
        for scheme, codec, cached in (("hilbert", "zstd", False), ("hilbert", "zstd", True), ("nested", "zstd", None),
                                      ("nested", "cm", None)):
            if cached is False:
                box_order.cache_clear()
            t0 = time.perf_counter()
            blob = encode_packet("r", 0, 0, scheme, codec, 0.1, keys, states, box=box)
            t1 = time.perf_counter()
            if cached is False:
                box_order.cache_clear()
            decode_packet(blob)
            t2 = time.perf_counter()
            rows.append({"dims": dims, "cells": cells, "scheme": scheme, "codec": codec, "order_cached": cached,
                         "bytes": len(blob), "encode_Mcells_per_s": round(cells / (t1 - t0) / 1e6, 1),
                         "decode_Mcells_per_s": round(cells / (t2 - t1) / 1e6, 1)})
    for r in rows:
        print(r)
    return {"rows": rows}


CODEC_STREAMS = [("kaist03/pcd", 0.2), ("quick_shack/pcd", 0.1), ("norlab/pcd", 0.2)]


def codecs(data: Path, runs: int) -> dict:
    """Whole `voxtool encode` processes, hilbert/zstd against nested/cm, PCD, unlimited range.
    First run: numba's cache in a new empty folder (NUMBA_CACHE_DIR), so every kernel the command
    needs compiles, as on a fresh install; warm: the best of `runs` more, the codecs alternating
    (this machine drifts 20-30 % from one minute to the next)."""
    import os

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rel, res in CODEC_STREAMS:
            src = data / rel
            if not src.exists():
                print(f"skip {rel}: {src} absent", file=sys.stderr)
                continue
            got: dict = {}
            for attempt in range(1 + runs):
                for codec in ("zstd", "cm"):
                    env = dict(os.environ)
                    if attempt == 0:
                        env["NUMBA_CACHE_DIR"] = str(Path(tmp) / f"numba_{rel.replace('/', '_')}_{codec}")
                    log = Path(tmp) / f"{codec}.mcap"
                    cmd = ["voxtool", "encode", str(src), "-o", str(log), "--resolution", str(res), "--codec", codec,
                           "--robot", "r1", "--json", "--no-progress"]
                    t0 = time.perf_counter()
                    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
                    wall = time.perf_counter() - t0
                    rep = json.loads(out)
                    key = "first" if attempt == 0 else "warm"
                    best = got.setdefault((codec, key), {"wall_s": float("inf")})
                    if wall < best["wall_s"]:
                        best.update(wall_s=round(wall, 2), time_encode_s=rep["time_encode_s"], bytes=rep["bytes"])
            for key in ("first", "warm"):
                z, c = got["zstd", key], got["cm", key]
                rows.append({"stream": rel, "resolution": res, "run": key, "zstd_s": z["wall_s"], "cm_s": c["wall_s"],
                             "cm_over_zstd": round(c["wall_s"] / z["wall_s"], 2),
                             "zstd_encode_s": z["time_encode_s"], "cm_encode_s": c["time_encode_s"],
                             "zstd_bytes": z["bytes"], "cm_bytes": c["bytes"]})
    print(f"{'stream':<16} {'run':<5} {'zstd s':>7} {'cm s':>7} {'cm/zstd':>7} {'zstd enc s':>10} {'cm enc s':>8} "
          f"{'zstd bytes':>10} {'cm bytes':>10}")
    for r in rows:
        print(f"{r['stream']:<16} {r['run']:<5} {r['zstd_s']:>7.2f} {r['cm_s']:>7.2f} {r['cm_over_zstd']:>7.2f} "
              f"{r['zstd_encode_s']:>10.2f} {r['cm_encode_s']:>8.2f} {r['zstd_bytes']:>10} {r['cm_bytes']:>10}")
    return {"runs": runs, "rows": rows}


PAPER_TABLE_IV_MS = {"pack": 5.30, "recv2insert": 7.08}  # ogm-sync-hilbert.md, Table IV (onboard computer)


def onboard(data: Path) -> dict:
    """Per packet at the paper's setting: quick_shack's handheld Livox stream (200 scans), 0.1 m,
    7 m range, a packet at 50,000 changes or 0.5 s. pack: the packet from its changed voxels
    (box, Hilbert order, 2-bit payload, zstd, header and CRC); recv2insert: from the received
    bytes to the voxels in the fused map (checks, decompression, cells, Morton codes, the latest-
    state set, whose batch merges show in the p95). One thread, each packet timed alone."""
    from voxtool.api import encode_log
    from voxtool.codec.encode import EncodeOptions
    from voxtool.codec.fusion import LatestStates
    from voxtool.codec.log import read_log
    from voxtool.codec.packet import decode_packet, encode_packet
    from voxtool.config import MapParams, SensorModel
    from voxtool.keys import morton_encode
    from voxtool.sources import SourceOptions

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scheme, codec in (("hilbert", "zstd"), ("nested", "cm")):
            log = Path(tmp) / f"{codec}.mcap"
            encode_log(data / "quick_shack" / "pcd", log, SourceOptions(stop=200), MapParams(resolution=0.1, max_range=7.0),
                       SensorModel(), "octree", {}, EncodeOptions(robot="r1", scheme=scheme, codec=codec,
                                                                  max_changes=50_000, max_interval=0.5), False)
            _, messages = read_log(log)
            blobs = [blob for _, _, blob in messages]
            decoded = [decode_packet(b) for b in blobs]
            for p in decoded[:3]:  # kernels loaded before timing
                encode_packet(p.robot, p.seq, p.stamp_ns, p.scheme, p.codec, p.resolution, p.keys, p.states,
                              box=(np.array(p.box_min), np.array(p.box_dims)))
            pack = []
            for p in decoded:
                t0 = time.perf_counter()
                encode_packet(p.robot, p.seq, p.stamp_ns, p.scheme, p.codec, p.resolution, p.keys, p.states,
                              box=(np.array(p.box_min), np.array(p.box_dims)))
                pack.append(time.perf_counter() - t0)
            latest, recv = LatestStates(), []
            for blob in blobs:
                t0 = time.perf_counter()
                p = decode_packet(blob, ordered=False)
                latest.add(morton_encode(p.keys), p.states)
                recv.append(time.perf_counter() - t0)
            latest.result()
            for stage, times in (("pack", pack), ("recv2insert", recv)):
                ms = np.array(times) * 1e3
                rows.append({"scheme": scheme, "codec": codec, "stage": stage, "packets": len(ms),
                             "median_ms": round(float(np.median(ms)), 4), "p95_ms": round(float(np.percentile(ms, 95)), 4),
                             "paper_ms": PAPER_TABLE_IV_MS[stage],
                             "mean_bytes": round(float(np.mean([len(b) for b in blobs])), 1),
                             "mean_changes": round(float(np.mean([p.count for p in decoded])), 1)})
    print(f"{'scheme/codec':<14} {'stage':<12} {'packets':>7} {'median ms':>10} {'p95 ms':>8} {'paper ms':>9} "
          f"{'bytes':>8} {'changes':>8}")
    for r in rows:
        print(f"{r['scheme'] + '/' + r['codec']:<14} {r['stage']:<12} {r['packets']:>7} {r['median_ms']:>10.3f} "
              f"{r['p95_ms']:>8.3f} {r['paper_ms']:>9.2f} {r['mean_bytes']:>8.0f} {r['mean_changes']:>8.0f}")
    return {"rows": rows, "paper_table_iv_ms": PAPER_TABLE_IV_MS}


def _run(args: list, tree: Path | None = None, stdout: list | None = None) -> tuple[float, float]:
    """A whole voxtool command (of the revision checked out at `tree`, or the installed one):
    (seconds from start to exit, its own peak memory in MiB); what it printed is appended to
    `stdout` if given. It runs in the temporary folder: from the checkout, `python -m` would
    import this checkout's voxtool whatever PYTHONPATH says."""
    import os

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_octree import _LAUNCH

    env = {**os.environ, "PYTHONPATH": str(tree)} if tree is not None else None
    proc = subprocess.run([sys.executable, "-c", _LAUNCH, sys.executable, "-m", "voxtool.cli", *map(str, args),
                           "--no-progress"], capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    wall, rss, code = json.loads(proc.stderr.strip().splitlines()[-1])
    if code != 0:
        raise SystemExit(f"voxtool {' '.join(map(str, args))} failed: {proc.stderr.strip().splitlines()[-2:]}")
    if stdout is not None:
        stdout.append(proc.stdout)
    return wall, rss / 2**20


def _trees(base: str | None, tmp: Path, stack: contextlib.ExitStack) -> list[tuple[str, Path | None]]:
    """[(name, checkout)] to run the commands of: this revision (the installed voxtool, None), and
    before it `base` checked out in a worktree under tmp (removed when the stack closes)."""
    trees: list[tuple[str, Path | None]] = [("now", None)]
    if base is not None:
        sys.path.insert(0, str(Path(__file__).parent))
        from worktree import check_imports, revision

        tree = stack.enter_context(revision(base, tmp))
        check_imports(tree, Path(tempfile.gettempdir()))
        trees.insert(0, (base, tree))
    return trees


def long_log(packets: list, path: Path, megabytes: float) -> float:
    """A log of `megabytes` or more: the packets written again and again as one robot whose
    sequence and stamps go on (headers rewritten, CRCs made anew). Returns its size in MB."""
    import zlib

    from voxtool.codec.log import PacketLogWriter
    from voxtool.codec.packet import HEADER

    size = sum(len(blob) for _, _, blob in packets)
    span = packets[-1][1] - packets[0][1] + 100_000_000
    rounds = max(1, int(np.ceil(megabytes * 1e6 / size)))
    seq = 0
    with PacketLogWriter(path) as writer:
        for k in range(rounds):
            for _, stamp, blob in packets:
                fields = list(HEADER.unpack_from(blob, 0))
                fields[6], fields[7], fields[21] = seq, stamp + k * span, 0
                head = HEADER.pack(*fields)[:-4]
                crc = zlib.crc32(blob[HEADER.size:], zlib.crc32(head))
                writer.write("r1", seq, fields[7], head + crc.to_bytes(4, "little") + blob[HEADER.size:])
                seq += 1
    return path.stat().st_size / 1e6


def disk(data: Path, log_mb: float, base: str | None = None, repeats: int = 5) -> dict:
    """Whole commands on kaist03 at unlimited range (21 scans, hilbert/zstd): encode, stats,
    merge and decode of its log against building the map from the scans, and merge of two robots'
    logs (the first 11 scans and the other 10, encoded apart); then `stats` of a long
    log of `log_mb` MB or more (kaist03's packets over and over), in MB of log a second beyond
    start-up (the same command on a log of one packet). Peak memory of each command's own
    process; medians of `repeats` runs. `base`: the same commands of another revision too (a git
    worktree; each command run once untimed first, so that its kernels are compiled)."""
    from voxtool.codec.log import read_log

    scans = data / "kaist03" / "pcd"
    rows = []
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        tmp = Path(tmp)
        trees = _trees(base, tmp, stack)
        log = tmp / "r1.mcap"
        halves = [tmp / "first", tmp / "second"]  # two robots: scans 0-10 and 11-20, a log each
        files = sorted(scans.glob("*.pcd"))
        for half, part in zip(halves, (files[:11], files[11:])):
            half.mkdir()
            for f in part:
                (half / f.name).symlink_to(f)
        runs: dict[tuple[str, str], list] = {}
        commands_of = {}
        for name, tree in trees:
            commands = commands_of[name] = (("build", ["build", scans, "-o", tmp / "b.vxm"]),
                        ("encode", ["encode", scans, "-o", log, "--robot", "r1"]),
                        ("stats", ["stats", log]), ("merge", ["merge", log, "-o", tmp / "m.vxm"]),
                        ("decode", ["decode", log, "-o", tmp / "d.vxm"]),
                        ("encode 2 robots", ["encode", *halves, "-o", f"{tmp}/"]),
                        ("merge 2 logs", ["merge", tmp / "first.mcap", tmp / "second.mcap", "-o", tmp / "m2.vxm"]))
            for command, args in commands:
                if tree is not None:
                    _run(args, tree)  # compiles the revision's kernels
                runs[(name, command)] = [_run(args, tree)]
        # the rest of the `repeats` runs alternate between commands and revisions, so that the
        # machine's drift (20-30 % between minutes) falls on all of them alike
        for _ in range(repeats - 1):
            for name, tree in trees:
                for command, args in commands_of[name]:
                    runs[(name, command)].append(_run(args, tree))
        for (name, command), times in runs.items():
            rows.append({"revision": name, "command": command,
                         "seconds": round(float(np.median([t for t, _ in times])), 3),
                         "fastest_s": round(min(t for t, _ in times), 3), "runs": len(times),
                         "peak_rss_mib": round(float(np.median([m for _, m in times])), 1),
                         "log_mb": round(log.stat().st_size / 1e6, 2)})
        for name, _ in trees:
            build = runs[(name, "build")]
            for command in ("merge", "decode", "merge 2 logs"):  # item 3: against building from the scans
                pairs = [t / b for (t, _), (b, _) in zip(runs[(name, command)], build)]
                print(f"{name}: {command} / build, median of {len(pairs)} paired runs: {np.median(pairs):.3f}")
        _, messages = read_log(log)
        packets = list(messages)
        size = long_log(packets, tmp / "long.mcap", log_mb)
        long_log(packets[:1], tmp / "one.mcap", 0)  # start-up: the same command on a log of one packet
        for name, tree in trees:
            for plot in ([], ["--plot", tmp / "bw.png"]):
                if plot and tree is not None:
                    continue  # the base's --plot reads as its stats does
                start, _ = _run(["stats", tmp / "one.mcap", *plot], tree)
                seconds, peak = _run(["stats", tmp / "long.mcap", *plot], tree)
                rows.append({"revision": name, "command": f"stats{' --plot' if plot else ''} of a {size:.0f} MB log",
                             "seconds": round(seconds, 3), "start_up_s": round(start, 3), "peak_rss_mib": round(peak, 1),
                             "log_mb": round(size, 1),
                             "MB_per_s_beyond_start_up": round(size / max(seconds - start, 1e-9), 1)})
    print(f"{'revision':<10} {'command':<30} {'seconds':>8} {'fastest':>8} {'log MB':>8} {'peak MiB':>9}")
    for r in rows:
        print(f"{r['revision']:<10} {r['command']:<30} {r['seconds']:>8.2f} {r.get('fastest_s', ''):>8} {r['log_mb']:>8} "
              f"{r['peak_rss_mib']:>9}"
              + (f"   {r['MB_per_s_beyond_start_up']} MB/s beyond start-up ({r['start_up_s']} s)"
                 if "MB_per_s_beyond_start_up" in r else ""))
    return {"rows": rows}


def replay_scans(src: Path, out: Path, scans: int, lap_m: float) -> None:
    """A long drive from a short one: the PCD scans of `src` (sensor frame, VIEWPOINT poses)
    written again lap after lap until there are `scans`, each lap `lap_m` further along the
    drive's direction (first to last viewpoint, level), so that every lap maps new ground."""
    from voxtool.io.export import pcd_header, pcd_rows
    from voxtool.sources.pcd import read_pcd

    clouds = [read_pcd(f) for f in sorted(src.glob("*.pcd"))]
    first, last = np.array(clouds[0].viewpoint[:3]), np.array(clouds[-1].viewpoint[:3])
    ahead = last - first
    ahead[2] = 0
    ahead /= np.linalg.norm(ahead)
    out.mkdir(parents=True, exist_ok=True)
    for i in range(scans):
        cloud = clouds[i % len(clouds)]
        viewpoint = list(cloud.viewpoint)
        viewpoint[:3] = list(np.array(viewpoint[:3]) + (i // len(clouds)) * lap_m * ahead)
        xyz = np.asarray(cloud.xyz, np.float32)
        (out / f"{i:06d}.pcd").write_bytes(pcd_header(len(xyz), False, False, tuple(viewpoint)) + pcd_rows(xyz, None))


CODECS = {"zstd": ["--scheme", "hilbert", "--codec", "zstd"], "cm": ["--scheme", "nested", "--codec", "cm"]}


def long(data: Path, scans: int = 141, lap_m: float = 180.0, base: str | None = None, repeats: int = 3,
         only: str | None = None) -> dict:
    """Whole commands at 0.2 m and unlimited range on two streams: a long drive (kaist03's 21
    Ouster scans replayed `scans` long, each lap `lap_m` further on: ~9,400 zstd packets, 48 MB)
    and kaist03 itself. Per codec (hilbert/zstd, nested/cm): `encode --json` (its time_encode_s
    against its time_map_s), `merge` and `decode` of the log against `build` of the same scans
    (ratios paired run by run, medians), and `stats`. Then, on the long drive only, per-packet
    costs against the log's length (encode and merge of its first third, two thirds, all).
    `base`: the same commands of another revision too, run alternately with this one's. `only`:
    one of the two streams."""
    rows, growth = [], []
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        tmp = Path(tmp)
        trees = _trees(base, tmp, stack)
        streams = {"long": tmp / "long", "kaist03": data / "kaist03" / "pcd"}
        streams = {k: v for k, v in streams.items() if only in (None, k)}
        if "long" in streams:
            replay_scans(data / "kaist03" / "pcd", streams["long"], scans, lap_m)
        common = ["--resolution", "0.2", "--robot", "r1"]
        commands = []
        for stream, scans_dir in streams.items():
            commands.append((stream, "build", ["build", scans_dir, "--resolution", "0.2", "-o", tmp / "b.vxm"]))
            for codec, flags in CODECS.items():
                log = tmp / f"{stream}_{codec}.mcap"
                commands += [(stream, f"encode {codec}", ["encode", scans_dir, "-o", log, *common, *flags, "--json"]),
                             (stream, f"stats {codec}", ["stats", log]),
                             (stream, f"merge {codec}", ["merge", log, "-o", tmp / "m.vxm"]),
                             (stream, f"decode {codec}", ["decode", log, "-o", tmp / "d.vxm"])]
        runs: dict[tuple, list] = {}
        encode_json: dict[tuple, list] = {}
        for _, tree in trees:  # one stream's commands once, untimed: every revision's kernels compiled
            for stream, _, args in commands:
                if stream == list(streams)[-1]:
                    _run(args, tree)
        # the runs alternate between commands and revisions, so that the machine's drift
        # (20-30 % between minutes) falls on all of them alike
        for _ in range(repeats):
            for name, tree in trees:
                for stream, command, args in commands:
                    out: list = []
                    runs.setdefault((name, stream, command), []).append(_run(args, tree, out))
                    if command.startswith("encode"):
                        encode_json.setdefault((name, stream, command), []).append(json.loads(out[-1]))
        for name, _ in trees:
            for stream in streams:
                build = runs[(name, stream, "build")]
                for stream_, command, _args in commands:
                    if stream_ != stream:
                        continue
                    times = runs[(name, stream, command)]
                    row = {"revision": name, "stream": stream, "command": command,
                           "seconds": round(float(np.median([t for t, _ in times])), 3), "runs": len(times),
                           "peak_rss_mib": round(float(np.median([m for _, m in times])), 1)}
                    if command.startswith(("merge", "decode")):
                        row["vs_build"] = round(float(np.median([t / b for (t, _), (b, _) in zip(times, build)])), 3)
                        row["memory_vs_build"] = round(float(np.median([m / b for (_, m), (_, b) in zip(times, build)])), 3)
                    if command.startswith("encode"):
                        reports = encode_json[(name, stream, command)]
                        row.update(time_map_s=round(float(np.median([r["time_map_s"] for r in reports])), 3),
                                   time_encode_s=round(float(np.median([r["time_encode_s"] for r in reports])), 3),
                                   encode_vs_map=round(float(np.median([r["time_encode_s"] / r["time_map_s"]
                                                                        for r in reports])), 3),
                                   packets=reports[-1]["packets"], log_mb=round(reports[-1]["bytes"] / 1e6, 2))
                    rows.append(row)
        # per packet against the log's length (this revision only): the first third, two thirds, all
        files = sorted(streams["long"].glob("*.pcd")) if "long" in streams else []
        for share in (1 / 3, 2 / 3, 1.0) if files else ():
            part = tmp / f"part{share:.2f}"
            part.mkdir()
            for f in files[:max(1, round(share * len(files)))]:
                (part / f.name).symlink_to(f)
            for codec, flags in CODECS.items():
                out = []
                log = tmp / f"part_{codec}.mcap"
                _run(["encode", part, "-o", log, *common, *flags, "--json"], None, out)
                report = json.loads(out[-1])
                merge_s, _ = _run(["merge", log, "-o", tmp / "m.vxm"])
                growth.append({"scans": len(list(part.iterdir())), "codec": codec, "packets": report["packets"],
                               "log_mb": round(report["bytes"] / 1e6, 2),
                               "encode_ms_per_packet": round(1e3 * report["time_encode_s"] / report["packets"], 3),
                               "map_ms_per_scan": round(1e3 * report["time_map_s"] / report["scans"], 2),
                               "merge_ms_per_packet": round(1e3 * merge_s / report["packets"], 3)})
    print(f"{'revision':<10} {'stream':<8} {'command':<13} {'seconds':>8} {'peak MiB':>9}  figure")
    for r in rows:
        figure = ""
        if "encode_vs_map" in r:
            figure = (f"encode {r['time_encode_s']:.2f} s vs map {r['time_map_s']:.2f} s ({r['encode_vs_map']:.2f}x), "
                      f"{r['packets']} packets, {r['log_mb']} MB")
        elif "vs_build" in r:
            figure = f"{r['vs_build']:.2f}x build's time, {r['memory_vs_build']:.2f}x its memory"
        print(f"{r['revision']:<10} {r['stream']:<8} {r['command']:<13} {r['seconds']:>8.2f} {r['peak_rss_mib']:>9.0f}  {figure}")
    print(f"\n{'scans':>6} {'codec':<5} {'packets':>8} {'log MB':>7} {'encode ms/packet':>17} {'map ms/scan':>12} "
          f"{'merge ms/packet':>16}")
    for g in growth:
        print(f"{g['scans']:>6} {g['codec']:<5} {g['packets']:>8} {g['log_mb']:>7} {g['encode_ms_per_packet']:>17} "
              f"{g['map_ms_per_scan']:>12} {g['merge_ms_per_packet']:>16}")
    return {"scans": scans, "lap_m": lap_m, "repeats": repeats, "rows": rows, "per_packet_by_length": growth}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=["fig5", "streams", "intervals", "throughput", "split", "lossless", "codecs",
                                     "onboard", "disk", "long"])
    ap.add_argument("--log-mb", type=float, default=120.0, help="disk: the long log's size for `stats`")
    ap.add_argument("--base", default=None, help="disk, long: also run the commands of this git revision (before/after)")
    ap.add_argument("--repeats", type=int, default=None,
                    help="disk, long: runs of each command (the median is reported; default 5 and 3)")
    ap.add_argument("--scans", type=int, default=141, help="long: scans of the long drive (141: ~9,400 packets)")
    ap.add_argument("--only", choices=["long", "kaist03"], default=None, help="long: one of its two streams")
    ap.add_argument("--samples", type=int, default=10)
    ap.add_argument("--runs", type=int, default=2, help="codecs: warm runs of each codec (the best is kept)")
    ap.add_argument("--pcd", action="store_true", help="streams: the PCD directories instead of the MCAP files")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    args = ap.parse_args()
    result = {"fig5": lambda: fig5(args.samples), "streams": lambda: streams(Path(args.data), args.pcd),
              "intervals": lambda: intervals(Path(args.data)), "throughput": throughput,
              "split": lambda: split(Path(args.data)), "lossless": lambda: lossless(Path(args.data)),
              "codecs": lambda: codecs(Path(args.data), args.runs), "onboard": lambda: onboard(Path(args.data)),
              "disk": lambda: disk(Path(args.data), args.log_mb, args.base, args.repeats or 5),
              "long": lambda: long(Path(args.data), args.scans, base=args.base, repeats=args.repeats or 3,
                                   only=args.only)}[args.mode]()
    OUT.mkdir(exist_ok=True)
    suffix = "_pcd" if args.pcd and args.mode == "streams" else ""
    (OUT / f"packets_{args.mode}{suffix}.json").write_text(json.dumps(result, indent=2, default=str))


if __name__ == "__main__":
    main()
