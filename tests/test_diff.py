"""`voxtool diff` against independent truths: a brute-force set difference of the two maps'
exports read back by Open3D, OctoMap's own .bt of the same scans, and compare_octrees' KL
divergence computed with the real OctoMap library (pyoctomap)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli
from test_octree import world_scans

from voxtool.cli.common import SAMPLE_DIR
from voxtool.config import MapParams, SensorModel
from voxtool.io.mapfile import save_map
from voxtool.maps.octree import OctreeMap

RES = 0.2


@pytest.fixture(scope="module")
def street_maps(tmp_path_factory):
    """A generated street built from scans 0..3 (A) and 0..13 (B): N and N + 10 scans."""
    from voxtool.synthetic import Lidar, street, write_pcd_scans

    tmp = tmp_path_factory.mktemp("diff")
    write_pcd_scans(street(14, seed=5, lidar=Lidar(beams=16, columns=512)), tmp / "scans")
    for name, stop in (("a", ["--stop", "4"]), ("b", [])):
        code, _, err = cli("build", tmp / "scans", "--resolution", RES, "-o", tmp / f"{name}.vxm", *stop)
        assert code == 0, err
    return tmp


def exported_states(path, tmp):
    """{voxel centre (rounded, mm): 'occupied' | 'free'} from `voxtool export` .ply files read by Open3D."""
    import open3d as o3d

    states = {}
    for what, extra in (("free", ["--free"]), ("occupied", [])):
        out = tmp / f"{path.stem}-{what}.ply"
        code, _, err = cli("export", path, "-o", out, *extra)
        assert code == 0, err
        centres = np.round(np.asarray(o3d.io.read_point_cloud(str(out)).points) * 1000).astype(np.int64)
        states.update((tuple(c), what) for c in centres.tolist())  # the occupied pass overwrites
    return states


def test_diff_lists_exactly_the_voxels_whose_state_differs(street_maps, tmp_path):
    import open3d as o3d

    a, b = street_maps / "a.vxm", street_maps / "b.vxm"
    code, out, err = cli("diff", a, b, "--json", "--ply", tmp_path / "changed.ply", "--png", tmp_path / "where.png")
    assert code == 0, err
    report = json.loads(out)
    sa, sb = exported_states(a, tmp_path), exported_states(b, tmp_path)
    truth = {}
    for key in sa.keys() | sb.keys():
        was, now = sa.get(key, "unknown"), sb.get(key, "unknown")
        if was != now:
            truth[f"{was}_to_{now}"] = truth.get(f"{was}_to_{now}", 0) + 1
    assert report["changes"] == {k: truth.get(k, 0) for k in report["changes"]}
    assert report["changed_voxels"] == sum(truth.values()) > 1000
    points = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "changed.ply")).points)
    changed = {tuple(c) for c in np.round(points * 1000).astype(np.int64).tolist()}
    assert changed == {k for k in sa.keys() | sb.keys() if sa.get(k, "unknown") != sb.get(k, "unknown")}
    box = np.array([report["changed_bbox"]["min"], report["changed_bbox"]["max"]]) * 1000
    centres = np.array(sorted(changed))
    assert np.allclose(box[0], centres.min(axis=0) - RES * 500, atol=1) and \
        np.allclose(box[1], centres.max(axis=0) + RES * 500, atol=1)
    assert report["png"]["changed_pixels"] > 0 and (tmp_path / "where.png").read_bytes()[:4] == b"\x89PNG"


def test_a_map_against_itself_and_the_exit_code(street_maps):
    b = street_maps / "b.vxm"
    code, out, err = cli("diff", b, b, "--json", "--max-changed", "0")
    assert code == 0, err
    report = json.loads(out)
    assert report["changed_voxels"] == 0 and report["kl_divergence"] == 0.0 and report["changed_bbox"] is None
    assert report["same_state_other_log_odds"] == 0 and report["common_known_voxels"] > 0
    code, out, err = cli("diff", street_maps / "a.vxm", b, "--max-changed", "10")
    assert code == 7 and "more than --max-changed 10" in err and len(err.strip().splitlines()) == 1
    assert "changed voxels" in out  # the report is printed before the verdict


def test_against_octomaps_own_bt_of_the_same_scans(sample_map):
    """The sample's reference .bt was written by OctoMap from the same scans: no voxel differs in
    state; the log-odds do (a .bt keeps only occupied / free, read back at the clamps)."""
    out, _ = sample_map
    code, text, err = cli("diff", out, SAMPLE_DIR / "reference_octomap_res0.2.bt", "--json")
    assert code == 0, err
    report = json.loads(text)
    assert report["changed_voxels"] == 0 and report["common_known_voxels"] > 100_000
    assert report["same_state_other_log_odds"] > 0


def test_kl_divergence_equals_compare_octrees_with_pyoctomap(tmp_path):
    pyoctomap = pytest.importorskip("pyoctomap")
    scans = world_scans(5, 200, seed=9)
    trees, paths = [], []
    for name, use in (("a", scans[:3]), ("b", scans)):
        tree, ours = pyoctomap.OcTree(RES), OctreeMap(MapParams(resolution=RES), SensorModel())
        for scan in use:
            tree.insertPointCloud(scan.points.astype(np.float64), scan.origin.astype(np.float64))
            ours.integrate(scan)
        paths.append(tmp_path / f"{name}.vxm")
        save_map(paths[-1], ours, {})
        trees.append(tree)
    # compare_octrees: every voxel of tree 1 (expanded) that tree 2 knows, KL(p1 || p2)
    kl, common = 0.0, 0
    for leaf in trees[0].begin_leafs():
        size = leaf.getSize()
        n = int(round(size / RES))
        corner = np.array(leaf.getCoordinate()) - size / 2
        steps = (np.arange(n) + 0.5) * RES
        for dx in steps:
            for dy in steps:
                for dz in steps:
                    centre = corner + np.array([dx, dy, dz])
                    node = trees[1].search(centre)
                    if node is None:
                        continue
                    p1, p2 = trees[0].search(centre).getOccupancy(), node.getOccupancy()
                    kl += np.log(p1 / p2) * p1 + np.log((1 - p1) / (1 - p2)) * (1 - p1)
                    common += 1
    code, out, err = cli("diff", *paths, "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["common_known_voxels"] == common
    assert kl > 1.0 and report["kl_divergence"] == pytest.approx(kl, rel=1e-6)


def test_sharded_maps_are_compared_part_by_part(sample_map, tmp_path):
    """A sharded map against its single-file twin and against itself: no change; against the
    map of fewer scans: the single-file diff's figures."""
    distributed = pytest.importorskip("dask.distributed")
    out, _ = sample_map
    sharded = tmp_path / "sharded"
    fewer = tmp_path / "fewer.vxm"
    code, _, err = cli("build", "--sample", "-o", fewer, "--stop", "3")
    assert code == 0, err
    # both sharded maps built on one real cluster of 2 worker processes (a cluster's start is most of a build here)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        code, _, err = cli("build", "--sample", "-o", sharded, "--sharded", "--scheduler", cluster.scheduler_address,
                           "--no-progress")
        assert code == 0, err
        other_cut = tmp_path / "other_cut"  # another shard depth: other partitions
        code, _, err = cli("build", "--sample", "-o", other_cut, "--sharded", "--scheduler", cluster.scheduler_address,
                           "--no-progress", "--param", "shard_depth=9")
        assert code == 0, err
    for a, b in ((sharded, out), (out, sharded), (sharded, sharded), (sharded, other_cut)):
        code, text, err = cli("diff", a, b, "--json")
        assert code == 0, err
        assert json.loads(text)["changed_voxels"] == 0
    reports = []
    for a, b in ((fewer, out), (fewer, sharded), (other_cut, fewer)):
        code, text, err = cli("diff", a, b, "--json")
        assert code == 0, err
        reports.append(json.loads(text))
    assert reports[0]["changed_voxels"] > 0
    assert reports[0]["changes"] == reports[1]["changes"]
    assert reports[0]["kl_divergence"] == pytest.approx(reports[1]["kl_divergence"], rel=1e-9)
    flipped = {f"{k.split('_to_')[1]}_to_{k.split('_to_')[0]}": v for k, v in reports[0]["changes"].items()}
    assert reports[2]["changes"] == flipped  # B -> A: every change the other way


