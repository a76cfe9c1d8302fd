"""The octree backend against independent truths: a line-by-line Python transcription of
OctoMap's ray casting and update rule, and the real OctoMap library (pyoctomap)."""

from __future__ import annotations

import numpy as np
import pytest
from reference import DictOctoMap, scan_update_sets
from scenes import box_scene

from voxtool.config import MapParams, SensorModel
from voxtool.geometry import Pose
from voxtool.io.bt import bt_bytes, read_bt
from voxtool.keys import expand_leaves, morton_decode, morton_encode
from voxtool.maps.octree import OctreeMap, scan_updates
from voxtool.sources.scan import Scan

SENSOR = SensorModel()


def world_scans(n_scans=3, n_points=250, seed=0):
    out = []
    for pts, origin, yaw in box_scene(n_scans, n_points, seed):
        pose = Pose.from_quat(origin, np.cos(yaw / 2), 0, 0, np.sin(yaw / 2))
        out.append(Scan(pose.apply(pts), origin.astype(np.float32)))
    return out


def finest_values(m: OctreeMap) -> dict:
    lv = m.leaves()
    codes = expand_leaves(lv.codes, lv.depths)
    vals = np.repeat(lv.values, (1 << (3 * (16 - lv.depths.astype(np.int64)))))
    return {tuple(int(v) for v in k): float(x) for k, x in zip(morton_decode(codes), vals)}


@pytest.mark.parametrize("max_range", [-1.0, 2.5])
@pytest.mark.parametrize("res", [0.1, 0.25])
def test_scan_updates_equal_reference_ray_sets(res, max_range):
    for scan in world_scans(2, 200, seed=int(res * 100)):
        packed, _, _ = scan_updates(scan, MapParams(resolution=res, max_range=max_range))
        assert np.all(np.diff(packed >> 1) > 0), "updates must be Morton-sorted and unique"
        keys = [tuple(int(v) for v in k) for k in morton_decode(packed >> 1)]
        occ = {k for k, p in zip(keys, packed) if p & 1}
        free = {k for k, p in zip(keys, packed) if not p & 1}
        ref_free, ref_occ = scan_update_sets(scan.points, scan.origin, res, max_range)
        assert occ == ref_occ
        assert free == ref_free


def test_map_values_equal_per_voxel_reference_over_many_scans():
    m = OctreeMap(MapParams(resolution=0.2), SENSOR)
    ref = DictOctoMap(SENSOR.hit_log, SENSOR.miss_log, SENSOR.clamp_min_log, SENSOR.clamp_max_log)
    for scan in world_scans(12, 150, seed=3):
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin, 0.2)
    ours = finest_values(m)
    assert ours.keys() == ref.values.keys()
    assert all(ours[k] == float(v) for k, v in ref.values.items())


def test_pruning_and_inner_max_match_pyoctomap_node_for_node(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    res = 0.2
    tree = pyoctomap.OcTree(res)
    m = OctreeMap(MapParams(resolution=res), SENSOR)
    for scan in world_scans(6, 400, seed=7):
        m.integrate(scan)
        tree.insertPointCloud(scan.points.astype(np.float64), scan.origin.astype(np.float64))
    leaves, inner = m.node_counts()
    assert leaves + inner == tree.size()
    assert leaves == tree.getNumLeafNodes()
    # every OctoMap leaf answers the same log-odds from our tree, at its own depth
    ours = finest_values(m)
    count = 0
    for leaf in tree.begin_leafs():
        c = np.array(leaf.getCoordinate())
        key = tuple(int(v) for v in np.floor(c / res).astype(np.int64) + 32768)
        node = tree.search(c)
        assert ours[key] == pytest.approx(node.getLogOdds(), abs=0)
        count += 1
    assert count == leaves


def test_bt_export_loads_in_octomap_with_same_occupancy(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    m = OctreeMap(MapParams(resolution=0.2), SENSOR)
    for scan in world_scans(4, 300, seed=11):
        m.integrate(scan)
    path = tmp_path / "m.bt"
    path.write_bytes(bt_bytes(m.leaves(), 0.2, SENSOR.threshold_log))
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(path))
    assert tree.getResolution() == pytest.approx(0.2)
    ours = finest_values(m)
    keys = np.array(list(ours.keys()))
    centres = (keys - 32768 + 0.5) * 0.2
    for k, c in zip(map(tuple, keys), centres):
        node = tree.search(c)
        assert node is not None
        assert tree.isNodeOccupied(node) == (ours[k] > 0)
    # and our reader gives back the same voxel sets
    bt = read_bt(path)
    occ = set(expand_leaves(bt.codes[bt.occupied], bt.depths[bt.occupied]).tolist())
    ref_occ = set(morton_encode(np.array([k for k, v in ours.items() if v > 0])).tolist())
    assert occ == ref_occ


def test_query_answers_like_the_leaf_table():
    m = OctreeMap(MapParams(resolution=0.25), SENSOR)
    for scan in world_scans(3, 200, seed=5):
        m.integrate(scan)
    ours = finest_values(m)
    keys = np.array(list(ours.keys()))
    got = m.query(morton_encode(keys))
    assert np.array_equal(got, np.array([ours[tuple(k)] for k in keys], dtype=np.float32))
    unknown = morton_encode(np.array([[100, 100, 100]]))
    assert np.isnan(m.query(unknown)[0])


def test_snapshot_round_trip_is_lossless(tmp_path):
    from voxtool.io.mapfile import load_map, save_map

    m = OctreeMap(MapParams(resolution=0.2), SENSOR)
    for scan in world_scans(4, 200, seed=2):
        m.integrate(scan)
    path = tmp_path / "m.vxm"
    save_map(path, m, {"scans": 4})
    back, snap = load_map(path)
    a, b = m.leaves(), back.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.depths, b.depths)
    assert np.array_equal(a.values, b.values)
    assert back.node_counts() == m.node_counts()
    assert snap.header["backend"] == "octree" and snap.header["info"]["scans"] == 4


def forked_child_builds_the_same_map(make_map, scans) -> int | None:
    """Build a map from `scans` here (big scans: the two-thread ray casting), then again in a
    forked child; the child's exit code: 0 when its map equals this one, None if it hung."""
    import multiprocessing
    import os

    parent = make_map()
    for scan in scans:
        parent.integrate(scan)
    want = parent.leaves()

    def child():
        m = make_map()
        for scan in scans:
            m.integrate(scan)
        got = m.leaves()
        os._exit(0 if np.array_equal(got.codes, want.codes) and np.array_equal(got.values, want.values) else 3)

    p = multiprocessing.get_context("fork").Process(target=child)
    p.start()
    p.join(120)
    if p.exitcode is None:
        p.kill()
    return p.exitcode


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_a_child_forked_after_a_parallel_cast_builds_the_same_map():
    """A forked child inherits the ray pool but none of its threads: the child must get a pool
    of its own (it hung waiting for work no thread ran) and build the same map."""
    from voxtool.maps.octree import SMALL_SCAN

    scans = world_scans(2, SMALL_SCAN + 500, seed=8)
    assert forked_child_builds_the_same_map(lambda: OctreeMap(MapParams(0.1), SensorModel()), scans) == 0
