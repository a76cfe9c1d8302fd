"""The sharded octree: the same map whatever the threads and the shard depth, OctoMap's pruning
across brick and shard borders, clamping, and maps loaded with leaves coarser than a brick."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_octree import world_scans

from voxtool.config import MapParams, SensorModel
from voxtool.io.mapfile import load_map, save_map
from voxtool.io.snapshot import snapshot_bytes
from voxtool.keys import morton_encode
from voxtool.maps.octree import OctreeMap
from voxtool.sources.scan import Scan

SENSOR = SensorModel()


def same_leaves(a, b) -> bool:
    la, lb = a.leaves(), b.leaves()
    return (np.array_equal(la.codes, lb.codes) and np.array_equal(la.depths, lb.depths)
            and np.array_equal(la.values, lb.values))


def sphere_scans(n_scans: int, n_points: int, radius: float, seed: int = 0) -> list[Scan]:
    """Dense fans of rays from near the world origin (where the key space is split at every
    depth) to a sphere: after a few scans the space inside is uniformly clamped free, so whole
    bricks, and groups of bricks across shard borders, prune."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_scans):
        origin = rng.uniform(-0.3, 0.3, 3).astype(np.float32)
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out.append(Scan((origin + radius * d).astype(np.float32), origin))
    return out


def build(scans, res, **kw) -> OctreeMap:
    m = OctreeMap(MapParams(resolution=res), SENSOR, **kw)
    for scan in scans:
        m.integrate(scan)
    return m


@pytest.mark.parametrize("threads, depth", [(2, 8), (3, 13), (8, 11)])
def test_threads_and_shard_depths_build_the_same_map(threads, depth):
    scans = world_scans(6, 3000, seed=21)  # scans large enough for several ray runs and update runs
    one = build(scans, 0.1, threads=1, shard_depth=10)
    many = build(scans, 0.1, threads=threads, shard_depth=depth)
    assert same_leaves(one, many)
    assert one.node_counts() == many.node_counts()
    header = {"backend": "octree"}
    assert snapshot_bytes(header, one.state_arrays()) == snapshot_bytes(header, many.state_arrays())


def test_pruning_across_brick_and_shard_borders_matches_octomap():
    pyoctomap = pytest.importorskip("pyoctomap")
    res = 1.0
    scans = sphere_scans(8, 20000, 30.0, seed=3)
    tree = pyoctomap.OcTree(res)
    for scan in scans:
        tree.insertPointCloud(scan.points.astype(np.float64), scan.origin.astype(np.float64))
    for depth in (8, 13):
        m = build(scans, res, threads=2, shard_depth=depth)
        leaves, inner = m.node_counts()
        assert (leaves, leaves + inner) == (tree.getNumLeafNodes(), tree.size())
        lv = m.leaves()
        assert lv.depths.min() < 13  # bricks pruned into coarser leaves: across brick borders
        # every OctoMap leaf is a leaf of ours: same depth, same log-odds
        ours = {(int(c), int(d)): float(v) for c, d, v in zip(lv.codes, lv.depths, lv.values)}
        for leaf in tree.begin_leafs():
            d = leaf.getDepth()
            size = leaf.getSize()
            corner = np.array(leaf.getCoordinate()) - size / 2 + res / 2
            code = int(morton_encode(np.floor(corner[None] / res).astype(np.int64) + 32768)[0])
            assert ours[(code, d)] == pytest.approx(tree.search(leaf.getCoordinate()).getLogOdds(), abs=0)


def test_clamping_holds_at_both_bounds():
    scans = sphere_scans(12, 500, 6.0, seed=5)
    m = build(scans, 0.5, threads=2)
    lv = m.leaves()
    assert lv.values.min() == np.float32(SENSOR.clamp_min_log)
    assert lv.values.max() == np.float32(SENSOR.clamp_max_log)
    assert np.all((lv.values >= np.float32(SENSOR.clamp_min_log)) & (lv.values <= np.float32(SENSOR.clamp_max_log)))


def test_query_depth_is_the_depth_of_the_leaf_holding_the_voxel():
    scans = sphere_scans(8, 3000, 20.0, seed=9)
    m = build(scans, 1.0, threads=2, shard_depth=12)
    lv = m.leaves()
    rng = np.random.default_rng(1)
    codes = np.concatenate([lv.codes, lv.codes + rng.integers(0, 64, lv.codes.shape[0]),
                            morton_encode(rng.integers(32700, 32840, size=(2000, 3)))])
    value, depth = m.query_depth(codes)
    k = np.searchsorted(lv.codes, codes, side="right") - 1
    inside = (k >= 0) & (codes < lv.codes[np.maximum(k, 0)] + (np.int64(1) << (3 * (16 - lv.depths[np.maximum(k, 0)].astype(np.int64)))))
    assert np.array_equal(depth[inside], lv.depths[k[inside]])
    assert np.array_equal(value[inside], lv.values[k[inside]])
    assert np.all(depth[~inside] == -1) and np.all(np.isnan(value[~inside]))


