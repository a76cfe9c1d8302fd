"""LAS / LAZ / COPC tiles (voxtool.sources.las) against laspy, the library that reads them: the
Autzen tile's coordinates read in international feet and put in metres, the map of its occupied
voxels equal to the voxels its points fall in (brute force), LAZ equal to LAS, a COPC tile's heights
in US survey feet, and a tile read in chunks equal to one read whole."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli, map_voxels

from voxtool.sources import SourceOptions, open_source

laspy = pytest.importorskip("laspy")


def _metres(path, scale):
    tile = laspy.read(str(path))
    return np.stack([np.asarray(tile.x), np.asarray(tile.y), np.asarray(tile.z)], axis=1) * scale


def test_a_tile_in_feet_reads_in_metres(las_files):
    path = las_files / "autzen_trim.laz"
    code, text, _ = cli("info", path, "--json")
    info = json.loads(text)
    assert code == 0 and info["units"]["horizontal"] == {"name": "foot", "metres": 0.3048}
    assert info["units"]["vertical"]["metres"] == 0.3048 and info["points_in_tile"] == 110_000
    origin = (194_000.0, 258_800.0, 120.0)
    scans = list(open_source(path, SourceOptions(origin=origin)).scans)
    assert len(scans) == 1 and scans[0].hits_only
    expected = (_metres(path, 0.3048) - np.array(origin)).astype(np.float32)
    assert np.array_equal(scans[0].points, expected)
    span = expected.max(axis=0) - expected.min(axis=0)
    assert 350 < span[0] < 370 and 160 < span[1] < 180  # the stadium's 1,177 x 563 ft


def test_the_map_of_a_tile_is_the_voxels_its_points_fall_in(las_files, tmp_path):
    """Occupied: exactly the voxels holding a point (OctoMap's coordToKey on the float32 points
    about the local origin); free: none, since no ray was cast; said on one line."""
    from voxtool.api import load_leaves
    from voxtool.keys import keys_inside, morton_encode

    path = las_files / "autzen_trim.laz"
    out = tmp_path / "m.vxm"
    code, text, err = cli("build", path, "--origin", "auto", "--resolution", "0.5", "-o", out, "--json", "--no-progress")
    assert code == 0, err
    assert "free space stays unknown" in err
    origin = np.array(load_leaves(out)[3]["info"]["origin"])  # the local origin --origin auto chose
    points = (_metres(path, 0.3048) - origin).astype(np.float32)
    keys, inside = keys_inside(points, 0.5)
    assert inside.all()
    occ, free = map_voxels(out)
    assert np.array_equal(occ, np.unique(morton_encode(keys))) and free.size == 0
    assert json.loads(text)["points"] == 110_000


def test_laz_maps_as_las_and_chunks_as_a_whole(las_files, tmp_path, monkeypatch):
    import voxtool.sources.las as las

    maps = {}
    for name in ("simple.las", "simple.laz"):
        out = tmp_path / f"{name}.vxm"
        code, _, err = cli("build", las_files / name, "--origin", "auto", "--resolution", "0.5", "-o", out, "--no-progress")
        assert code == 0, (name, err)
        maps[name] = map_voxels(out)
    monkeypatch.setattr(las, "CHUNK_POINTS", 100)  # 11 scans of at most 100 points
    assert len(list(open_source(las_files / "simple.laz", SourceOptions()).scans)) == 11
    out = tmp_path / "chunked.vxm"
    assert cli("build", las_files / "simple.laz", "--origin", "auto", "--resolution", "0.5", "-o", out,
               "--no-progress")[0] == 0
    maps["chunked"] = map_voxels(out)
    reference = maps["simple.las"]
    assert reference[0].size > 500
    for name, (occ, free) in maps.items():
        assert np.array_equal(occ, reference[0]) and free.size == 0, name


def test_copc_with_heights_in_us_survey_feet(las_files):
    """simple.copc.laz holds simple.las's points under a compound system: metres across, heights
    in US survey feet (its WKT's VERT_CS); simple.las names no system (metres assumed). Read in
    metres, the COPC heights are the LAS ones times 1200/3937."""
    code, text, _ = cli("info", las_files / "simple.copc.laz", "--json")
    units = json.loads(text)["units"]
    assert code == 0 and units["horizontal"]["metres"] == 1.0
    assert units["vertical"]["name"] == "US survey foot" and units["vertical"]["metres"] == pytest.approx(1200 / 3937)
    origin = (637300.0, 851200.0, 0.0)
    copc = next(open_source(las_files / "simple.copc.laz", SourceOptions(origin=origin)).scans).points
    expected = (_metres(las_files / "simple.las", np.array([1.0, 1.0, 0.304800609601219])) - origin).astype(np.float32)
    key = np.dtype("f4,f4,f4")
    close = np.sort(copc.view(key).ravel()).view(np.float32).reshape(-1, 3) - \
        np.sort(expected.view(key).ravel()).view(np.float32).reshape(-1, 3)
    assert copc.shape == expected.shape and np.abs(close).max() < 1e-3  # the two files' offsets differ by 1e-10


def test_us_survey_feet_from_the_wkt(las_files):
    code, text, _ = cli("info", las_files / "file_with_both_wkt_and_geotiff_vlrs.las", "--json")
    units = json.loads(text)["units"]
    assert code == 0 and units["from"] == "WKT" and units["horizontal"]["metres"] == pytest.approx(1200 / 3937, rel=1e-9)


def test_what_needs_rays_refuses_a_tile_on_one_line(las_files, tmp_path):
    path = las_files / "simple.las"
    for args in (["build", path, "--backend", "hashmap", "-o", tmp_path / "h.vxm"],
                 ["clean", path, "-o", tmp_path / "c.pcd"]):
        code, _, err = cli(*args, "--origin", "auto", "--no-progress")
        lines = [line for line in err.splitlines() if line.strip() and "warning" not in line]
        assert code != 0 and len(lines) == 1 and "no sensor origin" in lines[0], err
        assert not args[-1].exists()


def test_odometry_refuses_a_tile_on_one_line(las_files, tmp_path):
    """A tile's points are placed already: there are no scans to register (it gave "poses" of a
    10,659 m voxel registration before)."""
    code, _, err = cli("odometry", las_files / "simple.las", "-o", tmp_path / "poses.txt", "--no-progress")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 3 and len(lines) == 1 and "survey tile" in lines[0] and "--poses" in lines[0], err
    assert not (tmp_path / "poses.txt").exists()


def test_a_file_that_is_not_las_fails_on_one_line(tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"LASF" + bytes(300))
    code, _, err = cli("build", bad, "-o", tmp_path / "m.vxm", "--no-progress")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code != 0 and len(lines) == 1 and str(bad) in lines[0] and "LAS" in lines[0]
    assert not (tmp_path / "m.vxm").exists()


@pytest.mark.parametrize("name, keep", [("simple.las", 5000), ("autzen_trim.laz", 30000), ("simple.copc.laz", 3000)])
def test_a_tile_cut_short_fails_on_one_line(las_files, tmp_path, name, keep):
    """A copy of a real tile cut short: one line naming it and the points its header declares,
    exit 3, nothing written (laspy and lazrs raise numpy's and their own errors mid-read)."""
    cut = tmp_path / name
    cut.write_bytes((las_files / name).read_bytes()[:keep])
    commands = [["build", cut, "--origin", "auto", "-o", tmp_path / "m.vxm"]]
    if name.endswith(".las"):  # its size tells, so info (which reads the header only) says so too
        commands.append(["info", cut])
    for args in commands:
        code, _, err = cli(*args, "--no-progress") if args[0] == "build" else cli(*args)
        lines = [line for line in err.splitlines() if line.strip() and "warning" not in line]
        assert code == 3 and len(lines) == 1 and str(cut) in lines[0] and "declares" in lines[0], err
    assert not (tmp_path / "m.vxm").exists()


def test_every_backend_that_builds_a_tile_and_encode_agree(las_files, tmp_path):
    """octocache and tiny take the octree's bricks of a tile; encode + merge carries them."""
    path = las_files / "simple.laz"
    common = ["--origin", "auto", "--resolution", "0.5", "--no-progress"]
    assert cli("build", path, "-o", tmp_path / "octree.vxm", *common)[0] == 0
    reference = map_voxels(tmp_path / "octree.vxm")
    for backend, extra in (("octocache", []), ("tiny", ["--map-size", "10000"])):  # the tile spans 3.4 x 4.6 km
        code, _, err = cli("build", path, "--backend", backend, *extra, "-o", tmp_path / f"{backend}.vxm", *common)
        assert code == 0, err
        occ, free = map_voxels(tmp_path / f"{backend}.vxm")
        assert np.array_equal(occ, reference[0]) and free.size == 0, backend
    code, _, err = cli("encode", path, "-o", tmp_path / "e.mcap", *common)
    assert code == 0, err
    assert cli("merge", tmp_path / "e.mcap", "-o", tmp_path / "m.vxm", "--no-progress")[0] == 0
    occ, free = map_voxels(tmp_path / "m.vxm")
    assert np.array_equal(occ, reference[0]) and free.size == 0


@pytest.mark.parametrize("chunk_points", [None, 10_007])
def test_a_tile_with_its_trajectory_casts_rays_from_the_sensor(tmp_path, monkeypatch, chunk_points):
    """The shipped sample's five real scans as one tile (laspy writes it: world points, each
    scan's points at the scan's GPS time) with the sensor's trajectory (--poses by GPS time): the
    map of the same points, grouped by time with laspy and written as world-frame PCDs whose
    VIEWPOINT is the trajectory's position (--no-viewpoint), voxel for voxel; free space cleared.
    Read in chunks that cut every scan (10,007 points), still one scan a time slice."""
    import voxtool.sources.las as las

    if chunk_points:
        monkeypatch.setattr(las, "CHUNK_POINTS", chunk_points)
    from pathlib import Path

    from scenes import write_pcd

    import voxtool

    sample = Path(voxtool.__file__).parent / "data" / "sample"
    scans = list(open_source(sample, SourceOptions()).scans)
    world = np.concatenate([s.points for s in scans]).astype(np.float64)
    times = np.concatenate([np.full(len(s.points), 1000.0 + 0.1 * k) for k, s in enumerate(scans)])
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [0.0001] * 3, np.floor(world.min(axis=0))
    tile = laspy.LasData(header)
    tile.x, tile.y, tile.z, tile.gps_time = world[:, 0], world[:, 1], world[:, 2], times
    tile.write(tmp_path / "tile.las")
    trajectory = tmp_path / "trajectory.txt"
    trajectory.write_text("".join(f"{1000.0 + 0.1 * k:.1f} " + " ".join(repr(float(v)) for v in s.origin) + " 0 0 0 1\n"
                                  for k, s in enumerate(scans)))
    code, text, err = cli("build", tmp_path / "tile.las", "--poses", trajectory, "-o", tmp_path / "las.vxm", "--json",
                          "--no-progress")
    assert code == 0, err
    assert json.loads(text)["scans"] == len(scans) and "no sensor origin" not in err
    back = laspy.read(str(tmp_path / "tile.las"))
    xyz = np.stack([np.asarray(back.x), np.asarray(back.y), np.asarray(back.z)], axis=1).astype(np.float32)
    pcd = tmp_path / "pcd"
    pcd.mkdir()
    for k, (t, s) in enumerate(zip(np.unique(np.asarray(back.gps_time)), scans)):
        write_pcd(pcd / f"{k:03d}.pcd", xyz[np.asarray(back.gps_time) == t], viewpoint=(*map(float, s.origin), 1, 0, 0, 0))
    assert cli("build", pcd, "--no-viewpoint", "-o", tmp_path / "pcd.vxm", "--no-progress")[0] == 0
    occ, free = map_voxels(tmp_path / "las.vxm")
    pcd_occ, pcd_free = map_voxels(tmp_path / "pcd.vxm")
    assert free.size > occ.size > 1000
    assert np.array_equal(occ, pcd_occ) and np.array_equal(free, pcd_free)


def test_the_tile_warning_is_said_once_and_info_reads_the_header_only(las_files, monkeypatch):
    """`--origin auto` peeks at the first scan before the build reads them all: the tile's
    one-line warning is still said once. `info` gives the chunks from the header's point count,
    without reading (or warning about) a point."""
    import voxtool.sources.las as las

    code, _, err = cli("build", las_files / "autzen_trim.laz", "--origin", "auto", "--no-progress")
    assert code == 0 and err.count("no sensor origin") == 1, err
    monkeypatch.setattr(las, "CHUNK_POINTS", 100)
    monkeypatch.setattr(las, "las_stream", None)  # info must not read the scans
    code, text, err = cli("info", las_files / "simple.laz", "--json")
    info = json.loads(text)
    assert code == 0 and "warning" not in err, err
    assert info["points_in_tile"] == 1065 and info["scans"] == 11
    assert info["points_per_scan"] == {"min": 65, "median": 100.0, "max": 100}
