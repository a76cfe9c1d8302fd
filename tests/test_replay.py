"""`merge --view` / `decode --view`: the ROS 2 SceneUpdates, read with rosbags' AnyReader and
applied by Foxglove's rule (an entity replaces the one with its id; deletions remove), end in
exactly the fused map's occupied voxels, each in the colour of the robot that set it last."""

from __future__ import annotations

import json

import numpy as np
from conftest import cli
from matplotlib.colors import to_hex

from voxtool.codec.fusion import packets_of
from voxtool.codec.packet import OCCUPIED
from voxtool.keys import coords_to_keys, morton_encode


def _apply_updates(path):
    from rosbags.highlevel import AnyReader

    entities, stamps = {}, []
    with AnyReader([path]) as reader:
        for conn, log_time, raw in reader.messages():
            assert conn.msgtype == "foxglove_msgs/msg/SceneUpdate" and conn.topic == "/voxtool/fusion"
            update = reader.deserialize(raw, conn.msgtype)
            stamps.append(log_time)
            for deletion in update.deletions:  # a keyframe deletes all, then re-sends everything
                if deletion.type == deletion.ALL:
                    entities.clear()
                else:
                    entities.pop(deletion.id, None)
            for entity in update.entities:
                entities[entity.id] = entity
    return entities, stamps


def _last_writers(logs, until_ns=None):
    """Brute force: every packet's voxels (up to a time) in (stamp, robot, sequence) order; the
    last one wins."""
    packets = sorted((p for log in logs for p in packets_of(log) if until_ns is None or p.stamp_ns <= until_ns),
                     key=lambda p: (p.stamp_ns, p.robot, p.seq))
    owner = {}
    for p in packets:
        for code, state in zip(morton_encode(p.keys).tolist(), p.states.tolist()):
            owner[code] = (p.robot, state)
    return {code: robot for code, (robot, state) in owner.items() if state == OCCUPIED}


def test_merge_view_replays_to_the_fused_map_in_robot_colours(sample_logs, tmp_path):
    logs = [sample_logs["a"][0], sample_logs["b"][0]]
    view = tmp_path / "fused.mcap"
    code, text, err = cli("merge", *logs, "--view", view, "--view-period", "0", "--json")
    assert code == 0, err
    report = json.loads(text)
    entities, stamps = _apply_updates(view)
    assert len(stamps) == report["view_messages"] > 2 and stamps == sorted(stamps)
    resolution = packets_of(logs[0])[0].resolution
    drawn = {}
    for entity_id, entity in entities.items():
        robot = entity_id.split("/")[0]
        first = entity.cubes[0].color
        assert to_hex((first.r, first.g, first.b)) == report["view_colours"][robot]
        centres = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in entity.cubes])
        for code in morton_encode(coords_to_keys(centres, resolution)).tolist():
            assert code not in drawn
            drawn[code] = robot
    expect = _last_writers(logs)
    assert len(drawn) == report["occupied_voxels"] == len(expect) and drawn == expect
    assert set(drawn.values()) == {"a", "b"}


def test_decode_view_is_refused_with_relay_and_for_another_suffix(sample_logs, tmp_path):
    log = sample_logs["r1"][0]
    code, _, err = cli("decode", log, "--view", tmp_path / "v.png")
    assert code == 2 and "--view" in err and ".mcap" in err
    code, _, err = cli("decode", log, "--view", tmp_path / "v.mcap", "--relay")
    assert code == 2 and not (tmp_path / "v.mcap").exists()


def test_view_period_spaces_the_messages(sample_logs, tmp_path):
    """Messages at the first packet time, then at the first packet time at least a period after
    the previous message, then the last packet's; period 0: one per distinct packet time."""
    logs = [sample_logs["a"][0], sample_logs["b"][0]]
    times = sorted({p.stamp_ns for log in logs for p in packets_of(log)})
    assert len(times) > 4
    for period in (0.0, 0.25, 1.0):
        view = tmp_path / f"v{period}.mcap"
        code, _, err = cli("merge", *logs, "--view", view, "--view-period", period)
        assert code == 0, err
        _, stamps = _apply_updates(view)
        expect = [times[0]]
        for t in times[1:]:
            if t - expect[-1] >= period * 1e9:
                expect.append(t)
        if expect[-1] != times[-1]:
            expect.append(times[-1])
        assert stamps == expect, period


def test_every_keyframe_alone_shows_the_whole_fused_map_at_its_time(sample_logs, tmp_path):
    """A viewer that starts at a keyframe: the keyframe's entities alone are every voxel occupied
    in the fused map of the packets up to its time, each in its last writer's colour; the first
    message is one, and they come --view-keyframe seconds of packet time apart."""
    from rosbags.highlevel import AnyReader

    logs = [sample_logs["a"][0], sample_logs["b"][0]]
    view = tmp_path / "kf.mcap"
    code, text, err = cli("merge", *logs, "--view", view, "--view-period", "0", "--view-keyframe", "0.15", "--json")
    assert code == 0, err
    report = json.loads(text)
    resolution = packets_of(logs[0])[0].resolution
    keyframes = []
    with AnyReader([view]) as reader:
        for conn, log_time, raw in reader.messages():
            update = reader.deserialize(raw, conn.msgtype)
            if any(d.type == d.ALL for d in update.deletions):
                keyframes.append((log_time, update))
    assert len(keyframes) == report["view_keyframes"] >= 3
    assert keyframes[0][0] == min(p.stamp_ns for log in logs for p in packets_of(log))
    gaps = np.diff([t for t, _ in keyframes])
    assert (gaps >= 0.15e9).all()
    for log_time, update in keyframes:
        drawn = {}
        for entity in update.entities:
            robot = entity.id.split("/")[0]
            centres = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in entity.cubes])
            for code in morton_encode(coords_to_keys(centres, resolution)).tolist():
                drawn[code] = robot
        assert drawn == _last_writers(logs, log_time), log_time
