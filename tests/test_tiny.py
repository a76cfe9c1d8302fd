"""TinyOctoMap backend against a brute-force integer-level reference, and its memory budget."""

from __future__ import annotations

import numpy as np
import pytest
from reference import scan_update_sets
from test_octree import world_scans

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.keys import expand_leaves, morton_decode
from voxtool.maps.octree import OctreeMap
from voxtool.maps.tiny import TinyMap


def levels_of(m: TinyMap) -> dict:
    codes, depths, levels = m.level_leaves()
    full = expand_leaves(codes, depths)
    lv = np.repeat(levels, np.left_shift(1, 3 * (16 - depths.astype(np.int64))))
    return {tuple(int(v) for v in k): int(x) for k, x in zip(morton_decode(full), lv)}


@pytest.mark.parametrize("hit,miss,prior,pool_blocks", [(2, 1, 6, 4096), (3, 2, 8, 1 << 16), (2, 1, 6, None)])
def test_levels_equal_brute_force_integer_reference(hit, miss, prior, pool_blocks):
    """The paper's 16-bit pool of 4,096 blocks, a fixed 32-bit pool (the finest level packed, 4
    bits a voxel) and a grown one (packed, grown from 256 blocks as it fills)."""
    m = TinyMap(MapParams(0.2), SensorModel(), pool_blocks=pool_blocks, map_size=25.6, hit=hit, miss=miss,
                prior=prior)
    ref: dict = {}
    for scan in world_scans(10, 150, seed=4):
        m.integrate(scan)
        free, occ = scan_update_sets(scan.points, scan.origin, 0.2)
        for keys, step in ((free, -miss), (occ, hit)):
            for k in keys:
                ref[k] = min(max(ref.get(k, prior) + step, 1), 15)
    assert levels_of(m) == ref
    stats = m.pool_stats()
    assert stats["dropped_updates"] == 0 and stats["finest_level_packed"] == (pool_blocks != 4096)
    if pool_blocks is None:  # the finest level outgrew its first pool, and pruning gave blocks back
        assert stats["leaf_blocks"] > 256 and stats["pool_blocks"] > 256


def test_packed_finest_level_prunes_and_gives_blocks_back():
    """The same scan again and again from one spot: the free space near the sensor clamps, its
    8-voxel blocks prune into their parents and the packed blocks go back to the free list;
    the levels still equal the brute-force reference, and a snapshot reloads them."""
    from voxtool.sources.scan import Scan

    rng = np.random.default_rng(2)
    direction = rng.normal(size=(3000, 3))
    points = (6.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True)).astype(np.float32)
    scan = Scan(points, np.array([0.05, 0.05, 0.05], dtype=np.float32))
    m = TinyMap(MapParams(0.2), SensorModel(), map_size=25.6)
    ref: dict = {}
    free, occ = scan_update_sets(scan.points, scan.origin, 0.2)
    for _ in range(8):
        m.integrate(scan)
        for keys, step in ((free, -1), (occ, 2)):
            for k in keys:
                ref[k] = min(max(ref.get(k, 6) + step, 1), 15)
    assert levels_of(m) == ref
    assert m.meta[5] > 0  # packed blocks given back
    back = TinyMap(MapParams(0.2), SensorModel(), map_size=25.6)
    back.load_state(m.state_arrays())
    assert levels_of(back) == ref and back.used_bytes() == m.used_bytes()


def test_sixteen_bit_nodes_for_the_papers_pool_and_wider_beyond():
    assert TinyMap(MapParams(0.1), SensorModel(), pool_blocks=4096).pool.dtype == np.uint16
    assert TinyMap(MapParams(0.1), SensorModel(), pool_blocks=4096).memory_bytes() == 65536
    assert TinyMap(MapParams(0.1), SensorModel(), pool_blocks=4097).pool.dtype == np.uint32


