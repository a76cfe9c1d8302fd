"""`export map.png`: the picture's pixels against a brute-force projection of the map's voxels,
and the figure's furniture (axes in metres, colour bar, legend, scale bar) read back from matplotlib."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import cli

from voxtool.api import load_leaves
from voxtool.errors import ParameterError
from voxtool.io import picture
from voxtool.keys import expand_leaves, keys_to_coords, morton_decode


def _occupied_voxels(leaves, threshold):
    occ = leaves.values > np.float32(threshold)
    return morton_decode(expand_leaves(leaves.codes[occ], leaves.depths[occ])).astype(np.int64)


@pytest.mark.parametrize("view", ["top", "front", "side"])
def test_view_pixels_equal_a_brute_force_projection(sample_map, view):
    leaves, res, thr, _ = load_leaves(sample_map[0])
    raster = picture.picture(leaves, res, thr, view)
    u, w, a, from_plus = picture.VIEWS[view]
    keys = _occupied_voxels(leaves, thr)
    px = (keys[:, u] - raster.kmin[0]) >> raster.shift
    py = (keys[:, w] - raster.kmin[1]) >> raster.shift
    flat = py * raster.width + px
    assert int((raster.state == picture.OCCUPIED).sum()) == len(np.unique(flat))
    # the colour: the coordinate of the occupied voxel nearest the viewer on each pixel's line
    near = np.full(raster.width * raster.height, -np.inf)
    np.maximum.at(near, flat, keys[:, a] if from_plus else -keys[:, a])
    expect = keys_to_coords(np.where(np.isfinite(near), np.abs(near), np.nan), res).reshape(raster.height, -1)
    got = raster.values_m(res)
    assert np.array_equal(np.isnan(got), np.isnan(expect))
    assert np.allclose(got[~np.isnan(got)], expect[~np.isnan(expect)])


def test_slice_shows_exactly_the_occupied_voxels_of_one_layer(sample_map):
    leaves, res, thr, _ = load_leaves(sample_map[0])
    keys = _occupied_voxels(leaves, thr)
    layer = int(np.bincount(keys[:, 2] - keys[:, 2].min()).argmax() + keys[:, 2].min())  # the fullest layer
    z = float(keys_to_coords(np.array([layer]), res)[0])
    raster = picture.picture(leaves, res, thr, "top", slice_z=z)
    assert raster.layer == layer
    in_layer = keys[keys[:, 2] == layer]
    cells = np.unique(((in_layer[:, 1] - raster.kmin[1]) >> raster.shift) * raster.width
                      + ((in_layer[:, 0] - raster.kmin[0]) >> raster.shift))
    assert np.array_equal(np.flatnonzero(raster.state == picture.OCCUPIED), cells)
    with pytest.raises(ParameterError, match="--view top"):
        picture.picture(leaves, res, thr, "side", slice_z=z)


@pytest.mark.parametrize("view,sliced", [("top", False), ("top", True), ("front", False), ("side", False)])
def test_free_and_occupied_pixels_equal_every_voxels_projection(tmp_path, view, sliced):
    """Coarse pixels (several voxels a side) on a grid that starts off the leaves' alignment: a
    pixel's state is the largest of every voxel projecting onto it, free leaves included (a
    slice: of the leaves that hold its layer)."""
    from voxtool.maps.base import Leaves

    path = tmp_path / "small.vxm"
    assert cli("build", "--sample", "--stop", 1, "--max-range", 8, "-o", path)[0] == 0
    leaves, _, thr, _ = load_leaves(path)
    lo, hi = picture.key_bounds(leaves)
    layer = (int(lo[2]) + int(hi[2])) // 2 if sliced else None
    shown = leaves
    if sliced:
        first = morton_decode(leaves.codes)[:, 2].astype(np.int64)
        edge = 1 << (16 - leaves.depths.astype(np.int64))
        held = (first <= layer) & (layer < first + edge)
        shown = Leaves(leaves.codes[held], leaves.depths[held], leaves.values[held])
    keys = morton_decode(expand_leaves(shown.codes, shown.depths)).astype(np.int64)
    states = np.repeat(np.where(shown.values > np.float32(thr), picture.OCCUPIED, picture.FREE),
                       1 << (3 * (16 - shown.depths.astype(np.int64)))).astype(np.int8)
    u, w, _, _ = picture.VIEWS[view]
    for max_side, offset in ((37, 3), (20, 5)):
        raster = picture.Raster.covering(view, lo - offset, hi, layer, max_side=max_side)
        raster.add(leaves, thr)
        assert raster.shift >= 2
        expect = np.zeros(raster.width * raster.height, np.int8)
        flat = (((keys[:, w] - raster.kmin[1]) >> raster.shift) * raster.width
                + ((keys[:, u] - raster.kmin[0]) >> raster.shift))
        np.maximum.at(expect, flat, states)
        assert np.array_equal(raster.state, expect)


def test_figure_has_metric_axes_colour_bar_legend_and_scale_bar(sample_map):
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    leaves, res, thr, _ = load_leaves(sample_map[0])
    raster = picture.picture(leaves, res, thr, "front")
    fig = picture.figure(raster, res, "sample")
    ax, bar = fig.axes
    left, right, bottom, top = raster.metres(res)
    assert ax.get_xlim() == pytest.approx((left, right)) and ax.get_ylim() == pytest.approx((bottom, top))
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("x (m)", "z (m)")
    values = raster.values_m(res)
    lo, hi = bar.get_xlim() if bar.get_xlabel() else bar.get_ylim()
    occupied = values[~np.isnan(values)]
    # the 1st to 99th percentile (the sample's far returns reach 180 m out), the rest at the ends, said
    assert lo == pytest.approx(np.percentile(occupied, 1)) and hi == pytest.approx(np.percentile(occupied, 99))
    assert occupied.min() < lo - 10 and raster.colour_range[2] == pytest.approx(
        np.mean((occupied < lo) | (occupied > hi)))
    assert "(m)" in (bar.get_xlabel() + bar.get_ylabel()) and "beyond the bar, drawn at its ends" in (bar.get_xlabel() + bar.get_ylabel())
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["free", "unknown"]
    bars = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    assert len(bars) == 1 and bars[0].txt_label.get_text().endswith(" m")
    caption = " ".join(t.get_text() for t in fig.texts) + (fig._supxlabel.get_text() if fig._supxlabel else "")
    assert f"resolution {res:g} m" in caption and f"{int((raster.state == picture.OCCUPIED).sum()):,} occupied" in caption


def test_cli_png_is_readable_and_free_is_refused(sample_map, tmp_path):
    import json

    from matplotlib.image import imread

    out = tmp_path / "side.png"
    code, text, err = cli("export", sample_map[0], "-o", out, "--view", "side", "--json")
    assert code == 0, err
    report = json.loads(text)
    image = imread(out)
    assert image.shape[:2] == (report["height"], report["width"]) and report["view"] == "side"
    code, _, err = cli("export", sample_map[0], "-o", tmp_path / "f.png", "--free")
    assert code != 0 and "--free is for .ply/.pcd" in err and not (tmp_path / "f.png").exists()


@pytest.mark.parametrize("view", ["top", "front"])
def test_the_caption_does_not_overlap_the_tick_labels(sample_map, view):
    """The caption sits below the x tick labels and the x label, in the drawn figure (it once
    overlapped them: a figure text the layout did not make room for)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    leaves, res, thr, _ = load_leaves(sample_map[0])
    fig = picture.figure(picture.picture(leaves, res, thr, view), res, "sample")
    for extra in fig.axes[1:]:  # as diff and eval pictures do: no colour bar
        extra.remove()
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    caption = next(t for t in [*fig.texts, fig._supxlabel] if t is not None and "resolution" in t.get_text())
    box = caption.get_window_extent(renderer)
    ax = fig.axes[0]
    for other in [*ax.get_xticklabels(), ax.xaxis.label]:
        if other.get_text():
            assert not box.overlaps(other.get_window_extent(renderer)), other.get_text()


