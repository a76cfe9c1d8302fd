"""`build --decay`: the octree's log-odds fade towards unknown in scan time (docs/decay.md),
checked against a per-voxel transcription of the documented rule; OctoMap's map when off."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli
from test_octree import finest_values, world_scans

from voxtool.config import MapParams, SensorModel
from voxtool.keys import morton_decode, morton_encode
from voxtool.maps.octree import FORGET_BELOW, OctreeMap, scan_updates
from voxtool.sources.scan import Scan

SENSOR = SensorModel()


def reference_decay(scans, stamps_s, resolution, half_life):
    """The documented model, voxel by voxel in float64: before each scan every known log-odds
    is multiplied by 2^(-dt / half-life) and those below FORGET_BELOW are forgotten; then the
    scan's hits and misses are added as OctoMap adds them (from 0 for an unknown voxel, clamped);
    reading the map is one more step with dt = 0."""
    values: dict[tuple, float] = {}
    last = None
    for scan, t in zip(scans, stamps_s):
        if last is not None:
            f = 2.0 ** (-(t - last) / half_life)
            values = {k: v * f for k, v in values.items() if abs(v * f) >= FORGET_BELOW}
        last = t
        packed, _, _ = scan_updates(scan, MapParams(resolution=resolution))
        for key, item in zip(morton_decode(packed >> 1), packed):
            k = tuple(int(c) for c in key)
            v = values.get(k, 0.0) + (SENSOR.hit_log if item & 1 else SENSOR.miss_log)
            values[k] = min(max(v, SENSOR.clamp_min_log), SENSOR.clamp_max_log)
    return {k: v for k, v in values.items() if abs(v) >= FORGET_BELOW}


def stamped(scans, stamps_s):
    return [Scan(s.points, s.origin, i, int(round(t * 1e9)), "test") for i, (s, t) in enumerate(zip(scans, stamps_s))]


@pytest.mark.parametrize("half_life", [0.3, 2.0])
def test_decay_equals_the_documented_rule_voxel_by_voxel(half_life):
    scans = world_scans(10, 200, seed=5)
    stamps = np.cumsum(np.random.default_rng(1).uniform(0.05, 0.6, len(scans)))
    m = OctreeMap(MapParams(resolution=0.2), SENSOR, decay_half_life=half_life)
    for scan in stamped(scans, stamps):
        m.integrate(scan)
    ours = finest_values(m)
    ref = reference_decay(scans, stamps, 0.2, half_life)
    assert len(ref) > 100
    assert ours.keys() == ref.keys()
    for k, v in ref.items():
        assert ours[k] == pytest.approx(v, rel=1e-5, abs=1e-6)


def test_one_voxel_fades_by_the_half_life_and_is_forgotten():
    """One hit at t=0, then scans far away: the voxel holds 0.85 * 2^(-t/h) until it nears unknown."""
    h = 2.0
    m = OctreeMap(MapParams(resolution=0.5), SENSOR, decay_half_life=h)
    target = np.array([[1.2, 0.2, 0.2]], dtype=np.float32)
    far = np.array([[-40.0, -40.0, 0.2]], dtype=np.float32)
    m.integrate(Scan(target, np.zeros(3, np.float32), 0, 0, "t"))
    voxel = morton_encode(np.array([[32768 + 2, 32768, 32768]], dtype=np.int64))  # the key of (1.2, 0.2, 0.2)
    for i, t in enumerate([1.0, 3.0, 7.5], start=1):
        m.integrate(Scan(far, np.array([-39.0, -39.0, 0.2], np.float32), i, int(t * 1e9), "t"))
        assert m.query(voxel)[0] == pytest.approx(SENSOR.hit_log * 2 ** (-t / h), rel=1e-6)
    # 0.85 * 2^(-t/2) < 0.01 from t = 12.8 s
    m.integrate(Scan(far, np.array([-39.0, -39.0, 0.2], np.float32), 4, int(13e9), "t"))
    assert np.isnan(m.query(voxel)[0])


def test_without_decay_the_map_is_octomaps_whatever_the_stamps():
    scans = stamped(world_scans(6, 200, seed=2), np.arange(6) * 5.0)
    plain, timed = OctreeMap(MapParams(resolution=0.2), SENSOR), OctreeMap(MapParams(resolution=0.2), SENSOR)
    for scan, bare in zip(scans, world_scans(6, 200, seed=2)):
        timed.integrate(scan)
        plain.integrate(bare)
    a, b = plain.leaves(), timed.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)


def test_a_long_run_resettles_without_drift():
    """Past 40 half-lives the stored values are settled mid-run; a voxel hit every scan holds
    the fixed point of the rule."""
    m = OctreeMap(MapParams(resolution=0.5), SENSOR, decay_half_life=0.1)
    pts = np.array([[1.2, 0.2, 0.2]], dtype=np.float32)
    for i in range(120):  # 0.05 s apart: 6 s, 60 half-lives
        m.integrate(Scan(pts, np.zeros(3, np.float32), i, int(i * 5e7), "t"))
    assert 2.0**-40 <= m.tree.scale < 1.0  # 2^-59.5 had it not been settled mid-run
    # v = v * 2^-0.5 + hit each scan: the fixed point hit / (1 - 2^-0.5), below the clamp
    assert np.nanmax(m.leaves().values) == pytest.approx(SENSOR.hit_log / (1 - 2**-0.5), rel=1e-5)


def test_cli_decay_on_a_generated_street(tmp_path):
    """--decay forgets: fewer voxels than OctoMap's map, recorded in the snapshot; no times, refused."""
    from voxtool.synthetic import street, write_pcd_scans

    scans = tmp_path / "scans"
    write_pcd_scans(street(12, seed=3), scans)
    out = {}
    for name, extra in (("plain", []), ("decay", ["--decay", "0.1"])):
        code, stdout, err = cli("build", str(scans), "--poses", str(scans / "poses.txt"), "--resolution", "0.2",
                                "-o", str(tmp_path / f"{name}.vxm"), "--json", *extra)
        assert code == 0, err
        out[name] = json.loads(stdout)
    assert out["decay"]["decay_half_life_s"] == 0.1
    known = {k: v["occupied_voxels"] + v["free_voxels"] for k, v in out.items()}
    assert known["decay"] < 0.9 * known["plain"]
    code, stdout, err = cli("stats", str(tmp_path / "decay.vxm"), "--json")
    assert code == 0, err
    assert json.loads(stdout)["free_voxels"] == out["decay"]["free_voxels"]
    # without --poses, a PCD directory's scan times come from the poses.txt beside its scans
    code, stdout, err = cli("build", str(scans), "--resolution", "0.2", "--decay", "0.1", "--json",
                            "-o", str(tmp_path / "beside.vxm"))
    assert code == 0, err
    assert json.loads(stdout)["free_voxels"] == out["decay"]["free_voxels"]
    # ... and without that file it has none
    (scans / "poses.txt").rename(tmp_path / "poses.txt")
    code, _, err = cli("build", str(scans), "--decay", "1", "-o", str(tmp_path / "none.vxm"))
    assert code != 0 and "increasing scan times" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "none.vxm").exists()
    for bad in (["--decay", "0"], ["--decay", "1", "--backend", "hashmap"]):
        code, _, err = cli("build", str(scans), *bad)
        assert code == 2, err
