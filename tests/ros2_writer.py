"""Write small ROS 2 MCAP files for tests (PointCloud2 + /tf or Odometry)."""

from __future__ import annotations

import numpy as np

TIME = "int32 sec\nuint32 nanosec\n"
HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
SEP = "=" * 80 + "\n"
POINTCLOUD2 = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nPointField[] fields\nbool is_bigendian\n"
    "uint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n"
    + SEP + "MSG: std_msgs/Header\n" + HEADER + SEP + "MSG: builtin_interfaces/Time\n" + TIME
    + SEP + "MSG: sensor_msgs/PointField\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n"
)
VEC_QUAT = (SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
            + SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n")
TFMESSAGE = (
    "geometry_msgs/TransformStamped[] transforms\n" + SEP + "MSG: geometry_msgs/TransformStamped\n"
    "std_msgs/Header header\nstring child_frame_id\nTransform transform\n" + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME + SEP + "MSG: geometry_msgs/Transform\n"
    "Vector3 translation\nQuaternion rotation\n" + VEC_QUAT
)
ODOMETRY = (
    "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
    "geometry_msgs/TwistWithCovariance twist\n" + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
    + SEP + "MSG: geometry_msgs/PoseWithCovariance\nPose pose\nfloat64[36] covariance\n"
    + SEP + "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n"
    + SEP + "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n"
    + SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
    + SEP + "MSG: geometry_msgs/TwistWithCovariance\nTwist twist\nfloat64[36] covariance\n"
    + SEP + "MSG: geometry_msgs/Twist\nVector3 linear\nVector3 angular\n"
    + SEP + "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
)


POSESTAMPED = (
    "std_msgs/Header header\ngeometry_msgs/Pose pose\n" + SEP + "MSG: std_msgs/Header\n" + HEADER
    + SEP + "MSG: builtin_interfaces/Time\n" + TIME
    + SEP + "MSG: geometry_msgs/Pose\nPoint position\nQuaternion orientation\n"
    + SEP + "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n"
    + SEP + "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
)


def stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def cloud_msg(points: np.ndarray, ns: int, frame: str, point_step: int = 12, row_step: int | None = None) -> dict:
    pts = np.asarray(points, dtype="<f4")
    data = pts.tobytes()
    return {
        "header": {"stamp": stamp(ns), "frame_id": frame}, "height": 1, "width": len(pts),
        "fields": [{"name": n, "offset": 4 * i, "datatype": 7, "count": 1} for i, n in enumerate("xyz")],
        "is_bigendian": False, "point_step": point_step, "row_step": row_step if row_step is not None else 12 * len(pts),
        "data": data, "is_dense": True,
    }


def tf_msg(parent: str, child: str, ns: int, t, q_wxyz) -> dict:
    return {"transforms": [{
        "header": {"stamp": stamp(ns), "frame_id": parent}, "child_frame_id": child,
        "transform": {"translation": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                      "rotation": {"x": float(q_wxyz[1]), "y": float(q_wxyz[2]), "z": float(q_wxyz[3]), "w": float(q_wxyz[0])}},
    }]}


def odom_msg(ns: int, t, q_wxyz) -> dict:
    return {
        "header": {"stamp": stamp(ns), "frame_id": "map"}, "child_frame_id": "lidar",
        "pose": {"pose": {"position": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                          "orientation": {"x": float(q_wxyz[1]), "y": float(q_wxyz[2]), "z": float(q_wxyz[3]), "w": float(q_wxyz[0])}},
                 "covariance": [0.0] * 36},
        "twist": {"twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.0}},
                  "covariance": [0.0] * 36},
    }


def write_mcap(path, scans, mode: str = "tf", cloud_overrides: dict | None = None, skip_tf: bool = False,
               chunk_size: int = 1 << 20,
               cloud_log_times: list[int] | None = None) -> None:
    """scans: [(sensor points, origin, q_wxyz)]. mode 'tf': map->odom (identity) ->lidar chain;
    'odom': an Odometry topic /odom gives the lidar pose; 'pose': a PoseStamped topic /pose.
    cloud_log_times: the clouds' MCAP log times (default: their header stamps)."""
    from mcap_ros2.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        s_cloud = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2)
        s_tf = w.register_msgdef("tf2_msgs/msg/TFMessage", TFMESSAGE)
        s_odom = w.register_msgdef("nav_msgs/msg/Odometry", ODOMETRY)
        s_pose = w.register_msgdef("geometry_msgs/msg/PoseStamped", POSESTAMPED)
        for i, (pts, origin, q) in enumerate(scans):
            ns = 1_000_000_000 + i * 100_000_000
            tf_ns = ns
            if mode == "tf" and not skip_tf:
                w.write_message("/tf", s_tf, tf_msg("map", "odom", tf_ns, (0, 0, 0), (1, 0, 0, 0)), ns, ns)
                w.write_message("/tf", s_tf, tf_msg("odom", "lidar", tf_ns, origin, q), ns, ns)
            elif mode == "odom":
                w.write_message("/odom", s_odom, odom_msg(ns, origin, q), ns, ns)
            elif mode == "pose":
                m = odom_msg(ns, origin, q)
                w.write_message("/pose", s_pose, {"header": m["header"], "pose": m["pose"]["pose"]}, ns, ns)
            msg = cloud_msg(pts, ns, "lidar")
            if cloud_overrides and i == 0:
                msg.update(cloud_overrides)
            log_ns = cloud_log_times[i] if cloud_log_times is not None else ns
            w.write_message("/points", s_cloud, msg, log_ns, log_ns)
        w.finish()


def write_graph(path, scans) -> None:
    """OctoMap ScanGraph: per node points (int32 3 + 3 float64), pose, id; no edges."""
    import struct

    out = bytearray(struct.pack("<I", len(scans)))
    for pts, origin, q in scans:
        out += struct.pack("<I", len(pts))
        rec = np.zeros(len(pts), dtype=[("n", "<i4"), ("xyz", "<f8", (3,))])
        rec["n"] = 3
        rec["xyz"] = np.asarray(pts, dtype=np.float32).astype(np.float64)
        out += rec.tobytes()
        out += struct.pack("<i3d", 3, *map(float, origin)) + struct.pack("<i4d", 4, *map(float, q)) + struct.pack("<I", 12345)
    out += struct.pack("<I", 0)
    path.write_bytes(bytes(out))