def test_bad_input(street_maps, tmp_path):
    a = street_maps / "a.vxm"
    coarse = tmp_path / "coarse.vxm"
    code, _, err = cli("build", "--sample", "--resolution", "0.4", "-o", coarse)
    assert code == 0, err
    code, _, err = cli("diff", a, coarse, "--png", tmp_path / "x.png")
    assert code == 2 and "different resolutions" in err and not (tmp_path / "x.png").exists()
    bad = tmp_path / "bad.vxm"
    bad.write_bytes(b"not a snapshot")
    code, _, err = cli("diff", a, bad)
    assert code == 5 and str(bad) in err and len(err.strip().splitlines()) == 1
    code, _, err = cli("diff", a, a, "--ply", tmp_path / "x.txt")
    assert code == 2


def test_diff_png_crop_draws_the_changes_in_the_box(sample_map, tmp_path):
    """diff --png --crop frames the picture on a box and counts the changed voxels in it: the
    --ply of every changed voxel, filtered to the box, holds as many."""
    import open3d as o3d

    full, _ = sample_map
    less = tmp_path / "less.vxm"
    assert cli("build", "--sample", "--stop", 3, "-o", less, "--no-progress")[0] == 0
    box = (-20.0, -20.0, -3.0, 20.0, 20.0, 5.0)
    code, text, err = cli("diff", less, full, "--png", tmp_path / "d.png", "--ply", tmp_path / "d.ply",
                          "--crop", ",".join(map(str, box)), "--json")
    assert code == 0, err
    report = json.loads(text)
    pts = np.asarray(o3d.io.read_point_cloud(str(tmp_path / "d.ply")).points)
    inside = np.all((pts >= np.array(box[:3]) - 1e-4) & (pts <= np.array(box[3:]) + 1e-4), axis=1)
    assert sum(report["png"]["voxels"].values()) == int(inside.sum()) < len(pts)
    code, _, err = cli("diff", less, full, "--crop", ",".join(map(str, box)))
    assert code == 2 and "--crop frames the --png picture" in err


