"""`export --above-ground MIN,MAX`: the ground found in the map (voxtool.ground) and the 2D grid of
what stands on it, against a generated sloped terrain whose heights are known (brute force)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import cli
from test_grid import read_nav2_map

from voxtool.keys import TREE_MAX_VAL, morton_encode

RES = 0.2
SIDE = 150  # columns per side: 30 m
BOXES = [(30, 40), (80, 100), (110, 20)]  # corner columns of 1 m x 1 m boxes, 1 m tall
CANOPY = (60, 60)  # a 3 m x 3 m tree crown, 2.6-3.4 m above the ground, the ground under it seen


def ground_key(x: np.ndarray) -> np.ndarray:
    """The ground's z key at column x: a 15 % slope along x (4.5 m over the 30 m)."""
    return TREE_MAX_VAL + np.floor(0.15 * x).astype(np.int64)


@pytest.fixture(scope="module")
def terrain(tmp_path_factory):
    xs, ys = np.meshgrid(np.arange(SIDE), np.arange(SIDE), indexing="ij")
    xs, ys = xs.ravel(), ys.ravel()
    box = np.zeros(xs.shape, bool)
    for bx, by in BOXES:
        box |= (xs >= bx) & (xs < bx + 5) & (ys >= by) & (ys < by + 5)
    keys = [np.c_[xs[~box], ys[~box], ground_key(xs[~box])]]  # no ground seen under a box
    for k in range(1, 6):  # the boxes: 1 m above the ground, from the voxel above it
        keys.append(np.c_[xs[box], ys[box], ground_key(xs[box]) + k])
    crown = (xs >= CANOPY[0]) & (xs < CANOPY[0] + 15) & (ys >= CANOPY[1]) & (ys < CANOPY[1] + 15)
    for k in range(13, 18):
        keys.append(np.c_[xs[crown], ys[crown], ground_key(xs[crown]) + k])
    keys = np.concatenate(keys) + np.array([TREE_MAX_VAL, TREE_MAX_VAL, 0])
    path = tmp_path_factory.mktemp("terrain") / "terrain.vxm"
    save_occupied(keys, path)
    return path, xs, ys, box, crown