def test_a_top_view_of_a_room_shows_its_floor_plan_below_the_ceiling(tmp_path, sample_map):
    """A closed room's top view showed only its ceiling; now it is drawn below the ceiling and the
    caption says so. Outdoors (the sample) and with --crop the picture is unchanged."""
    import json

    from scenes import box_scene, write_pcd, yaw_quat

    d = tmp_path / "room"
    d.mkdir()
    for i, (pts, o, yaw) in enumerate(box_scene(6, 4000, seed=5)):  # walls |x|, |y| <= 3 m, floor 0, ceiling 3 m
        write_pcd(d / f"{i}.pcd", pts, (*o, *yaw_quat(yaw)))
    m = tmp_path / "room.vxm"
    assert cli("build", d, "-o", m, "--resolution", 0.1, "--no-progress")[0] == 0
    code, text, err = cli("export", m, "-o", tmp_path / "top.png", "--json")
    assert code == 0, err
    roof = json.loads(text)["below_roof_m"]
    assert 2.5 < roof <= 3.0
    leaves, res, thr, _ = load_leaves(m)
    raster = picture.picture(leaves, res, thr, "top")
    assert picture.roof_height(raster, res) == pytest.approx(roof)
    tops = raster.values_m(res)
    assert np.nanmedian(tops) > 2.5  # the whole picture: the ceiling
    # the same picture as a crop below the ceiling, given by hand (whose heights are kept)
    auto = json.loads(text)
    code, text, _ = cli("export", m, "-o", tmp_path / "crop.png", "--crop", f"-9,-9,-1,9,9,{roof}", "--json")
    by_hand = json.loads(text)
    assert code == 0 and "below_roof_m" not in by_hand
    assert (by_hand["occupied_pixels"], by_hand["free_pixels"]) == (auto["occupied_pixels"], auto["free_pixels"])
    code, text, _ = cli("export", sample_map[0], "-o", tmp_path / "out.png", "--json")
    assert code == 0 and "below_roof_m" not in json.loads(text)


