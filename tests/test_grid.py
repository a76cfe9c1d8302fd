"""2D occupancy grids (export .pgm + .yaml, the .mcap's /projected_map) against a brute-force
projection of the voxels voxtool exports, read back as nav2's map_server and rosbags read them."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import cli

from voxtool.keys import TREE_MAX_VAL


def exported_voxels(map_path, tmp_path, z_range):
    """(centres, occupied) of every voxel `export --free --crop` writes to a PLY, read by hand
    from the PLY bytes (binary little-endian x y z red green blue)."""
    from voxtool.io.export import OCCUPIED_RGB

    ply = tmp_path / "all.ply"
    lo, hi = z_range if z_range else (-1e4, 1e4)
    code, _, err = cli("export", map_path, "-o", ply, "--free", "--crop", f"-1e4,-1e4,{lo},1e4,1e4,{hi}")
    assert code == 0, err
    data = ply.read_bytes()
    body = data[data.index(b"end_header\n") + len(b"end_header\n"):]
    rec = np.frombuffer(body, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    xyz = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64)
    occupied = (rec["r"] == OCCUPIED_RGB[0]) & (rec["g"] == OCCUPIED_RGB[1]) & (rec["b"] == OCCUPIED_RGB[2])
    return xyz, occupied


def brute_force_grid(xyz, occupied, resolution):
    """{(column x, column y): 100 or 0} by a dictionary over the voxels: occupied if any is."""
    cols = np.floor(xyz[:, :2] / resolution).astype(np.int64)
    out = {}
    for (cx, cy), occ in zip(map(tuple, cols.tolist()), occupied.tolist()):
        out[(cx, cy)] = 100 if occ or out.get((cx, cy)) == 100 else 0
    return out


def read_nav2_map(yaml_path):
    """(cells[row from the bottom, col], resolution, origin) as nav2's map_server loads a
    trinary map: occ = (255 - pixel) / 255 (negate 0), occupied above occupied_thresh, free
    below free_thresh, unknown between. The image is read by Pillow."""
    import yaml
    from PIL import Image

    doc = yaml.safe_load(yaml_path.read_text())
    assert set(doc) == {"image", "mode", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    assert doc["mode"] == "trinary" and doc["negate"] == 0 and len(doc["origin"]) == 3
    pixels = np.asarray(Image.open(yaml_path.parent / doc["image"]), dtype=np.float64)
    occ = (255 - pixels) / 255.0
    cells = np.where(occ > doc["occupied_thresh"], 100, np.where(occ < doc["free_thresh"], 0, -1))
    return cells[::-1], doc["resolution"], doc["origin"]


def grid_dict(cells, resolution, origin):
    rows, cols = np.nonzero(cells >= 0)
    x0, y0 = int(round(origin[0] / resolution)), int(round(origin[1] / resolution))
    return {(int(c) + x0, int(r) + y0): int(cells[r, c]) for r, c in zip(rows, cols)}


@pytest.mark.parametrize("z_range", [(0.2, 1.5), (-0.5, 0.3)])
def test_pgm_grid_equals_brute_force_projection(sample_map, tmp_path, z_range):
    path, _ = sample_map
    code, _, err = cli("export", path, "-o", tmp_path / "map.pgm", "--z-range", f"{z_range[0]},{z_range[1]}")
    assert code == 0, err
    cells, res, origin = read_nav2_map(tmp_path / "map.yaml")
    xyz, occupied = exported_voxels(path, tmp_path, z_range)
    expected = brute_force_grid(xyz, occupied, res)
    assert grid_dict(cells, res, origin) == expected
    assert 0 < sum(v == 100 for v in expected.values()) < len(expected)


def test_mcap_occupancy_grid_reads_in_rosbags(sample_map, tmp_path):
    from test_viewer_mcap import read_ros2

    path, _ = sample_map
    out = tmp_path / "map.mcap"
    assert cli("export", path, "-o", out, "--z-range", "0.2,1.5")[0] == 0
    assert cli("export", path, "-o", tmp_path / "map.pgm", "--z-range", "0.2,1.5")[0] == 0
    msgtype, _, grid = read_ros2(out)["/projected_map"]
    assert msgtype == "nav_msgs/msg/OccupancyGrid" and grid.header.frame_id == "map"
    cells = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    pgm, res, origin = read_nav2_map(tmp_path / "map.yaml")
    assert grid.info.resolution == pytest.approx(res)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == pytest.approx(tuple(origin[:2]))
    assert np.array_equal(cells, pgm)


def test_pruned_leaves_paint_their_whole_square(tmp_path):
    """A pruned free leaf covers 2^k x 2^k cells; an occupied voxel inside it wins its cell."""
    from voxtool.grid import FREE, OCCUPIED, UNKNOWN, project
    from voxtool.keys import morton_encode
    from voxtool.maps.base import Leaves

    base = np.array([[TREE_MAX_VAL, TREE_MAX_VAL, TREE_MAX_VAL]])
    codes = np.concatenate([morton_encode(base), morton_encode(base + [[4, 1, 0]])])
    leaves = Leaves(codes, np.array([14, 16], np.uint8), np.array([-1.0, 2.0], np.float32))  # a 4^3 free leaf
    grid = project(leaves, 0.5, 0.0)
    assert grid.cells.shape == (4, 5) and grid.origin == (0.0, 0.0)
    expected = np.full((4, 5), FREE, np.int8)
    expected[:, 4] = UNKNOWN
    expected[1, 4] = OCCUPIED
    assert np.array_equal(grid.cells, expected)
    band = project(leaves, 0.5, 0.0, (0.5, 1.0)).cells  # the map's footprint; the occupied voxel's layer is z 0
    assert band.shape == (4, 5) and np.all(band[:, :4] == FREE) and np.all(band[:, 4] == UNKNOWN)


def test_every_grid_of_one_map_lies_on_the_others(sample_map, tmp_path):
    """--z-range bands and --above-ground span the map's footprint: one origin, one size, so that
    grids of one map overlay cell for cell (they differed by the extent of what each band held)."""
    path, _ = sample_map
    grids = []
    for option, value in (("--z-range", "0.2,1.5"), ("--z-range", "-0.5,0.3"), ("--above-ground", "0.3,2")):
        out = tmp_path / f"g{len(grids)}.pgm"
        code, _, err = cli("export", path, "-o", out, option, value)
        assert code == 0, err
        grids.append(read_nav2_map(out.with_suffix(".yaml")))
    assert len({g[0].shape for g in grids}) == 1 and len({tuple(g[2]) for g in grids}) == 1
    assert not np.array_equal(grids[0][0], grids[2][0])  # the same cells, not the same grid


def test_bad_z_range_is_one_line(sample_map, tmp_path):
    path, _ = sample_map
    for bad, words in (("1,0", "MIN must be at most MAX"), ("a,b", "two numbers"), ("500,600", "no voxel")):
        code, _, err = cli("export", path, "-o", tmp_path / "g.pgm", "--z-range", bad)
        assert code == 2 and err.count("\n") == 1 and words in err, err
    code, _, err = cli("export", path, "-o", tmp_path / "g.ply", "--z-range", "0,1")
    assert code == 2 and "--z-range is for the 2D grid" in err
    assert not (tmp_path / "g.pgm").exists() and not (tmp_path / "g.yaml").exists()


def test_the_yaml_origin_is_written_as_people_write_it():
    """key * resolution gives -3.4000000000000004; the .yaml says -3.4 (the same within 1e-9 m)."""
    from voxtool.grid import Grid2D, map_yaml

    grid = Grid2D(np.zeros((2, 2), np.int8), 0.2, (-17 * 0.2, 3 * 0.1), None)
    assert grid.origin == (-3.4000000000000004, 0.30000000000000004)
    assert "origin: [-3.4, 0.3, 0.0]\n" in map_yaml(grid, "g.pgm")
    assert "origin: [96.6, 5.3, 0.0]\n" in map_yaml(grid, "g.pgm", local_origin=(100.0, 5.0, 0.0))

