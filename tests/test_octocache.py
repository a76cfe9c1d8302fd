"""OctoCache answers exactly like the plain octree, at every scan, for every setting."""

from __future__ import annotations

import numpy as np
import pytest
from test_octree import world_scans

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.keys import morton_encode
from voxtool.maps.octocache import OctoCacheMap
from voxtool.maps.octree import OctreeMap

SENSOR = SensorModel()


def same_leaves(a, b):
    la, lb = a.leaves(), b.leaves()
    return (np.array_equal(la.codes, lb.codes) and np.array_equal(la.depths, lb.depths)
            and np.array_equal(la.values, lb.values))


@pytest.mark.parametrize("overlap", [0, 1])
@pytest.mark.parametrize("tau,buckets,order", [(4, None, "morton"), (1, 64, "random"), (2, 1024, "xyz"),
                                               (16, 256, "bucket"), (4, 1 << 16, "morton")])
def test_queries_interleaved_with_insertion_equal_octree(tau, buckets, order, overlap):
    params = MapParams(resolution=0.2)
    plain = OctreeMap(params, SENSOR)
    cached = OctoCacheMap(params, SENSOR, buckets=buckets, tau=tau, overlap=overlap, order=order)
    rng = np.random.default_rng(tau)
    for scan in world_scans(8, 200, seed=13):
        plain.integrate(scan)
        cached.integrate(scan)
        # query known voxels and random ones (many unknown) without flushing the cache
        lv = plain.leaves()
        codes = np.concatenate([rng.choice(lv.codes, 300),
                                morton_encode(rng.integers(32700, 32840, size=(300, 3)))])
        np.testing.assert_array_equal(cached.query(codes), plain.query(codes))
    hits = sum(cached.counters.hits)
    assert 0 < hits < sum(cached.counters.updates)
    assert same_leaves(cached, plain)
    assert cached.node_counts() == plain.node_counts()
    cached.close()


def test_cache_takes_updates_off_the_octree():
    params = MapParams(resolution=0.2)
    cached = OctoCacheMap(params, SENSOR, tau=4)
    for scan in world_scans(10, 300, seed=1):
        cached.integrate(scan)
    before_flush = cached.counters.written_to_octree
    assert before_flush < sum(cached.counters.updates)
    cached.flush()
    assert int(cached.count.sum()) == 0


def test_snapshot_round_trip_after_flush(tmp_path):
    from voxtool.io.mapfile import load_map, save_map

    params = MapParams(resolution=0.2)
    cached = OctoCacheMap(params, SENSOR, buckets=512, tau=2)
    plain = OctreeMap(params, SENSOR)
    for scan in world_scans(5, 200, seed=9):
        cached.integrate(scan)
        plain.integrate(scan)
    save_map(tmp_path / "c.vxm", cached, {})
    back, snap = load_map(tmp_path / "c.vxm")
    assert back.name == "octocache" and snap.header["backend_params"]["tau"] == 2
    assert same_leaves(back, plain)


@pytest.mark.parametrize("kwargs,message", [({"buckets": 100}, "power of two"), ({"tau": 0}, "tau=0"),
                                            ({"overlap": 3}, "overlap=3"), ({"order": "ray"}, "order 'ray'")])
def test_bad_parameters(kwargs, message):
    with pytest.raises(ParameterError, match=message):
        OctoCacheMap(MapParams(0.2), SENSOR, **kwargs)