def save_occupied(keys: np.ndarray, path, values: np.ndarray | None = None) -> None:
    """A map whose occupied voxels are `keys` (N, 3) and nothing else, saved as a snapshot;
    `values`: their log-odds (default 2.0, a few hits), one per key."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.io.mapfile import save_map
    from voxtool.maps.octree import OctreeMap

    codes = morton_encode(keys.astype(np.uint16))
    occupied, first = np.unique(codes, return_index=True)
    values = np.full(codes.shape[0], 2.0) if values is None else np.asarray(values)
    m = OctreeMap(MapParams(resolution=RES), SensorModel())
    m.load_state({"leaf_codes": occupied, "leaf_depths": np.full(occupied.shape[0], 16, np.uint8),
                  "leaf_values": values[first].astype(np.float32)})
    save_map(path, m, {"source": "generated"})


def test_returns_under_the_road_are_not_its_ground(tmp_path):
    """Real car scans hold returns metres under the road (multipath, wet asphalt): patches a few
    voxels wide, each hit once, 2-8 m down. The ground stays the road (its height known to the
    voxel), the road is free and a box on it occupied; a lowest voxel would take the patches."""
    from voxtool.ground import ground_of, occupied_voxels, project_above_ground
    from voxtool.io.mapfile import load_map

    rng = np.random.default_rng(5)
    side = 80
    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(side), np.arange(side), indexing="ij"))
    box = (xs >= 40) & (xs < 45) & (ys >= 40) & (ys < 45)
    keys, values = [np.c_[xs, ys, np.zeros(xs.shape, np.int64)]], [np.full(xs.shape, 3.5)]  # the road, hit often
    keys += [np.c_[xs[box], ys[box], np.full(int(box.sum()), k)] for k in range(3, 8)]
    values += [np.full(int(box.sum()), 3.5)] * 5
    for _ in range(40):  # reflections: 3 x 3 columns, two layers, one hit each
        x, y, z = rng.integers(2, side - 5), rng.integers(2, side - 5), -rng.integers(10, 40)
        patch = np.array([(x + i, y + j, z + k) for i in range(3) for j in range(3) for k in range(2)])
        keys.append(patch)
        values.append(np.full(len(patch), 0.85))
    keys = np.concatenate(keys) + np.array([TREE_MAX_VAL, TREE_MAX_VAL, TREE_MAX_VAL])
    save_occupied(keys, tmp_path / "road.vxm", np.concatenate(values))
    backend = load_map(tmp_path / "road.vxm")[0]
    voxels, hits = occupied_voxels(backend.leaves(), backend.sensor.threshold_log)
    ground = ground_of(voxels, RES, weights=hits)
    np.testing.assert_allclose(ground.under(xs + TREE_MAX_VAL, ys + TREE_MAX_VAL), 0.0, atol=1e-9)
    grid = project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, (0.3, 2.0))
    assert np.array_equal(grid.cells[ys, xs], np.where(box, 100, 0))


def test_a_lower_obstacle_threshold_marks_a_bush_rays_pass_through(tmp_path):
    """A bush whose voxels were hit once and missed three times (log-odds 0.85 - 3 x 0.41 = -0.37)
    is free in the map: no obstacle at the map's threshold, an obstacle at obstacle_log -0.4 (and
    with `export --obstacle-threshold 0.4`). A voxel missed once and never hit (-0.41) stays free
    at -0.4, and the ground is the road both ways; a post beside them makes the map 3D."""
    from voxtool.config import SensorModel
    from voxtool.ground import project_above_ground
    from voxtool.io.mapfile import load_map

    hit, miss = SensorModel().hit_log, SensorModel().miss_log
    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(30), np.arange(30), indexing="ij"))
    bush = (xs >= 10) & (xs < 14) & (ys >= 10) & (ys < 14)
    seen_once = (xs >= 20) & (xs < 24) & (ys >= 5) & (ys < 9)
    post = (xs == 2) & (ys == 2)
    keys = [np.c_[xs, ys, np.zeros(xs.shape, np.int64)], np.c_[np.full((5, 2), 2), np.arange(1, 6)]]  # road, post
    values = [np.full(xs.shape, 3.5), np.full(5, 3.5)]  # hit often
    for k in (4, 5):  # 0.8-1.2 m over the road
        keys += [np.c_[xs[bush], ys[bush], np.full(int(bush.sum()), k)],
                 np.c_[xs[seen_once], ys[seen_once], np.full(int(seen_once.sum()), k)]]
        values += [np.full(int(bush.sum()), hit + 3 * miss), np.full(int(seen_once.sum()), miss)]
    save_occupied(np.concatenate(keys) + TREE_MAX_VAL, tmp_path / "bush.vxm", np.concatenate(values))
    backend = load_map(tmp_path / "bush.vxm")[0]
    plain = project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, (0.3, 2.0))
    lower = project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, (0.3, 2.0), obstacle_log=-0.4)
    assert np.array_equal(plain.cells[ys, xs], np.where(post, 100, 0))
    assert np.array_equal(lower.cells[ys, xs], np.where(bush | post, 100, 0))
    # the same from the command line, as a probability (0.4: log-odds -0.405, under the bush's -0.37)
    code, text, err = cli("export", tmp_path / "bush.vxm", "-o", tmp_path / "g.pgm", "--above-ground", "0.3,2",
                          "--obstacle-threshold", "0.4", "--json")
    assert code == 0 and json.loads(text)["obstacle_threshold"] == 0.4, err
    assert np.array_equal(read_nav2_map(tmp_path / "g.yaml")[0][ys, xs], np.where(bush | post, 100, 0))
    for args, says in ((["--obstacle-threshold", "0.4"], "is for the --above-ground grid"),
                       (["--above-ground", "0.3,2", "--obstacle-threshold", "1"], "must be a probability")):
        code, _, err = cli("export", tmp_path / "bush.vxm", "-o", tmp_path / "h.pgm", *args)
        assert code == 2 and says in err and len(err.splitlines()) == 1 and not (tmp_path / "h.pgm").exists()


def test_a_low_bush_whose_base_hides_the_ground_is_an_obstacle_and_a_kerb_is_not(tmp_path):
    """Under a low bush the map sees no ground: its lowest voxel (one layer over the road) was the
    floor, and the bush, 0.2-0.6 m over the road, stood one layer over it: under a 0.3 m band. A
    floor a layer over its surroundings on a patch 5 columns across or less is not ground in the
    grid, so the bush is an obstacle; a sidewalk a layer over the road (a kerb, 10 columns wide)
    stays free, and a 20 % grade's staircase of layers stays the ground, layer for layer."""
    from voxtool.ground import MAP_GRID_GROUND, GroundParams, ground_of, occupied_voxels, project_above_ground
    from voxtool.io.mapfile import load_map

    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(40), np.arange(40), indexing="ij"))
    bush = (xs >= 10) & (xs < 13) & (ys >= 10) & (ys < 13)
    sidewalk = xs >= 30
    floor = np.where(sidewalk, 1, 0)
    keys = [np.c_[xs[~bush], ys[~bush], floor[~bush]]]
    keys += [np.c_[xs[bush], ys[bush], np.full(int(bush.sum()), k)] for k in (1, 2)]
    save_occupied(np.concatenate(keys) + TREE_MAX_VAL, tmp_path / "bush.vxm")
    backend = load_map(tmp_path / "bush.vxm")[0]
    grid = project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, (0.3, 2.0))
    assert np.array_equal(grid.cells[ys, xs], np.where(bush, 100, 0))
    before = project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, (0.3, 2.0), GroundParams())
    assert not np.any(before.cells[ys, xs] == 100)  # the bush's base as its ground: nothing in the band

    slope = xs // 5  # a layer every 5 columns: a 20 % grade
    save_occupied(np.c_[xs, ys, slope] + TREE_MAX_VAL, tmp_path / "slope.vxm")
    backend = load_map(tmp_path / "slope.vxm")[0]
    voxels, hits = occupied_voxels(backend.leaves(), backend.sensor.threshold_log)
    ground = ground_of(voxels, RES, MAP_GRID_GROUND, weights=hits)
    np.testing.assert_allclose(ground.under(xs + TREE_MAX_VAL, ys + TREE_MAX_VAL), slope * RES, atol=1e-9)


