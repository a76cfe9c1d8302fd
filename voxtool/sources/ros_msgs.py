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
VELODYNE = "velodyne_msgs/msg/VelodyneScan"  # a revolution of driver packets (sources.velodyne)
SCAN_TYPES = (CLOUD, LASER, VELODYNE)
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


NO_RETURN_BEYOND = 1.01  # a no-return beam's point lies this far past its range, where its ray is cut


def decode_laserscan(where: str, msg) -> tuple[np.ndarray, np.ndarray | None, float]:
    """(N, 3) float32 points of a LaserScan in its frame (z = 0), reading i at angle angle_min +
    i * angle_increment; and its no-return beams. A reading at or above range_max (or +Inf, REP
    117) is the scanner's "nothing there": it becomes a NaN point and a miss, a point past
    range_max along its beam whose ray clears free space up to range_max and marks no hit (as
    gmapping's maxUrange and octomap_server's max_range treat it). A reading below range_min,
    NaN or -Inf becomes a NaN point, which the scan reader drops and counts. Returns (points,
    misses or None, range_max)."""
    ranges = np.asarray(msg.ranges, dtype=np.float64)
    if ranges.shape[0] > MAX_POINTS:
        raise SourceError(f"{where} declares {ranges.shape[0]} ranges (limit {MAX_POINTS})")
    inc = float(msg.angle_increment)
    if not np.isfinite(inc) or not np.isfinite(float(msg.angle_min)):
        raise SourceError(f"{where}: angle_min {msg.angle_min} / angle_increment {inc} is not finite")
    angles = float(msg.angle_min) + inc * np.arange(ranges.shape[0])
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges >= rmin) & (ranges < rmax)
        no_return = (ranges >= rmax) & (ranges > 0) & ~np.isnan(ranges) if np.isfinite(rmax) and rmax > 0 else None
    r = np.where(valid, ranges, np.nan)
    points = np.stack([r * np.cos(angles), r * np.sin(angles), np.zeros_like(r)], axis=1).astype(np.float32)
    if no_return is None or not no_return.any():
        return points, None, rmax
    a = angles[no_return]
    far = rmax * NO_RETURN_BEYOND
    misses = np.stack([far * np.cos(a), far * np.sin(a), np.zeros_like(a)], axis=1).astype(np.float32)
    return points, misses, rmax


def decode_scan(where: str, msgtype: str, msg) -> tuple[np.ndarray, np.ndarray | None, float]:
    """The sensor-frame points of a PointCloud2 or LaserScan message, its no-return beams (a
    LaserScan's, decode_laserscan) and the range at which they are cut."""
    if msgtype == LASER:
        return decode_laserscan(where, msg)
    if msgtype == VELODYNE:
        from voxtool.sources.velodyne import decode_revolution

        return decode_revolution(where, msg)[0], None, -1.0
    return decode_pointcloud2(where, msg), None, -1.0


# message types of LiDAR drivers' raw packets or own point formats (Velodyne, Hesai, Ouster,
# RoboSense, Livox, TIER IV's nebula): logs recorded before the driver's point cloud node
PACKET_MARKERS = ("VelodyneScan", "PandarScan", "Packet", "rslidarScan", "CustomMsg")  # "Packet": PacketMsg, NebulaPackets


def no_scan_topic(where: str, topics: dict[str, str]) -> str:
    """The one line for a log with no scan topic (PointCloud2, LaserScan, VelodyneScan): what it
    holds instead."""
    packets = sorted(t for t, s in topics.items() if any(m in s.rsplit("/", 1)[-1] for m in PACKET_MARKERS))
    if packets:
        named = ", ".join(f"{t} ({topics[t]})" for t in packets[:3])
        return (f"{where}: no PointCloud2 or LaserScan topic: {named} holds the sensor driver's raw packets or its own "
                "format, not points; turn them into PointCloud2 with that driver (play the log into its point cloud "
                "node and record the output) and build from the recording")
    listed = ", ".join(f"{t} ({s})" for t, s in sorted(topics.items())[:5]) or "none"
    more = f" and {len(topics) - 5} more" if len(topics) > 5 else ""
    return f"{where}: no PointCloud2 or LaserScan topic to build from (its topics: {listed}{more})"


def scan_topic(where: str, topics: dict[str, str], topic: str | None) -> str:
    """The scan topic to read (`topics`: every topic's message type): the one given, which must
    be a PointCloud2, LaserScan or VelodyneScan topic, or else the log's only one (a driver's
    point cloud before its packets, where a log holds both)."""
    scans = sorted(t for t, s in topics.items() if s in SCAN_TYPES)
    if topic is None:
        if not scans:
            raise SourceError(no_scan_topic(where, topics))
        clouds = [t for t in scans if topics[t] != VELODYNE]
        if len(scans) != 1 and len(clouds) != 1:
            raise SourceError(f"{where}: found {len(scans)} PointCloud2/LaserScan/VelodyneScan topics "
                              f"({', '.join(scans) or 'none'}); choose one with --topic")
        topic = scans[0] if len(scans) == 1 else clouds[0]
    elif topics.get(topic) not in SCAN_TYPES:
        raise SourceError(f"{where}: topic '{topic}' is not a PointCloud2, LaserScan or VelodyneScan topic "
                          f"(those topics: {', '.join(scans) or 'none'})")
    if topics[topic] == VELODYNE:
        from voxtool.sources.velodyne import decoder_module

        decoder_module(f"{where}: topic '{topic}'")  # the extra's one line before any reading
    return topic


