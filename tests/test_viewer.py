"""`voxtool view`: what it draws (against Open3D's reading of the .ply export and a brute-force
expansion of free leaves), and `--screenshot` rendered under a real X server (Xvfb)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import cli

from voxtool.api import load_leaves
from voxtool.keys import expand_leaves, keys_to_coords, morton_decode
from voxtool.viewer import load_scene


def test_scene_holds_exactly_the_exported_occupied_voxels(sample_map, tmp_path):
    import open3d as o3d

    ply = tmp_path / "occ.ply"
    assert cli("export", sample_map[0], "-o", ply)[0] == 0
    exported = np.asarray(o3d.io.read_point_cloud(str(ply)).points)
    scene = load_scene(sample_map[0])
    centres = keys_to_coords(scene.occupied, scene.resolution)
    assert len(centres) == sample_map[1]["occupied_voxels"] == len(exported)
    assert np.allclose(np.unique(np.round(centres, 3), axis=0), np.unique(np.round(exported, 3), axis=0))


def test_free_cells_are_the_coarse_cells_holding_free_voxels(tmp_path):
    path = tmp_path / "small.vxm"
    assert cli("build", "--sample", "--stop", 1, "--max-range", 8, "-o", path)[0] == 0
    leaves, _, thr, _ = load_leaves(path)
    free = ~(leaves.values > np.float32(thr))
    voxels = morton_decode(expand_leaves(leaves.codes[free], leaves.depths[free])).astype(np.int64)
    for limit in (10**7, 20_000, 2_000):  # every voxel its own cell, then coarser cells
        scene = load_scene(path)
        scene.max_free = limit
        expect = np.unique(voxels >> scene.free_shift, axis=0)
        assert len(scene.free) <= limit and np.array_equal(scene.free, expect)
        if limit == 10**7:
            assert scene.free_shift == 0


def _xvfb_view(*args):
    if shutil.which("xvfb-run") is None:
        pytest.skip("no xvfb-run (Debian: xvfb) on this machine")
    proc = subprocess.run(["xvfb-run", "-a", sys.executable, "-m", "voxtool.cli", "view", *map(str, args), "--json"],
                          capture_output=True, text=True, timeout=120)
    if "OpenGL context" in proc.stderr or "xvfb-run: error" in proc.stderr:
        pytest.skip(f"no OpenGL under Xvfb here: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_screenshot_under_xvfb_draws_the_map_and_an_empty_slice_draws_nothing(sample_map, tmp_path):
    from matplotlib.image import imread

    shot = tmp_path / "shot.png"
    report = _xvfb_view(sample_map[0], "--screenshot", shot, "--size", "640x480")
    assert report["occupied_voxels_shown"] == sample_map[1]["occupied_voxels"]
    assert report["rendered_pixels"] > 1_000  # of 640 x 480: the sample is a sparse 360 m scene
    image = imread(shot)
    assert image.shape[:2] == (report["height"], report["width"])
    top = sample_map[1]["occupied_bbox"]["max"][2]
    empty = _xvfb_view(sample_map[0], "--screenshot", tmp_path / "empty.png", "--size", "640x480",
                       "--slice", top + 5)
    assert empty["occupied_voxels_shown"] == 0 and empty["rendered_pixels"] == 0
    scene = load_scene(sample_map[0])
    z_keys, counts = np.unique(scene.occupied[:, 2], return_counts=True)
    fullest = float(keys_to_coords(z_keys[counts.argmax()], scene.resolution))
    sliced = _xvfb_view(sample_map[0], "--screenshot", tmp_path / "slice.png", "--size", "640x480",
                        "--slice", fullest, "--free")
    assert sliced["occupied_voxels_shown"] == counts.max() < report["occupied_voxels_shown"]
    assert sliced["free_cells_shown"] > 0 and sliced["rendered_pixels"] > 0
