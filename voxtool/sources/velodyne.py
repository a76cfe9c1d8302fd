"""Velodyne driver packets as scans, through velodyne-decoder (BSD-3), an optional extra.

A log recorded before the driver's point cloud node holds `velodyne_msgs/VelodyneScan`
messages: one revolution each, as the sensor's 1206-byte UDP packets; a capture (.pcap,
.pcapng, read with dpkt) holds the packets themselves, cut into revolutions here as the
driver cuts them. velodyne-decoder turns a
message's packets into the revolution's points in the sensor frame (the model is found from
the packets; both returns of a dual-return sensor are kept: each is a surface). The messages
are read by what reads the log (rosbags, mcap), never by ROS.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import SourceError

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


def _sensor(decoder) -> dict:
    """The model and return mode a velodyne-decoder ScanDecoder found in the packets it decoded."""
    return {"model": str(decoder.model_id).rsplit(".", 1)[-1],
            "return_mode": str(decoder.return_mode).rsplit(".", 1)[-1]}


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
    return np.ascontiguousarray(cloud[:, :3], dtype=np.float32), _sensor(decoder)


def _udp_payload(buf: bytes, datalink: int):
    """The UDP payload of a captured frame (Ethernet or Linux cooked capture), None otherwise."""
    import dpkt

    try:
        frame = dpkt.sll.SLL(buf) if datalink == dpkt.pcap.DLT_LINUX_SLL else dpkt.ethernet.Ethernet(buf)
    except (dpkt.UnpackError, dpkt.NeedData):
        return None
    ip = frame.data
    udp = getattr(ip, "data", None)
    return udp.data if isinstance(udp, dpkt.udp.UDP) else None


def _data_packets(path: Path, packet_size: int, others: dict[int, int]):
    """(capture stamp, payload) of each Velodyne data packet of a capture (.pcap or .pcapng);
    the other UDP payloads (position packets, other traffic) are counted by size in `others`."""
    import struct

    import dpkt

    with open(path, "rb") as raw:
        f = _ShortReads(raw)
        try:
            reader = dpkt.pcap.UniversalReader(f)
        except (ValueError, dpkt.Error) as err:
            raise SourceError(f"{path}: not a pcap or pcapng capture ({err})") from None
        datalink = reader.datalink()
        try:
            for stamp, buf in reader:
                if f.short:  # the last record, cut short: what came before it is whole
                    break
                payload = _udp_payload(buf, datalink)
                if payload is None:
                    continue
                if len(payload) != packet_size:
                    others[len(payload)] = others.get(len(payload), 0) + 1
                    continue
                yield stamp, payload
        except (ValueError, dpkt.Error, struct.error) as err:
            if not f.short:  # else a record (or its header) cut short by the file's end: what came before is whole
                raise SourceError(f"{path}: the capture cannot be read on ({err})") from None
        if f.short:
            import warnings

            from voxtool.errors import VoxtoolWarning

            warnings.warn(f"{path}: the capture is cut short in its last record (a recording that was stopped or a "
                          "copy cut short): read up to that record, which is left out", VoxtoolWarning, stacklevel=2)


class _ShortReads:
    """A file whose reads note when one returns some but not all of the bytes asked for: dpkt
    yields a record cut short by the end of the file as if it were whole."""

    def __init__(self, f) -> None:
        self._f = f
        self.short = False

    def read(self, size: int = -1) -> bytes:
        data = self._f.read(size)
        if 0 < len(data) < size:
            self.short = True
        return data

    def __getattr__(self, name):
        return getattr(self._f, name)


def pcap_revolutions(path: Path):
    """(capture stamp in ns, (N, 3) float32 sensor-frame points, bytes) of each revolution of a
    Velodyne capture (.pcap or .pcapng: the sensor's UDP data packets; others are passed over),
    cut where the azimuth wraps, as the driver cuts them."""
    vd = decoder_module(str(path))
    decoder = vd.StreamDecoder(vd.Config())
    size = 0
    others: dict[int, int] = {}  # payload size -> UDP packets that are no Velodyne data packet

    def revolution(result):
        nonlocal size
        stamp, cloud = result
        out = int(round(stamp.host * 1e9)), np.ascontiguousarray(cloud[:, :3], dtype=np.float32), size
        size = 0
        return out

    for stamp, payload in _data_packets(path, vd.PACKET_SIZE, others):
        size += len(payload)
        try:
            result = decoder.decode(stamp, payload)
        except ValueError as err:
            raise SourceError(f"{path}: the capture cannot be read on ({err})") from None
        if result is not None:
            yield revolution(result)
    result = decoder.finish()
    if result is not None:
        yield revolution(result)
    elif size == 0:
        raise SourceError(no_velodyne_packets(path, others))


def no_velodyne_packets(path: Path, others: dict[int, int]) -> str:
    """The one line for a capture without a Velodyne data packet: what it holds instead, and for
    an Ouster capture (a metadata .json beside it) how to convert it."""
    held = (f"its {sum(others.values()):,} UDP packets are {max(others, key=others.get)} bytes long (most of them)"
            if others else "it holds no UDP packet")
    ouster = (" It looks like an Ouster capture (a .json beside it): voxtool does not decode those (ouster-sdk 1.x's "
              "licence forbids competing products, 0.x pins rosbags 0.9.23 against voxtool's >= 0.10); write its "
              "frames as PCD with ouster-sdk's `ouster-cli source CAPTURE save OUT.pcd` and build them with --poses"
              if any(path.parent.glob(f"{path.stem}*.json")) else "")
    return (f"{path}: no Velodyne data packet (a 1206-byte UDP payload) in the capture: {held}.{ouster}")


def capture_sensor(path: Path, packets: int = 400) -> dict:
    """{model, return_mode} of a capture, decoded from its first data packets ({} without any)."""
    from itertools import islice

    vd = decoder_module(str(path))
    found = vd.PacketVector()
    for stamp, payload in islice(_data_packets(path, vd.PACKET_SIZE, {}), packets):
        found.append(vd.VelodynePacket(stamp, payload))
    if not len(found):
        return {}
    decoder = vd.ScanDecoder(vd.Config())
    decoder.decode(found)
    return _sensor(decoder)


def pcap_stream(path: Path, options):
    """A Velodyne capture as a ScanStream: one scan per revolution, posed by --poses (a capture
    holds no poses; `voxtool odometry` estimates them)."""
    from voxtool.geometry import Pose
    from voxtool.sources import BadScans, ScanStream, _pose_rows, make_scan

    if options.poses is None and not options.sensor_frame:
        raise SourceError(f"{path}: a Velodyne capture holds no poses: give --poses (one row per revolution); "
                          "`voxtool odometry` estimates them")
    decoder_module(str(path))  # the extra's one line before any reading
    rows = _pose_rows(options, None, "revolutions")
    bad = BadScans(options.bad_scans)

    def scans():
        from itertools import islice

        for i, (stamp, points, nbytes) in islice(enumerate(pcap_revolutions(path)), options.start, options.stop,
                                                  options.every):
            pose = Pose.identity()
            if rows is not None:
                if i >= len(rows):
                    raise SourceError(f"{options.poses}: pose file has {len(rows)} poses, the capture more revolutions "
                                      f"({i + 1} or more)")
                stamp_s, pose = rows[i]
                stamp = int(round(stamp_s * 1e9)) if stamp_s is not None else stamp
            yield make_scan(points, pose, i, stamp, f"{path}#{i}", nbytes, options)

    return ScanStream("pcap", path, None, scans(), bad)