def test_small_pool_drops_updates_never_corrupts_and_reloads(tmp_path):
    from voxtool.io.mapfile import load_map, save_map

    m = TinyMap(MapParams(0.1), SensorModel(), pool_blocks=64, map_size=12.8)
    for scan in world_scans(6, 300, seed=8):
        m.integrate(scan)
    stats = m.pool_stats()
    assert stats["pool_blocks_used"] == 64 and stats["dropped_updates"] > 0
    # what is in the tree is still an exact integer-level history of the updates that fitted
    lv = m.leaves()
    assert np.all(np.diff(lv.codes) > 0) and np.all(np.isfinite(lv.values))
    save_map(tmp_path / "t.vxm", m, {})
    back, _ = load_map(tmp_path / "t.vxm")
    b = back.leaves()
    assert np.array_equal(b.codes, lv.codes) and np.array_equal(b.values, lv.values)
    assert back.pool_stats() == stats


def test_occupancy_agrees_with_octree_within_quantization():
    params = MapParams(0.2)
    t = TinyMap(params, SensorModel(), pool_blocks=1 << 16, map_size=25.6)
    o = OctreeMap(params, SensorModel())
    for scan in world_scans(10, 300, seed=6):
        t.integrate(scan)
        o.integrate(scan)
    tl, ol = t.leaves(), o.leaves()
    t_occ = set(expand_leaves(tl.codes[tl.values > 0], tl.depths[tl.values > 0]).tolist())
    o_occ = set(expand_leaves(ol.codes[ol.values > 0], ol.depths[ol.values > 0]).tolist())
    t_all = set(expand_leaves(tl.codes, tl.depths).tolist())
    o_all = set(expand_leaves(ol.codes, ol.depths).tolist())
    assert t_all == o_all  # the same voxels are known
    assert len(t_occ ^ o_occ) <= 0.1 * len(o_occ)  # hit 2 levels (0.81) vs 0.847: rare flips


def test_points_outside_the_map_are_counted():
    m = TinyMap(MapParams(0.1), SensorModel(), pool_blocks=256, map_size=1.0)
    for scan in world_scans(1, 50, seed=1):
        m.integrate(scan)
    assert m.pool_stats()["outside_map_updates"] > 0


@pytest.mark.parametrize("kw", [{"pool_blocks": 1}, {"prior": 15}, {"map_size": 1e9}])
def test_bad_parameters(kw):
    with pytest.raises(ParameterError):
        TinyMap(MapParams(0.1), SensorModel(), **kw)


@pytest.mark.parametrize("backend", ["octree", "tiny"])
def test_merged_rays_give_the_unmerged_map(backend):
    from voxtool.maps import make_backend

    kw = {"pool_blocks": 1 << 15, "map_size": 25.6} if backend == "tiny" else {}
    plain = make_backend(backend, MapParams(0.2), SensorModel(), **kw)
    merged = make_backend(backend, MapParams(0.2, merge_rays=True), SensorModel(), **kw)
    total = merged_count = 0
    for scan in world_scans(4, 400, seed=2):
        # duplicate rays: the same points twice, and points nudged within their voxel
        pts = np.concatenate([scan.points, scan.points, scan.points + np.float32(1e-4)])
        scan.points = pts
        plain.integrate(scan)
        t = merged.integrate(scan)
        total += t.rays
        merged_count += t.merged_rays
    a, b = plain.leaves(), merged.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)
    assert merged_count >= total // 3  # at least the exact copies merge


def test_ray_signature_separates_different_paths():
    from voxtool.maps.octree import merge_rays
    from voxtool.sources.scan import Scan

    origin = np.zeros(3, np.float32)
    # same end voxel, different traversal: enter the end voxel from different sides
    pts = np.array([[2.05, 0.05, 0.05], [2.05, 0.05, 0.05], [0.05, 2.05, 0.05]], np.float32)
    kept = merge_rays(Scan(pts, origin), MapParams(0.1)).points
    assert kept.shape[0] == 2