def test_a_road_across_a_voxel_boundary_is_free(tmp_path):
    """Real roads straddle voxel boundaries: each column holds the floor voxel and the one above it
    (KITTI: 0.2 m voxels, road points within 5 cm of a boundary). That upper voxel is still the
    road, one layer over the floor, not an obstacle; a box 0.4-1.2 m over the road is one."""
    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(40), np.arange(40), indexing="ij"))
    box = (xs >= 20) & (xs < 25) & (ys >= 20) & (ys < 25)
    keys = [np.c_[xs, ys, np.full(xs.shape, TREE_MAX_VAL + k)] for k in (0, 1)]  # the road, two layers
    keys += [np.c_[xs[box], ys[box], np.full(int(box.sum()), TREE_MAX_VAL + k)] for k in range(3, 7)]
    save_occupied(np.concatenate(keys) + np.array([TREE_MAX_VAL, TREE_MAX_VAL, 0]), tmp_path / "road.vxm")
    code, _, err = cli("export", tmp_path / "road.vxm", "-o", tmp_path / "g.pgm", "--above-ground", "0.3,2.0")
    assert code == 0, err
    cells = read_nav2_map(tmp_path / "g.yaml")[0]
    assert np.array_equal(cells[ys, xs], np.where(box, 100, 0))


def test_above_ground_grid_equals_the_terrain_truth(terrain, tmp_path):
    """Occupied exactly where a box stands (0.3-2 m above the ground under it); free on the slope
    and under the tree crown (above 2 m); unknown nowhere on the terrain."""
    path, xs, ys, box, crown = terrain
    code, _, err = cli("export", path, "-o", tmp_path / "g.pgm", "--above-ground", "0.3,2.0")
    assert code == 0, err
    cells, res, origin = read_nav2_map(tmp_path / "g.yaml")
    assert res == pytest.approx(RES) and origin[:2] == pytest.approx([0.0, 0.0])
    assert cells.shape == (SIDE, SIDE)
    got = cells[ys, xs]  # row: y from the bottom, column: x
    expected = np.where(box, 100, 0)
    assert np.array_equal(got, expected), (np.sum(got != expected), np.unique(got[crown]))
    # the map .mcap's OccupancyGrid, read by rosbags, is the same grid
    from test_viewer_mcap import read_ros2

    assert cli("export", path, "-o", tmp_path / "g.mcap", "--above-ground", "0.3,2.0")[0] == 0
    grid = read_ros2(tmp_path / "g.mcap")["/projected_map"][2]
    data = np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width)
    assert np.array_equal(data, cells.astype(np.int8))


def test_fixed_heights_fail_on_the_slope_where_height_above_ground_does_not(terrain, tmp_path):
    """The same band as --z-range 0.3,2.0 (metres of the map's frame): the slope itself comes out
    occupied uphill and unknown downhill, which is why the ground is needed."""
    path, xs, ys, box, _ = terrain
    code, _, err = cli("export", path, "-o", tmp_path / "z.pgm", "--z-range", "0.3,2.0")
    assert code == 0, err
    cells, _, origin = read_nav2_map(tmp_path / "z.yaml")
    x0 = int(round(origin[0] / RES))
    uphill = (xs > 20) & (xs < 60) & ~box
    col = xs[uphill] - x0
    inside = (col >= 0) & (col < cells.shape[1])
    assert (cells[ys[uphill][inside], col[inside]] == 100).mean() > 0.5  # the ground itself is an obstacle there


def test_bad_above_ground_is_one_line(terrain, tmp_path):
    path = terrain[0]
    for args, says in ((["--above-ground", "2,1"], "need 0 <= MIN <= MAX"),
                       (["--above-ground", "x"], "give two numbers MIN,MAX"),
                       (["--above-ground", "0.3,2", "--z-range", "0,1"], "give one")):
        code, _, err = cli("export", path, "-o", tmp_path / "g.pgm", *args)
        assert code == 2 and says in err and err.count("\n") == 1, err
        assert not (tmp_path / "g.pgm").exists()
    code, _, err = cli("export", path, "-o", tmp_path / "g.ply", "--above-ground", "0.3,2")
    assert code == 2 and "--above-ground is for the 2D grid" in err


