"""Sensor poses of ROS messages: the /tf tree (+ /tf_static), or a nav_msgs/Odometry or
geometry_msgs/PoseStamped topic, interpolated at a cloud's stamp. Shared by every reader of ROS
logs (MCAP files, ROS 1 and ROS 2 bags): they differ in how they read messages, not in this."""

from __future__ import annotations

import shlex
from collections import deque

import numpy as np

from voxtool.errors import SourceError
from voxtool.geometry import Pose, interpolate_pose

STAMP_TOLERANCE_NS = 1_000_000  # a cloud this close outside a transform's time range uses its end value
TF = "tf2_msgs/msg/TFMessage"
LEGACY_TF = "tf/msg/tfMessage"  # ROS 1 before tf2 (Willow Garage-era bags): the same fields on /tf
TF_TYPES = (TF, LEGACY_TF)
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped",
              "geometry_msgs/msg/TransformStamped")


class OutsideTransforms(SourceError):
    """A scan taken before the first transform that poses it (or after the last): a tf message
    filter drops such scans, and so do the log readers (counted and warned about once)."""

    def __init__(self, message: str, before: bool, span: tuple[int, int], pose_topic: str | None = None) -> None:
        super().__init__(message)
        self.before = before
        self.span = span  # the stamps (ns) the poses that were missing span
        self.pose_topic = pose_topic  # None: /tf's transforms

    @property
    def what(self) -> str:
        return "transform" if self.pose_topic is None else f"pose of '{self.pose_topic}'"


class NoPoseSource(SourceError):
    """Nothing in the log poses the scans' frame: no scan can be built (not a bad scan)."""


def tf_topics(topics: dict[str, str]) -> list[str]:
    """The topics of a log (name -> message type) that carry transforms: /tf and /tf_static as
    tf2 or legacy tf messages."""
    return [t for t, s in topics.items() if s in TF_TYPES]


def topic_type(types) -> str:
    """The message type of a topic recorded on connections of `types`: the one type, or TF where
    /tf came as both tf/tfMessage and tf2_msgs/TFMessage (the same fields; bags of several nodes of
    both eras hold both); "" where the types differ otherwise."""
    types = set(types)
    if len(types) == 1:
        return types.pop() or ""
    return TF if types and types <= set(TF_TYPES) else ""


def pose_hint(where: str, frame: str, topics: dict[str, str]) -> str:
    """What would pose a log's scans when its /tf cannot: its Odometry / PoseStamped topics (for
    --pose-topic), a static sensor's own frame (--world-frame), or LiDAR odometry's poses."""
    candidates = sorted(t for t, s in topics.items() if s in POSE_TYPES)
    options = [f"--pose-topic {t}" for t in candidates[:3]]
    options.append(f"--world-frame {shlex.quote(frame)} (a static sensor: the map in its own frame)")  # '' if empty
    return ("pose them with " + ", or ".join(options) + f"; or estimate them: `voxtool odometry {where} -o poses.txt`, "
            "then --poses poses.txt")


def _warn(line: str) -> None:
    import warnings

    from voxtool.errors import VoxtoolWarning

    warnings.warn(line, VoxtoolWarning, stacklevel=3)


