"""The Python API as docs/python.md shows it (its code blocks run here), `voxtool query`, and
OctoMap .bt import."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import cli

import voxtool
from voxtool.io.bt import read_bt
from voxtool.keys import expand_leaves, keys_to_coords, morton_decode

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "voxtool" / "data" / "sample"


def test_docs_python_examples_run(tmp_path, monkeypatch):
    text = (ROOT / "docs" / "python.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 4
    monkeypatch.chdir(tmp_path)
    namespace = {"SAMPLE": SAMPLE}
    for block in blocks:
        exec(compile(block, "docs/python.md", "exec"), namespace)
    assert (tmp_path / "sample.bt").is_file()


def voxel_centres(leaves, mask, resolution):
    codes = expand_leaves(leaves.codes[mask], leaves.depths[mask])
    return keys_to_coords(morton_decode(codes), resolution)


def check_query(map_path, ply_path, tmp_path, free_samples=10_000):
    import open3d as o3d  # an independent reader of the exported occupied voxel centres

    m = voxtool.load(map_path)
    centres = np.asarray(o3d.io.read_point_cloud(str(ply_path)).points)
    assert centres.shape[0] == m.stats()["occupied_voxels"]
    assert (m.state(centres) == "occupied").all()
    leaves = m.leaves()
    free = voxel_centres(leaves, leaves.values <= 0, m.resolution)
    pick = free[np.random.default_rng(0).choice(free.shape[0], min(free_samples, free.shape[0]), replace=False)]
    assert (m.state(pick) == "free").all()
    # a voxel next to nothing known
    far = np.array([[keys_to_coords(np.array([0]), m.resolution)[0]] * 3])
    assert m.state(far)[0] == "unknown" and m.query(far)["depth"][0] == -1
    return m, centres


def test_query_answers_occupied_free_unknown_on_the_sample(sample_map, tmp_path):
    path, _ = sample_map
    assert cli("export", path, "-o", tmp_path / "occ.ply")[0] == 0
    m, centres = check_query(path, tmp_path / "occ.ply", tmp_path)
    # the command line agrees with the API, one point and a file of points
    x, y, z = centres[7]
    code, text, _ = cli("query", path, "--json", "--", x, y, z)  # "--" still works
    assert code == 0 and json.loads(text)["state"] == "occupied"
    negative = next(c for c in centres if (c < 0).sum() >= 2)  # -20 is a coordinate, not an option '-2'
    code, text, err = cli("query", path, "--json", *negative)
    assert code == 0 and json.loads(text)["state"] == "occupied", err
    pts = tmp_path / "pts.csv"
    pts.write_text("x,y,z\n" + "\n".join(f"{a},{b},{c}" for a, b, c in centres[:50]) + "\n1e6,0,0\n")
    code, text, _ = cli("query", path, "--points", pts, "--json", "-o", tmp_path / "answers.csv")
    result = json.loads(text)
    assert code == 0 and result["occupied"] == 50 and result["unknown"] == 1 and result["points"] == 51
    rows = np.loadtxt(tmp_path / "answers.csv", delimiter=",", skiprows=1, dtype=str)
    assert rows.shape == (51, 6) and (rows[:50, 3] == "occupied").all() and rows[50, 3] == "unknown"
    assert rows[50, 5] == "-1" and np.allclose(rows[:50, :3].astype(float), centres[:50], atol=1e-6)
    # whitespace-separated, no header: the same answers; a short line is named by its line number
    spaced = tmp_path / "spaced.csv"
    spaced.write_text("\n".join(f"{a} {b} {c}" for a, b, c in centres[:50]) + "\n\n1e6 0 0\n")
    again = json.loads(cli("query", path, "--points", spaced, "--json")[1])
    assert {k: again[k] for k in ("points", "occupied", "free", "unknown")} == {k: result[k] for k in again}
    spaced.write_text("1 2 3\n4 5\n")
    code, text, err = cli("query", path, "--points", spaced)
    assert code != 0 and text == "" and err.count("\n") == 1 and "spaced.csv" in err and "line 2" in err


def test_query_depth_is_the_pruned_leaf(tmp_path):
    # a map of one pruned leaf: every voxel inside answers with its depth
    from voxtool.maps.base import Leaves

    code = 7 << 45  # key (32768, 32768, 32768): the voxel at the origin
    vm = voxtool.voxelmap.VoxelMap(Leaves(np.array([code], np.int64), np.array([13], np.uint8),
                                          np.array([2.0], np.float32)), 0.2, 0.0)
    inside = keys_to_coords(np.array([[32768 + 7, 32768 + 3, 32768]]), 0.2)
    a = vm.query(np.vstack([inside, [[-0.1, 0, 0]]]))
    assert a["state"].tolist() == [2, 0] and a["depth"].tolist() == [13, -1]
    assert a["probability"][0] == pytest.approx(1 - 1 / (1 + np.exp(2.0)))


def test_query_on_kaist03(shared_data, tmp_path):
    out = tmp_path / "k.vxm"
    assert cli("build", shared_data / "kaist03" / "pcd", "-o", out)[0] == 0
    assert cli("export", out, "-o", tmp_path / "k.ply")[0] == 0
    check_query(out, tmp_path / "k.ply", tmp_path)  # its speed: benchmarks/bench_query.py


def test_geb079_bt_round_trips_voxel_for_voxel(shared_data, tmp_path):
    src = shared_data / "octomap_share" / "geb079.bt"
    code, _, err = cli("build", src, "-o", tmp_path / "geb.vxm")
    assert code == 0, err
    assert cli("export", tmp_path / "geb.vxm", "-o", tmp_path / "back.bt")[0] == 0
    a, b = read_bt(src), read_bt(tmp_path / "back.bt")
    for occupied in (True, False):
        va = np.sort(expand_leaves(a.codes[a.occupied == occupied], a.depths[a.occupied == occupied]))
        vb = np.sort(expand_leaves(b.codes[b.occupied == occupied], b.depths[b.occupied == occupied]))
        assert np.array_equal(va, vb)


def test_bt_import_through_export_and_refusals(sample_map, tmp_path):
    path, built = sample_map
    assert cli("export", path, "-o", tmp_path / "a.bt")[0] == 0
    code, text, _ = cli("export", tmp_path / "a.bt", "-o", tmp_path / "a.vxm", "--json")
    assert code == 0 and json.loads(text)["occupied_voxels"] == built["occupied_voxels"]
    assert voxtool.load(tmp_path / "a.vxm").stats()["occupied_voxels"] == built["occupied_voxels"]
    code, _, err = cli("export", path, "-o", tmp_path / "b.vxm")
    assert code == 2 and "only an OctoMap .bt" in err and not (tmp_path / "b.vxm").exists()