def test_a_top_view_coloured_by_height_above_the_ground(terrain, tmp_path):
    """Colours by height above the ground: every slope pixel shows 0.1 m (its ground voxel's
    centre) though the slope climbs 4.5 m, the crown 3.5 m, the boxes 1.1 m within a voxel (their
    ground is filled from around); `export` writes it."""
    from voxtool.api import load_leaves
    from voxtool.io.picture import picture

    path, xs, ys, box, crown = terrain
    leaves, res, thr, _ = load_leaves(path)
    raster = picture(leaves, res, thr, above_ground=(0.0, 4.0))
    above = raster.values_m(res)
    assert raster.shift == 0 and above.shape == (SIDE, SIDE)
    got = above[ys, xs]  # rows from the bottom (y), columns x
    slope = ~box & ~crown
    assert np.allclose(got[slope], 0.1) and np.allclose(got[crown], 3.5)
    # no ground is seen under a box: filled from the slope around it, within a voxel of the truth
    assert np.all(np.abs(got[box] - 1.1) <= RES + 1e-9)
    plain = picture(leaves, res, thr).values_m(res)[ys, xs]
    assert np.ptp(plain[slope]) > 4.0  # the same pixels by absolute height: the slope's 4.5 m
    code, text, err = cli("export", path, "-o", tmp_path / "g.png", "--above-ground", "0,4", "--json")
    assert code == 0 and "height above the ground" in __import__("json").loads(text)["caption"], err
    code, _, err = cli("export", path, "-o", tmp_path / "s.png", "--above-ground", "0,4", "--view", "side")
    assert code == 2 and "top view" in err


def test_clean_pictures_colour_by_height_above_the_ground():
    """clean --png --above-ground: on a 15 % slope every ground point gets one colour (it is at
    the ground) while a box on it gets another; by absolute height the slope spans the scale."""
    from voxtool.plots import clean_figure

    rng = np.random.default_rng(5)
    ground = rng.uniform(0, 30, (40_000, 2))
    ground = np.c_[ground, 0.15 * ground[:, 0] + 0.05]
    box = np.c_[rng.uniform(10, 12, (3000, 2)), np.zeros(3000)]
    box[:, 2] = 0.15 * box[:, 0] + rng.uniform(0.3, 1.5, 3000)  # standing on the slope, up to 1.5 m
    points = np.concatenate([ground, box]).astype(np.float32)
    dynamic = np.zeros(len(points), bool)

    def after_colours(**kw):
        fig, _ = clean_figure(points, dynamic, "slope", **kw)
        image = fig.axes[1].images[0].get_array()
        lit = image[..., 3] > 0
        return image, lit

    def region(image, lit, x0, x1):  # pixel columns of x in [x0, x1) over the 30 m extent
        cols = image.shape[1]
        mask = np.zeros_like(lit)
        mask[:, int(x0 / 30 * cols):int(x1 / 30 * cols)] = True
        return image[mask & lit][:, :3]

    image, lit = after_colours(above_ground=(0.0, 2.0), resolution=0.2)
    low, high = region(image, lit, 1, 8), region(image, lit, 20, 29)
    assert np.abs(low.mean(axis=0) - high.mean(axis=0)).max() < 0.05  # the slope: one colour, low or high
    plain, plain_lit = after_colours()
    assert np.abs(region(plain, plain_lit, 1, 8).mean(axis=0) - region(plain, plain_lit, 20, 29).mean(axis=0)).max() > 0.2
    code, _, err = cli("clean", "--sample", "--png", "x.png", "--above-ground", "0,2", "--view", "side")
    assert code == 2 and "top view" in err


# -- the kernels against brute force --------------------------------------------------------------

def _window_brute_force(a, half, take_min):
    """Each cell's minimum (maximum) over the square window around it, ignoring cells without a
    floor (NONE); NONE where the window holds none."""
    from voxtool.ground import NONE

    rows, cols = a.shape
    out = np.full_like(a, NONE)
    for r in range(rows):
        for c in range(cols):
            window = a[max(0, r - half):r + half + 1, max(0, c - half):c + half + 1]
            values = window[window != NONE]
            if values.size:
                out[r, c] = values.min() if take_min else values.max()
    return out


@pytest.mark.parametrize("shape, half", [((9, 13), 1), ((9, 13), 2), ((17, 5), 4), ((6, 6), 7), ((1, 20), 3)])
def test_window_filters_equal_brute_force(shape, half):
    from voxtool.ground import NONE, _filter

    rng = np.random.default_rng(half)
    a = rng.integers(32700, 32800, shape).astype(np.int32)
    a[rng.random(shape) < 0.3] = NONE
    for take_min in (True, False):
        np.testing.assert_array_equal(_filter(a, half, take_min), _window_brute_force(a, half, take_min))


