"""Write ROS 1 bags and ROS 2 bag directories for tests with rosbags' own writers (not voxtool's
code): PointCloud2 or LaserScan scans posed by /tf (map -> odom -> lidar) or an Odometry topic."""

from __future__ import annotations

from pathlib import Path

import numpy as np

BAG_KINDS = ("ros1", "ros2-db3", "ros2-mcap")


def _store(kind: str):
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if kind == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in store.fielddefs:  # rosbags' Noetic store lacks it: ROS's own definition
        from rosbags.typesys import get_types_from_msg

        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return store


def _header(T, kind: str, ns: int, frame: str, seq: int = 0):
    stamp = T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    if kind == "ros1":
        return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)
    return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def cloud(T, kind: str, pts, ns: int, frame: str = "lidar"):
    pts = np.asarray(pts, dtype="<f4")
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    return T["sensor_msgs/msg/PointCloud2"](
        header=_header(T, kind, ns, frame), height=1, width=len(pts), fields=fields, is_bigendian=False,
        point_step=12, row_step=12 * len(pts), data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=True)


def laser(T, kind: str, ranges, angle_min: float, angle_inc: float, ns: int, frame: str = "lidar",
          range_max: float = 30.0):
    return T["sensor_msgs/msg/LaserScan"](
        header=_header(T, kind, ns, frame), angle_min=angle_min, angle_max=angle_min + angle_inc * (len(ranges) - 1),
        angle_increment=angle_inc, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=range_max,
        ranges=np.asarray(ranges, dtype=np.float32), intensities=np.zeros(0, dtype=np.float32))


def _transform(T, kind: str, parent: str, child: str, ns: int, t, q_wxyz):
    tr = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        rotation=T["geometry_msgs/msg/Quaternion"](x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]),
                                                   w=float(q_wxyz[0])))
    ts = T["geometry_msgs/msg/TransformStamped"](header=_header(T, kind, ns, parent), child_frame_id=child, transform=tr)
    return T["tf2_msgs/msg/TFMessage"](transforms=[ts])


def _odometry(T, kind: str, ns: int, t, q_wxyz, child: str = "lidar"):
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]),
                                                      w=float(q_wxyz[0])))
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=_header(T, kind, ns, "map"), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                         covariance=np.zeros(36)))


def write_bag(path: Path, scans, kind: str = "ros1", mode: str = "tf", messages=None) -> Path:
    """scans: [(sensor points, origin, q_wxyz)] at 10 Hz from 1 s, posed by /tf (mode "tf"), an
    Odometry topic ("odom") or nothing ("none"); `messages(T, kind, i, ns)`
    may give scan i's message instead of a PointCloud2 of its points (a LaserScan, a broken one).
    Returns what a user passes: the .bag file or the ROS 2 bag directory."""
    store = _store(kind)
    T = store.types
    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), store.serialize_cdr
    with writer:
        first = messages(T, kind, 0, 1_000_000_000) if messages else None
        scan_type = first.__msgtype__ if first is not None else "sensor_msgs/msg/PointCloud2"
        c_scan = writer.add_connection("/points", scan_type, typestore=store)
        if mode != "none":  # "none": the clouds alone, no topic that could pose them
            c_tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
            c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        for i, (pts, origin, q) in enumerate(scans):
            ns = 1_000_000_000 + i * 100_000_000
            if mode == "none":
                pass
            elif mode == "tf":
                writer.write(c_tf, ns, serialize(_transform(T, kind, "map", "odom", ns, (0, 0, 0), (1, 0, 0, 0)),
                                                 "tf2_msgs/msg/TFMessage"))
                writer.write(c_tf, ns, serialize(_transform(T, kind, "odom", "lidar", ns, origin, q), "tf2_msgs/msg/TFMessage"))
            else:
                writer.write(c_odom, ns, serialize(_odometry(T, kind, ns, origin, q), "nav_msgs/msg/Odometry"))
            msg = messages(T, kind, i, ns) if messages else cloud(T, kind, pts, ns)
            writer.write(c_scan, ns, msg if isinstance(msg, bytes) else serialize(msg, scan_type))
    return path
