"""Maps as MCAP for robotics viewers, read back with readers voxtool did not write: rosbags'
AnyReader and mcap-ros2-support's decoder (each from the definitions the file embeds), and
OctoMap itself (pyoctomap) for the tree stream; the embedded foxglove_msgs definitions are
checked against Foxglove's schema package."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import cli

from voxtool.api import load_leaves
from voxtool.io.bt import HEADER, read_bt
from voxtool.keys import TREE_MAX_VAL, expand_leaves, morton_encode
from voxtool.maps.tree import max_likelihood


def voxels(codes, depths):
    return np.sort(expand_leaves(codes, depths))


def snapshot_sets(path):
    leaves, res, thr, _ = load_leaves(path)
    occ = leaves.values > np.float32(thr)
    return voxels(leaves.codes[occ], leaves.depths[occ]), voxels(leaves.codes[~occ], leaves.depths[~occ]), res, thr


def octomap_reads_stream(data: bytes, resolution: float, tmp_path):
    """The tree stream after a .bt header, loaded by OctoMap and written back by it: its voxels."""
    pyoctomap = pytest.importorskip("pyoctomap")
    from voxtool.kernels.bt import parse_bt

    # the header's node count (OctoMap checks it against the stream)
    nodes = parse_bt(np.frombuffer(data, np.uint8), 4 * len(data) + 1)[3]
    src = tmp_path / "stream.bt"
    src.write_bytes(f"{HEADER.decode()}\nid OcTree\nsize {nodes}\nres {resolution}\ndata\n".encode() + data)
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(src))
    assert tree.getResolution() == pytest.approx(resolution)
    back = tmp_path / "octomap_wrote.bt"
    assert tree.writeBinary(str(back))
    bt = read_bt(back)
    return voxels(bt.codes[bt.occupied], bt.depths[bt.occupied]), voxels(bt.codes[~bt.occupied], bt.depths[~bt.occupied])


def read_ros2(path):
    """{topic: (msgtype, log time, message)} of a one-message-per-topic MCAP, by rosbags."""
    from rosbags.highlevel import AnyReader

    with AnyReader([path]) as reader:
        out = {}
        for conn, log_time, raw in reader.messages():
            assert conn.topic not in out
            out[conn.topic] = (conn.msgtype, log_time, reader.deserialize(raw, conn.msgtype))
    return out


def test_map_mcap_scene_and_octomap_topics(sample_map, tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, _ = sample_map
    out = tmp_path / "map.mcap"
    code, text, err = cli("export", path, "-o", out)
    assert code == 0, err
    # the summary is words and numbers, not Python's dicts and lists
    assert not any(c in text for c in "{}[]'"), text
    assert "/octomap_binary, /voxtool/map, /projected_map" in text
    occ, free, res, thr = snapshot_sets(path)
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        decoded = {d.channel.topic: d for d in reader.iter_decoded_messages()}
    assert set(decoded) == {"/voxtool/map", "/octomap_binary", "/projected_map"}
    assert {d.schema.encoding for d in decoded.values()} == {"ros2msg"}
    assert decoded["/voxtool/map"].schema.name == "foxglove_msgs/msg/SceneUpdate"
    scene = decoded["/voxtool/map"].decoded_message  # mcap-ros2-support's decoder
    by_rosbags = read_ros2(out)["/voxtool/map"][2]
    (entity,) = scene.entities
    assert entity.id == "occupied" and entity.frame_id == "map"
    # every cube is a leaf of the max-likelihood tree: together exactly the occupied voxels
    centres = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in entity.cubes])
    assert np.array_equal(centres, [[c.pose.position.x, c.pose.position.y, c.pose.position.z]
                                    for c in by_rosbags.entities[0].cubes])
    assert {(c.pose.orientation.x, c.pose.orientation.w) for c in entity.cubes} == {(0.0, 1.0)}
    sizes = np.array([c.size.x for c in entity.cubes])
    assert np.array_equal(sizes, [c.size.z for c in entity.cubes])
    cells = np.round(sizes / res).astype(np.int64)
    depths = (16 - np.log2(cells)).astype(np.uint8)
    lo_keys = np.round(centres / res - cells[:, None] / 2 + TREE_MAX_VAL).astype(np.uint16)
    assert np.array_equal(voxels(morton_encode(lo_keys), depths), occ)
    tree = max_likelihood(load_leaves(path)[0], thr)
    assert len(entity.cubes) == int((tree.values > 0).sum())
    # coloured by height on the pictures' colour map: the lowest cube at its start, the highest at its end
    from matplotlib import colormaps

    from voxtool.io.picture import COLORMAP

    z = centres[:, 2]
    rgb = np.array([(c.color.r, c.color.g, c.color.b) for c in entity.cubes])
    ends = colormaps[COLORMAP]([0.0, 1.0])[:, :3]
    assert np.allclose(rgb[np.argmin(z)], ends[0], atol=1e-6) and np.allclose(rgb[np.argmax(z)], ends[1], atol=1e-6)
    assert (np.diff(rgb[np.argsort(z, kind="stable")][:, 1]) >= -1e-6).all()  # viridis: green rises with height
    ros = decoded["/octomap_binary"]
    msg = ros.decoded_message
    assert ros.schema.name == "octomap_msgs/msg/Octomap"
    assert msg.binary and msg.id == "OcTree" and msg.resolution == pytest.approx(res)
    data = np.asarray(msg.data, dtype=np.int8).tobytes()
    occ2, free2 = octomap_reads_stream(data, res, tmp_path)
    assert np.array_equal(occ2, occ) and np.array_equal(free2, free)


def test_map_mcap_opens_in_rosbags(sample_map, tmp_path):
    """One file for every viewer: rosbags' AnyReader opens both topics (before, the Foxglove
    scene was protobuf and rosbags could not open the file); --ros2-only changes nothing."""
    path, _ = sample_map
    out, old_flag = tmp_path / "map.mcap", tmp_path / "flag.mcap"
    assert cli("export", path, "-o", out)[0] == 0
    assert cli("export", path, "-o", old_flag, "--ros2-only")[0] == 0
    got = read_ros2(out)
    assert {t: v[0] for t, v in got.items()} == {"/octomap_binary": "octomap_msgs/msg/Octomap",
                                                 "/voxtool/map": "foxglove_msgs/msg/SceneUpdate",
                                                 "/projected_map": "nav_msgs/msg/OccupancyGrid"}
    assert {t: v[0] for t, v in read_ros2(old_flag).items()} == {t: v[0] for t, v in got.items()}
    msg = got["/octomap_binary"][2]
    occ, free, res, _ = snapshot_sets(path)
    assert msg.binary and msg.id == "OcTree" and msg.resolution == pytest.approx(res)
    occ2, free2 = octomap_reads_stream(msg.data.astype(np.int8).tobytes(), res, tmp_path)
    assert np.array_equal(occ2, occ) and np.array_equal(free2, free)


def test_embedded_scene_definition_has_foxglove_schema_fields():
    """The foxglove_msgs types the file embeds have the fields of Foxglove's schema package, in
    its order (ROS types: Timestamp -> builtin_interfaces/Time, Pose -> geometry_msgs/Pose...)."""
    pb = pytest.importorskip("foxglove_schemas_protobuf.SceneUpdate_pb2")
    from voxtool.io.ros2 import typestore

    store = typestore()
    seen = set()

    def check(descriptor, rostype):
        if rostype in seen:
            return
        seen.add(rostype)
        ros_fields = [name for name, _ in store.fielddefs[rostype][1]]
        assert ros_fields == [f.name for f in descriptor.fields], rostype
        for f in descriptor.fields:  # Foxglove's types, not google.protobuf's Timestamp and Duration
            if f.message_type is not None and f.message_type.full_name.startswith("foxglove."):
                ((kind, detail),) = [t for name, t in store.fielddefs[rostype][1] if name == f.name]
                # a type by name, or a sequence / array of one: ((NAME, type), size)
                check(f.message_type, detail if isinstance(detail, str) else detail[0][1])

    check(pb.SceneUpdate.DESCRIPTOR, "foxglove_msgs/msg/SceneUpdate")
    assert {"foxglove_msgs/msg/SceneEntity", "foxglove_msgs/msg/CubePrimitive", "foxglove_msgs/msg/Color",
            "geometry_msgs/msg/Pose", "geometry_msgs/msg/Point"} <= seen


def test_free_entity(tmp_path):
    path = tmp_path / "small.vxm"  # free space as cubes is large: one scan, 8 m rays
    assert cli("build", "--sample", "--stop", 1, "--max-range", 8, "-o", path)[0] == 0
    out = tmp_path / "free.mcap"
    assert cli("export", path, "-o", out, "--free")[0] == 0
    scene = read_ros2(out)["/voxtool/map"][2]
    assert [e.id for e in scene.entities] == ["occupied", "free"]
    assert all(c.color.a < 0.2 for c in scene.entities[1].cubes[:100])
    _, free, res, _ = snapshot_sets(path)
    sizes = np.array([c.size.x for c in scene.entities[1].cubes]) / res
    assert int(np.round(sizes ** 3).sum()) == free.shape[0]


def test_map_mcap_is_stamped_with_the_last_scan(tmp_path):
    """The exported map's messages (log time, ROS header stamp, Foxglove entity time) carry the
    time of the last scan the map holds: 0.3 s for 4 scans at 10 Hz from --poses times."""
    from voxtool.synthetic import Lidar, street, write_pcd_scans

    scans = tmp_path / "scans"
    write_pcd_scans(street(4, seed=2, lidar=Lidar(beams=8, columns=256)), scans)
    path = tmp_path / "m.vxm"
    assert cli("build", scans, "--poses", scans / "poses.txt", "--resolution", 0.4, "-o", path)[0] == 0
    out = tmp_path / "map.mcap"
    assert cli("export", path, "-o", out)[0] == 0
    got = read_ros2(out)
    assert [v[1] for v in got.values()] == [300_000_000] * 3
    msg, scene = got["/octomap_binary"][2], got["/voxtool/map"][2]
    grid = got["/projected_map"][2]
    assert (grid.header.stamp.sec, grid.header.stamp.nanosec) == (0, 300_000_000)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 300_000_000)
    assert (scene.entities[0].timestamp.sec, scene.entities[0].timestamp.nanosec) == (0, 300_000_000)


def test_sharded_map_mcap_equals_the_single_maps(tmp_path):
    """A sharded map's .mcap is written part by part (memory: a part): the same Octomap and
    OccupancyGrid as the single snapshot's of the same scans, stamped with the build's last scan,
    and a SceneUpdate per part whose cubes together cover exactly the single map's occupied voxels."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from voxtool.io.sharded import read_manifest
    from voxtool.synthetic import Lidar, street, write_pcd_scans

    scans = tmp_path / "scans"
    write_pcd_scans(street(4, seed=3, lidar=Lidar(beams=8, columns=256)), scans)
    common = [scans, "--poses", scans / "poses.txt", "--resolution", 0.4, "--no-progress"]
    assert cli("build", *common, "-o", tmp_path / "one.vxm")[0] == 0
    code, _, err = cli("build", *common, "-o", tmp_path / "parts", "--sharded", "--workers", "2")
    assert code == 0, err
    for name in ("one.vxm", "parts"):
        code, _, err = cli("export", tmp_path / name, "-o", tmp_path / f"{name}.mcap", "--z-range", "-1,3")
        assert code == 0, err

    def messages(path):
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
            return [(d.channel.topic, d.message.log_time, d.decoded_message) for d in reader.iter_decoded_messages()]

    one, parts = messages(tmp_path / "one.vxm.mcap"), messages(tmp_path / "parts.mcap")
    assert {t for t, _, _ in parts} == {t for t, _, _ in one} and {s for _, s, _ in parts} == {300_000_000}
    by_topic = {t: [m for topic, _, m in parts if topic == t] for t in ("/octomap_binary", "/projected_map",
                                                                        "/voxtool/map")}
    single = {t: m for t, _, m in one}
    assert bytes(np.asarray(by_topic["/octomap_binary"][0].data, np.int8)) == bytes(
        np.asarray(single["/octomap_binary"].data, np.int8))
    g1, g2 = single["/projected_map"], by_topic["/projected_map"][0]
    assert (g1.info.width, g1.info.height, list(g1.data)) == (g2.info.width, g2.info.height, list(g2.data))
    assert len(by_topic["/voxtool/map"]) == len(read_manifest(tmp_path / "parts")["parts"]) > 1

    def voxels(updates, res=0.4):
        out = []
        for update in updates:
            for entity in update.entities:
                for c in entity.cubes:
                    n = int(round(c.size.x / res))
                    lo = np.array([c.pose.position.x, c.pose.position.y, c.pose.position.z]) - c.size.x / 2
                    grid = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
                    out.append(np.round(lo / res).astype(np.int64) + grid)
        v = np.concatenate(out)
        return v[np.lexsort(v.T)]

    assert np.array_equal(voxels(by_topic["/voxtool/map"]), voxels([single["/voxtool/map"]]))
