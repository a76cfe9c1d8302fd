"""`merge --view` / `decode --view`: the SceneUpdates, read with Foxglove's protobuf classes and
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
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from mcap.reader import make_reader

    entities, stamps = {}, []
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schema.name == "foxglove.SceneUpdate" and channel.topic == "/voxtool/fusion"
            update = SceneUpdate.FromString(message.data)
            stamps.append(message.log_time)
            for deletion in update.deletions:
                entities.pop(deletion.id, None)
            for entity in update.entities:
                entities[entity.id] = entity
    return entities, stamps


def _last_writers(logs):
    """Brute force: every packet's voxels in (stamp, robot, sequence) order; the last one wins."""
    packets = sorted((p for log in logs for p in packets_of(log)), key=lambda p: (p.stamp_ns, p.robot, p.seq))
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
