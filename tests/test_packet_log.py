"""Packet logs as ROS 2 MCAP: readers voxtool did not write (rosbags, the mcap reader with
mcap-ros2-support's decoder) decode every header field, and logs of the old layout still read."""

from __future__ import annotations

import pytest

from voxtool.codec.log import LEGACY_SCHEMA, MESSAGE_TYPE, read_log
from voxtool.codec.packet import HEADER, decode_packet
from voxtool.errors import FormatError


def test_rosbags_decodes_every_header_field_of_a_log(sample_logs):
    from rosbags.highlevel import AnyReader

    log = sample_logs["r1"][0]
    _, messages = read_log(log)
    packets = [blob for _, _, blob in messages]
    with AnyReader([log]) as reader:
        (conn,) = reader.connections
        assert (conn.topic, conn.msgtype) == ("/voxtool/packets/r1", MESSAGE_TYPE)
        decoded = [(stamp, reader.deserialize(raw, conn.msgtype)) for _, stamp, raw in reader.messages()]
    assert len(decoded) == len(packets) > 10
    for (stamp, msg), blob in zip(decoded, packets):
        p = decode_packet(blob)
        assert bytes(msg.packet) == blob and msg.stamp_ns == stamp == p.stamp_ns
        assert (msg.robot, msg.sequence, msg.scheme, msg.codec, msg.kind) == (p.robot, p.seq, p.scheme, p.codec, p.kind)
        assert msg.resolution == p.resolution and tuple(msg.map_origin) == p.map_origin
        assert tuple(msg.box_min) == p.box_min and tuple(msg.box_size) == p.box_dims
        assert (msg.count, msg.raw_size, msg.stored_size) == (p.count, p.raw_size, p.stored_size)
        assert msg.stored_size + HEADER.size == len(blob) and msg.version == blob[4]


def test_a_log_of_the_old_layout_reads_the_same_packets(sample_logs, tmp_path):
    from mcap.writer import CompressionType, Writer

    log = sample_logs["r1"][0]
    meta, messages = read_log(log)
    packets = list(messages)
    old = tmp_path / "old.mcap"
    with open(old, "wb") as f:  # voxtool 0.3's layout: the packet is the message
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start(profile="", library="voxtool")
        schema = writer.register_schema(LEGACY_SCHEMA, "voxtool-packet-v1", b"see formats/packet.md")
        channel = writer.register_channel("/voxtool/packets/r1", "voxtool-packet-v1", schema, {"robot": "r1"})
        for seq, (_, stamp, blob) in enumerate(packets):
            writer.add_message(channel, stamp, blob, stamp, sequence=seq)
        writer.add_metadata("voxtool", {"robot": "r1", "info": '{"scans": 5}'})
        writer.finish()
    old_meta, old_messages = read_log(old)
    assert list(old_messages) == packets and old_meta == {"r1": {"scans": 5}}


def test_a_log_with_a_different_definition_is_refused_in_one_line(sample_logs, tmp_path):
    blob = sample_logs["r1"][0].read_bytes()
    bad = tmp_path / "other.mcap"
    bad.write_bytes(blob.replace(b"uint32 count ", b"uint64 count "))  # same length, another definition
    with pytest.raises(FormatError, match=f"{MESSAGE_TYPE} definition is not the one this voxtool writes"):
        read_log(bad)
