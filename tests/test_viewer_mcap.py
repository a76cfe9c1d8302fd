"""Maps as MCAP for robotics viewers, read back with readers voxtool did not write: the mcap
library with Foxglove's protobuf classes, mcap-ros2-support's decoder, rosbags, and OctoMap
itself (pyoctomap) for the tree stream."""

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


def test_map_mcap_scene_and_octomap_topics(sample_map, tmp_path):
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, _ = sample_map
    out = tmp_path / "map.mcap"
    code, _, err = cli("export", path, "-o", out)
    assert code == 0, err
    occ, free, res, thr = snapshot_sets(path)
    with open(out, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()], validate_crcs=True)
        messages = {channel.topic: (schema, message) for schema, channel, message in reader.iter_messages()}
        assert set(messages) == {"/voxtool/map", "/octomap_binary"}
        schema, message = messages["/voxtool/map"]
        assert schema.name == "foxglove.SceneUpdate" and schema.encoding == "protobuf"
        scene = SceneUpdate.FromString(message.data)  # Foxglove's own classes
        ros = list(reader.iter_decoded_messages(topics=["/octomap_binary"]))
    (entity,) = scene.entities
    assert entity.id == "occupied" and entity.frame_id == "map"
    # every cube is a leaf of the max-likelihood tree: together exactly the occupied voxels
    centres = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in entity.cubes])
    sizes = np.array([c.size.x for c in entity.cubes])
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
    (decoded,) = ros
    msg = decoded.decoded_message
    assert decoded.schema.name == "octomap_msgs/msg/Octomap" and decoded.schema.encoding == "ros2msg"
    assert msg.binary and msg.id == "OcTree" and msg.resolution == pytest.approx(res)
    data = np.asarray(msg.data, dtype=np.int8).tobytes()
    occ2, free2 = octomap_reads_stream(data, res, tmp_path)
    assert np.array_equal(occ2, occ) and np.array_equal(free2, free)


def test_ros2_only_map_mcap_opens_in_rosbags(sample_map, tmp_path):
    from rosbags.highlevel import AnyReader

    path, _ = sample_map
    out = tmp_path / "ros.mcap"
    assert cli("export", path, "-o", out, "--ros2-only")[0] == 0
    with AnyReader([out]) as reader:
        (conn,) = [c for c in reader.connections if c.topic == "/octomap_binary"]
        assert conn.msgtype == "octomap_msgs/msg/Octomap"
        (raw,) = [raw for _, _, raw in reader.messages(connections=[conn])]
        msg = reader.deserialize(raw, conn.msgtype)
    occ, free, res, _ = snapshot_sets(path)
    assert msg.binary and msg.id == "OcTree" and msg.resolution == pytest.approx(res)
    occ2, free2 = octomap_reads_stream(msg.data.astype(np.int8).tobytes(), res, tmp_path)
    assert np.array_equal(occ2, occ) and np.array_equal(free2, free)


def test_free_entity_and_refusals(tmp_path):
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader

    path = tmp_path / "small.vxm"  # free space as cubes is large: one scan, 8 m rays
    assert cli("build", "--sample", "--stop", 1, "--max-range", 8, "-o", path)[0] == 0
    out = tmp_path / "free.mcap"
    assert cli("export", path, "-o", out, "--free")[0] == 0
    with open(out, "rb") as f:
        (msg,) = [m for _, c, m in make_reader(f).iter_messages() if c.topic == "/voxtool/map"]
    scene = SceneUpdate.FromString(msg.data)
    assert [e.id for e in scene.entities] == ["occupied", "free"]
    assert all(c.color.a < 0.2 for c in scene.entities[1].cubes[:100])
    _, free, res, _ = snapshot_sets(path)
    sizes = np.array([c.size.x for c in scene.entities[1].cubes]) / res
    assert int(np.round(sizes ** 3).sum()) == free.shape[0]
    code, _, err = cli("export", path, "-o", tmp_path / "x.mcap", "--free", "--ros2-only")
    assert code == 2 and err.count("\n") == 1 and not (tmp_path / "x.mcap").exists()


def test_map_mcap_is_stamped_with_the_last_scan(tmp_path):
    """The exported map's messages (log time, ROS header stamp, Foxglove entity time) carry the
    time of the last scan the map holds: 0.3 s for 4 scans at 10 Hz from --poses times."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    from voxtool.synthetic import Lidar, street, write_pcd_scans

    scans = tmp_path / "scans"
    write_pcd_scans(street(4, seed=2, lidar=Lidar(beams=8, columns=256)), scans)
    path = tmp_path / "m.vxm"
    assert cli("build", scans, "--poses", scans / "poses.txt", "--resolution", 0.4, "-o", path)[0] == 0
    ros, both = tmp_path / "ros.mcap", tmp_path / "both.mcap"
    assert cli("export", path, "-o", ros, "--ros2-only")[0] == 0
    assert cli("export", path, "-o", both)[0] == 0
    with AnyReader([ros]) as reader:
        ((_, log_time, raw),) = list(reader.messages())
        msg = reader.deserialize(raw, "octomap_msgs/msg/Octomap")
    assert log_time == 300_000_000 and (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 300_000_000)
    with open(both, "rb") as f:
        messages = list(make_reader(f).iter_messages())
    assert [m.log_time for _, _, m in messages] == [300_000_000] * 2
    (scene,) = [SceneUpdate.FromString(m.data) for _, c, m in messages if c.topic == "/voxtool/map"]
    assert scene.entities[0].timestamp.ToNanoseconds() == 300_000_000
