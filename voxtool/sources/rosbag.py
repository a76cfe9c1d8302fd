"""ROS 1 `.bag` files and ROS 2 bag directories (`metadata.yaml` + `.db3` or `.mcap`), read by
rosbags without ROS: PointCloud2 or LaserScan scans, posed by /tf (+ /tf_static) or a
--pose-topic exactly as the MCAP source poses them (voxtool.sources.tf)."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

from voxtool.errors import SourceError
from voxtool.sources.bag_limits import bag_errors, bound_bag_chunks
from voxtool.sources.ros_msgs import VELODYNE, scan_messages, scan_topic
from voxtool.sources.tf import POSE_TYPES, SensorFrame, SensorPoses, tf_topics, topic_type


def bag_root(path: Path) -> Path:
    """What rosbags opens: a ROS 1 `.bag` file, or the ROS 2 bag directory (also when given one
    of its storage files: `.db3`, or an `.mcap` beside a `metadata.yaml`)."""
    if path.is_file() and path.suffix.lower() != ".bag" and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


BLANK_STORAGE = re.compile(r'^(\s*storage_identifier:\s*)(""|\'\')\s*$', re.M)
BLANK_FORMAT = re.compile(r'^(\s*serialization_format:\s*)(""|\'\')\s*$', re.M)


def ros2_blanks_filled(root: Path):
    """A ROS 2 bag whose metadata.yaml leaves its storage or its topics' serialization blank (as
    some rosbag2 releases wrote them; `ros2 bag` takes the storage from the files' extension and
    CDR, ROS 2's only format): a temporary folder with the blanks filled in and links to the
    bag's files, or None when nothing is blank."""
    import tempfile

    meta = root / "metadata.yaml"
    if not (root.is_dir() and meta.is_file()):
        return None
    text = meta.read_text(errors="replace")
    if not (BLANK_STORAGE.search(text) or BLANK_FORMAT.search(text)):
        return None
    storage = "mcap" if any(root.glob("*.mcap")) else "sqlite3"
    folder = tempfile.TemporaryDirectory(prefix="voxtool-bag-")
    for f in root.iterdir():
        if f.name == "metadata.yaml":
            continue
        if f.suffix == ".db3" and _blank_db_formats(f):
            # the database's topics are blank too: rosbags pairs them with metadata.yaml's by format,
            # and would read no message of them. A copy with the blanks filled (the file is left as it is)
            import shutil
            import sqlite3

            shutil.copyfile(f, Path(folder.name) / f.name)
            with sqlite3.connect(Path(folder.name) / f.name) as db:
                db.execute("UPDATE topics SET serialization_format = 'cdr' WHERE serialization_format = ''")
            continue
        (Path(folder.name) / f.name).symlink_to(f.resolve())
    text = BLANK_FORMAT.sub(r"\g<1>cdr", BLANK_STORAGE.sub(rf"\g<1>{storage}", text))
    (Path(folder.name) / "metadata.yaml").write_text(text)
    return folder


def _blank_db_formats(db3: Path) -> bool:
    """Whether a rosbag2 sqlite file's topics table leaves a serialization format blank."""
    import sqlite3

    try:
        with sqlite3.connect(f"file:{db3}?mode=ro", uri=True) as db:
            return bool(db.execute("SELECT count(*) FROM topics WHERE serialization_format = ''").fetchone()[0])
    except sqlite3.Error:
        return False  # not a database rosbags can read either: its own error says so


def _problem(err: Exception) -> str:
    text = str(err) or type(err).__name__
    return f"{type(err).__name__}: {text}" if text != type(err).__name__ else text


