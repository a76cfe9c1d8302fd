"""Points that are not returns: a point exactly at the sensor's own position ("no return" as many
drivers write it in organized clouds) is dropped and counted by every command that reads scans,
and the results equal those of the same scans without it."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import cli
from test_clean import one_moving_box

from voxtool.io.export import pcd_header, pcd_rows
from voxtool.io.mapfile import load_map
from voxtool.sources.pcd import read_pcd
from voxtool.synthetic import write_pcd_scans


@pytest.fixture(scope="module")
def scans_with_and_without(tmp_path_factory):
    """(scans, the same scans each with one (0, 0, 0) point added, their number)."""
    root = tmp_path_factory.mktemp("no_return")
    plain = root / "plain"
    write_pcd_scans(one_moving_box(12), plain)
    zeros = root / "zeros"
    shutil.copytree(plain, zeros)
    files = sorted(zeros.glob("*.pcd"))
    for f in files:
        cloud = read_pcd(f)
        points = np.insert(cloud.xyz.astype(np.float32), len(cloud.xyz) // 2, 0.0, axis=0)  # mid-scan, as organized
        f.write_bytes(pcd_header(len(points), False, viewpoint=cloud.viewpoint) + pcd_rows(points, None))
    return plain, zeros, len(files)


def _json(*args):
    code, text, err = cli(*args, "--json", "--no-progress")
    assert code == 0, err
    return json.loads(text)


def test_build_drops_and_counts_points_at_the_sensor(scans_with_and_without, tmp_path):
    plain, zeros, n = scans_with_and_without
    a = _json("build", plain, "-o", tmp_path / "a.vxm", "--resolution", "0.1")
    b = _json("build", zeros, "-o", tmp_path / "b.vxm", "--resolution", "0.1")
    assert b["points"] == a["points"] + n
    assert b["points_dropped_at_origin"] == b["points_dropped"] == n and a["points_dropped"] == 0
    la, lb = load_map(tmp_path / "a.vxm")[0].leaves(), load_map(tmp_path / "b.vxm")[0].leaves()
    assert np.array_equal(la.codes, lb.codes) and np.array_equal(la.values, lb.values)
    text = cli("build", zeros, "-o", tmp_path / "c.vxm", "--resolution", "0.1", "--no-progress")[1]
    assert f"{n} dropped: {n} at the sensor's own position" in text


def test_clean_judges_the_scans_as_without_those_points(scans_with_and_without, tmp_path):
    """One such point per scan made every scan's sensor voxel a hit, and clean removed nothing."""
    plain, zeros, n = scans_with_and_without
    a = _json("clean", plain, "--labels", tmp_path / "a.npy", "--resolution", "0.1")
    b = _json("clean", zeros, "--labels", tmp_path / "b.npy", "--resolution", "0.1")
    assert a["points_removed"] > 500  # the moving box
    assert np.array_equal(np.load(tmp_path / "a.npy"), np.load(tmp_path / "b.npy"))
    assert b["points_removed"] == a["points_removed"] and b["points_dropped"] == n


def test_encode_and_eval_count_them(scans_with_and_without, tmp_path):
    _, zeros, n = scans_with_and_without
    enc = _json("encode", zeros, "-o", tmp_path / "z.mcap", "--resolution", "0.2")
    assert enc["points_dropped_at_origin"] == n
    ev = _json("eval", zeros, "--resolution", "0.2")
    assert ev["points_dropped_at_origin"] == n and ev["points_dropped"] == n


def test_odometry_counts_them(scans_with_and_without, tmp_path):
    pytest.importorskip("kiss_icp")
    _, zeros, n = scans_with_and_without
    got = _json("odometry", zeros, "-o", tmp_path / "poses.txt")
    assert got["points_dropped_at_origin"] == n


