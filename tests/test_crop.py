"""`export --crop`: the voxels whose centres lie in the box (edges inclusive), for
every output type, against a brute-force filter of the uncropped export."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli

from voxtool.io.bt import read_bt
from voxtool.keys import expand_leaves, keys_to_coords, morton_decode

BOX = (-3.0, -2.0, -0.4, 4.0, 3.4, 1.2)  # on voxel faces: no centre on an edge


def inside(centres):
    return np.all((centres >= np.array(BOX[:3]) - 1e-6) & (centres <= np.array(BOX[3:]) + 1e-6), axis=1)


def test_crop_keeps_exactly_the_voxels_inside_the_box(sample_map, tmp_path):
    import open3d as o3d

    out, _ = sample_map
    crop = ",".join(str(v) for v in BOX)
    for suffix in (".ply", ".pcd"):
        full, cut = tmp_path / f"full{suffix}", tmp_path / f"cut{suffix}"
        assert cli("export", out, "-o", full, "--free")[0] == 0
        code, _, err = cli("export", out, "-o", cut, "--free", "--crop", crop)
        assert code == 0, err
        a = np.asarray(o3d.io.read_point_cloud(str(full)).points)
        b = np.asarray(o3d.io.read_point_cloud(str(cut)).points)
        expect = np.unique(np.round(a[inside(a)] * 1000).astype(np.int64), axis=0)
        assert np.array_equal(np.unique(np.round(b * 1000).astype(np.int64), axis=0), expect)
        assert 1000 < len(expect) < len(a)
    # .bt: the same voxels, each in the same state, read by voxtool's reader (and OctoMap's below)
    full_bt, cut_bt = tmp_path / "full.bt", tmp_path / "cut.bt"
    assert cli("export", out, "-o", full_bt)[0] == 0
    assert cli("export", out, "-o", cut_bt, "--crop", crop)[0] == 0
    states = []
    for path in (full_bt, cut_bt):
        bt = read_bt(path)
        codes = expand_leaves(bt.codes, bt.depths)
        occupied = np.repeat(bt.occupied, 1 << (3 * (16 - bt.depths.astype(np.int64))))
        centres = keys_to_coords(morton_decode(codes), 0.2)
        keep = inside(centres) if path == full_bt else np.ones(len(codes), bool)
        rows = np.column_stack([np.round(centres[keep] * 1000).astype(np.int64), occupied[keep]])
        states.append(np.unique(rows, axis=0))
    assert np.array_equal(states[0], states[1]) and states[1][:, 3].any()
    pyoctomap = pytest.importorskip("pyoctomap")
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(cut_bt))
    assert sum(1 for _ in tree.begin_leafs()) == read_bt(cut_bt).codes.shape[0]


def test_crop_of_a_picture_and_bad_boxes(sample_map, tmp_path):
    out, _ = sample_map
    code, text, err = cli("export", out, "-o", tmp_path / "c.png", "--crop", ",".join(str(v) for v in BOX), "--json")
    assert code == 0, err
    # the picture covers the box only: 7 m x 5.4 m at 0.2 m (35 x 27 voxels)
    report = json.loads(text)
    assert (report["raster_width"], report["raster_height"]) == (35, 27)
    for bad in ("1,2,3", "0,0,0,-1,1,1", "a,b,c,d,e,f"):
        code, _, err = cli("export", out, "-o", tmp_path / "x.ply", "--crop", bad)
        assert code == 2 and "--crop" in err and not (tmp_path / "x.ply").exists()
    code, _, err = cli("export", out, "-o", tmp_path / "x.png", "--crop", "500,500,500,501,501,501")
    assert code == 2 and "no voxel" in err


def test_box_edges_on_voxel_centres_are_inclusive(sample_map, tmp_path):
    """Edges lying exactly on voxel centres (x = -19.9 is the centre of a 0.2 m voxel, but
    -19.9 / 0.2 is not exactly -99.5 in floating point) keep those voxels: the crop equals an
    inclusive filter of the uncropped export's centres (it once lost whole layers)."""
    import open3d as o3d

    out, _ = sample_map
    box = (-19.9, -20.1, -1.9, 20.1, 19.9, 4.9)
    full, cut = tmp_path / "full.ply", tmp_path / "cut.ply"
    assert cli("export", out, "-o", full, "--free")[0] == 0
    assert cli("export", out, "-o", cut, "--free", "--crop", ",".join(map(str, box)))[0] == 0
    a = np.asarray(o3d.io.read_point_cloud(str(full)).points)
    b = np.asarray(o3d.io.read_point_cloud(str(cut)).points)
    keep = np.all((a >= np.array(box[:3]) - 1e-4) & (a <= np.array(box[3:]) + 1e-4), axis=1)
    on_edge = np.any(np.isclose(a, np.array(box[:3]), atol=1e-4) | np.isclose(a, np.array(box[3:]), atol=1e-4), axis=1)
    assert (keep & on_edge).sum() > 1000  # the edges do lie on centres
    assert len(b) == int(keep.sum())
