"""What reading raw recordings costs: a whole `build` from each against `build` of the same
scans written as PCD (sensor frame, the same poses), and the decoder's own rate.

    python benchmarks/bench_sources.py [--repeats 5]

Inputs (scripts/fetch_samples.py; a missing one is left out of the table): TIER IV nebula's
VLS-128 and VLP-32C packet bags (velodyne-decoder), a pcap of the VLS-128 packets (dpkt writes it
here), pye57's real terrestrial scan as E57, and a 3 M-point survey tile that laspy writes here as
LAS and LAZ from the shared kaist03 scans (no PCD twin: a tile builds its occupied voxels only).
A packet bag is also timed against its scans as PointCloud2 messages in the same kind of bag
(sqlite, types named, not defined): what the decoding itself adds, the bag's own start-up (rosbags
and its type store) being in both. The maps of each pair are checked equal (for the pcap: the
same points; its revolutions are cut where the azimuth wraps). Medians of `repeats` runs
alternating between the commands of an input. Prints a table and writes
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


def _pairs(tmp: Path) -> list[tuple]:
    """(name, build args of the recording, build args of its scans as PCD, points, (path,
    SourceOptions) that read it[, build args of its scans as a PointCloud2 bag]) per input."""
    from voxtool.io.export import pcd_header, pcd_rows
    from voxtool.sources import SourceOptions, open_source

    def as_pcd(scans, folder: Path) -> int:
        folder.mkdir()
        n = 0
        for s in scans:
            (folder / f"{s.index:06d}.pcd").write_bytes(pcd_header(len(s.points), False) + pcd_rows(s.points, None))
            n += len(s.points)
        return n

    def as_cloud_bag(scans, folder: Path, frame: str) -> None:
        """The scans as PointCloud2 messages in a ROS 2 sqlite bag that, as the packet bags, names
        its types without defining them (a bag recorded before Iron): the same container, so the
        two builds differ by the decoding alone."""
        import sqlite3

        sys.path.insert(0, str(ROOT / "tests"))
        from bag_writer import _store, cloud
        from rosbags.rosbag2 import StoragePlugin, Writer

        store = _store("ros2")
        with Writer(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as writer:
            topic = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
            for s in scans:
                msg = cloud(store.types, "ros2", s.points, s.stamp_ns, frame)
                writer.write(topic, s.stamp_ns, store.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
        with sqlite3.connect(next(folder.glob("*.db3"))) as db:
            db.execute("DELETE FROM message_definitions")

    pairs = []
    for sensor, frame in (("vls128", "velodyne_top"), ("vlp32", "velodyne_front")):
        bag = FETCHED / "nebula" / sensor
        if (bag / "metadata.yaml").is_file():
            scans = list(open_source(bag, SourceOptions(world_frame=frame)).scans)
            n = as_pcd(scans, tmp / f"{sensor}_pcd")
            as_cloud_bag(scans, tmp / f"{sensor}_clouds", frame)
            pairs.append((f"{sensor} packet bag", [bag, "--world-frame", frame], [tmp / f"{sensor}_pcd"], n,
                          (bag, SourceOptions(world_frame=frame)), [tmp / f"{sensor}_clouds", "--world-frame", frame]))
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
    shared = ROOT.parent / "shared" / "data" / "kaist03" / "pcd"
    if shared.is_dir():  # a survey tile: kaist03's points in the world, four times side by side, 3 M points
        import laspy

        world = np.concatenate([s.points for s in open_source(shared, SourceOptions()).scans]).astype(np.float64)
        world = np.concatenate([world + [500.0 * k, 0, 0] for k in range(4)])
        for ext in ("las", "laz"):
            header = laspy.LasHeader(point_format=1, version="1.2")
            header.scales, header.offsets = [0.001] * 3, world.min(axis=0)
            tile = laspy.LasData(header)
            tile.x, tile.y, tile.z = world[:, 0], world[:, 1], world[:, 2]
            tile.write(tmp / f"tile.{ext}")
            # no PCD twin: a tile has no sensor origin, so it builds its occupied voxels only
            pairs.append((f"{ext.upper()} tile", [tmp / f"tile.{ext}", "--origin", "auto"], None, len(world),
                          (tmp / f"tile.{ext}", SourceOptions(origin=tuple(header.offsets)))))
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

        for name, recording, pcd, points, (path, options), *clouds in _pairs(tmp):
            reads = []
            for _ in range(args.repeats):  # the decoder alone, in this process
                t0 = time.perf_counter()
                read = sum(len(scan.points) for scan in open_source(path, options).scans)
                reads.append(read / (time.perf_counter() - t0))
            common = ["--resolution", args.resolution]
            a = ["build", *recording, "-o", tmp / "a.vxm", *common]
            b = ["build", *pcd, "-o", tmp / "b.vxm", *common] if pcd else None
            c = ["build", *clouds[0], "-o", tmp / "c.vxm", *common] if clouds else None
            _run(a)  # the kernels and the decoder loaded once before timing
            times = {"recording": [], "pcd": [], "clouds": []}
            for _ in range(args.repeats):
                times["recording"].append(_run(a)[0])
                if b:
                    times["pcd"].append(_run(b)[0])
                if c:
                    times["clouds"].append(_run(c)[0])
            row = {"input": name, "points": points, "build_recording_s": round(float(np.median(times["recording"])), 3),
                   "read_Mpoints_per_s": round(float(np.median(reads)) / 1e6, 2)}
            if b:
                row["build_pcd_s"] = round(float(np.median(times["pcd"])), 3)
                row["recording_vs_pcd"] = round(float(np.median([x / y for x, y in zip(times["recording"],
                                                                                      times["pcd"])])), 3)
                row["maps_equal"] = all(np.array_equal(x, y) for x, y in zip(map_voxels(tmp / "a.vxm"),
                                                                            map_voxels(tmp / "b.vxm")))
            if c:  # the decoding alone: the same scans as clouds in the same bag container
                row["build_clouds_s"] = round(float(np.median(times["clouds"])), 3)
                row["recording_vs_clouds"] = round(float(np.median([x / y for x, y in zip(times["recording"],
                                                                                         times["clouds"])])), 3)
                row["maps_equal"] = row["maps_equal"] and all(
                    np.array_equal(x, y) for x, y in zip(map_voxels(tmp / "a.vxm"), map_voxels(tmp / "c.vxm")))
            rows.append(row)
    print(f"{'input':<22} {'points':>9} {'build it':>9} {'as PCD':>8} {'ratio':>6} {'as clouds':>9} {'ratio':>6} "
          f"{'read Mpt/s':>11} maps equal")
    for r in rows:
        pcd = f"{r['build_pcd_s']:>7.2f}s {r['recording_vs_pcd']:>6.2f}" if "build_pcd_s" in r else f"{'':>8} {'':>6}"
        clouds = (f"{r['build_clouds_s']:>8.2f}s {r['recording_vs_clouds']:>6.2f}" if "build_clouds_s" in r
                  else f"{'':>9} {'':>6}")
        print(f"{r['input']:<22} {r['points']:>9,} {r['build_recording_s']:>8.2f}s {pcd} {clouds} "
              f"{r['read_Mpoints_per_s']:>11} {r.get('maps_equal', '')}")
    OUT.mkdir(exist_ok=True)
    (OUT / "sources.json").write_text(json.dumps({"repeats": args.repeats, "resolution": args.resolution, "rows": rows},
                                                 indent=2))


if __name__ == "__main__":
    main()
