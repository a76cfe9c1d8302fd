"""ROS 2 MCAP source: sensor_msgs/msg/PointCloud2 with sensor poses from /tf (+ /tf_static) or
from a nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped topic. No ROS install needed."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from voxtool.errors import SourceError, mcap_problem
from voxtool.geometry import Pose, interpolate_pose
from voxtool.sources.pcd import MAX_POINTS

CLOUD = "sensor_msgs/msg/PointCloud2"
TF = "tf2_msgs/msg/TFMessage"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped")
def _decode_errors() -> tuple:
    """Exceptions the mcap / ROS 2 decoders raise on corrupt bytes (turned into SourceError)."""
    import struct

    import zstandard
    from mcap.exceptions import McapError

    return (McapError, ValueError, EOFError, KeyError, IndexError, AssertionError, struct.error, zstandard.ZstdError)


_PF_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
STAMP_TOLERANCE_NS = 1_000_000  # a cloud this close outside a transform's time range uses its end value


def _stamp(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose_of(translation, rotation) -> Pose:
    return Pose.from_quat((translation.x, translation.y, translation.z), rotation.w, rotation.x, rotation.y, rotation.z)


_POSES: dict[tuple, tuple] = {}  # the last files' poses (insertion order: the oldest goes first)


class StampedPoses:
    """Time series of one transform, interpolated (linear + slerp) at a query stamp."""

    def __init__(self) -> None:
        self.stamps: list[int] = []
        self.poses: list[Pose] = []
        self.static = False
        self._sorted: np.ndarray | None = None  # the stamps as an array, made on the first lookup

    def add(self, stamp: int, pose: Pose) -> None:
        self.stamps.append(stamp)
        self.poses.append(pose)
        self._sorted = None

    def at(self, stamp: int) -> Pose | None:
        if self.static:
            return self.poses[-1]
        s = self.stamps
        if self._sorted is None:
            self._sorted = np.asarray(s, dtype=np.int64)
        i = int(np.searchsorted(self._sorted, stamp))
        if i < len(s) and s[i] == stamp:
            return self.poses[i]
        if i == 0:
            return self.poses[0] if s[0] - stamp <= STAMP_TOLERANCE_NS else None
        if i == len(s):
            return self.poses[-1] if stamp - s[-1] <= STAMP_TOLERANCE_NS else None
        return interpolate_pose(stamp, s[i - 1], self.poses[i - 1], s[i], self.poses[i])


def decode_pointcloud2(path: Path, msg, index: int) -> np.ndarray:
    """(N, 3) float32 x, y, z of a PointCloud2, every declared size checked against the data."""
    where = f"{path}: PointCloud2 message {index}"
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


class McapCloudSource:
    """Streams (sensor points, pose, stamp, raw bytes) from a ROS 2 MCAP file."""

    def __init__(self, path: str | Path, topic: str | None, world_frame: str | None, pose_topic: str | None) -> None:
        from mcap.reader import make_reader

        self.path = Path(path)
        self.world_frame = world_frame
        self.pose_topic = pose_topic
        try:
            self._handle = open(self.path, "rb")
            self._decoders = _decoder_factory()
            self._reader = make_reader(self._handle, decoder_factories=[self._decoders], validate_crcs=True)
            summary = self._reader.get_summary()
        except OSError as err:
            raise SourceError(f"{self.path}: cannot read: {err.strerror}") from err
        except _decode_errors() as err:
            raise SourceError(f"{self.path}: cannot be read as MCAP: {mcap_problem(err)}") from err
        if summary is None:
            raise SourceError(f"{self.path}: MCAP has no summary section (truncated or not finished)")
        topics = {c.topic: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "" for c in summary.channels.values()}
        counts = {summary.channels[cid].topic: n for cid, n in (summary.statistics.channel_message_counts.items() if summary.statistics else [])}
        clouds = sorted(t for t, s in topics.items() if s == CLOUD)
        if topic is None:
            if len(clouds) != 1:
                raise SourceError(
                    f"{self.path}: found {len(clouds)} PointCloud2 topics ({', '.join(clouds) or 'none'}); choose one with --topic"
                )
            topic = clouds[0]
        elif topics.get(topic) != CLOUD:
            raise SourceError(f"{self.path}: topic '{topic}' is not a PointCloud2 topic (PointCloud2 topics: {', '.join(clouds) or 'none'})")
        self.topic = topic
        self.count = counts.get(topic)
        if pose_topic is not None and topics.get(pose_topic) not in POSE_TYPES:
            raise SourceError(f"{self.path}: pose topic '{pose_topic}' is not Odometry or PoseStamped")
        self._tf_topics = [t for t, s in topics.items() if s == TF]
        self._edges: dict[tuple[str, str], StampedPoses] = {}
        self._sensor_poses: StampedPoses | None = None

    def _load_poses(self) -> None:
        """The sensor poses (--pose-topic) or the /tf edges, read once per process and file: a
        Dask worker that reads several batches of one bag reads its transforms once."""
        st = os.fstat(self._handle.fileno())  # the file being read, even if the path was replaced since
        key = (str(self.path.resolve()), st.st_size, st.st_mtime_ns, self.pose_topic, tuple(self._tf_topics))
        if key in _POSES:
            self._sensor_poses, self._edges = _POSES[key]
            return
        self._read_poses()
        _POSES[key] = (self._sensor_poses, self._edges)
        while len(_POSES) > 4:
            _POSES.pop(next(iter(_POSES)))

    def _read_poses(self) -> None:
        try:
            if self.pose_topic is not None:
                series = StampedPoses()
                for _, _, _, msg in self._reader.iter_decoded_messages(topics=[self.pose_topic], log_time_order=True):
                    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
                    series.add(_stamp(msg.header), _pose_of(pose.position, pose.orientation))
                if not series.stamps:
                    raise SourceError(f"{self.path}: pose topic '{self.pose_topic}' holds no messages")
                self._sensor_poses = series
                return
            for _, channel, _, msg in self._reader.iter_decoded_messages(topics=self._tf_topics, log_time_order=True):
                for tr in msg.transforms:
                    key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
                    series = self._edges.setdefault(key, StampedPoses())
                    series.static = channel.topic == "/tf_static"
                    stamp = _stamp(tr.header)
                    if series.stamps and stamp < series.stamps[-1]:
                        raise SourceError(f"{self.path}: transform {key[0]} -> {key[1]} stamps go backwards at {stamp} ns")
                    series.add(stamp, _pose_of(tr.transform.translation, tr.transform.rotation))
        except _decode_errors() as err:
            raise SourceError(f"{self.path}: cannot read its poses: {mcap_problem(err)}") from err

    def _root_of(self, frame: str) -> str:
        """The top of the /tf tree above `frame` (the default world frame)."""
        parents = {child: parent for parent, child in self._edges}
        seen = {frame}
        while frame in parents:
            frame = parents[frame]
            if frame in seen:
                raise SourceError(f"{self.path}: /tf has a cycle through '{frame}'")
            seen.add(frame)
        return frame

    def _chain(self, frame: str, stamp: int) -> Pose:
        """Pose of `frame` in the world frame at `stamp`, walking /tf edges either way."""
        if self.world_frame is None:
            root = self._root_of(frame)
            if root == frame:
                raise SourceError(
                    f"{self.path}: no /tf transform reaches the cloud frame '{frame}' and no --pose-topic was given "
                    f"(pass --world-frame {frame} to take the clouds as world-frame)")
            self.world_frame = root
        if frame == self.world_frame:
            return Pose.identity()
        # breadth-first search over the (undirected) transform tree
        prev: dict[str, tuple[str, tuple[str, str], bool]] = {}
        seen = {self.world_frame}
        queue = deque([self.world_frame])
        while queue:
            node = queue.popleft()
            for (parent, child) in self._edges:
                for a, b, forward in ((parent, child, True), (child, parent, False)):
                    if a == node and b not in seen:
                        seen.add(b)
                        prev[b] = (a, (parent, child), forward)
                        queue.append(b)
        if frame not in prev:
            raise SourceError(f"{self.path}: no transform chain from '{self.world_frame}' to '{frame}' in /tf")
        pose = Pose.identity()
        node = frame
        while node != self.world_frame:
            a, edge, forward = prev[node]
            p = self._edges[edge].at(stamp)
            if p is None:
                s = self._edges[edge].stamps
                raise SourceError(
                    f"{self.path}: transform {edge[0]} -> {edge[1]} has no value at {stamp} ns (known {s[0]}..{s[-1]})"
                )
            if not forward:
                r = p.rotation.T
                p = Pose(r, -r @ p.translation)
            pose = p.compose(pose)
            node = a
        return pose

    def _log_times(self) -> np.ndarray | None:
        """Sorted log times of the cloud topic's messages, from the message index records the
        summary points to (no chunk is decompressed); None when the file has no usable index."""
        import io

        from mcap.data_stream import ReadDataStream
        from mcap.records import MessageIndex

        summary = self._reader.get_summary()
        channel = next(cid for cid, c in summary.channels.items() if c.topic == self.topic)
        times: list[int] = []
        try:
            for chunk in summary.chunk_indexes:
                offset = chunk.message_index_offsets.get(channel)
                if offset is None:
                    continue
                self._handle.seek(offset + 1 + 8, io.SEEK_SET)  # past the record's opcode and length
                times.extend(t for t, _ in MessageIndex.read(ReadDataStream(self._handle)).records)
        except _decode_errors():
            return None
        if not summary.chunk_indexes or (self.count is not None and len(times) != self.count):
            return None  # no index, or one that does not cover the topic: read from the start
        return np.sort(np.asarray(times, dtype=np.int64), kind="stable")

    def scans(self, start: int = 0, stop: int | None = None, every: int = 1) -> Iterator[tuple[int, np.ndarray, Pose, int, int]]:
        """(index, points, pose, stamp, bytes) of the cloud messages start, start + every, ...
        before stop. Reading starts at the chunk holding message `start` (found by the file's
        message index), so a Dask task that reads scans 2000..2007 of a bag does not read the
        2000 before; without an index they are read but not decoded."""
        self._load_poses()
        decoders: dict[int, object] = {}
        index, starting_at = 0, None
        times = self._log_times() if start > 0 else None
        if times is not None and start < len(times):
            starting_at = int(times[start])
            index = int(np.searchsorted(times, starting_at, side="left"))  # messages before that log time
        try:
            for schema, channel, message in self._reader.iter_messages(topics=[self.topic], log_time_order=True,
                                                                       starting_at=starting_at):
                if stop is not None and index >= stop:
                    return
                if index < start or (index - start) % every:
                    index += 1
                    continue
                if schema.id not in decoders:
                    decoders[schema.id] = self._decoders.decoder_for(channel.message_encoding, schema)
                    if decoders[schema.id] is None:
                        raise SourceError(f"{self.path}: '{self.topic}' is encoded as '{channel.message_encoding}', "
                                          "not ROS 2 CDR (cdr)")
                msg = decoders[schema.id](message.data)
                points = decode_pointcloud2(self.path, msg, index)
                stamp = _stamp(msg.header)
                if self._sensor_poses is not None:
                    pose = self._sensor_poses.at(stamp)
                    if pose is None:
                        raise SourceError(f"{self.path}: pose topic '{self.pose_topic}' has no pose at {stamp} ns")
                else:
                    pose = self._chain(msg.header.frame_id.lstrip("/"), stamp)
                yield index, points, pose, stamp, len(message.data)
                index += 1
        except _decode_errors() as err:
            raise SourceError(f"{self.path}: cannot read message {index} of '{self.topic}': {mcap_problem(err)}") from err


def _decoder_factory():
    from mcap_ros2.decoder import DecoderFactory

    return DecoderFactory()
