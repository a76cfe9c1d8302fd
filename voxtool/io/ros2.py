"""ROS 2 messages in MCAP: the files voxtool writes for viewers (`export .mcap`, `--view`).

Every message is a ROS 2 message (profile `ros2`, schemas `ros2msg`, messages `cdr`), so one
file opens in rosbags' AnyReader, in ROS 2 tools and in Foxglove:
- `octomap_msgs/msg/Octomap` (msg/Octomap.msg) for RViz's OctoMap plugin;
- `foxglove_msgs/msg/SceneUpdate` (msg/SceneUpdate.msg) for Foxglove's 3D panel.

The definitions are the packages' own, written out with every type they use, as a ROS 2
recorder embeds them. Messages are serialized by rosbags' typestore, which generates a
serializer per type from those definitions: a map's 19.6 MB of OctoMap stream goes in as one
numpy array (mcap-ros2-support writes an int8[] value by value: 25 s for that array alone),
and 100,000 cubes take 0.8 s against its 3.8 s (docs/design/viewer.md).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import IO

MSG_DIR = Path(__file__).with_name("msg")
SEPARATOR = "=" * 80 + "\n"
TYPES = {"octomap_msgs/msg/Octomap": "Octomap.msg", "foxglove_msgs/msg/SceneUpdate": "SceneUpdate.msg"}


def message_definition(msgtype: str) -> str:
    """The ros2msg schema text of a type: its fields, then `MSG: pkg/Type` sections. TYPES are
    the packages' own files; a standard type (nav_msgs, ...) comes from rosbags' Humble store."""
    if msgtype not in TYPES:
        return typestore().generate_msgdef(msgtype, ros_version=2)[0]
    return (MSG_DIR / TYPES[msgtype]).read_text()


def _sections(msgtype: str, text: str) -> dict[str, str]:
    """{full type name: its own fields} of a concatenated definition."""
    parts = text.split(SEPARATOR)
    out = {msgtype: parts[0]}
    for part in parts[1:]:
        head, body = part.split("\n", 1)
        pkg, name = head.split()[1].split("/")
        out[f"{pkg}/msg/{name}"] = body
    return out


@lru_cache(maxsize=1)
def typestore():
    """A rosbags typestore that knows TYPES (and the standard types they use)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    new = {}
    for msgtype in TYPES:
        for name, body in _sections(msgtype, message_definition(msgtype)).items():
            if name not in store.fielddefs:
                new.update(get_types_from_msg(body, name))
    store.register(new)
    return store


def msg(msgtype: str):
    """The message class of a type (a dataclass of rosbags' typestore)."""
    return typestore().types[msgtype]


def serialize(message, msgtype: str) -> bytes:
    """CDR bytes of a message (what an MCAP message holds)."""
    return typestore().serialize_cdr(message, msgtype)


def stamp(stamp_ns: int):
    """builtin_interfaces/Time of a time in nanoseconds."""
    return msg("builtin_interfaces/msg/Time")(sec=int(stamp_ns) // 10**9, nanosec=int(stamp_ns) % 10**9)


class Ros2McapWriter:
    """An MCAP of ROS 2 messages on a handle: `channel(topic, msgtype)` once per topic, then
    `write(channel, message, log_time_ns)`."""

    def __init__(self, handle: IO[bytes]) -> None:
        from mcap.writer import Writer

        from voxtool import __version__

        self._writer = Writer(handle)
        self._writer.start(profile="ros2", library=f"voxtool {__version__}")
        self._schemas: dict[str, int] = {}
        self._types: dict[int, str] = {}
        self._sequence = 0

    def channel(self, topic: str, msgtype: str) -> int:
        if msgtype not in self._schemas:
            self._schemas[msgtype] = self._writer.register_schema(
                name=msgtype, encoding="ros2msg", data=message_definition(msgtype).encode())
        channel = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=self._schemas[msgtype])
        self._types[channel] = msgtype
        return channel

    def write(self, channel: int, message, log_time_ns: int) -> int:
        """Serialize and add one message; returns its size in bytes."""
        return self.write_serialized(channel, serialize(message, self._types[channel]), log_time_ns)

    def write_serialized(self, channel: int, data: bytes, log_time_ns: int) -> int:
        """Add one message already serialized (serialize()) for the channel's type."""
        self._writer.add_message(channel_id=channel, log_time=int(log_time_ns), data=data,
                                 publish_time=int(log_time_ns), sequence=self._sequence)
        self._sequence += 1
        return len(data)

    def finish(self) -> None:
        self._writer.finish()
