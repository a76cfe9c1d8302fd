"""Packet logs as ROS 2 MCAP: readers voxtool did not write (rosbags, the mcap reader with
mcap-ros2-support's decoder) decode every header field, and logs of the old layout still read."""

from __future__ import annotations

import pytest
from conftest import cli

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


def write_legacy_log(path, packets, info: dict | None = None):
    """A packet log in the first layout (schema voxtool/MapPacket, the packet as the whole message)
    of robot r1's (robot, stamp, packet) messages; `info`: its metadata record."""
    import json

    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.NONE)
        writer.start(profile="", library="voxtool")
        schema = writer.register_schema(LEGACY_SCHEMA, "voxtool-packet-v1", b"see formats/packet.md")
        channel = writer.register_channel("/voxtool/packets/r1", "voxtool-packet-v1", schema, {"robot": "r1"})
        for seq, (_, stamp, blob) in enumerate(packets):
            writer.add_message(channel, stamp, blob, stamp, sequence=seq)
        if info is not None:
            writer.add_metadata("voxtool", {"robot": "r1", "info": json.dumps(info)})
        writer.finish()
    return path


def test_a_log_of_the_old_layout_reads_the_same_packets(sample_logs, tmp_path):
    log = sample_logs["r1"][0]
    meta, messages = read_log(log)
    packets = list(messages)
    old = write_legacy_log(tmp_path / "old.mcap", packets, {"scans": 5})
    old_meta, old_messages = read_log(old)
    assert list(old_messages) == packets and old_meta == {"r1": {"scans": 5}}


def test_a_log_with_a_different_definition_is_refused_in_one_line(sample_logs, tmp_path):
    blob = sample_logs["r1"][0].read_bytes()
    bad = tmp_path / "other.mcap"
    bad.write_bytes(blob.replace(b"uint32 count ", b"uint64 count "))  # same length, another definition
    with pytest.raises(FormatError, match=f"{MESSAGE_TYPE} definition is not one this voxtool reads"):
        read_log(bad)


def test_a_log_with_the_earlier_map_origin_comment_still_reads(sample_logs, tmp_path):
    """Logs written before the map_origin comment was corrected ("key 0") decode as before."""
    from mcap_ros2.writer import Writer

    from voxtool.codec.log import MESSAGE_DEFINITION, packet_message

    meta, messages = read_log(sample_logs["r1"][0])
    packets = list(messages)
    old = tmp_path / "old.mcap"
    earlier = MESSAGE_DEFINITION.replace("world position of the key-32768 corner, m", "world position of key 0, m")
    assert earlier != MESSAGE_DEFINITION
    with open(old, "wb") as f:
        writer = Writer(f)
        schema = writer.register_msgdef(MESSAGE_TYPE, earlier)
        for robot, stamp, blob in packets:
            writer.write_message(f"/voxtool/packets/{robot}", schema, packet_message(blob), log_time=stamp,
                                 publish_time=stamp)
        writer.finish()
    _, old_messages = read_log(old)
    assert list(old_messages) == packets


def test_log_names_its_writer_and_its_message_text_is_the_specs(sample_logs):
    """The metadata record carries the writer's version; the message definition embedded in the
    log (read by the mcap library) is the one formats/packet.md prints, word for word."""
    import re
    from pathlib import Path

    from mcap.reader import make_reader

    import voxtool

    with open(sample_logs["r1"][0], "rb") as f:
        reader = make_reader(f)
        records = list(reader.iter_metadata())
        schemas = list(reader.get_summary().schemas.values())
    assert [r.metadata["writer"] for r in records] == [f"voxtool {voxtool.__version__}"]
    embedded = schemas[0].data.decode()
    spec = (Path(__file__).resolve().parents[1] / "formats" / "packet.md").read_text()
    block = re.search(r"```\n(\s*string robot .*?)```", spec, re.S)
    assert block is not None
    fields = [line for line in embedded.splitlines() if not line.startswith("#")]  # the two lead comments
    assert [line.strip() for line in block.group(1).strip().splitlines()] == fields
    assert "key-32768 corner" in embedded


