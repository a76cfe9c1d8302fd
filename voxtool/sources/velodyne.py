"""Velodyne driver packets as scans, through velodyne-decoder (BSD-3), an optional extra.

A log recorded before the driver's point cloud node holds `velodyne_msgs/VelodyneScan`
messages: one revolution each, as the sensor's 1206-byte UDP packets. velodyne-decoder turns a
message's packets into the revolution's points in the sensor frame (the model is found from
the packets; both returns of a dual-return sensor are kept: each is a surface). The messages
are read by what reads the log (rosbags, mcap), never by ROS.
"""

from __future__ import annotations

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import SourceError

VELODYNE_SCAN = "velodyne_msgs/msg/VelodyneScan"
EXTRA = f"pip install '{DISTRIBUTION}[velodyne]' (velodyne-decoder)"
# the ROS 2 definitions (velodyne_msgs): a ROS 2 bag stored in sqlite carries only the type's name
ROS2_DEFINITIONS = {
    "velodyne_msgs/msg/VelodynePacket": "builtin_interfaces/Time stamp\nuint8[1206] data",
    "velodyne_msgs/msg/VelodyneScan": "std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets",
}


def register_ros2_types(store) -> None:
    """Teach a rosbags type store the Velodyne packet messages (where it does not know them)."""
    from rosbags.typesys import get_types_from_msg

    types: dict = {}
    for name, text in ROS2_DEFINITIONS.items():
        if name not in store.fielddefs:
            types.update(get_types_from_msg(text, name))
    if types:
        store.register(types)


def decoder_module(where: str):
    try:
        import velodyne_decoder
    except ImportError:
        raise SourceError(f"{where}: holds Velodyne packets (velodyne_msgs/VelodyneScan); decoding them needs "
                          f"velodyne-decoder: {EXTRA}") from None
    return velodyne_decoder


def _packet_bytes(data) -> bytes:
    return data.tobytes() if hasattr(data, "tobytes") else bytes(data)


def decode_revolution(where: str, msg) -> tuple[np.ndarray, dict]:
    """(N, 3) float32 sensor-frame points of a VelodyneScan message, and what the decoder found
    (model, return mode)."""
    vd = decoder_module(where)
    packets = vd.PacketVector()
    for p in msg.packets:
        data = _packet_bytes(p.data)
        if len(data) != vd.PACKET_SIZE:
            raise SourceError(f"{where}: a packet of {len(data)} bytes (a Velodyne data packet has {vd.PACKET_SIZE})")
        packets.append(vd.VelodynePacket(int(p.stamp.sec) + int(p.stamp.nanosec) * 1e-9, data))
    if not len(packets):
        return np.zeros((0, 3), np.float32), {}
    decoder = vd.ScanDecoder(vd.Config())
    try:
        _, cloud = decoder.decode(packets)
    except (RuntimeError, ValueError) as err:  # a model it cannot tell, packets it cannot read
        raise SourceError(f"{where}: its Velodyne packets cannot be decoded ({err})") from None
    found = {"model": str(decoder.model_id).rsplit(".", 1)[-1], "return_mode": str(decoder.return_mode).rsplit(".", 1)[-1]}
    return np.ascontiguousarray(cloud[:, :3], dtype=np.float32), found