def test_fill_spreads_the_ground_ring_by_ring_as_brute_force_does():
    """Each round, every unknown cell beside a known one takes the mean of its known 8-neighbours
    (as known before the round), for the given number of rounds."""
    from voxtool.ground import _fill

    rng = np.random.default_rng(5)
    height = rng.normal(0.0, 1.0, (15, 21))
    known = rng.random(height.shape) < 0.05
    want_h, want_k = height.copy(), known.copy()
    for _ in range(3):
        new_h, new_k = want_h.copy(), want_k.copy()
        for r in range(15):
            for c in range(21):
                if want_k[r, c]:
                    continue
                around = [(r + i, c + j) for i in (-1, 0, 1) for j in (-1, 0, 1)
                          if 0 <= r + i < 15 and 0 <= c + j < 21 and want_k[r + i, c + j]]
                if around:
                    new_h[r, c] = np.mean([want_h[p] for p in around])
                    new_k[r, c] = True
        want_h, want_k = new_h, new_k
    _fill(height, known, 3)
    np.testing.assert_array_equal(known, want_k)
    np.testing.assert_allclose(height[known], want_h[want_k], rtol=0, atol=1e-12)
    assert 0 < known.sum() < known.size


def test_clean_s_ground_is_the_terrain_and_not_what_stands_on_it():
    """clean.ground_points on points of a 10 % slope with boxes (their tops seen, not the ground
    under them) and a canopy over seen ground: every terrain point is ground, and nothing more
    than 0.3 m above the slope (with a column's width of slope and a voxel of rounding beyond) is."""
    from voxtool.clean import ground_points

    rng = np.random.default_rng(2)
    xy = rng.uniform(0.0, 40.0, (200_000, 2))
    slope = 0.1 * xy[:, 0]
    on_box = ((xy[:, 0] % 10.0) < 2.0) & ((xy[:, 1] % 10.0) < 2.0)  # 2 m x 2 m boxes: their tops, 1-2 m up
    under_canopy = (np.abs(xy[:, 0] - 25.0) < 3.0) & (np.abs(xy[:, 1] - 25.0) < 3.0)
    tops = 1.0 + (np.floor(xy[:, 0] / 10.0) + np.floor(xy[:, 1] / 10.0)) % 3 * 0.5
    height = np.where(on_box, tops, rng.normal(0.0, 0.01, xy.shape[0]))
    height[under_canopy & (rng.random(xy.shape[0]) < 0.5)] = rng.uniform(3.0, 4.0)  # a crown above seen ground
    points = np.c_[xy, slope + height].astype(np.float32)
    is_ground = ground_points(points, 0.1, 0.3)
    terrain = ~on_box & (height < 0.1)
    assert is_ground[terrain].all()
    assert not is_ground[height > 0.3 + 0.1 * 0.2 + 0.1].any()
    from voxtool import clean

    # the keys made a chunk at a time: the same flags as at once
    saved, clean.GROUND_CHUNK = clean.GROUND_CHUNK, 7_777
    try:
        assert np.array_equal(ground_points(points, 0.1, 0.3), is_ground)
    finally:
        clean.GROUND_CHUNK = saved
    keys = np.floor(points[:, :2].astype(np.float64) / 0.1).astype(np.int64) + 32768  # as OctoMap keys them
    np.testing.assert_array_equal(clean.point_columns(points, 0.1), keys[:, 0] << 16 | keys[:, 1])


def test_above_ground_refuses_a_2d_scanner_s_map(tmp_path):
    """A level 2D scanner's map (LaserScans round a room, posed by their true path) holds its walls
    in one or two voxel layers: the ground model took them for the floor, and the grid lost
    them (315 occupied cells of 437 on a Gazebo log). One line, exit 2, nothing written; the plain
    grid keeps every wall."""
    from test_odometry_2d import loop, write_scans, write_truth_poses

    truth = loop(100)
    bag, poses = tmp_path / "room.bag", tmp_path / "poses.txt"
    write_scans(bag, truth)
    write_truth_poses(poses, truth)
    code, _, err = cli("build", bag, "--poses", poses, "-o", tmp_path / "m.vxm", "--resolution", "0.05", "--no-progress")
    assert code == 0, err
    code, _, err = cli("export", tmp_path / "m.vxm", "-o", tmp_path / "g.pgm", "--above-ground", "0.1,0.5")
    assert code == 2 and not (tmp_path / "g.pgm").exists() and not (tmp_path / "g.yaml").exists()
    assert "m.vxm: --above-ground: its occupied voxels lie in 1 layer(s) of 0.05 m" in err and len(err.splitlines()) == 1
    code, text, err = cli("export", tmp_path / "m.vxm", "-o", tmp_path / "g.pgm", "--json")
    assert code == 0 and json.loads(text)["occupied_cells"] > 300, err


