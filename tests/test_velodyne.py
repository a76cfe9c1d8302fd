"""Velodyne driver packets (velodyne_msgs/VelodyneScan) in real ROS 2 bags, decoded through
velodyne-decoder (voxtool.sources.velodyne), against a second decoder: TIER IV nebula's own
output for one message of each bag (VLP-16 dual return, VLP-32C, VLS-128). The maps they make
are those of the same points written as PCD."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from conftest import cli, map_voxels, skip_unfetched
from scenes import write_pcd

from voxtool.sources import SourceOptions, open_source
from voxtool.sources.pcd import read_pcd

pytest.importorskip("velodyne_decoder")

FRAMES = {"vlp16": "velodyne", "vlp32": "velodyne_front", "vls128": "velodyne_top"}


def _bag(nebula_bags, sensor):
    root = nebula_bags[0].parent
    if not (root / sensor / "metadata.yaml").is_file():
        pytest.skip(f"the nebula {sensor} bag is absent")
    return root / sensor


@pytest.mark.parametrize("sensor", sorted(FRAMES))
def test_revolutions_match_nebulas_decoder(nebula_bags, sensor):
    import open3d as o3d

    bag = _bag(nebula_bags, sensor)
    truth_file = next((bag.parent / "ground_truth" / sensor).glob("*.pcd"), None)
    if truth_file is None:
        skip_unfetched("nebula's decoded clouds are absent", "nebula")
    # the message nebula decoded, by its log time (the file's name), read from the bag's database itself
    times = [t for (t,) in sqlite3.connect(next(bag.glob("*.db3"))).execute("SELECT timestamp FROM messages ORDER BY timestamp")]
    scans = list(open_source(bag, SourceOptions(world_frame=FRAMES[sensor])).scans)
    assert len(scans) == len(times)
    ours = scans[times.index(int(truth_file.stem))].points.astype(np.float64)
    theirs = read_pcd(truth_file).xyz.astype(np.float64)
    assert abs(len(ours) - len(theirs)) <= 0.01 * len(theirs)
    a, b = (o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)) for p in (ours, theirs))
    for d in (np.asarray(a.compute_point_cloud_distance(b)), np.asarray(b.compute_point_cloud_distance(a))):
        # the two decoders' calibrations and azimuth interpolation differ by millimetres to centimetres
        assert np.median(d) < 0.03 and np.percentile(d, 95) < 0.15


def test_info_names_the_sensor_its_return_mode_and_rate(nebula_bags):
    code, text, err = cli("info", _bag(nebula_bags, "vlp16"), "--json")
    assert code == 0, err
    info = json.loads(text)
    assert info["scan_type"] == "velodyne_msgs/msg/VelodyneScan" and info["scans"] == 4
    assert info["lidar"]["model"] == "VLP16" and info["lidar"]["return_mode"] == "BOTH"
    assert 9.0 < info["lidar"]["rate_hz"] < 11.0  # a VLP-16 at 600 rpm
    assert info["points_per_scan"]["min"] > 14_000


def test_a_packet_bag_maps_as_its_points_in_pcd(nebula_bags, tmp_path):
    """build, encode and merge of the VLS-128 bag (its topics' serialization left blank, as some
    rosbag2 releases wrote them) hold the map of the same revolutions written as PCD scans."""
    bag = _bag(nebula_bags, "vls128")
    scans = list(open_source(bag, SourceOptions(world_frame=FRAMES["vls128"])).scans)
    assert len(scans) == 4 and min(s.points.shape[0] for s in scans) > 100_000
    pcd = tmp_path / "pcd"
    pcd.mkdir()
    for s in scans:
        write_pcd(pcd / f"{s.index:03d}.pcd", s.points)
    common = ["--resolution", "0.2", "--max-range", "30", "--no-progress"]  # rays cut at 30 m: seconds, not tens
    assert cli("build", bag, "-o", tmp_path / "bag.vxm", "--world-frame", FRAMES["vls128"], *common)[0] == 0
    assert cli("build", pcd, "-o", tmp_path / "pcd.vxm", *common)[0] == 0
    code, text, err = cli("encode", bag, "-o", tmp_path / "e.mcap", "--world-frame", FRAMES["vls128"], "--json", *common)
    assert code == 0, err
    assert cli("merge", tmp_path / "e.mcap", "-o", tmp_path / "m.vxm", "--no-progress")[0] == 0
    built = map_voxels(tmp_path / "bag.vxm")
    assert built[0].size > 10_000
    for other in ("pcd.vxm", "m.vxm"):
        occ, free = map_voxels(tmp_path / other)
        assert np.array_equal(occ, built[0]) and np.array_equal(free, built[1])


def test_odometry_poses_a_packet_bag(nebula_bags, tmp_path):
    bag = _bag(nebula_bags, "vlp32")
    code, _, err = cli("odometry", bag, "-o", tmp_path / "poses.txt", "--no-progress")
    assert code == 0, err
    rows = [line.split() for line in (tmp_path / "poses.txt").read_text().splitlines() if not line.startswith("#")]
    # a pose per revolution, at the revolution's own stamp
    stamps = [s.stamp_ns for s in open_source(bag, SourceOptions(world_frame=FRAMES["vlp32"])).scans]
    assert [round(float(r[0]) * 1e9) for r in rows] == pytest.approx(stamps, abs=1000)
    code, text, err = cli("build", bag, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "m.vxm", "--json",
                          "--no-progress")
    assert code == 0, err
    assert json.loads(text)["scans"] == 5


def _capture(bag, path, fmt):
    """The bag's Velodyne packets as a capture written by dpkt (Ethernet, IP, UDP to port 2368),
    each packet at its own stamp."""
    import dpkt

    from voxtool.sources.rosbag import open_bag

    opened = open_bag(bag, False)
    msgs = [opened.deserialize(raw, t) for _, t, raw in opened.messages(list(opened.topics))]
    with open(path, "wb") as f:
        writer = dpkt.pcap.Writer(f) if fmt == "pcap" else dpkt.pcapng.Writer(f)
        for m in msgs:
            for p in m.packets:
                udp = dpkt.udp.UDP(sport=2368, dport=2368, data=p.data.tobytes())
                udp.ulen = len(udp)
                ip = dpkt.ip.IP(src=bytes([192, 168, 1, 201]), dst=bytes([255] * 4), p=dpkt.ip.IP_PROTO_UDP, data=udp)
                ip.len = len(ip)
                frame = dpkt.ethernet.Ethernet(src=bytes(6), dst=b"\xff" * 6, type=dpkt.ethernet.ETH_TYPE_IP, data=ip)
                writer.writepkt(bytes(frame), ts=p.stamp.sec + p.stamp.nanosec * 1e-9)
    return path


@pytest.mark.parametrize("fmt", ["pcap", "pcapng"])
def test_a_capture_holds_the_points_of_its_packets(nebula_bags, tmp_path, fmt):
    """A capture of the VLP-16 bag's packets is cut into revolutions where the azimuth wraps,
    not where the messages were, but holds exactly their points; it needs poses, which odometry
    gives, and info names the sensor."""
    bag = _bag(nebula_bags, "vlp16")
    capture = _capture(bag, tmp_path / f"v.{fmt}", fmt)
    from_bag = np.concatenate([s.points for s in open_source(bag, SourceOptions(world_frame="velodyne")).scans])
    code, _, err = cli("build", capture, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code != 0 and "holds no poses" in err and not (tmp_path / "m.vxm").exists()
    assert cli("odometry", capture, "-o", tmp_path / "poses.txt", "--no-progress")[0] == 0
    scans = list(open_source(capture, SourceOptions(poses=str(tmp_path / "poses.txt"))).scans)
    assert len(scans) == 4
    ours = np.concatenate([s.points for s in scans])
    # the first pose is the identity: compare the first revolution's points, and all points' count
    assert ours.shape == from_bag.shape
    key = np.dtype("f4,f4,f4")
    first = scans[0].points
    assert np.isin(first.view(key).ravel(), from_bag.view(key).ravel()).all()
    code, text, _ = cli("info", capture, "--json")
    info = json.loads(text)
    assert code == 0 and info["scans"] == 4 and info["lidar"]["model"] == "VLP16"
    assert sorted(map(tuple, np.concatenate([s.points for s in open_source(
        capture, SourceOptions(sensor_frame=True)).scans]).tolist())) == sorted(map(tuple, from_bag.tolist()))


def test_a_capture_cut_short_reads_up_to_its_cut_record_and_says_so(nebula_bags, tmp_path):
    """A recording that was stopped: the file ends inside its last record (in the packet, or in
    the record's header). The packets before it read as the capture without that record, with
    one warning (dpkt itself yields a record cut in its data as if whole, and raises on a cut
    header)."""
    import warnings

    whole = _capture(_bag(nebula_bags, "vlp16"), tmp_path / "whole.pcap", "pcap").read_bytes()
    record = 16 + 14 + 20 + 8 + 1206  # pcap record header, Ethernet, IP, UDP, a data packet
    (tmp_path / "ends_whole.pcap").write_bytes(whole[:-record])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a capture of whole records: no warning
        expected = [s.points for s in open_source(tmp_path / "ends_whole.pcap", SourceOptions(sensor_frame=True)).scans]
    for name, keep in (("in_packet", len(whole) - 500), ("in_header", len(whole) - record + 8)):
        cut = tmp_path / f"{name}.pcap"
        cut.write_bytes(whole[:keep])
        code, text, err = cli("info", cut, "--json")
        assert code == 0 and err.count("cut short in its last record") == 1, err
        assert json.loads(text)["scans"] == len(expected)
        from voxtool.errors import VoxtoolWarning

        with pytest.warns(VoxtoolWarning, match="cut short in its last record"):
            got = [s.points for s in open_source(cut, SourceOptions(sensor_frame=True)).scans]
        assert len(got) == len(expected) and all(np.array_equal(a, b) for a, b in zip(got, expected))


def test_the_rate_of_a_capture_started_mid_revolution(nebula_bags, tmp_path):
    """A capture started a quarter turn late (its first 90 of 603 packets left out): its first
    revolution is cut, and the rate stays the sensor's (over the stamps' span it read 12.5/s)."""
    whole = _capture(_bag(nebula_bags, "vlp16"), tmp_path / "whole.pcap", "pcap")
    record = 16 + 14 + 20 + 8 + 1206
    late = tmp_path / "late.pcap"
    late.write_bytes(whole.read_bytes()[:24] + whole.read_bytes()[24 + 90 * record:])  # the file header, then packets
    rates = []
    for capture in (whole, late):
        code, text, err = cli("info", capture, "--json")
        assert code == 0, err
        rates.append(json.loads(text)["lidar"]["rate_hz"])
    assert abs(rates[0] - 10.0) < 0.1 and abs(rates[1] - rates[0]) < 0.05 * rates[0], rates


def test_a_file_that_is_no_capture_fails_on_one_line(tmp_path):
    bad = tmp_path / "x.pcap"
    bad.write_bytes(b"not a capture at all" * 10)
    code, _, err = cli("info", bad)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code != 0 and len(lines) == 1 and str(bad) in lines[0] and "pcap" in lines[0]


def test_an_ouster_capture_is_one_line_that_says_how_to_convert_it(tmp_path):
    """Ouster's own test captures (scripts/fetch_samples.py ouster): no Velodyne packet in them, so
    one line, exit 3, naming the packets' size and the conversion; no map written."""
    from conftest import FETCHED

    captures = sorted((FETCHED / "ouster").glob("*.pcap"))
    if not captures:
        skip_unfetched("the Ouster captures are absent", "ouster")
    for capture in captures:
        (tmp_path / "poses.txt").write_text("0 0 0 0 0 0 0 1\n")
        code, _, err = cli("build", capture, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "m.vxm", "--no-progress")
        lines = [line for line in err.splitlines() if line.strip()]
        assert code == 3 and len(lines) == 1 and not (tmp_path / "m.vxm").exists()
        assert str(capture) in lines[0] and "no Velodyne data packet" in lines[0] and "ouster-cli" in lines[0]


