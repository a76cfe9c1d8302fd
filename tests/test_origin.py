"""Scans far from their frame's origin (a city or UTM frame) build about a local origin
(--origin): the map is OctoMap's map of the shifted scans, the origin is recorded and reported,
and point outputs go back to the scans' frame without float32 blur."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.api import load_leaves
from voxtool.geometry import Pose
from voxtool.keys import expand_leaves

RES = 0.1
FAR = np.array([512_345.678, 5_401_234.321, 87.65])  # metres: a UTM position (zone easting, northing)


@pytest.fixture(scope="module")
def far_scans(tmp_path_factory):
    """A PCD directory of box-room scans whose poses sit at FAR, and the scans as (sensor
    points, pose)."""
    d = tmp_path_factory.mktemp("far")
    scans = []
    for i, (pts, origin, yaw) in enumerate(box_scene(4, 500, seed=8)):
        q = yaw_quat(yaw)
        t = origin + FAR
        write_pcd(d / f"{i}.pcd", pts, (*t, *q))
        scans.append((pts, Pose.from_quat(t, *q)))
    return d, scans


def voxel_set(leaves, thr):
    occ = leaves.values > np.float32(thr)
    return np.sort(expand_leaves(leaves.codes[occ], leaves.depths[occ])), np.sort(
        expand_leaves(leaves.codes[~occ], leaves.depths[~occ]))


def assert_same_voxels_as_octomap(out, tree, tmp_path) -> None:
    """voxtool's map `out` and OctoMap's `tree` (written as .bt, read back by the same reader)
    hold the same occupied and the same free voxels, over a thousand occupied."""
    tree.writeBinary(str(tmp_path / "octomap.bt"))
    ours, _, thr, _ = load_leaves(out)
    theirs, _, bt_thr, _ = load_leaves(tmp_path / "octomap.bt")
    occ, free = voxel_set(ours, thr)
    t_occ, t_free = voxel_set(theirs, bt_thr)
    assert occ.size > 1000 and np.array_equal(occ, t_occ) and np.array_equal(free, t_free)


def test_far_scans_are_refused_with_the_option_named(far_scans, tmp_path):
    code, _, err = cli("build", far_scans[0], "-o", tmp_path / "m.vxm", "--resolution", RES, "--no-progress")
    assert code == 4 and err.count("\n") == 1 and "--origin auto" in err, err
    assert not (tmp_path / "m.vxm").exists()


def test_the_map_about_a_local_origin_is_octomaps_map_of_the_shifted_scans(far_scans, tmp_path):
    """OctoMap (pyoctomap) inserts the scans moved by -origin (the pose's translation less the
    origin, float64, then float32 points as insertPointCloud takes them); voxtool's map with
    --origin auto has the same voxels, and its .bt (local frame) reads the same in OctoMap."""
    pyoctomap = pytest.importorskip("pyoctomap")
    d, scans = far_scans
    out = tmp_path / "m.vxm"
    code, text, err = cli("build", d, "-o", out, "--resolution", RES, "--origin", "auto", "--json", "--no-progress")
    assert code == 0, err
    origin = np.array(json.loads(text)["origin"])
    # auto: the first scan's sensor position snapped to the voxel grid
    assert np.allclose(origin, np.round(scans[0][1].translation / RES) * RES, atol=1e-6)
    assert np.allclose(origin / RES, np.round(origin / RES), atol=1e-6)
    tree = pyoctomap.OcTree(RES)
    for pts, pose in scans:
        shifted = Pose(pose.rotation, pose.translation - origin)
        world = shifted.apply(pts).astype(np.float64)
        tree.insertPointCloud(world, shifted.translation.astype(np.float32).astype(np.float64))
    assert_same_voxels_as_octomap(out, tree, tmp_path)
    code, text, _ = cli("stats", out, "--json")
    assert json.loads(text)["origin"] == pytest.approx(origin.tolist())
    assert "local origin" in cli("stats", out)[1]


def test_point_outputs_are_in_the_scans_frame_in_float64(far_scans, tmp_path):
    d, _ = far_scans
    out = tmp_path / "m.vxm"
    assert cli("build", d, "-o", out, "--resolution", RES, "--origin", "auto", "--no-progress")[0] == 0
    leaves, _, thr, meta = load_leaves(out)
    origin = np.array(meta["info"]["origin"])
    from voxtool.io.export import voxel_centres

    local = voxel_centres(leaves, leaves.values > np.float32(thr), RES).astype(np.float64)
    ply = tmp_path / "m.ply"
    assert cli("export", out, "-o", ply)[0] == 0
    import open3d as o3d

    def read(path):  # Open3D's tensor reader keeps float64 (its legacy PCD reader reads doubles as 0)
        return o3d.t.io.read_point_cloud(str(path)).point.positions.numpy()

    cloud = read(ply)  # a reader voxtool did not write
    assert b"property double x" in ply.read_bytes()[:300]
    assert cloud.shape == local.shape and np.abs(cloud - (local + origin)).max() < 1e-6
    pcd = tmp_path / "m.pcd"
    assert cli("export", out, "-o", pcd)[0] == 0
    assert read(pcd).dtype == np.float64 and np.abs(read(pcd) - (local + origin)).max() < 1e-6
    # the .mcap: the scene and the grid in the scans' frame, the Octomap in map_local below it
    from test_viewer_mcap import read_ros2

    assert cli("export", out, "-o", tmp_path / "m.mcap")[0] == 0
    got = read_ros2(tmp_path / "m.mcap")
    tf = got["/tf_static"][2].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "map_local")
    assert [tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z] == pytest.approx(
        origin.tolist())
    assert got["/octomap_binary"][2].header.frame_id == "map_local"
    cubes = got["/voxtool/map"][2].entities[0].cubes
    centre = np.array([[c.pose.position.x, c.pose.position.y, c.pose.position.z] for c in cubes])
    assert np.all(np.abs(centre - FAR).max(axis=1) < 10)
    grid = got["/projected_map"][2]
    assert abs(grid.info.origin.position.x - FAR[0]) < 10 and abs(grid.info.origin.position.y - FAR[1]) < 10
    # the nav2 .yaml beside a .pgm: the same corner as the .mcap's grid, and a comment saying why
    import yaml

    assert cli("export", out, "-o", tmp_path / "m.pgm")[0] == 0
    text = (tmp_path / "m.yaml").read_text()
    doc = yaml.safe_load(text)
    assert doc["origin"][:2] == pytest.approx([grid.info.origin.position.x, grid.info.origin.position.y], abs=1e-6)
    assert "local origin" in text.splitlines()[0] and text.startswith("#")
    # a picture's axes are the local frame: its caption says so, with the origin
    code, text, err = cli("export", out, "-o", tmp_path / "m.png", "--json")
    assert code == 0, err
    assert f"local frame: add the origin ({origin[0]:.3f}, {origin[1]:.3f}" in json.loads(text)["caption"]


def test_clean_about_a_local_origin_writes_the_scans_frame(far_scans, tmp_path):
    d, scans = far_scans
    code, text, err = cli("clean", d, "-o", tmp_path / "s.ply", "--origin", "auto", "--json", "--no-progress")
    assert code == 0, err
    assert np.allclose(json.loads(text)["origin"], np.round(scans[0][1].translation / RES) * RES, atol=1e-6)
    import open3d as o3d

    kept = o3d.t.io.read_point_cloud(str(tmp_path / "s.ply")).point.positions.numpy()
    # the scans' points as clean judged them (float32 about the origin), moved back in float64
    origin = np.array(json.loads(text)["origin"])
    every = np.concatenate([Pose(pose.rotation, pose.translation - origin).apply(pts).astype(np.float64) + origin
                            for pts, pose in scans])
    assert 0 < len(kept) <= len(every)
    assert set(map(tuple, kept.tolist())) <= set(map(tuple, every.tolist()))


def test_query_and_diff_use_the_scans_frame(far_scans, tmp_path):
    d, scans = far_scans
    a, b = tmp_path / "a.vxm", tmp_path / "b.vxm"
    assert cli("build", d, "-o", a, "--resolution", RES, "--origin", "auto", "--no-progress")[0] == 0
    from voxtool.voxelmap import load

    vmap = load(a)
    leaves, _, thr, _ = load_leaves(a)
    from voxtool.io.export import voxel_centres

    occupied = voxel_centres(leaves, leaves.values > np.float32(thr), RES).astype(np.float64) + vmap.origin
    assert (vmap.query(occupied)["state"] == 2).all()  # every occupied centre, asked in the scans' frame
    code, text, _ = cli("query", a, "--json", "--", *occupied[0])
    assert code == 0 and json.loads(text)["state"] == "occupied"
    x, y, z = (float(v) + 0.3 for v in vmap.origin)
    assert cli("build", d, "-o", b, "--resolution", RES, "--origin", f"{x},{y},{z}", "--no-progress")[0] == 0
    code, _, err = cli("diff", a, b)
    assert code == 2 and "same --origin" in err, err
    code, _, err = cli("build", d, "-o", b, "--resolution", RES, "--origin", "1,2", "--no-progress")
    assert code == 2 and "--origin 1,2" in err


def _write_world_pcd_f8(path, points: np.ndarray, sensor: np.ndarray) -> None:
    """World-frame x y z as doubles (PCL's TYPE F SIZE 8), the sensor position as VIEWPOINT."""
    n = len(points)
    vp = " ".join(repr(float(v)) for v in (*sensor, 1, 0, 0, 0))
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT {vp}\nPOINTS {n}\nDATA binary\n").encode()
    path.write_bytes(head + np.asarray(points, dtype="<f8").tobytes())


def _write_world_ply_f8(path, points: np.ndarray) -> None:
    n = len(points)
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty double x\nproperty double y\n"
            "property double z\nend_header\n").encode()
    path.write_bytes(head + np.asarray(points, dtype="<f8").tobytes())


