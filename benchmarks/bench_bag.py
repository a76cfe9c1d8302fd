"""A long ROS 2 or ROS 1 bag at full sensor rate: does `voxtool build` stream it in bounded
memory, at a steady speed?

    python benchmarks/bench_bag.py [--data ../shared/data] [--scans 2000] [--resolution 0.5]
                                   [--bag bench-results/long.mcap] [--out bench-results/bag.json]
    python benchmarks/bench_bag.py --bag bench-results/long.bag --out bench-results/bag1.json   # ROS 1

The bag: kaist03's 21 real Ouster OS1-64 scans (../shared/data/kaist03/pcd, sensor frame)
played in turn at 10 Hz until `--scans` messages, each pass moved 4 m further round a circle of
radius 20 m (so the map keeps growing slowly, as on a robot that revisits its area), as
sensor_msgs/msg/PointCloud2 on /points with a /tf world -> lidar transform per scan: a ROS 2
MCAP as a recorder writes it (zstd chunks), serialized by rosbags, or with a `.bag` name a ROS 1
bag written by rosbags' rosbag1 writer. It is written once and kept.

Then the build (`voxtool build BAG --resolution R -o map.vxm`'s library call, with its progress
bar, so that the per-scan latencies come back) runs as its own process: the
whole command's time and peak RSS, the RSS sampled every 0.25 s (memory after each tenth of the
run: it must level off with the map, not grow with the bag), and the scans per second of each
tenth of the scans (from the per-scan latencies). Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np


def bag_messages(pcd_dir: Path, scans: int, store):
    """(topic, message type, time ns, message) of the long bag, in time order: a /tf world ->
    lidar transform and a PointCloud2 per scan (the same for ROS 1 and ROS 2: only a ROS 1
    header has a seq)."""
    from voxtool.sources.pcd import read_pcd

    T = store.types
    clouds = [read_pcd(f) for f in sorted(pcd_dir.glob("*.pcd"))]
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    ros1 = "seq" in store.fielddefs["std_msgs/msg/Header"][1][0]

    def header(stamp, frame, seq):
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame) if ros1 else \
            T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    for i in range(scans):
        cloud = clouds[i % len(clouds)]
        lap = i // len(clouds)
        vp = cloud.viewpoint  # tx ty tz qw qx qy qz: the scan's own pose in its drive
        angle = 4.0 / 20.0 * lap
        shift = np.array([20.0 * math.cos(angle) - 20.0, 20.0 * math.sin(angle), 0.0])
        t = np.asarray(vp[:3], float) + shift
        ns = 1_700_000_000 * 10**9 + i * 100_000_000
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        tf = T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, "world", i), child_frame_id="lidar",
            transform=T["geometry_msgs/msg/Transform"](
                translation=T["geometry_msgs/msg/Vector3"](x=t[0], y=t[1], z=t[2]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=vp[4], y=vp[5], z=vp[6], w=vp[3])))
        yield "/tf", "tf2_msgs/msg/TFMessage", ns, T["tf2_msgs/msg/TFMessage"](transforms=[tf])
        xyz = np.ascontiguousarray(cloud.xyz, dtype="<f4")
        yield "/points", "sensor_msgs/msg/PointCloud2", ns, T["sensor_msgs/msg/PointCloud2"](
            header=header(stamp, "lidar", i), height=1, width=len(xyz), fields=fields, is_bigendian=False,
            point_step=12, row_step=12 * len(xyz), data=xyz.view(np.uint8).ravel(), is_dense=True)


def write_bag(pcd_dir: Path, scans: int, path: Path) -> None:
    """A ROS 2 MCAP (zstd chunks) or, for a .bag path, a ROS 1 bag (as rosbag record writes it,
    uncompressed chunks), written by the mcap library or rosbags."""
    from rosbags.typesys import Stores, get_typestore

    tmp = path.with_name(path.name + ".partial")
    if path.suffix == ".bag":
        from rosbags.rosbag1 import Writer as Ros1Writer
        from rosbags.typesys import get_types_from_msg

        store = get_typestore(Stores.ROS1_NOETIC)
        if "tf2_msgs/msg/TFMessage" not in store.fielddefs:  # not in rosbags' Noetic store: ROS's definition
            store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
        tmp.unlink(missing_ok=True)
        with Ros1Writer(tmp) as w:
            conns = {}
            for topic, msgtype, ns, msg in bag_messages(pcd_dir, scans, store):
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=store)
                w.write(conns[topic], ns, store.serialize_ros1(msg, msgtype))
        tmp.replace(path)
        return
    from mcap.writer import CompressionType, Writer

    store = get_typestore(Stores.ROS2_HUMBLE)
    with open(tmp, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="voxtool bench_bag")
        ids, seq = {}, 0
        for topic, msgtype, ns, msg in bag_messages(pcd_dir, scans, store):
            if topic not in ids:
                text, _ = store.generate_msgdef(msgtype, ros_version=2)
                schema = w.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
                ids[topic] = w.register_channel(topic=topic, message_encoding="cdr", schema_id=schema)
            w.add_message(ids[topic], log_time=ns, publish_time=ns, sequence=seq, data=store.serialize_cdr(msg, msgtype))
            seq += 1
        w.finish()
    tmp.replace(path)


# `voxtool build BAG --resolution R -o MAP --progress` through the library call the command makes,
# printing its JSON with the per-scan series (the command's --json leaves them out)
BUILD = """import json, sys
from voxtool.jit import start
start()
from voxtool.api import build_map
from voxtool.config import MapParams, SensorModel
from voxtool.sources import SourceOptions
r = build_map(sys.argv[1], SourceOptions(), MapParams(resolution=float(sys.argv[2])), SensorModel(),
              output=sys.argv[3], progress=True, per_scan=True)