def test_logs_on_clocks_years_apart(sample_logs, tmp_path):
    """The sample's log is stamped in epoch time (its poses.txt); a generated street's from 0.
    Fusing them warns that the latest stamp means nothing across them; the bandwidth windows
    count only seconds that hold packets (a window per second of 53 years would not fit)."""
    import numpy as np

    from voxtool.codec.logstats import _bandwidth
    from voxtool.synthetic import Lidar, street, write_pcd_scans

    scans = tmp_path / "street"
    write_pcd_scans(street(3, seed=5, lidar=Lidar(beams=4, columns=64)), scans)
    (scans / "poses.txt").unlink()  # index / 10 Hz from 0
    code, _, err = cli("encode", scans, "-o", tmp_path / "s.mcap", "--robot", "s", "--max-range", 20, "--no-progress")
    assert code == 0, err
    code, _, err = cli("merge", sample_logs["r1"][0], tmp_path / "s.mcap", "-o", tmp_path / "f.vxm", "--no-progress")
    assert code == 0, err
    assert err.count("voxtool: warning:") == 1 and "robot 'r1' is stamped" in err and "days after robot 's'" in err
    code, _, err = cli("merge", sample_logs["a"][0], sample_logs["b"][0], "-o", tmp_path / "g.vxm", "--no-progress")
    assert code == 0 and "warning" not in err, err

    years = 5 * 365 * 86_400 * 10**9
    got = _bandwidth(np.array([0, 10**8, years], np.int64), np.array([10, 20, 7], np.int64), 1.0)
    assert got["max_Bps"] == 37.0  # the average over the 1 s span given; the busiest second holds 30
    got = _bandwidth(np.array([0, 10**8, years], np.int64), np.array([10, 20, 7], np.int64), years / 1e9)
    assert got["max_Bps"] == 30.0


def test_logs_encoded_without_robot_are_named_after_their_files(tmp_path):
    """Two logs encoded without --robot used to both be 'r1', and merge refused them as one
    robot's log given twice; now each robot is named after its log's file."""
    import json

    for name, (start, stop) in (("north", (0, 2)), ("south-robot-with-a-long-name", (2, 4))):
        code, text, err = cli("encode", "--sample", "-o", tmp_path / f"{name}.mcap", "--start", start, "--stop", stop,
                              "--max-range", 20, "--json", "--no-progress")
        assert code == 0, err
    assert json.loads(text)["robot"] == "south-robot-with"  # cut to the format's 16 bytes
    code, text, err = cli("merge", tmp_path / "north.mcap", tmp_path / "south-robot-with-a-long-name.mcap",
                          "-o", tmp_path / "fused.vxm", "--json", "--no-progress")
    assert code == 0, err
    assert set(json.loads(text)["robots"]) == {"north", "south-robot-with"}
    for name in ("a", "b"):
        assert cli("encode", "--sample", "-o", tmp_path / f"{name}.mcap", "--robot", "same", "--stop", 2,
                   "--max-range", 20, "--no-progress")[0] == 0
    code, _, err = cli("merge", tmp_path / "a.mcap", tmp_path / "b.mcap", "-o", tmp_path / "f2.vxm", "--no-progress")
    assert code == 2 and "encode each with its own --robot" in err, err


@pytest.mark.parametrize("scheme, codec", [("hilbert", "zstd"), ("nested", "cm"), ("racer", "zstd"),
                                           ("occupied", "zstd")])
def test_stats_from_the_headers_equal_the_decoded_packets(tmp_path, scheme, codec):
    """`stats` reads packet headers, not payloads: its counts equal those of every packet decoded
    here, the RACER comparison is the brute-force sum of RACER's sizes, and a log of the old
    layout (the packet as the whole message) gives the same figures."""
    import json

    import numpy as np

    from voxtool.codec.fusion import packets_of
    from voxtool.codec.packet import address_width

    log = tmp_path / f"{scheme}.mcap"
    code, _, err = cli("encode", "--sample", "-o", log, "--scheme", scheme, "--codec", codec, "--max-range", "20",
                       "--robot", "r1", "--no-progress")
    assert code == 0, err
    code, text, err = cli("stats", log, "--json")
    assert code == 0, err
    got = json.loads(text)["robots"]["r1"]
    packets = packets_of(log)
    deltas = [p for p in packets if p.kind == 0]
    assert got["packets"] == len(packets) and got["bytes"] == sum(p.wire_bytes for p in packets)
    assert got["changed_voxels"] == sum(int(p.keys.shape[0]) for p in deltas) > 1000
    assert got["raw_payload_bytes"] == sum(p.raw_size for p in packets)
    racer = sum(96 + len(p.keys) * address_width((int(np.prod(p.box_dims)), 1, 1)) + (len(p.keys) + 3) // 4
                for p in deltas)
    assert got["vs_racer"] == pytest.approx(racer / got["bytes"], abs=1e-3)

    _, messages = read_log(log)
    old = write_legacy_log(tmp_path / "old.mcap", list(messages))
    old_stats = json.loads(cli("stats", old, "--json")[1])["robots"]["r1"]
    same = ("packets", "bytes", "changed_voxels", "raw_payload_bytes", "stored_payload_bytes", "vs_racer")
    assert {k: old_stats[k] for k in same} == {k: got[k] for k in same}