@pytest.mark.parametrize("kind", ["pcd", "ply"])
def test_world_frame_doubles_keep_their_precision_until_the_origin_is_subtracted(far_scans, tmp_path, kind):
    """World-frame clouds stored as doubles (UTM coordinates, --no-viewpoint for PCD, identity
    poses for PLY): the map equals OctoMap's map of the scans shifted in float64 by the origin.
    Read as float32 first, y (5.4e6 m) would snap to 0.5 m and the map would be another."""
    pyoctomap = pytest.importorskip("pyoctomap")
    _, scans = far_scans
    d = tmp_path / kind
    d.mkdir()
    worlds = []
    for i, (pts, pose) in enumerate(scans):
        world = pts.astype(np.float64) @ pose.rotation.T + pose.translation  # float64 all the way
        worlds.append((world, pose.translation))
        if kind == "pcd":
            _write_world_pcd_f8(d / f"{i}.pcd", world, pose.translation)
        else:
            _write_world_ply_f8(d / f"{i}.ply", world)
    options = ["--no-viewpoint"] + ([] if kind == "pcd" else ["--poses", tmp_path / "poses.txt"])
    if kind == "ply":  # the sensor positions as a TUM file; --no-viewpoint: the points are world-frame
        (tmp_path / "poses.txt").write_text("".join(f"{i} {float(t[0])!r} {float(t[1])!r} {float(t[2])!r} 0 0 0 1\n"
                                                    for i, (_, t) in enumerate(worlds)))
    out = tmp_path / "m.vxm"
    code, text, err = cli("build", d, "-o", out, "--resolution", RES, "--origin", "auto", "--json", "--no-progress",
                          *options)
    assert code == 0, err
    origin = np.array(json.loads(text)["origin"])
    tree = pyoctomap.OcTree(RES)
    for world, sensor in worlds:
        tree.insertPointCloud((world - origin).astype(np.float32).astype(np.float64),
                              (sensor - origin).astype(np.float32).astype(np.float64))
    assert_same_voxels_as_octomap(out, tree, tmp_path)
    # the float32 reading this replaces moves y by up to a quarter metre: another map
    y32 = worlds[0][0][:, 1].astype(np.float32).astype(np.float64)
    assert np.abs(y32 - worlds[0][0][:, 1]).max() > 0.05