VELODYNE_SCAN_ROS2MSG = """std_msgs/Header header
velodyne_msgs/VelodynePacket[] packets
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
================================================================================
MSG: velodyne_msgs/VelodynePacket
builtin_interfaces/Time stamp
uint8[1206] data
"""


def test_an_mcap_of_packets_reads_as_the_bag(nebula_bags, tmp_path):
    """The VLP-16 bag's messages, byte for byte, in an MCAP (written by the mcap library with the
    message definition, as `ros2 bag record -s mcap` stores them): the same revolutions."""
    from mcap.writer import Writer

    bag = _bag(nebula_bags, "vlp16")
    rows = sqlite3.connect(next(bag.glob("*.db3"))).execute(
        "SELECT messages.timestamp, messages.data FROM messages ORDER BY messages.timestamp").fetchall()
    path = tmp_path / "packets.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2")
        schema = writer.register_schema(name="velodyne_msgs/msg/VelodyneScan", encoding="ros2msg",
                                        data=VELODYNE_SCAN_ROS2MSG.encode())
        channel = writer.register_channel(topic="/velodyne_packets", message_encoding="cdr", schema_id=schema)
        for k, (stamp, data) in enumerate(rows):
            writer.add_message(channel, log_time=stamp, data=bytes(data), publish_time=stamp, sequence=k)
        writer.finish()
    options = SourceOptions(world_frame="velodyne")
    from_mcap = [s.points for s in open_source(path, options).scans]
    from_bag = [s.points for s in open_source(bag, options).scans]
    assert len(from_mcap) == 4 and all(np.array_equal(a, b) for a, b in zip(from_mcap, from_bag))
