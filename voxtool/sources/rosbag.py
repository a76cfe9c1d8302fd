"""ROS 1 `.bag` files and ROS 2 bag directories (`metadata.yaml` + `.db3` or `.mcap`), read by
rosbags without ROS: PointCloud2 or LaserScan scans, posed by /tf (+ /tf_static) or a
--pose-topic exactly as the MCAP source poses them (voxtool.sources.tf)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from voxtool.errors import SourceError
from voxtool.geometry import Pose
from voxtool.sources.ros_msgs import scan_messages, scan_topic
from voxtool.sources.tf import POSE_TYPES, TF, SensorPoses


def bag_errors() -> tuple:
    """What rosbags and its decompressors raise on a corrupt or truncated bag (-> SourceError)."""
    import struct
    import zlib

    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    errors = [AnyReaderError, Reader1Error, Reader2Error, ValueError, EOFError, KeyError, IndexError, struct.error,
              zlib.error, AssertionError, OSError, BagBomb]
    try:
        import sqlite3

        errors.append(sqlite3.Error)
    except ImportError:  # a Python built without sqlite reads no .db3 bag anyway
        pass
    return tuple(errors)


class BagBomb(Exception):
    """A bag chunk that expands beyond what real data does (_bounded)."""


def _bounded(name: str, decompress) -> callable:
    """A chunk decompressor that stops at what real data expands to (compression.check_expansion's
    bound on the chunk's compressed bytes) instead of expanding a bomb to its end."""
    from voxtool.compression import expansion_limit

    def bounded(data, *_):
        limit = expansion_limit(len(data))
        out = decompress(bytes(data), limit + 1)
        if len(out) > limit:
            raise BagBomb(f"a {name} chunk of {len(data):,} bytes expands beyond {limit:,} bytes: more than real "
                          "data expands to (a corrupt bag, or a decompression bomb)")
        return out

    return bounded


def _bz2(data: bytes, most: int) -> bytes:
    import bz2

    return bz2.BZ2Decompressor().decompress(data, max_length=most)


def _lz4(data: bytes, most: int) -> bytes:
    import lz4.frame

    return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=most)


def _zstd(data: bytes, most: int) -> bytes:
    import zstandard

    with zstandard.ZstdDecompressor().stream_reader(data) as reader:
        return reader.read(most)


_BOUNDED = False


def bound_bag_chunks() -> None:
    """rosbags decompresses a chunk whole, to whatever it expands to (a ROS 1 chunk by bz2 or lz4,
    a ROS 2 MCAP chunk by zstd or lz4, a ROS 2 bag's messages by zstd). Its decompressors are
    swapped, once per process, for bounded ones, so that a bag bomb is refused before it fills
    memory (rosbags offers no limit of its own)."""
    global _BOUNDED
    if _BOUNDED:
        return
    from rosbags.rosbag1 import reader as ros1
    from rosbags.rosbag2 import reader as ros2_reader
    from rosbags.rosbag2 import storage_mcap as ros2

    ros1.decompressors.update(bz2=_bounded("bz2", _bz2), lz4=_bounded("lz4", _lz4))
    ros2.DECOMPRESSORS.update(zstd=_bounded("zstd", _zstd), lz4=_bounded("lz4", _lz4))
    ros2_reader.zstd = _MessageZstd(ros2_reader.zstd)  # a ROS 2 bag compressed message by message
    _BOUNDED = True


class _MessageZstd:
    """rosbags' zstd module with decompress() bounded (its file-mode reading streams to disk)."""

    def __init__(self, real) -> None:
        self._real = real
        self.decompress = _bounded("zstd message", _zstd)

    def __getattr__(self, name: str):
        return getattr(self._real, name)


def bag_root(path: Path) -> Path:
    """What rosbags opens: a ROS 1 `.bag` file, or the ROS 2 bag directory (also when given one
    of its storage files: `.db3`, or an `.mcap` beside a `metadata.yaml`)."""
    if path.is_file() and path.suffix.lower() != ".bag" and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def _problem(err: Exception) -> str:
    text = str(err) or type(err).__name__
    return f"{type(err).__name__}: {text}" if text != type(err).__name__ else text


class BagCloudSource:
    """Streams (index, sensor points, pose, stamp, raw bytes) of one scan topic of a bag."""

    def __init__(self, path: str | Path, topic: str | None, world_frame: str | None, pose_topic: str | None) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        bound_bag_chunks()
        root = bag_root(self.path)
        store = get_typestore(Stores.ROS1_NOETIC if root.suffix.lower() == ".bag" else Stores.ROS2_HUMBLE)
        try:
            self._reader = AnyReader([root], default_typestore=store)
            self._reader.open()
        except FileNotFoundError as err:
            raise SourceError(f"{self.path}: no such bag") from err
        except (OSError, *bag_errors()) as err:
            raise SourceError(f"{self.path}: cannot be read as a ROS bag ({_problem(err)})") from err
        topics = {name: info.msgtype or "" for name, info in self._reader.topics.items()}
        self.topic = scan_topic(str(self.path), topics, topic)
        self._msgtype = topics[self.topic]
        self.count: int | None = self._reader.topics[self.topic].msgcount
        if pose_topic is not None and topics.get(pose_topic) not in POSE_TYPES:
            raise SourceError(f"{self.path}: pose topic '{pose_topic}' is not Odometry or PoseStamped "
                              f"(it is {topics.get(pose_topic) or 'not in the bag'})")
        self._poses = SensorPoses(str(self.path), world_frame, pose_topic)
        self._tf_topics = [t for t, s in topics.items() if s == TF]
        self._poses_read = False

    def close(self) -> None:
        if self._reader.stack is not None:
            self._reader.close()

    def _connections(self, topics: list[str]) -> list:
        return [c for c in self._reader.connections if c.topic in topics]

    def _read_poses(self) -> None:
        poses = self._poses
        topics = [poses.pose_topic] if poses.pose_topic is not None else self._tf_topics
        try:
            for conn, _, raw in self._reader.messages(connections=self._connections(topics)):
                msg = self._reader.deserialize(raw, conn.msgtype)
                if poses.pose_topic is not None:
                    poses.add_pose(msg)
                else:
                    poses.add_transforms(msg, conn.topic == "/tf_static")
        except bag_errors() as err:
            raise SourceError(f"{self.path}: cannot read its poses ({_problem(err)})") from err
        poses.check()
        self._poses_read = True

    def scans(self, start: int = 0, stop: int | None = None, every: int = 1,
              on_bad: Callable[[int, SourceError], None] | None = None) -> Iterator[tuple[int, np.ndarray, Pose, int, int]]:
        """(index, points, pose, stamp, bytes) of scans start, start + every, ... before stop.
        A scan that cannot be decoded or posed goes to `on_bad` (which raises, or records and
        lets the reading go on); a bag that cannot be read on from a message ends there."""
        if not self._poses_read:
            self._read_poses()
        messages = self._reader.messages(connections=self._connections([self.topic]))

        def decode(item) -> tuple:
            conn, _, raw = item
            return self._reader.deserialize(raw, conn.msgtype), len(raw)

        yield from scan_messages(messages, decode, self._poses, str(self.path), self.topic, self._msgtype, bag_errors(),
                                 _problem, start, stop, every, on_bad)