def test_low_objects_on_real_kitti_frames_are_marked_and_the_road_stays_free(kitti_sample, tmp_path):
    """SemanticKITTI's labels on frames 0-9 of sequence 05 (survey poses, 0.2 m): the grid's ground
    (no step over a patch 5 columns across or less) marks more of the labelled object cells than
    clean's ground (a 0.3 m step at every window) did (84.2 -> 85.8 %), keeps 99 % of the road
    cells free and the driven path as free as before (the scoring is benchmarks/bench_ground.py's)."""
    import sys
    from pathlib import Path

    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.ground import MAP_GRID_GROUND, GroundParams, project_above_ground
    from voxtool.io.mapfile import load_map
    from voxtool.sources import SourceOptions, open_source

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_ground import BAND, _share, labelled_cells, path_cells

    sequence = kitti_sample / "05"
    build_map(sequence, SourceOptions(), MapParams(resolution=RES), SensorModel(), "octree", tmp_path / "05.vxm", False)
    backend = load_map(tmp_path / "05.vxm")[0]
    scans = list(open_source(sequence, SourceOptions()).scans)
    points = np.concatenate([s.points for s in scans]).astype(np.float64)
    labels = np.concatenate([np.fromfile(f, dtype="<u4") & 0xFFFF for f in sorted((sequence / "labels").glob("*.label"))])
    origins = np.array([s.origin for s in scans])
    now, before = (project_above_ground(backend.leaves(), RES, backend.sensor.threshold_log, BAND, params)
                   for params in (MAP_GRID_GROUND, GroundParams()))
    road, objects = labelled_cells(now, points, labels)  # the two grids share the map's footprint
    assert _share(now, objects, 100) >= _share(before, objects, 100) + 1.0
    assert _share(now, road, 0) >= 99.0
    assert _share(now, path_cells(now, origins), 0) == _share(before, path_cells(before, origins), 0)


def test_the_grid_of_the_returns_marks_what_the_map_holds_or_a_far_return_the_map_has_not_cleared(tmp_path):
    """project_returns_above_ground's rule, voxel by voxel, 0.8 m over a road: a voxel the map holds
    occupied is an obstacle with no return in it; one the map holds under its threshold but over
    its floor is one where a return from 3.5 m or more off its sensor lies in it, and not where the
    return came from 1 m off (a car's own body), nor where the map cleared it to its floor, nor
    where `evidence` leaves the return out (clean: its voxel void)."""
    from voxtool.config import SensorModel
    from voxtool.ground import project_returns_above_ground, return_floor_log
    from voxtool.io.mapfile import load_map

    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(30), np.arange(30), indexing="ij"))
    over = {"far": (5, 5), "near": (20, 20), "cleared": (10, 20), "occupied": (25, 5), "left out": (15, 15)}
    held = {"far": -1.0, "near": -1.0, "cleared": SensorModel().clamp_min_log, "occupied": 1.0, "left out": -1.0}
    assert SensorModel().clamp_min_log < return_floor_log(SensorModel()) < -1.0
    keys = np.concatenate([np.c_[xs, ys, np.zeros(xs.shape, np.int64)], [(x, y, 4) for x, y in over.values()]])
    save_occupied(keys + TREE_MAX_VAL, tmp_path / "m.vxm", np.r_[np.full(xs.shape, 3.5), list(held.values())])
    backend = load_map(tmp_path / "m.vxm")[0]

    def centre(x, y, z):
        return ((np.array([x, y, z]) + 0.5) * RES).astype(np.float32)

    road = ((np.c_[xs, ys, np.zeros(xs.shape)] + 0.5) * RES).astype(np.float32)
    first = np.concatenate([road, [centre(*over[k], 4) for k in ("far", "cleared", "left out")]])
    second = centre(*over["near"], 4)[None]
    origins = np.array([(-5.0, -5.0, 1.7), second[0] + (1.0, 0.0, 0.9)])
    points = np.concatenate([first, second])
    evidence = np.ones(points.shape[0], bool)
    evidence[len(road) + 2] = False  # "left out"
    grid, figures = project_returns_above_ground(points, np.array([0, len(first), len(points)]), origins, backend,
                                                 (0.3, 2.0), evidence=evidence)
    marked = {k for k, (x, y) in over.items() if grid.cells[y, x] == 100}
    assert marked == {"far", "occupied"} and figures["cells_by_returns"] == 1
    assert (grid.cells == 100).sum() == 2 and (grid.cells == 0).sum() == 30 * 30 - 2


