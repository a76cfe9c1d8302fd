"""`voxtool eval` against a brute-force reference and OctoMap's own eval_octree_accuracy (PyPI
cmeel-octomap, skipped where it is not installed); `export SCANS -o scans.graph` feeds that tool."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from conftest import cli
from reference import DictOctoMap, scan_update_sets
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.geometry import Pose

RES = 0.2


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    scans = []
    for i, (pts, origin, yaw) in enumerate(box_scene(7, 300, seed=17)):
        q = yaw_quat(yaw)
        write_pcd(d / f"{i}.pcd", pts, (*origin, *q))
        pose = Pose.from_quat(origin, *q)
        scans.append((pose.apply(pts), pose.translation.astype(np.float32)))
    return d, scans


def brute_force(scans, held):
    """eval_octree_accuracy's counting on OctoMap's per-voxel rule (reference.DictOctoMap)."""
    ref = DictOctoMap(0.8473, -0.4055, -2.0, 3.511)
    for i, (pts, origin) in enumerate(scans):
        if i not in held:
            ref.integrate(pts, origin, RES)
    rows = []
    for i in sorted(held):
        free, occ = scan_update_sets(scans[i][0], scans[i][1], RES)
        row = {"correct": 0, "wrong": 0, "unknown": 0}
        for keys, want in ((free, False), (occ, True)):
            for k in keys:
                if k not in ref.values:
                    row["unknown"] += 1
                else:
                    row["correct" if (ref.values[k] > 0) == want else "wrong"] += 1
        rows.append(row)
    return rows


@pytest.mark.parametrize("how", [("--holdout-every", "3"), ("--holdout", "0,4")])
def test_eval_equals_the_brute_force_count(scenes, how):
    d, scans = scenes
    code, text, err = cli("eval", d, "--resolution", RES, *how, "--json", "--no-progress")
    assert code == 0, err
    got = json.loads(text)
    held = [2, 5] if how[0] == "--holdout-every" else [0, 4]
    assert got["held_out"] == held and got["scans_built"] == len(scans) - len(held)
    expected = brute_force(scans, set(held))
    assert [{k: r[k] for k in ("correct", "wrong", "unknown")} for r in got["per_scan"]] == expected
    total = got["total"]
    assert total["correct"] == sum(r["correct"] for r in expected) > 0 and total["wrong"] > 0
    assert total["percent_correct"] == pytest.approx(100 * total["correct"] / (total["correct"] + total["wrong"]))


def test_min_correct_gate_and_picture(scenes, tmp_path):
    d, _ = scenes
    code, text, err = cli("eval", d, "--resolution", RES, "--json", "--no-progress")
    pct = json.loads(text)["total"]["percent_correct"]
    assert code == 0 and json.loads(text)["held_out"] == [4]  # OctoMap's every 5th by default
    png = tmp_path / "where.png"
    code, _, err = cli("eval", d, "--resolution", RES, "--min-correct", f"{pct + 0.5:.3f}", "--png", png,
                       "--no-progress")
    assert code == 8 and "below --min-correct" in err and err.count("\n") == 1, err
    from matplotlib.image import imread

    assert imread(png).shape[0] > 100  # the picture is written before the gate fails
    code, text, err = cli("eval", d, "--resolution", RES, "--png", png, "--json", "--no-progress")
    got = json.loads(text)
    # the legend names the printed totals (points) beside the voxels it draws
    unknown, wrong = got["png"]["legend"]
    assert f"{got['total']['wrong']:,} points in {got['png']['voxels']['wrong']:,} voxels" in wrong
    assert f"{got['total']['unknown']:,} points in" in unknown
    assert cli("eval", d, "--resolution", RES, "--min-correct", f"{pct - 0.5:.3f}", "--no-progress")[0] == 0
    for bad, words in ((("--holdout", "0,99"), "scan indices are 0..6"), (("--holdout-every", "1"), "at least 2"),
                       (("--start", "1"), "use --stop")):
        code, _, err = cli("eval", d, "--resolution", RES, *bad, "--no-progress")
        assert code == 2 and words in err, err


def _octomap_tool(name):
    path = shutil.which(name)
    if path is None:
        pytest.skip(f"OctoMap's {name} is not installed (pip install cmeel-octomap)")
    return path


def _tool_counts(tool, graph, res):
    out = subprocess.run([tool, str(graph), "-res", str(res)], capture_output=True, text=True, check=True).stdout
    m = re.search(r"Voxels correct: (\d+) #wrong: (\d+) #unknown: (\d+)", out)
    return tuple(int(v) for v in m.groups())


def test_eval_equals_octomaps_eval_octree_accuracy(shared_data, tmp_path):
    """quick_shack's first 40 real Livox scans, exported as a .graph by voxtool, evaluated by
    OctoMap's own tool and by voxtool: the same counts."""
    tool = _octomap_tool("eval_octree_accuracy")
    graph = tmp_path / "qs.graph"
    code, text, err = cli("export", shared_data / "quick_shack" / "pcd", "-o", graph, "--stop", 40, "--json")
    assert code == 0 and json.loads(text)["nodes"] == 40, err
    correct, wrong, unknown = _tool_counts(tool, graph, 0.1)
    for source, extra in ((graph, ()), (shared_data / "quick_shack" / "pcd", ("--stop", 40))):
        code, text, err = cli("eval", source, "--resolution", 0.1, *extra, "--json", "--no-progress")
        total = json.loads(text)["total"]
        assert (total["correct"], total["wrong"], total["unknown"]) == (correct, wrong, unknown), source


@pytest.mark.sweep
def test_kaist03_graph_eval_is_within_octomaps_float32_gap(shared_data):
    """kaist03's own .graph at 0.2 m: OctoMap transforms graph scans in float32, voxtool in
    float64: the counts agree within a few voxels (6,208,982 / 86,387 / 806,220 by the tool)."""
    tool = _octomap_tool("eval_octree_accuracy")
    graph = shared_data / "kaist03" / "kaist03_21scans.graph"
    theirs = _tool_counts(tool, graph, 0.2)
    code, text, err = cli("eval", graph, "--resolution", 0.2, "--json", "--no-progress")
    total = json.loads(text)["total"]
    ours = (total["correct"], total["wrong"], total["unknown"])
    assert max(abs(a - b) for a, b in zip(ours, theirs)) <= 12, (ours, theirs)