def header_stamp(header) -> int:
    """A std_msgs/Header's stamp in nanoseconds (ROS 1 and ROS 2 messages alike, as rosbags and
    mcap-ros2 decode them: sec + nanosec)."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose_of(translation, rotation) -> tuple:
    """A Transform's or Pose's fields as the 7 numbers StampedPoses keeps (x, y, z, qw, qx, qy, qz)."""
    return (translation.x, translation.y, translation.z, rotation.w, rotation.x, rotation.y, rotation.z)


class StampedPoses:
    """Time series of one transform, interpolated (linear + slerp) at a query stamp. It keeps each
    transform's 7 numbers and makes a Pose of the ones a lookup reads: a robot's /tf holds tens of
    thousands of transforms (wheels, joints) of which the scans read a few thousand."""

    def __init__(self) -> None:
        self.stamps: list[int] = []
        self.values: list[tuple] = []  # (x, y, z, qw, qx, qy, qz) of each stamp
        self.static = False
        self._sorted: np.ndarray | None = None  # the stamps as an array, made on the first lookup
        self._in_order = True  # stamps ascending, none repeated
        self._made: dict[int, Pose] = {}  # Poses made, by index into the ordered series

    def add(self, stamp: int, values: tuple) -> None:
        """Any stamp, in any order (as tf2's buffer takes them: several publishers of one edge,
        a late message): the series is put in stamp order on the next lookup."""
        if self.stamps and stamp <= self.stamps[-1]:
            self._in_order = False
        self.stamps.append(stamp)
        self.values.append(values)
        self._sorted = None
        self._made = {}

    def _order(self) -> None:
        """Sort by stamp; of repeated stamps the pose added last stays (the stable sort puts it last)."""
        order = np.argsort(np.asarray(self.stamps, dtype=np.int64), kind="stable")
        stamps = [self.stamps[i] for i in order]
        last = [k for k in range(len(stamps)) if k + 1 == len(stamps) or stamps[k + 1] != stamps[k]]
        self.stamps = [stamps[k] for k in last]
        self.values = [self.values[order[k]] for k in last]
        self._in_order = True
        self._made = {}  # indices moved

    def _pose(self, i: int) -> Pose:
        pose = self._made.get(i)
        if pose is None:
            x, y, z, qw, qx, qy, qz = self.values[i]
            pose = self._made[i] = Pose.from_quat((x, y, z), qw, qx, qy, qz)
        return pose

    def at(self, stamp: int) -> Pose | None:
        if self.static:  # the last one read, as tf2's static buffer keeps it
            return self._pose(len(self.values) - 1)
        if not self._in_order:
            self._order()
        s = self.stamps
        if self._sorted is None:
            self._sorted = np.asarray(s, dtype=np.int64)
        i = int(np.searchsorted(self._sorted, stamp))
        if i < len(s) and s[i] == stamp:
            return self._pose(i)
        if i == 0:
            return self._pose(0) if s[0] - stamp <= STAMP_TOLERANCE_NS else None
        if i == len(s):
            return self._pose(i - 1) if stamp - s[-1] <= STAMP_TOLERANCE_NS else None
        return interpolate_pose(stamp, s[i - 1], self._pose(i - 1), s[i], self._pose(i))


class SensorFrame:
    """The poses of a log read without its own (odometry registers the clouds in their sensor's
    frame; a --poses file poses them by message order): every cloud at the identity, no /tf read."""

    def pose_at(self, frame: str, stamp: int) -> Pose:
        return Pose.identity()


class SensorPoses:
    """Where a log's clouds were taken: fed the log's pose messages (add_transforms for /tf,
    add_pose for a --pose-topic), then asked for a cloud frame's pose at a stamp."""

    def __init__(self, where: str, world_frame: str | None, pose_topic: str | None,
                 topics: dict[str, str] | None = None) -> None:
        self.where = where
        self.topics = topics or {}  # the log's topics and types, for the hint of what would pose its scans
        self.world_frame = world_frame
        self.pose_topic = pose_topic
        self.edges: dict[tuple[str, str], StampedPoses] = {}
        self.sensor: StampedPoses | None = StampedPoses() if pose_topic is not None else None
        self.pose_child: str | None = None  # the frame a pose topic's poses are of (Odometry's child_frame_id)
        self.mount_note: str | None = None  # how a pose topic's frame reaches the scan frame: said once

    def add_transforms(self, msg, static: bool) -> None:
        """A tf2_msgs/TFMessage: every transform it holds, edge by edge."""
        for tr in msg.transforms:
            key = (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/"))
            series = self.edges.setdefault(key, StampedPoses())
            series.static = static
            stamp = header_stamp(tr.header)
            series.add(stamp, _pose_of(tr.transform.translation, tr.transform.rotation))

    def add_pose(self, msg) -> None:
        """A message of the pose topic: Odometry, PoseStamped, PoseWithCovarianceStamped or
        TransformStamped. Odometry and TransformStamped name the frame they pose (child_frame_id);
        the others pose a frame they do not name."""
        if hasattr(msg, "transform"):
            pose = _pose_of(msg.transform.translation, msg.transform.rotation)
        else:
            p = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
            pose = _pose_of(p.position, p.orientation)
        child = getattr(msg, "child_frame_id", "").lstrip("/")
        if child and self.pose_child is None:
            self.pose_child = child
        self.sensor.add(header_stamp(msg.header), pose)

    def check(self) -> None:
        """After the pose messages are read: a pose topic without messages is an error."""
        if self.sensor is not None and not self.sensor.stamps:
            raise SourceError(f"{self.where}: pose topic '{self.pose_topic}' holds no messages")

    def pose_at(self, frame: str, stamp: int) -> Pose:
        """The pose of a cloud taken in `frame` at `stamp`, in the world frame."""
        if self.sensor is not None:
            pose = self.sensor.at(stamp)
            if pose is None:
                s = self.sensor.stamps
                raise OutsideTransforms(f"{self.where}: pose topic '{self.pose_topic}' has no pose at {stamp} ns "
                                        f"(its poses span {s[0]}..{s[-1]})", stamp < s[0], (s[0], s[-1]),
                                        self.pose_topic)
            return pose.compose(self._mount(frame.lstrip("/"), stamp))
        return self._chain(frame.lstrip("/"), stamp)

    def _mount(self, frame: str, stamp: int) -> Pose:
        """The scan frame in the pose topic's frame, as tf2 users get it: /tf and /tf_static from
        the posed frame (an Odometry's child_frame_id: base_footprint, a body) to the scan's (the
        laser). Identity where the topic names no frame or /tf has no chain, said once (mount_note)."""
        child = self.pose_child
        if child is None or child == frame:
            if self.mount_note is None:
                self.mount_note = (f"'{self.pose_topic}' poses the scan frame '{frame}' itself" if child == frame else
                                   f"'{self.pose_topic}' names no frame it poses (no child_frame_id): its poses are "
                                   f"taken as the scan frame '{frame}'s, no mount")
                mounts = sorted(p for p, c in self.edges if c == frame)
                if child is None and mounts:  # the scan frame hangs on another: the pose is likely that one's
                    _warn(f"{self.where}: {self.mount_note}, though /tf mounts '{frame}' on '{mounts[0]}' "
                          f"(a body's pose used as the sensor's)")
            return Pose.identity()
        pose = self._path_pose(child, frame, stamp)
        if pose is None:
            if self.mount_note is None:
                self.mount_note = (f"no /tf or /tf_static chain from '{self.pose_topic}''s frame '{child}' to the scan "
                                   f"frame '{frame}': identity assumed (a sensor mount missing puts the map where the "
                                   f"'{child}' frame is)")
                _warn(f"{self.where}: {self.mount_note}")
            return Pose.identity()
        if self.mount_note is None:
            t = pose.translation
            self.mount_note = (f"'{self.pose_topic}' poses '{child}'; /tf mounts the scan frame '{frame}' on it at "
                               f"[{t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}] m")
        return pose

    def _root_of(self, frame: str) -> str:
        """The top of the /tf tree above `frame` (the default world frame)."""
        parents = {child: parent for parent, child in self.edges}
        seen = {frame}
        while frame in parents:
            frame = parents[frame]
            if frame in seen:
                raise SourceError(f"{self.where}: /tf has a cycle through '{frame}'")
            seen.add(frame)
        return frame

    def _chain(self, frame: str, stamp: int) -> Pose:
        """Pose of `frame` in the world frame at `stamp`, walking /tf edges either way."""
        if self.world_frame is None:
            root = self._root_of(frame)
            if root == frame and not any(frame in edge for edge in self.edges):
                known = sorted({f for edge in self.edges for f in edge})
                tree = f"its /tf frames: {', '.join(known[:8])}" if known else "the log has no /tf transform"
                raise NoPoseSource(f"{self.where}: no transform reaches the scan frame '{frame}' ({tree}); "
                                  f"{pose_hint(self.where, frame, self.topics)}")
            self.world_frame = root
        pose = self._path_pose(self.world_frame, frame, stamp)
        if pose is None:
            frames = sorted({f for edge in self.edges for f in edge})
            if frames and self.world_frame not in frames:
                raise NoPoseSource(f"{self.where}: --world-frame {self.world_frame} is not a frame of its /tf "
                                   f"(its frames: {', '.join(frames)}); or {pose_hint(self.where, frame, self.topics)}")
            raise NoPoseSource(f"{self.where}: no transform chain from '{self.world_frame}' to '{frame}' in /tf; "
                              f"{pose_hint(self.where, frame, self.topics)}")
        return pose

    def _path_pose(self, root: str, frame: str, stamp: int) -> Pose | None:
        """`frame`'s pose in `root` at `stamp`, walking /tf edges either way; None where no chain
        joins them (OutsideTransforms where one does but not at that time)."""
        if frame == root:
            return Pose.identity()
        # breadth-first search over the (undirected) transform tree
        prev: dict[str, tuple[str, tuple[str, str], bool]] = {}
        seen = {root}
        queue = deque([root])
        while queue:
            node = queue.popleft()
            for (parent, child) in self.edges:
                for a, b, forward in ((parent, child, True), (child, parent, False)):
                    if a == node and b not in seen:
                        seen.add(b)
                        prev[b] = (a, (parent, child), forward)
                        queue.append(b)
        if frame not in prev:
            return None
        pose = Pose.identity()
        node = frame
        while node != root:
            a, edge, forward = prev[node]
            p = self.edges[edge].at(stamp)
            if p is None:
                s = self.edges[edge].stamps
                raise OutsideTransforms(
                    f"{self.where}: transform {edge[0]} -> {edge[1]} has no value at {stamp} ns (known {s[0]}..{s[-1]})",
                    stamp < s[0], (s[0], s[-1]))
            if not forward:
                r = p.rotation.T
                p = Pose(r, -r @ p.translation)
            pose = p.compose(pose)
            node = a
        return pose