@pytest.fixture(scope="module")
def near_scans(far_scans, tmp_path_factory):
    """The far scans moved by -origin (the origin --origin auto picks) in float64: the same scans
    near the frame's origin, and that origin."""
    d, scans = far_scans
    origin = np.round(scans[0][1].translation / RES) * RES
    near = tmp_path_factory.mktemp("near")
    for i, (pts, pose) in enumerate(scans):
        q = yaw_quat(0.0)
        shifted = Pose(pose.rotation, pose.translation - origin)
        from voxtool.geometry import matrix_to_quat

        qw, qx, qy, qz = matrix_to_quat(shifted.rotation)
        write_pcd(near / f"{i}.pcd", pts, (*shifted.translation, qw, qx, qy, qz))
        assert q is not None
    return near, origin


def test_eval_about_a_local_origin_counts_what_it_counts_near_the_origin(far_scans, near_scans, tmp_path):
    d, _ = far_scans
    near, origin = near_scans
    code, _, err = cli("eval", d, "--resolution", RES, "--holdout-every", 2, "--no-progress")
    assert code == 4 and "--origin auto" in err, err
    code, text, err = cli("eval", d, "--resolution", RES, "--holdout-every", 2, "--origin", "auto", "--json",
                          "--no-progress")
    assert code == 0, err
    far = json.loads(text)
    expected = json.loads(cli("eval", near, "--resolution", RES, "--holdout-every", 2, "--json", "--no-progress")[1])
    assert far["origin"] == pytest.approx(origin.tolist())
    assert far["total"] == expected["total"] and far["total"]["correct"] > 100