def test_a_map_against_its_lossless_decode_says_what_its_log_odds_figures_mean(tmp_path):
    """A decoded packet log holds states, each voxel at its state's log-odds: against the map it was
    encoded from, no state changes, and the large KL divergence is that quantization, which the
    report names (state_maps) instead of leaving a bare number."""
    assert cli("build", "--sample", "-o", tmp_path / "m.vxm", "--max-range", "20", "--no-progress")[0] == 0
    assert cli("encode", "--sample", "-o", tmp_path / "m.mcap", "--max-range", "20", "--no-progress")[0] == 0
    assert cli("decode", tmp_path / "m.mcap", "-o", tmp_path / "d.vxm", "--no-progress")[0] == 0
    code, out, err = cli("diff", tmp_path / "m.vxm", tmp_path / "d.vxm", "--json")
    assert code == 0, err
    report = json.loads(out)
    assert report["changed_voxels"] == 0 and report["kl_divergence"] > 1.0
    assert report["state_maps"] == [str(tmp_path / "d.vxm")]
    text = cli("diff", tmp_path / "m.vxm", tmp_path / "d.vxm")[1]
    assert "holds states (decoded from packets)" in text and "not a change" in text
    assert json.loads(cli("diff", tmp_path / "m.vxm", tmp_path / "m.vxm", "--json")[1])["state_maps"] == []
