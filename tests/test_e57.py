"""E57 scans (voxtool.sources.e57) against pye57, the library that reads and writes them: the
real terrestrial scan of pye57's tests read point for point as pye57 reads it, and a file pye57
writes of the shipped sample's real scans, each with its pose, mapped exactly as the same scans
in PCD with their VIEWPOINT poses."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli, map_voxels

from voxtool.sources import SourceOptions, open_source

pye57 = pytest.importorskip("pye57")


def test_the_real_scan_reads_as_pye57_reads_it(e57_files):
    path = e57_files / "pumpAVisualReferenceImage.e57"
    reader = pye57.E57(str(path))
    truth = reader.read_scan(0, transform=True)  # valid points only, in the file's frame
    scans = list(open_source(path, SourceOptions()).scans)
    assert len(scans) == 1
    scan = scans[0]
    header = reader.get_header(0)
    assert scan.points_read == header.point_count == 155_201
    xyz = np.stack([truth["cartesianX"], truth["cartesianY"], truth["cartesianZ"]], axis=1)
    assert scan.points.shape[0] + scan.dropped_nonfinite == scan.points_read
    assert np.array_equal(scan.points, xyz.astype(np.float32))


def test_a_scan_with_a_translation_starts_its_rays_there(e57_files):
    path = e57_files / "translationWithoutRotation.e57"
    reader = pye57.E57(str(path))
    truth = reader.read_scan(0, transform=True, ignore_missing_fields=True)
    scan = next(open_source(path, SourceOptions()).scans)
    assert np.array_equal(scan.origin, np.float32([4, 5, 6])) and np.array_equal(reader.get_header(0).translation, [4, 5, 6])
    xyz = np.stack([truth[f"cartesian{a}"] for a in "XYZ"], axis=1).astype(np.float32)
    # its first point is (0, 0, 0) in the scan's frame: the scanner's own position, no return
    at_scanner = (xyz == scan.origin).all(axis=1)
    assert at_scanner.sum() == scan.dropped_at_origin == 1
    assert np.array_equal(scan.points, xyz[~at_scanner])


@pytest.fixture(scope="module")
def two_scans(tmp_path_factory):
    """The shipped sample's first two real scans (norlab, each with its VIEWPOINT pose) as an
    E57 that pye57 writes, each scan with its pose in its header, beside the PCDs themselves."""
    from pathlib import Path

    import voxtool
    from voxtool.sources.pcd import read_pcd

    tmp = tmp_path_factory.mktemp("e57")
    pcd = tmp / "pcd"
    pcd.mkdir()
    path = tmp / "two.e57"
    with pye57.E57(str(path), mode="w") as writer:
        for f in sorted((Path(voxtool.__file__).parent / "data" / "sample").glob("*.pcd"))[:2]:
            (pcd / f.name).write_bytes(f.read_bytes())
            cloud = read_pcd(f)
            xyz = np.asarray(cloud.xyz, np.float64)  # float32 values: the two files hold the same numbers
            vp = cloud.viewpoint
            writer.write_scan_raw({f"cartesian{a}": xyz[:, k].copy() for k, a in enumerate("XYZ")},
                                  rotation=np.array(vp[3:7], np.float64), translation=np.array(vp[:3], np.float64))
    return path, pcd, tmp


def test_posed_scans_map_as_the_same_scans_in_pcd(two_scans):
    path, pcd, tmp = two_scans
    for src, out in ((path, tmp / "e57.vxm"), (pcd, tmp / "pcd.vxm")):
        code, _, err = cli("build", src, "-o", out, "--resolution", "0.1", "--no-progress")
        assert code == 0, err
    occ, free = map_voxels(tmp / "e57.vxm")
    pcd_occ, pcd_free = map_voxels(tmp / "pcd.vxm")
    assert occ.size > 10_000 and free.size > occ.size
    assert np.array_equal(occ, pcd_occ) and np.array_equal(free, pcd_free)
    code, text, _ = cli("info", path, "--json")
    info = json.loads(text)
    assert code == 0 and info["scans"] == 2 and info["kind"] == "e57" and "2 of 2 scans" in info["pose_source"]


def test_an_e57_encoded_and_merged_is_its_build(two_scans):
    """encode reads it as build does: the merged log holds the built map's voxels."""
    path, _, tmp = two_scans
    built = tmp / "b.vxm"
    assert cli("build", path, "-o", built, "--resolution", "0.1", "--no-progress")[0] == 0
    code, text, err = cli("encode", path, "-o", tmp / "e.mcap", "--resolution", "0.1", "--json", "--no-progress")
    assert code == 0, err
    assert json.loads(text)["scans"] == 2
    assert cli("merge", tmp / "e.mcap", "-o", tmp / "m.vxm", "--no-progress")[0] == 0
    occ, free = map_voxels(built)
    m_occ, m_free = map_voxels(tmp / "m.vxm")
    assert occ.size > 1000 and np.array_equal(occ, m_occ) and np.array_equal(free, m_free)


def test_invalid_points_are_dropped_and_counted(tmp_path):
    xyz = np.random.default_rng(0).uniform(-5, 5, (40, 3))
    invalid = np.zeros(40, np.int8)
    invalid[[3, 7, 11]] = 2  # no return
    invalid[20] = 1  # a direction only
    path = tmp_path / "invalid.e57"
    with pye57.E57(str(path), mode="w") as writer:
        writer.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
                               "cartesianInvalidState": invalid})
    code, text, err = cli("build", path, "-o", tmp_path / "m.vxm", "--json", "--no-progress")
    assert code == 0, err
    report = json.loads(text)
    assert report["points_dropped_nonfinite"] == 4 and report["points_dropped"] == 4
    code, text, err = cli("build", path, "-o", tmp_path / "m2.vxm", "--no-progress")
    assert code == 0 and "4 dropped" in text + err  # said in the summary as well


def test_spherical_coordinates_as_pye57_converts_them():
    from pye57.utils import convert_spherical_to_cartesian

    from voxtool.sources.e57 import spherical_to_xyz

    rng = np.random.default_rng(1)
    rae = np.stack([rng.uniform(0.5, 80, 500), rng.uniform(-np.pi, np.pi, 500), rng.uniform(-1.5, 1.5, 500)], axis=1)
    assert np.allclose(spherical_to_xyz(*rae.T), convert_spherical_to_cartesian(rae), rtol=0, atol=1e-9)


def test_a_file_that_is_not_e57_fails_on_one_line_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.e57"
    bad.write_bytes(b"ASTM-E57" + bytes(2000))
    out = tmp_path / "m.vxm"
    code, _, err = cli("build", bad, "-o", out, "--no-progress")
    assert code != 0 and not out.exists()
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and str(bad) in lines[0] and "E57" in lines[0]