def test_the_vehicle_s_own_returns_go_with_ego_box(scans_with_and_without, tmp_path):
    """Points on the vehicle (in the sensor's frame, whatever the pose) dropped by --ego-box and
    counted apart: the map equals the map of the scans without them."""
    plain, _, n = scans_with_and_without
    body = tmp_path / "body"
    shutil.copytree(plain, body)
    rng = np.random.default_rng(3)
    for f in sorted(body.glob("*.pcd")):
        cloud = read_pcd(f)
        hood = rng.uniform((0.5, -0.8, -0.9), (2.0, 0.8, -0.4), (40, 3)).astype(np.float32)
        points = np.concatenate([cloud.xyz.astype(np.float32), hood])
        f.write_bytes(pcd_header(len(points), False, viewpoint=cloud.viewpoint) + pcd_rows(points, None))
    box = "0.4,-0.9,-1.0,2.1,0.9,-0.3"
    a = _json("build", plain, "-o", tmp_path / "a.vxm", "--resolution", "0.1", "--ego-box", box)
    b = _json("build", body, "-o", tmp_path / "b.vxm", "--resolution", "0.1", "--ego-box", box)
    assert a["points_dropped_ego_box"] == 0 and b["points_dropped_ego_box"] == b["points_dropped"] == 40 * n
    la, lb = load_map(tmp_path / "a.vxm")[0].leaves(), load_map(tmp_path / "b.vxm")[0].leaves()
    assert np.array_equal(la.codes, lb.codes) and np.array_equal(la.values, lb.values)
    c = _json("build", body, "-o", tmp_path / "c.vxm", "--resolution", "0.1")
    assert c["points_dropped"] == 0  # without the box they are points like any other
    code, _, err = cli("build", body, "-o", tmp_path / "d.vxm", "--ego-box", "1,2,3")
    assert code == 2 and err.strip().splitlines()[-1].startswith("voxtool: error: --ego-box 1,2,3: give six numbers")
    assert not (tmp_path / "d.vxm").exists()


def test_odometry_on_scans_without_poses_does_not_advise_itself(scans_with_and_without, tmp_path):
    """A driver's dump has no poses: that is what odometry is for, so its own read of the source's
    poses (to compare, where there are some) must not warn 'run voxtool odometry'."""
    pytest.importorskip("kiss_icp")
    plain, _, n = scans_with_and_without
    dump = tmp_path / "dump"
    dump.mkdir()
    for f in sorted(plain.glob("*.pcd")):  # the same sensor-frame points, no VIEWPOINT, no poses.txt
        points = read_pcd(f).xyz.astype(np.float32)
        (dump / f.name).write_bytes(pcd_header(len(points), False) + pcd_rows(points, None))
    code, text, err = cli("odometry", dump, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0 and err == "", err
    assert json.loads(text)["scans"] == n


def test_a_standing_sensor_s_jitter_adds_no_path():
    from voxtool.odometry import path_length

    rng = np.random.default_rng(1)
    standing = rng.normal(0.0, 0.002, (500, 3))  # 2 mm of registration noise a scan, 500 scans
    moved = np.vstack([standing, standing[-1] + [1.0, 0.0, 0.0]])
    naive = np.linalg.norm(np.diff(moved, axis=0), axis=1).sum()
    assert naive > 2.0 and 0.95 < path_length(moved, 0.05) < 1.05


def test_odometry_with_almost_nothing_to_register_says_it_may_have_diverged(tmp_path):
    """Scans of a dozen points each (a sensor facing a wall, most beams without return): the run
    is flagged on one warning line and in --json, not reported as a success."""
    pytest.importorskip("kiss_icp")
    rng = np.random.default_rng(2)
    dump = tmp_path / "dump"
    dump.mkdir()
    for i in range(12):
        points = np.c_[np.full(12, 0.3), rng.uniform(-0.2, 0.2, (12, 2))].astype(np.float32)
        (dump / f"{i:03d}.pcd").write_bytes(pcd_header(len(points), False) + pcd_rows(points, None))
    code, text, err = cli("odometry", dump, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0, err
    check = json.loads(text)["plausibility"]
    assert check["suspect"] and check["sparse_scans"] == 12 and check["first_sparse_scan"] == 0
    lines = [ln for ln in err.splitlines() if "may have diverged" in ln]
    assert len(lines) == 1 and "12 scans with fewer than 30 points to register" in lines[0], err
