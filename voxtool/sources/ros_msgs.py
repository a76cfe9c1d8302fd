"""Scan messages of ROS logs as points in the sensor frame: sensor_msgs PointCloud2 (3D LiDARs)
and LaserScan (2D scanners: rays in the scan plane). The same for ROS 1 and ROS 2 messages, as
rosbags and mcap-ros2 decode them (every declared size checked against the data)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from voxtool.errors import SourceError
from voxtool.sources.pcd import MAX_POINTS

CLOUD = "sensor_msgs/msg/PointCloud2"
LASER = "sensor_msgs/msg/LaserScan"
SCAN_TYPES = (CLOUD, LASER)
_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def decode_pointcloud2(where: str, msg) -> np.ndarray:
    """(N, 3) float32 x, y, z of a PointCloud2."""
    h, w, step, row_step = int(msg.height), int(msg.width), int(msg.point_step), int(msg.row_step)
    data = msg.data
    if h * w > MAX_POINTS:
        raise SourceError(f"{where} declares {h * w} points (limit {MAX_POINTS})")
    if w and step * w > row_step:
        raise SourceError(f"{where}: point_step {step} x width {w} exceeds row_step {row_step}")
    if len(data) < row_step * h:
        raise SourceError(f"{where}: data has {len(data)} bytes, row_step x height needs {row_step * h}")
    fields = {f.name: f for f in msg.fields}
    order = ">" if msg.is_bigendian else "<"
    cols = []
    for axis in "xyz":
        f = fields.get(axis)
        if f is None:
            raise SourceError(f"{where} has no '{axis}' field")
        dt = _PF_DTYPES.get(int(f.datatype))
        if dt is None:
            raise SourceError(f"{where}: field '{axis}' has unknown datatype {f.datatype}")
        size = np.dtype(dt).itemsize
        if f.offset + size > step:
            raise SourceError(f"{where}: field '{axis}' at offset {f.offset} does not fit point_step {step}")
        cols.append((int(f.offset), order + dt))
    buf = np.frombuffer(data, dtype=np.uint8, count=row_step * h).reshape(h, row_step)[:, : step * w]
    rows = np.ascontiguousarray(buf).reshape(h * w, step)
    out = np.empty((h * w, 3), dtype=np.float32)
    for k, (off, dt) in enumerate(cols):
        out[:, k] = rows[:, off : off + np.dtype(dt).itemsize].copy().view(dt)[:, 0]
    return out


def decode_laserscan(where: str, msg) -> np.ndarray:
    """(N, 3) float32 points of a LaserScan in its frame (z = 0): reading i lies at angle
    angle_min + i * angle_increment. A reading outside [range_min, range_max] (no return) or not
    finite becomes a NaN point, which the scan reader drops and counts."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    if ranges.shape[0] > MAX_POINTS:
        raise SourceError(f"{where} declares {ranges.shape[0]} ranges (limit {MAX_POINTS})")
    inc = float(msg.angle_increment)
    if not np.isfinite(inc) or not np.isfinite(float(msg.angle_min)):
        raise SourceError(f"{where}: angle_min {msg.angle_min} / angle_increment {inc} is not finite")
    angles = float(msg.angle_min) + inc * np.arange(ranges.shape[0])
    valid = np.isfinite(ranges) & (ranges >= float(msg.range_min)) & (ranges <= float(msg.range_max))
    r = np.where(valid, ranges, np.nan)
    return np.stack([r * np.cos(angles), r * np.sin(angles), np.zeros_like(r)], axis=1).astype(np.float32)


def decode_scan(where: str, msgtype: str, msg) -> np.ndarray:
    """The sensor-frame points of a PointCloud2 or LaserScan message."""
    return decode_laserscan(where, msg) if msgtype == LASER else decode_pointcloud2(where, msg)


def scan_topic(where: str, topics: dict[str, str], topic: str | None) -> str:
    """The scan topic to read (`topics`: every topic's message type): the one given, which must
    be a PointCloud2 or LaserScan topic, or else the log's only one."""
    scans = sorted(t for t, s in topics.items() if s in SCAN_TYPES)
    if topic is None:
        if len(scans) != 1:
            raise SourceError(f"{where}: found {len(scans)} PointCloud2/LaserScan topics ({', '.join(scans) or 'none'}); "
                              "choose one with --topic")
        return scans[0]
    if topics.get(topic) not in SCAN_TYPES:
        raise SourceError(f"{where}: topic '{topic}' is not a PointCloud2 or LaserScan topic "
                          f"(those topics: {', '.join(scans) or 'none'})")
    return topic


def scan_messages(items: Iterator, decode: Callable, poses, where: str, topic: str, msgtype: str, errors: tuple,
                  problem: Callable[[Exception], str], start: int, stop: int | None, every: int,
                  on_bad: Callable | None, index: int = 0) -> Iterator[tuple]:
    """(index, sensor points, pose, stamp, bytes) of a log's scan messages start, start + every,
    ... before stop, whatever reads the log (an MCAP file, a bag): `items` are its raw messages
    from message `index` on, `decode(item)` their (message, bytes), `poses` a tf.SensorPoses. A
    message that cannot be decoded or posed goes to `on_bad` (which raises, or records it and
    lets reading go on); a log that cannot be read on from a message ends there."""
    from voxtool.sources.tf import header_stamp

    kind = msgtype.rsplit("/", 1)[-1]
    while True:
        try:
            item = next(items, None)
        except errors as err:
            bad = SourceError(f"{where}: cannot read on from {kind} message {index} of '{topic}' ({problem(err)})")
            if on_bad is None:
                raise bad from err
            on_bad(index, bad)
            return
        if item is None or (stop is not None and index >= stop):
            return
        if index >= start and (index - start) % every == 0:
            try:
                msg, nbytes = decode(item)
                points = decode_scan(f"{where}: {kind} message {index} of '{topic}'", msgtype, msg)
                stamp = header_stamp(msg.header)
                pose = poses.pose_at(msg.header.frame_id, stamp)
            except (SourceError, *errors) as err:
                bad = err if isinstance(err, SourceError) else SourceError(
                    f"{where}: {kind} message {index} of '{topic}' cannot be decoded ({problem(err)})")
                if on_bad is None:
                    raise bad from err
                on_bad(index, bad)
            else:
                yield index, points, pose, stamp, nbytes
        index += 1
