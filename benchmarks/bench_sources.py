"""What reading raw recordings costs: a whole `build` from each against `build` of the same
scans written as PCD (sensor frame, the same poses), and the decoder's own rate.

    python benchmarks/bench_sources.py [--repeats 5]

Inputs (scripts/fetch_samples.py; a missing one is left out of the table): TIER IV nebula's
VLS-128 and VLP-32C packet bags (velodyne-decoder), a pcap of the VLS-128 packets (dpkt writes it
here), and pye57's real terrestrial scan as E57. The maps of each pair are checked equal
(for the pcap: the same points; its revolutions are cut where the azimuth wraps). Medians of
`repeats` runs alternating between the two commands of a pair. Prints a table and writes
bench-results/sources.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FETCHED = ROOT / ".fetched"
OUT = Path("bench-results")


def _pairs(tmp: Path) -> list[tuple[str, list, list, int, tuple]]:
    """(name, build args of the recording, build args of its scans as PCD, points, (path,
    SourceOptions) that read it) per input."""
    from voxtool.io.export import pcd_header, pcd_rows
    from voxtool.sources import SourceOptions, open_source

    def as_pcd(scans, folder: Path) -> int:
        folder.mkdir()
        n = 0
        for s in scans:
            (folder / f"{s.index:06d}.pcd").write_bytes(pcd_header(len(s.points), False) + pcd_rows(s.points, None))
            n += len(s.points)
        return n

    pairs = []
    for sensor, frame in (("vls128", "velodyne_top"), ("vlp32", "velodyne_front")):
        bag = FETCHED / "nebula" / sensor
        if (bag / "metadata.yaml").is_file():
            scans = list(open_source(bag, SourceOptions(world_frame=frame)).scans)
            n = as_pcd(scans, tmp / f"{sensor}_pcd")
            pairs.append((f"{sensor} packet bag", [bag, "--world-frame", frame], [tmp / f"{sensor}_pcd"], n,
                          (bag, SourceOptions(world_frame=frame))))
    bag = FETCHED / "nebula" / "vls128"
    if (bag / "metadata.yaml").is_file():
        sys.path.insert(0, str(ROOT / "tests"))
        from test_velodyne import _capture

        capture = _capture(bag, tmp / "vls128.pcap", "pcap")
        poses = tmp / "identity.txt"
        scans = list(open_source(capture, SourceOptions(sensor_frame=True)).scans)
        poses.write_text("".join(f"{s.stamp_ns / 1e9:.9f} 0 0 0 0 0 0 1\n" for s in scans))
        n = as_pcd(scans, tmp / "pcap_pcd")
        pairs.append(("vls128 pcap", [capture, "--poses", poses], [tmp / "pcap_pcd"], n,
                      (capture, SourceOptions(sensor_frame=True))))
    e57 = FETCHED / "e57" / "pumpAVisualReferenceImage.e57"
    if e57.is_file():
        scans = list(open_source(e57, SourceOptions()).scans)
        n = as_pcd(scans, tmp / "e57_pcd")
        pairs.append(("E57 terrestrial scan", [e57], [tmp / "e57_pcd"], n, (e57, SourceOptions())))
    return pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--resolution", default="0.1")
    args = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).parent))
    from bench_packets import _run

    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import map_voxels

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        from voxtool.sources import open_source

        for name, recording, pcd, points, (path, options) in _pairs(tmp):
            reads = []
            for _ in range(args.repeats):  # the decoder alone, in this process
                t0 = time.perf_counter()
                read = sum(len(scan.points) for scan in open_source(path, options).scans)
                reads.append(read / (time.perf_counter() - t0))
            common = ["--resolution", args.resolution]
            a = ["build", *recording, "-o", tmp / "a.vxm", *common]
            b = ["build", *pcd, "-o", tmp / "b.vxm", *common]
            _run(a), _run(b)  # the kernels and the decoder loaded once before timing
            times = {"recording": [], "pcd": []}
            for _ in range(args.repeats):
                times["recording"].append(_run(a)[0])
                times["pcd"].append(_run(b)[0])
            same = all(np.array_equal(x, y) for x, y in zip(map_voxels(tmp / "a.vxm"), map_voxels(tmp / "b.vxm")))
            ratio = float(np.median([x / y for x, y in zip(times["recording"], times["pcd"])]))
            rows.append({"input": name, "points": points, "build_recording_s": round(float(np.median(times["recording"])), 3),
                         "build_pcd_s": round(float(np.median(times["pcd"])), 3), "recording_vs_pcd": round(ratio, 3),
                         "read_Mpoints_per_s": round(float(np.median(reads)) / 1e6, 2), "maps_equal": same})
    print(f"{'input':<22} {'points':>9} {'build it':>9} {'as PCD':>8} {'ratio':>6} {'read Mpt/s':>11} maps equal")
    for r in rows:
        print(f"{r['input']:<22} {r['points']:>9,} {r['build_recording_s']:>8.2f}s {r['build_pcd_s']:>7.2f}s "
              f"{r['recording_vs_pcd']:>6.2f} {r.get('read_Mpoints_per_s', ''):>11} {r['maps_equal']}")
    OUT.mkdir(exist_ok=True)
    (OUT / "sources.json").write_text(json.dumps({"repeats": args.repeats, "resolution": args.resolution, "rows": rows},
                                                 indent=2))


if __name__ == "__main__":
    main()