class _IndexedBag:
    """A bag rosbags opens through its index (ROS 1 .bag, ROS 2 bag directory)."""

    lost = staticmethod(lambda: "")

    def __init__(self, reader, patched=None, deserialize=None) -> None:
        """deserialize(raw, type): where not the reader's own (AnyReader's)."""
        self._reader = reader
        self._deserialize = deserialize or reader.deserialize
        self._patched = patched  # the folder of a ros2_blanks_filled() copy, removed on close
        self.topics = {name: info.msgtype or topic_type(c.msgtype for c in reader.connections if c.topic == name)
                       for name, info in reader.topics.items()}

    def count(self, topic: str) -> int | None:
        return self._reader.topics[topic].msgcount

    def messages(self, topics: list[str]) -> Iterator:
        connections = [c for c in self._reader.connections if c.topic in topics]
        if not connections:  # rosbags reads every message for no connections: none is wanted here
            return iter(())
        return ((conn.topic, conn.msgtype, raw) for conn, _, raw in self._reader.messages(connections=connections))

    def deserialize(self, raw, msgtype: str):
        return self._deserialize(raw, msgtype)

    def close(self) -> None:
        still_open = self._reader.is_open if hasattr(self._reader, "is_open") else self._reader.stack is not None
        if still_open:
            self._reader.close()
        if self._patched is not None:
            self._patched.cleanup()


class _LinearBag:
    """A ROS 1 bag read record by record, without its index (voxtool.sources.bag1_linear)."""

    def __init__(self, bag) -> None:
        self._bag = bag
        self.topics = bag.topics
        self.lost = bag.lost

    def count(self, topic: str) -> int | None:
        return sum(self._bag.counts.get(c.id, 0) for c in self._bag.connections.values() if c.topic == topic)

    def messages(self, topics: list[str]) -> Iterator:
        return ((conn.topic, conn.msgtype, raw) for conn, _, raw in self._bag.messages(topics))

    def deserialize(self, raw, msgtype: str):
        return self._bag.deserialize(raw, msgtype)

    def close(self) -> None:
        pass


def _undefined_types_bag(root: Path, patched) -> _IndexedBag | None:
    """A ROS 2 bag whose storage names its types without defining them (sqlite, rosbag2 before
    Iron), read with ROS 2 Humble's definitions: its messages deserialized by that type store
    directly. AnyReader would first copy and register every type of the store again (the VLP-32C
    packet bag opened in 0.23 s that way, 0.16 s this way). None where the bag defines its types
    (AnyReader reads those)."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    from voxtool.sources.velodyne import register_ros2_types

    reader = Reader(root)
    reader.open()
    if any(c.msgdef.format != MessageDefinitionFormat.NONE for c in reader.connections):
        reader.close()
        return None
    store = get_typestore(Stores.ROS2_HUMBLE)
    if any(c.msgtype == VELODYNE for c in reader.connections):  # the driver packets voxtool decodes
        register_ros2_types(store)
    return _IndexedBag(reader, patched, store.deserialize_cdr)


def open_bag(path: Path, recover: bool):
    """The bag at `path` opened through its index, or (recover) read record by record where the
    index cannot be used: a recording that was killed, a file cut short, a damaged index. Its
    `topics` (name -> type), `count(topic)`, `messages(topics)` as (topic, type, raw) and
    `deserialize(raw, type)` are the same either way."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from voxtool.sources.bag1_linear import OLD_MAGIC, LinearBag

    bound_bag_chunks()
    root = bag_root(path)
    ros1 = root.suffix.lower() == ".bag"
    if ros1 and root.is_file():
        with open(root, "rb") as f:
            if f.read(len(OLD_MAGIC)) == OLD_MAGIC:
                return _LinearBag(LinearBag(root))  # raises the one line that says what to do
    patched = None if ros1 else ros2_blanks_filled(root)
    opened = Path(patched.name) if patched else root
    try:
        if not ros1 and (bag := _undefined_types_bag(opened, patched)) is not None:
            return bag
        store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        reader = AnyReader([opened], default_typestore=store)
        reader.open()
        return _IndexedBag(reader, patched)
    except FileNotFoundError as err:
        raise SourceError(f"{path}: no such bag") from err
    except (OSError, *bag_errors()) as err:
        problem = _problem(err)
    if patched is not None:
        patched.cleanup()
    if not ros1:
        raise SourceError(f"{path}: cannot be read as a ROS bag ({problem})")
    if not recover:
        raise SourceError(f"{path}: its index cannot be read ({problem}); --bad-scans skip builds from the scans "
                          "that can be read (or rebuild the index with ROS 1's `rosbag reindex`)")
    bag = LinearBag(root)
    if not bag.connections:
        raise SourceError(f"{path}: no scan can be read: not through its index ({problem}), nor record by record "
                          f"({bag.lost()})")
    return _LinearBag(bag)