def test_clean_grid_marks_85_percent_of_the_object_cells_on_kitti_s_hedge_lined_highway(kitti_sample):
    """SemanticKITTI 01 (frames 0-9, a highway between hedges and fences, survey poses, 0.2 m):
    the grid `clean --grid` writes marks >= 85 % of the cells holding a labelled object 0.3-2 m
    over the labelled ground (the map's grid: 68 %), keeps >= 99 % of the road cells and >= 97 %
    of the cells within 2 m of the driven path free (#59's targets; the bench's scoring)."""
    import sys
    from pathlib import Path

    from voxtool.sources import SourceOptions, open_source

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_ground import _share, cleaned_grids, labelled_cells, path_cells

    sequence = kitti_sample / "01"
    scans = list(open_source(sequence, SourceOptions()).scans)
    points = np.concatenate([s.points for s in scans]).astype(np.float64)
    labels = np.concatenate([np.fromfile(f, dtype="<u4") & 0xFFFF for f in sorted((sequence / "labels").glob("*.label"))])
    origins = np.array([s.origin for s in scans])
    _, grid = cleaned_grids(sequence, RES, origins)
    road, objects = labelled_cells(grid, points, labels)
    assert _share(grid, objects, 100) >= 85.0
    assert _share(grid, road, 0) >= 99.0
    assert _share(grid, path_cells(grid, origins), 0) >= 97.0


def _drive_past_a_hedge(directory, n_scans: int = 14):
    """A 32-beam car scanner driving 1 m a scan along a road, past a hedge (x 0..10 m, y 4..5 m,
    1.2 m high) in which 12 % of the rays that meet it stop, the rest reaching a wall behind it;
    a car overtaking in the next lane (8 m/s faster); and 20 returns a scan from the scanner's own
    car (1.3-1.8 m ahead of it, 0.7 m under it). Written as a PCD
    directory with poses (voxtool.synthetic.write_pcd_scans); returns (the truth: the overtaking car's
    points, the hedge, the car's body and scanner positions as boxes of world x, y)."""
    from types import SimpleNamespace

    from voxtool.synthetic import Box, Lidar, box_entries, first_hits, write_pcd_scans

    lidar = Lidar(beams=32, columns=1024, max_range=30.0, range_noise=0.01)
    hedge, wall = Box((0.0, 4.0, 0.0), (10.0, 5.0, 1.2)), Box((-20.0, 8.0, 0.0), (30.0, 9.0, 3.0))
    car = Box((-16.0, -3.8, 0.0), (-11.5, -2.0, 1.3), (18.0, 0.0, 0.0))
    body = np.random.default_rng(1).uniform((1.3, -1.0, -0.75), (1.8, 1.0, -0.65), (20, 3))
    starts = [np.array([-8.0 + i, 0.0, 1.7]) for i in range(n_scans)]

    def scans():
        rng = np.random.default_rng(0)
        dirs = lidar.directions()
        for i, origin in enumerate(starts):
            t = i / 10.0
            dist, moving = first_hits(origin, dirs, [wall, car], t, lidar.max_range)
            into, _ = box_entries(origin, dirs, [hedge], t)
            stop = (into < dist) & (rng.random(dirs.shape[0]) < 0.12)
            dist = np.where(stop, into + rng.uniform(0.0, 0.8, dirs.shape[0]), dist)
            hit = np.isfinite(dist)
            points = origin + dirs[hit] * dist[hit, None]
            yield (np.concatenate([points, origin + body]).astype(np.float32), origin, 0.0,
                   np.r_[(moving & ~stop)[hit], np.zeros(len(body), bool)])

    truth = write_pcd_scans(SimpleNamespace(scans=scans, rate_hz=10.0), directory)
    return truth, hedge, np.array(starts)