def test_a_reloaded_map_with_coarse_leaves_goes_on_like_the_original(tmp_path):
    """A snapshot of a map whose pruned leaves are coarser than a brick reloads with those leaves
    as they are; later scans split them exactly where OctoMap expands its pruned nodes."""
    res = 1.0
    first, later = sphere_scans(8, 20000, 30.0, seed=11), sphere_scans(3, 5000, 45.0, seed=12)
    whole = build(first + later, res, threads=2)
    part = build(first, res, threads=1)
    assert part.leaves().depths.min() < 13
    save_map(tmp_path / "m.vxm", part, {})
    back, _ = load_map(tmp_path / "m.vxm")
    assert back.tree.coarse.codes.shape[0] > 0 and same_leaves(back, part)
    for scan in later:
        back.integrate(scan)
    assert same_leaves(back, whole)
    assert back.node_counts() == whole.node_counts()


def test_leaves_in_chunks_and_a_snapshot_written_from_them_equal_the_whole_leaves(tmp_path):
    """A snapshot goes through a map's leaves a chunk at a time (ShardedOctree.leaf_chunks):
    joined, the chunks are leaves(), for any chunk size, on a map mixing bricks, pruned bricks
    and coarse leaves (a reloaded map); and the snapshot's bytes are those of the whole arrays."""
    from voxtool.io.snapshot import ChunkedArrays

    res = 1.0
    part = build(sphere_scans(8, 20000, 30.0, seed=11), res, threads=1)
    save_map(tmp_path / "m.vxm", part, {})
    m, _ = load_map(tmp_path / "m.vxm")
    m.tree.threads = 2
    assert m.tree.coarse.codes.shape[0] > 0
    whole = m.leaves()
    names = ("codes", "depths", "values")
    for max_leaves in (1, 7, 1000, None):
        m.tree._derived = None  # what was derived (and the joined leaves) is dropped: derive again
        assert m.tree.leaf_count() == len(whole)
        chunks = [tuple(getattr(c, f).copy() for f in names) for c in m.tree.leaf_chunks(max_leaves)]
        assert max_leaves is None or max(len(c[0]) for c in chunks) <= max(max_leaves, 512)  # a brick's at most
        for k, f in enumerate(names):
            assert np.array_equal(np.concatenate([c[k] for c in chunks]), getattr(whole, f))
    m.tree._derived = None
    streamed = m.state_arrays()
    assert isinstance(streamed["leaf_codes"], ChunkedArrays)
    arrays = {"leaf_codes": whole.codes, "leaf_depths": whole.depths, "leaf_values": whole.values}
    for codec in ("zstd", "raw"):
        assert snapshot_bytes({"backend": "octree"}, streamed, codec) == snapshot_bytes({"backend": "octree"}, arrays,
                                                                                        codec)


@pytest.mark.parametrize("decay", [None, 0.15])
def test_updates_from_brick_masks_equal_the_per_voxel_updates(tmp_path, decay):
    """A build applies each scan's updates straight from its brick masks (ShardedOctree.apply_masks);
    the per-voxel update list (PreparedScan.updates(), which `encode` and the other backends
    read) must give the same map: on a reloaded map with coarse leaves (new bricks start from
    the leaf they split), with clamping, and with decay forgetting voxels between scans."""
    part = build(sphere_scans(6, 20000, 30.0, seed=11), 1.0, threads=1)
    save_map(tmp_path / "m.vxm", part, {})
    later = sphere_scans(4, 4000, 45.0, seed=12) + world_scans(3, 3000, seed=5)
    maps = []
    for expand in (False, True):
        m, _ = load_map(tmp_path / "m.vxm")
        m.threads = m.tree.threads = 2
        m.decay_half_life = decay
        for i, scan in enumerate(later):
            scan.stamp_ns = i * 100_000_000
            prepared = m.prepare(scan)
            assert prepared.packed is None  # kept as masks until asked for
            if expand:
                prepared.updates()
            timing = m.apply(prepared)
            assert timing.voxel_updates == prepared.updates().shape[0]
        maps.append(m)
    assert same_leaves(*maps)


@given(st.integers(-(2**63), 2**63 - 1).filter(lambda x: x != 0))
def test_lowest_bit_is_the_index_of_the_lowest_set_bit(x):
    """The update walks a mask's set bits with it (kernels.octree.apply_masks): every bit
    position, the sign bit included."""
    from voxtool.kernels.raycast import lowest_bit

    assert lowest_bit(np.int64(x)) == ((x & -x).bit_length() - 1)