def test_a_snapshot_is_drawn_a_chunk_of_leaves_at_a_time(sample_map, tmp_path):
    """export .png reads an octree snapshot's leaves in chunks (kaist03 at 0.1 m: 2.4 GB -> 0.6 GB
    peak): the chunks are the stored leaves, and the picture is the one of the whole table."""
    import json

    from voxtool.io.mapfile import read_leaves, stream_leaves

    whole, res, thr, _ = read_leaves(sample_map[0])
    res2, thr2, _, chunks = stream_leaves(sample_map[0], piece=100_000)
    parts = list(chunks())
    assert len(parts) > 3 and (res2, thr2) == (res, thr)
    assert np.array_equal(np.concatenate([p.codes for p in parts]), whole.codes)
    assert np.array_equal(np.concatenate([p.values for p in parts]), whole.values)
    a = picture.write_png(tmp_path / "whole.png", whole, res, thr, False, label="map")
    b = picture.write_leaf_sets(tmp_path / "chunks.png", lambda: ((p, thr) for p in stream_leaves(
        sample_map[0], piece=100_000)[3]()), res, False, label="map")
    assert a == b and (tmp_path / "whole.png").read_bytes() == (tmp_path / "chunks.png").read_bytes()
    code, text, _ = cli("export", sample_map[0], "-o", tmp_path / "cli.png", "--json")
    got = json.loads(text)
    assert code == 0 and got.pop("caption") == "map.vxm" and a.pop("caption") == "map"
    assert {k: v for k, v in got.items() if k != "written"} == a


def _map_of(tmp_path, keys, name="m.vxm"):
    from voxtool.config import MapParams, SensorModel
    from voxtool.io.mapfile import save_map
    from voxtool.keys import TREE_MAX_VAL, morton_encode
    from voxtool.maps.octree import OctreeMap

    codes = np.unique(morton_encode((np.asarray(keys) + TREE_MAX_VAL).astype(np.uint16)))
    m = OctreeMap(MapParams(resolution=0.2), SensorModel())
    m.load_state({"leaf_codes": codes, "leaf_depths": np.full(codes.shape[0], 16, np.uint8),
                  "leaf_values": np.full(codes.shape[0], np.float32(2.0))})
    save_map(tmp_path / name, m, {"source": "generated"})
    return tmp_path / name


def test_one_height_gets_no_colour_bar_and_a_legend_that_says_it(tmp_path):
    """Every voxel at one height: nothing for a colour bar to scale (it read '1e-9+2.75e-1', ticks
    0-1); the legend names the height instead."""
    import json

    xs, ys = np.meshgrid(np.arange(40), np.arange(30), indexing="ij")
    path = _map_of(tmp_path, np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, 1)])
    code, text, err = cli("export", path, "-o", tmp_path / "flat.png", "--json")
    assert code == 0, err
    report = json.loads(text)
    assert report["colour_range_m"] is None and report["colour_clipped_share"] is None
    leaves, res, thr, _ = load_leaves(path)
    raster = picture.picture(leaves, res, thr, "top")
    fig = picture.figure(raster, res, "flat")
    assert len(fig.axes) == 1  # no colour bar's axes
    assert [t.get_text() for t in fig.legends[0].get_texts()][0] == "occupied (all at 0.3 m)"


def test_a_tall_front_view_fills_its_picture_and_its_legend_clears_the_title(tmp_path):
    """A map 4 m wide and 30 m tall, seen from the front: the picture is about as narrow as the map
    (it was 11 inches wide whatever the map, half of it blank) and the legend does not overlap the
    title (it sat over it)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    xs, zs = np.meshgrid(np.arange(20), np.arange(150), indexing="ij")
    path = _map_of(tmp_path, np.c_[xs.ravel(), np.zeros(xs.size, np.int64), zs.ravel()])
    leaves, res, thr, _ = load_leaves(path)
    raster = picture.picture(leaves, res, thr, "front")
    fig = picture.figure(raster, res, "tower")
    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    title, legend = ax.title.get_window_extent(renderer), fig.legends[0].get_window_extent(renderer)
    assert not title.overlaps(legend)
    picture_width = ax.get_window_extent(renderer).width
    assert picture_width > 0.25 * fig.bbox.width and fig.get_size_inches()[0] < 6
