"""ROS 2 MCAP source: sensor_msgs/msg/PointCloud2 (or LaserScan) with sensor poses from /tf
(+ /tf_static) or from a nav_msgs/msg/Odometry or geometry_msgs/msg/PoseStamped topic
(voxtool.sources.tf). No ROS install needed."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from voxtool.errors import FormatError, SourceError, mcap_problem
from voxtool.sources.ros_msgs import scan_messages, scan_topic
from voxtool.sources.tf import POSE_TYPES, SensorFrame, SensorPoses, tf_topics


def _decode_errors() -> tuple:
    """Exceptions the mcap / ROS 2 decoders raise on corrupt bytes (turned into SourceError)."""
    import struct

    import zstandard
    from mcap.exceptions import McapError

    return (McapError, ValueError, EOFError, KeyError, IndexError, AssertionError, struct.error, zstandard.ZstdError)


_POSES: dict[tuple, SensorPoses] = {}  # the last files' poses (insertion order: the oldest goes first)


class McapCloudSource:
    """Streams (sensor points, pose, stamp, raw bytes) from a ROS 2 MCAP file."""

    def __init__(self, path: str | Path, topic: str | None, world_frame: str | None, pose_topic: str | None,
                 recover: bool = False, own_poses: bool = True) -> None:
        """own_poses False: the file's /tf and pose topics are not read, every cloud is at the
        identity (SensorFrame)."""
        from mcap.reader import make_reader

        self.path = Path(path)
        self.world_frame = world_frame
        self.pose_topic = pose_topic
        self._linear = None  # a file read from its start (mcap_linear), where its summary cannot be
        problem = None
        try:
            self._handle = open(self.path, "rb")
            self._decoders = _decoder_factory()
            self._reader = make_reader(self._handle, decoder_factories=[self._decoders], validate_crcs=True)
            summary = self._reader.get_summary()
        except OSError as err:
            raise SourceError(f"{self.path}: cannot read: {err.strerror}") from err
        except _decode_errors() as err:
            summary, problem = None, f"cannot be read as MCAP: {mcap_problem(err)}"
        if summary is None and not recover:
            problem = problem or "MCAP has no summary section (cut short, or not closed by its recorder)"
            raise SourceError(f"{self.path}: {problem}; --bad-scans skip reads the messages it holds from its start "
                              "(`mcap recover` rewrites it whole)")
        if summary is None:
            from voxtool.sources.mcap_linear import LinearMcap

            self._linear = LinearMcap(self.path)
            self._reader = self._linear
            topics, counts = self._linear.topics(), self._linear.topic_counts()
        else:
            from voxtool.compression import check_mcap_chunks

            try:
                check_mcap_chunks(self._handle, summary, str(self.path))
            except FormatError as err:
                raise SourceError(str(err)) from err
            topics = {c.topic: summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else ""
                      for c in summary.channels.values()}
            counts = {summary.channels[cid].topic: n for cid, n in
                      (summary.statistics.channel_message_counts.items() if summary.statistics else [])}
        topic = scan_topic(str(self.path), topics, topic)
        self.topic = topic
        self.count = counts.get(topic)
        if pose_topic is not None and topics.get(pose_topic) not in POSE_TYPES:
            raise SourceError(f"{self.path}: pose topic '{pose_topic}' is not Odometry, PoseStamped, "
                              "PoseWithCovarianceStamped or TransformStamped")
        self._tf_topics = tf_topics(topics)
        self._topics = topics
        self._msgtype = topics[topic]
        self._poses: SensorPoses | SensorFrame | None = None if own_poses else SensorFrame()

    def _load_poses(self) -> None:
        """The sensor poses (--pose-topic) or the /tf edges, read once per process and file: a
        Dask worker that reads several batches of one bag reads its transforms once."""
        st = os.fstat(self._handle.fileno())  # the file being read, even if the path was replaced since
        key = (str(self.path.resolve()), st.st_size, st.st_mtime_ns, self.pose_topic, tuple(self._tf_topics),
               self.world_frame)
        if key not in _POSES:
            _POSES[key] = self._read_poses()
            while len(_POSES) > 4:
                _POSES.pop(next(iter(_POSES)))
        self._poses = _POSES[key]

    def _read_poses(self) -> SensorPoses:
        poses = SensorPoses(str(self.path), self.world_frame, self.pose_topic, self._topics)
        try:
            extra = {} if self._linear is None else {"decoder_factory": self._decoders}
            # with a pose topic, /tf too: the mount from the frame it poses to the scan frame
            topics = ([self.pose_topic] if self.pose_topic is not None else []) + self._tf_topics
            if topics:  # (no topics would mean every topic to the mcap reader)
                for _, channel, _, msg in self._reader.iter_decoded_messages(topics=topics, log_time_order=True,
                                                                             **extra):
                    if channel.topic == self.pose_topic:
                        poses.add_pose(msg)
                    else:
                        poses.add_transforms(msg, channel.topic == "/tf_static")
        except _decode_errors() as err:
            raise SourceError(f"{self.path}: cannot read its poses: {mcap_problem(err)}") from err
        poses.check()
        return poses

    def _log_times(self) -> np.ndarray | None:
        """Sorted log times of the cloud topic's messages, from the message index records the
        summary points to (no chunk is decompressed); None when the file has no usable index."""
        import io

        from mcap.data_stream import ReadDataStream
        from mcap.records import MessageIndex

        if self._linear is not None:
            return None  # no index: messages are read from the start
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

    def scans(self, start: int = 0, stop: int | None = None, every: int = 1,
              on_bad: Callable[[int, SourceError], None] | None = None) -> Iterator[tuple]:
        """(index, points, pose, stamp, bytes, (misses, miss range)) of the cloud messages start, start + every, ...
        before stop. Reading starts at the chunk holding message `start` (found by the file's
        message index), so a Dask task that reads scans 2000..2007 of a bag does not read the
        2000 before; without an index they are read but not decoded. A message that cannot be
        decoded or posed goes to `on_bad` (which raises, or records it and lets reading go on);
        a file that cannot be read on from a message ends there."""
        if self._poses is None:
            self._load_poses()
        decoders: dict[int, object] = {}
        index, starting_at = 0, None
        times = self._log_times() if start > 0 else None
        if times is not None and start < len(times):
            starting_at = int(times[start])
            index = int(np.searchsorted(times, starting_at, side="left"))  # messages before that log time
        messages = self._reader.iter_messages(topics=[self.topic], log_time_order=True, starting_at=starting_at)

        def decode(item) -> tuple:
            schema, channel, message = item
            if schema.id not in decoders:
                decoders[schema.id] = self._decoders.decoder_for(channel.message_encoding, schema)
            if decoders[schema.id] is None:
                raise SourceError(f"{self.path}: '{self.topic}' is encoded as '{channel.message_encoding}', "
                                  "not ROS 2 CDR (cdr)")
            return decoders[schema.id](message.data), len(message.data)

        yield from scan_messages(messages, decode, self._poses, str(self.path), self.topic, self._msgtype,
                                 _decode_errors(), mcap_problem, start, stop, every, on_bad, index)


    def topic_table(self) -> list[dict]:
        """Every topic with its type and message count (None where the file does not say), by name."""
        if self._linear is not None:
            counts = self._linear.topic_counts()
            return [{"topic": t, "type": kind, "messages": counts.get(t, 0)}
                    for t, kind in sorted(self._linear.topics().items())]
        summary = self._reader.get_summary()
        counts = dict(summary.statistics.channel_message_counts) if summary.statistics else {}
        return [{"topic": c.topic, "type": summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "",
                 "messages": counts.get(cid)} for cid, c in sorted(summary.channels.items(), key=lambda kv: kv[1].topic)]

    def lost(self) -> str:
        """How much of the file could not be read (empty: all of it, or it was read through its index)."""
        return "" if self._linear is None else self._linear.lost()


def _decoder_factory():
    from mcap_ros2.decoder import DecoderFactory

    return DecoderFactory()
