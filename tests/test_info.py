"""`voxtool info`: topics and counts as rosbags' own reader counts them, the /tf tree, points
per scan as the scans hold them, and the pose source build would use (or why none)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli
from scenes import box_scene, write_pcd, yaw_quat
from test_wild_bags import write_wild_bag


def _info(*args):
    code, text, err = cli("info", *args, "--json")
    assert code == 0, err
    return json.loads(text)


def test_real_bags_topics_and_counts_are_rosbags_own(shared_data):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    bags = sorted((shared_data / "bags").glob("*.bag"))
    if not bags:
        pytest.skip("no bags in ../shared/data/bags")
    for path in bags:
        try:
            with AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC)) as reader:
                truth = {t: (i.msgtype, i.msgcount) for t, i in reader.topics.items()}
        except Exception:  # rosbags cannot read it (damaged index, pre-2.0): info says so in one line
            code, _, err = cli("info", path)
            assert code == 3 and err.count("\n") == 1 and err.startswith("voxtool: error:"), err
            continue
        f = _info(path, *(["--topic", "/cloud"] if "sick" in path.name else []))
        assert {t["topic"]: (t["type"], t["messages"]) for t in f["topics"]} == truth, path.name
        assert f["scans"] == truth[f["scan_topic"]][1]


def test_johnny5_tree_and_pose_source(shared_data):
    path = shared_data / "bags" / "johnny5_data.bag"
    if not path.exists():
        pytest.skip("johnny5_data.bag absent")
    f = _info(path)
    edges = {(e["parent"], e["child"]) for e in f["tf"]}
    assert {("odom", "base_link"), ("base_link", "base_laser"), ("base_laser", "neato_laser")} <= edges
    assert f["pose_source"] == {"posed": True, "by": "/tf: scan frame 'neato_laser' in world frame 'odom'"}
    assert f["points_per_scan"] == {"min": 360, "median": 360.0, "max": 360}


@pytest.fixture(scope="module")
def scans():
    return [(pts, origin, yaw_quat(yaw)) for pts, origin, yaw in box_scene(5, 200, seed=3)]


def test_a_bag_nothing_poses_names_what_would(tmp_path, scans):
    path = write_wild_bag(tmp_path / "b.bag", scans, tf="none", odom=True)
    f = _info(path)
    assert f["pose_source"]["posed"] is False
    assert "--pose-topic /odom" in f["pose_source"]["why"]
    f = _info(path, "--pose-topic", "/odom")
    assert f["pose_source"] == {"posed": True, "by": "pose topic /odom", "mount": "'/odom' poses the scan frame 'lidar' itself"}
    assert f["scans"] == len(scans) and f["time_span"]["seconds"] == pytest.approx(0.4)
    assert f["points_per_scan"]["max"] == max(len(p) for p, _, _ in scans)


def test_legacy_tf_is_the_tree(tmp_path, scans):
    f = _info(write_wild_bag(tmp_path / "b.bag", scans, tf="legacy"))
    assert [(e["parent"], e["child"], e["transforms"]) for e in f["tf"]] == [("odom", "lidar", len(scans))]
    assert f["pose_source"]["posed"] is True


def test_a_pcd_folder(tmp_path):
    rng = np.random.default_rng(1)
    sizes = [30, 50, 40]
    for i, n in enumerate(sizes):
        write_pcd(tmp_path / f"{i}.pcd", rng.normal(size=(n, 3)).astype(np.float32))
    f = _info(tmp_path)
    assert f["scans"] == 3 and f["points_per_scan"] == {"min": 30, "median": 40.0, "max": 50}
    assert f["fields"] == ["x", "y", "z"]
    code, text, _ = cli("info", tmp_path)
    assert code == 0 and "points per scan  min 30, median 40, max 50" in text