print(json.dumps(r))
"""


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    ap.add_argument("--scans", type=int, default=2000)
    ap.add_argument("--resolution", type=float, default=0.5)
    ap.add_argument("--bag", default="bench-results/long.mcap")
    ap.add_argument("--out", default="bench-results/bag.json")
    args = ap.parse_args()
    bag = Path(args.bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    if not bag.exists():
        t0 = time.perf_counter()
        write_bag(Path(args.data) / "kaist03" / "pcd", args.scans, bag)
        print(f"wrote {bag} ({bag.stat().st_size / 2**20:,.0f} MiB) in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    out = Path(args.out)
    cmd = [sys.executable, "-c", BUILD, str(bag), str(args.resolution), str(out.with_suffix(".vxm"))]
    samples: list[tuple[float, float]] = []
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=None, text=True)  # its progress bar shows

    def sample() -> None:
        while proc.poll() is None:
            value = rss_mib(proc.pid)
            if value is not None:
                samples.append((time.perf_counter() - t0, value))
            time.sleep(0.25)

    poller = threading.Thread(target=sample, daemon=True)
    poller.start()
    stdout, _ = proc.communicate()
    wall = time.perf_counter() - t0
    poller.join()
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed with exit code {proc.returncode}")
    built = json.loads(stdout)
    latency = np.array(built["per_scan"]["latency_ms"]) if "per_scan" in built else None
    tenths = []
    n = built["scans"]
    for k in range(10):
        a, b = n * k // 10, n * (k + 1) // 10
        at = wall * (k + 1) / 10
        rss = max((v for s, v in samples if s <= at), default=None)
        rate = (b - a) / (latency[a:b].sum() / 1e3) if latency is not None and b > a else None
        tenths.append({"scans": f"{a}..{b - 1}", "scans_per_s": round(rate, 1) if rate else None,
                       "peak_rss_mib_so_far": round(rss, 1) if rss else None})
    result = {"bag": str(bag), "bag_mib": round(bag.stat().st_size / 2**20, 1), "scans": n,
              "points": built["points"], "resolution": args.resolution, "command_s": round(wall, 2),
              "scans_per_s": round(n / wall, 1), "peak_rss_mib": round(max(v for _, v in samples), 1),
              "occupied_voxels": built["occupied_voxels"], "leaves": built["logodds_leaf_nodes"],
              "timings_s": built["timings_s"], "tenths": tenths}
    print(f"{result['scans']:,} scans, {result['points']:,} points, bag {result['bag_mib']:,.0f} MiB, "
          f"{args.resolution} m: {wall:.1f} s ({result['scans_per_s']} scans/s), peak RSS {result['peak_rss_mib']} MiB, "
          f"{result['leaves']:,} leaves")
    print(f"{'scans':>12} {'scans/s (latency)':>18} {'peak RSS so far':>16}")
    for t in tenths:
        print(f"{t['scans']:>12} {t['scans_per_s'] or '-':>18} {t['peak_rss_mib_so_far'] or '-':>15} MiB")
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