def test_encode_about_a_local_origin_carries_it_in_every_packet(far_scans, tmp_path):
    """encode --origin: every packet's map_origin is the origin; merge's map is build's map about
    it (same occupied voxels) and records it, so exports go back to the scans' frame; logs
    about two origins are refused."""
    d, _ = far_scans
    log = tmp_path / "r1.mcap"
    code, text, err = cli("encode", d, "-o", log, "--resolution", RES, "--origin", "auto", "--json", "--no-progress")
    assert code == 0, err
    from voxtool.codec.fusion import packets_of

    packets = packets_of(log)
    built = tmp_path / "built.vxm"
    code, text, err = cli("build", d, "-o", built, "--resolution", RES, "--origin", "auto", "--json", "--no-progress")
    origin = json.loads(text)["origin"]
    assert packets and all(list(p.map_origin) == pytest.approx(origin) for p in packets)
    merged = tmp_path / "merged.vxm"
    code, _, err = cli("merge", log, "-o", merged, "--no-progress")
    assert code == 0, err
    a, _, thr_a, meta = load_leaves(merged)
    b, _, thr_b, _ = load_leaves(built)
    assert meta["info"]["origin"] == pytest.approx(origin)
    assert np.array_equal(voxel_set(a, thr_a)[0], voxel_set(b, thr_b)[0])
    x, y, z = (v + 1.0 for v in origin)
    other = tmp_path / "r2.mcap"
    assert cli("encode", d, "-o", other, "--resolution", RES, "--origin", f"{x},{y},{z}", "--robot", "r2",
               "--no-progress")[0] == 0
    code, _, err = cli("merge", log, other, "-o", tmp_path / "both.vxm", "--no-progress")
    assert code == 5 and "map origin" in err and "one --origin" in err and err.count("\n") == 1, err


def test_graph_export_and_cache_bench_about_a_local_origin(far_scans, tmp_path):
    """A .graph of far scans about --origin auto holds the shifted scans (OctoMap keeps float32),
    with the origin on whole metres; its map is the map of the far scans built about that origin.
    cache-bench takes --origin too."""
    d, _ = far_scans
    graph = tmp_path / "s.graph"
    code, text, err = cli("export", d, "-o", graph, "--origin", "auto", "--json")
    assert code == 0, err
    origin = json.loads(text)["origin"]
    assert origin == [round(v) for v in origin] and np.abs(np.array(origin) - FAR).max() < 10
    a, b = tmp_path / "g.vxm", tmp_path / "f.vxm"
    assert cli("build", graph, "-o", a, "--resolution", RES, "--no-progress")[0] == 0
    assert cli("build", d, "-o", b, "--resolution", RES, "--origin", ",".join(map(str, origin)), "--no-progress")[0] == 0
    la, _, ta, _ = load_leaves(a)
    lb, _, tb, _ = load_leaves(b)
    assert np.array_equal(voxel_set(la, ta)[0], voxel_set(lb, tb)[0])
    code, _, err = cli("export", a, "-o", tmp_path / "m.ply", "--origin", "auto")
    assert code == 2 and "--origin is for scans exported as .graph" in err
    code, _, err = cli("cache-bench", d, "--resolution", RES, "--tau", "2", "--buckets", "64")
    assert code == 4 and "--origin auto" in err and err.count("\n") == 1, err  # the worker's error, as itself
    code, text, err = cli("cache-bench", d, "--resolution", RES, "--origin", "auto", "--tau", "2", "--buckets", "64",
                          "--json")
    assert code == 0, err
    assert all(row["identical_to_octree"] for row in json.loads(text)["rows"])