def scan_messages(items: Iterator, decode: Callable, poses, where: str, topic: str, msgtype: str, errors: tuple,
                  problem: Callable[[Exception], str], start: int, stop: int | None, every: int,
                  on_bad: Callable | None, index: int = 0) -> Iterator[tuple]:
    """(index, sensor points, pose, stamp, bytes, (no-return beams, their range)) of a log's scan messages start, start + every,
    ... before stop, whatever reads the log (an MCAP file, a bag): `items` are its raw messages
    from message `index` on, `decode(item)` their (message, bytes), `poses` a tf.SensorPoses. A
    message that cannot be decoded or posed goes to `on_bad` (which raises, or records it and
    lets reading go on); a log that cannot be read on from a message ends there. Scans taken
    before the first transform that poses them, or after the last, are left out as a tf
    message filter leaves them out: counted (on_bad.unposed, where it has one) and warned about
    on one line when reading ends."""
    from voxtool.sources.tf import NoPoseSource, OutsideTransforms, header_stamp

    kind = msgtype.rsplit("/", 1)[-1]
    missed: list = []  # (index, OutsideTransforms, stamp) of each scan left out for want of a pose at its time
    posed = 0
    try:
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
                break
            if index >= start and (index - start) % every == 0:
                try:
                    msg, nbytes = decode(item)
                    points, misses, miss_range = decode_scan(f"{where}: {kind} message {index} of '{topic}'",
                                                             msgtype, msg)
                    stamp = header_stamp(msg.header)
                    pose = poses.pose_at(msg.header.frame_id, stamp)
                except OutsideTransforms as err:
                    missed.append((index, err, stamp))
                except NoPoseSource:
                    raise  # no scan of the log can be posed: one line, whatever --bad-scans says
                except (SourceError, *errors) as err:
                    bad = err if isinstance(err, SourceError) else SourceError(
                        f"{where}: {kind} message {index} of '{topic}' cannot be decoded ({problem(err)})")
                    if on_bad is None:
                        raise bad from err
                    on_bad(index, bad)
                else:
                    posed += 1
                    yield index, points, pose, stamp, nbytes, (misses, miss_range)
            index += 1
    finally:
        _report_unposed(where, topic, missed, on_bad)
    if missed and not posed:
        raise NoPoseSource(_none_posed(where, topic, missed))


def _none_posed(where: str, topic: str, missed: list) -> str:
    """Why no scan of a log could be posed: the poses' stamps against the scans'."""
    err = missed[0][1]
    stamps = [stamp for _, _, stamp in missed]
    source = f"pose topic '{err.pose_topic}'" if err.pose_topic else "/tf's chain to the scan frame"
    return (f"{where}: none of its {len(missed)} scans on '{topic}' can be posed: they span "
            f"{min(stamps) / 1e9:.3f}..{max(stamps) / 1e9:.3f} s, the {source} {err.span[0] / 1e9:.3f}.."
            f"{err.span[1] / 1e9:.3f} s (two clocks? a simulator's time beside the sensor's)")


def _report_unposed(where: str, topic: str, missed: list, on_bad) -> None:
    """One warning line for the scans left out for want of a transform (or a pose topic's pose)
    at their time (`missed`: scan_messages'; the first's error says which)."""
    if not missed:
        return
    before = [index for index, err, _ in missed if err.before]
    after = [index for index, err, _ in missed if not err.before]
    first = missed[0][1]
    import warnings

    from voxtool.errors import VoxtoolWarning

    record = getattr(on_bad, "unposed_scans", None)
    if record is not None:
        record(before, after)
    what = first.what
    parts = []
    if before:
        parts.append(f"{_indices(before)} taken before the first {what} that poses {'it' if len(before) == 1 else 'them'}")
    if after:
        parts.append(f"{_indices(after)} taken after the last")
    why = ", as a tf message filter drops them" if first.pose_topic is None else ""
    warnings.warn(f"{where}: left out {' and '.join(parts)} (topic '{topic}'){why}", VoxtoolWarning, stacklevel=3)


def _indices(indices: list[int]) -> str:
    shown = ", ".join(str(i) for i in indices[:4]) + (", ..." if len(indices) > 4 else "")
    return f"scan {shown}" if len(indices) == 1 else f"{len(indices)} scans ({shown})"