class BagCloudSource:
    """Streams (index, sensor points, pose, stamp, raw bytes) of one scan topic of a bag."""

    def __init__(self, path: str | Path, topic: str | None, world_frame: str | None, pose_topic: str | None,
                 recover: bool = False, bag=None, own_poses: bool = True) -> None:
        """bag: the bag already opened by open_bag() (else it is opened here). own_poses False:
        the bag's /tf and pose topics are not read, every cloud is at the identity (SensorFrame)."""
        self.path = Path(path)
        self._bag = bag if bag is not None else open_bag(self.path, recover)
        topics = self._bag.topics
        self.topic = scan_topic(str(self.path), topics, topic)
        self._msgtype = topics[self.topic]
        self.count: int | None = self._bag.count(self.topic)
        if pose_topic is not None and topics.get(pose_topic) not in POSE_TYPES:
            candidates = sorted(t for t, s in topics.items() if s in POSE_TYPES)
            raise SourceError(f"{self.path}: pose topic '{pose_topic}' is not Odometry, PoseStamped, "
                              "PoseWithCovarianceStamped or TransformStamped "
                              f"(it is {topics.get(pose_topic) or 'not in the bag'}; the bag's pose topics: "
                              f"{', '.join(candidates) or 'none'})")
        self._poses = SensorPoses(str(self.path), world_frame, pose_topic, topics) if own_poses else SensorFrame()
        self._tf_topics = tf_topics(topics)
        self._poses_read = not own_poses

    def lost(self) -> str:
        """How much of the file could not be read (empty: all of it)."""
        return self._bag.lost()

    def close(self) -> None:
        self._bag.close()

    def _read_poses(self) -> None:
        poses = self._poses
        # with a pose topic, /tf too: the mount from the frame it poses to the scan frame
        topics = ([poses.pose_topic] if poses.pose_topic is not None else []) + self._tf_topics
        try:
            for topic, msgtype, raw in self._bag.messages(topics):
                msg = self._bag.deserialize(raw, msgtype)
                if topic == poses.pose_topic:
                    poses.add_pose(msg)
                else:
                    poses.add_transforms(msg, topic == "/tf_static")
        except bag_errors() as err:
            raise SourceError(f"{self.path}: cannot read its poses ({_problem(err)})") from err
        poses.check()
        self._poses_read = True

    def scans(self, start: int = 0, stop: int | None = None, every: int = 1,
              on_bad: Callable[[int, SourceError], None] | None = None) -> Iterator[tuple]:
        """(index, points, pose, stamp, bytes, (misses, miss range)) of scans start, start + every, ... before stop.
        A scan that cannot be decoded or posed goes to `on_bad` (which raises, or records and
        lets the reading go on); a bag that cannot be read on from a message ends there."""
        if not self._poses_read:
            self._read_poses()
        messages = self._bag.messages([self.topic])

        def decode(item) -> tuple:
            _, msgtype, raw = item
            return self._bag.deserialize(raw, msgtype), len(raw)

        yield from scan_messages(messages, decode, self._poses, str(self.path), self.topic, self._msgtype, bag_errors(),
                                 _problem, start, stop, every, on_bad)