def test_clean_grid_marks_a_hedge_rays_pass_through_and_no_mover_nor_its_own_car(tmp_path):
    """`clean --grid`: the hedge, which most rays pass through, is free or unknown in the grid of
    the kept points' map (`clean --map` then `export --above-ground`) but an obstacle in --grid, by
    the returns that map has not cleared; the overtaking car, which clean removes, and the
    scanner's own car, whose returns land in a new voxel each scan, mark nothing: the road the
    car drove and the next lane stay free. Read back by nav2's YAML."""
    truth, hedge, origins = _drive_past_a_hedge(tmp_path / "scans")
    code, text, err = cli("clean", tmp_path / "scans", "--grid", tmp_path / "g.pgm", "--map", tmp_path / "s.vxm",
                          "--resolution", "0.2", "--json", "--no-progress")
    assert code == 0, err
    got = json.loads(text)
    assert got["points_removed"] >= 0.9 * truth.sum() > 300
    assert got["grid"]["above_ground"] == [0.3, 2.0] and got["grid"]["cells_by_returns"] > 0
    grid, resolution, origin = read_nav2_map(tmp_path / "g.yaml")
    code, _, err = cli("export", tmp_path / "s.vxm", "-o", tmp_path / "m.pgm", "--above-ground", "0.3,2")
    assert code == 0, err
    from_map, _, origin_map = read_nav2_map(tmp_path / "m.yaml")

    def cells(g, at, x0, x1, y0, y1):  # the grid's cells whose centres lie in the box
        xs = at[0] + (np.arange(g.shape[1]) + 0.5) * resolution
        ys = at[1] + (np.arange(g.shape[0]) + 0.5) * resolution
        return g[np.ix_((ys > y0) & (ys < y1), (xs > x0) & (xs < x1))]

    inner = (hedge.lo[0] + 0.5, hedge.hi[0] - 0.5, hedge.lo[1] + 0.2, hedge.hi[1] - 0.2)
    assert (cells(grid, origin, *inner) == 100).mean() >= 0.85  # 91 %
    assert (cells(from_map, origin_map, *inner) == 100).mean() <= 0.5  # 32 %: rays pass through, free in the map
    path = (origins[0, 0], origins[-1, 0], -1.2, 1.2)  # the road under the car, where its own body was
    lane = (origins[0, 0], 6.0, -3.6, -2.2)  # its lane, up to where it was in the last scans: no later one saw through
    for box in (path, lane):
        assert not np.any(cells(grid, origin, *box) == 100) and (cells(grid, origin, *box) == 0).mean() >= 0.95
    # the same grid as a .mcap's OccupancyGrid (read by rosbags), stamped with the last scan's time
    from test_viewer_mcap import read_ros2

    code, _, err = cli("clean", tmp_path / "scans", "--grid", tmp_path / "g.mcap", "--resolution", "0.2", "--no-progress")
    assert code == 0, err
    msgtype, _, message = read_ros2(tmp_path / "g.mcap")["/projected_map"]
    assert msgtype == "nav_msgs/msg/OccupancyGrid" and message.header.frame_id == "map"
    assert message.header.stamp.sec == 1 and message.header.stamp.nanosec == 300_000_000  # scan 13 of 10 a second
    data = np.asarray(message.data, dtype=np.int8).reshape(message.info.height, message.info.width)
    assert np.array_equal(data, grid.astype(np.int8))
    assert (message.info.origin.position.x, message.info.origin.position.y) == pytest.approx(tuple(origin[:2]))


def test_clean_grid_refusals_are_one_line_and_write_nothing(tmp_path):
    """A grid of another kind, a band with no grid nor picture, and a level 2D scanner's scans
    (no ground to stand on): one line, exit 2, and not even the -o asked beside it written."""
    from voxtool.synthetic import Box, Lidar, Scene, write_pcd_scans

    _drive_past_a_hedge(tmp_path / "scans", n_scans=2)
    room = [Box((-5.0, 4.0, 0.0), (5.0, 5.0, 3.0)), Box((-5.0, -5.0, 0.0), (5.0, -4.0, 3.0))]
    write_pcd_scans(Scene(room, Lidar(beams=1, min_elevation_deg=0.0, max_elevation_deg=0.0), n_scans=3), tmp_path / "2d")
    for scans, args, says in (("scans", ["--grid", tmp_path / "g.png"], "a .pgm"),
                              ("scans", ["-o", tmp_path / "g.pcd", "--above-ground", "0.3,2"],
                               "give --grid GRID.pgm or --png"),
                              ("2d", ["-o", tmp_path / "g.pcd", "--grid", tmp_path / "g.pgm"], "no ground")):
        code, _, err = cli("clean", tmp_path / scans, *args, "--no-progress")
        assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
        assert not any(tmp_path.glob("g.*"))


def test_a_grid_too_large_to_make_leaves_no_file(tmp_path):
    """A return 4 km off in x and y: the grid at 0.2 m would have 20,000 x 20,000 cells. `clean
    --grid` says so on one line (exit 2) after judging, and writes nothing, not even the -o that
    would have been written first."""
    from types import SimpleNamespace

    from voxtool.synthetic import write_pcd_scans

    xs, ys = (a.ravel() for a in np.meshgrid(np.arange(-5.0, 5.0, 0.2), np.arange(-5.0, 5.0, 0.2)))
    road = np.c_[xs, ys, np.zeros(xs.shape)]

    def scans():
        for i in range(2):
            points = np.concatenate([road, [(4000.0, 4000.0, 0.5)]]).astype(np.float32)
            yield points, np.array([0.1 * i, 0.0, 1.7]), 0.0, np.zeros(len(points), bool)

    write_pcd_scans(SimpleNamespace(scans=scans, rate_hz=10.0), tmp_path / "far")
    code, _, err = cli("clean", tmp_path / "far", "-o", tmp_path / "g.pcd", "--grid", tmp_path / "g.pgm",
                       "--resolution", "0.2", "--no-progress")
    assert code == 2 and "g.pgm: --grid: " in err and "columns of 0.2 m" in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.glob("g.*"))
