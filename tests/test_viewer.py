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
    assert proc.stderr.strip() == "", proc.stderr  # no GLFW / Mesa / Open3D lines on success
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


def test_view_without_a_display_is_one_line(sample_map):
    """No display: an error at once (it ran forever on an invisible EGL window)."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "voxtool.cli", "view", str(sample_map[0])], capture_output=True,
                          text=True, timeout=60, env=env)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1 and "--screenshot" in proc.stderr, proc.stderr


def test_screenshot_json_without_a_display_is_json_alone(sample_map, tmp_path):
    """No display: Open3D falls back to an EGL context and its C++ prints notes on stdout; with
    --json, stdout holds the JSON alone (the notes go to stderr)."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "voxtool.cli", "view", str(sample_map[0]), "--screenshot",
                           str(tmp_path / "s.png"), "--size", "320x240", "--json"], capture_output=True, text=True,
                          timeout=120, env=env)
    if proc.returncode != 0 and ("EGL" in proc.stderr or "OpenGL" in proc.stderr):
        pytest.skip(f"no offscreen OpenGL here: {proc.stderr.strip().splitlines()[-1]}")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["occupied_voxels_shown"] == sample_map[1]["occupied_voxels"], proc.stdout[:300]


def test_ctrl_c_ends_the_view_window(sample_map):
    """A window under a real X server (Xvfb): Ctrl-C (SIGINT) ends `view` with exit 130 (Open3D's
    run loop held the interpreter, and only SIGTERM ended it)."""
    import os
    import signal
    import time

    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip("no Xvfb (Debian: xvfb) on this machine")
    display = f":{200 + os.getpid() % 500}"
    server = subprocess.Popen([xvfb, display, "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(1.0)
        env = {**os.environ, "DISPLAY": display}
        proc = subprocess.Popen([sys.executable, "-m", "voxtool.cli", "view", str(sample_map[0])], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 60
        err = ""
        while "voxtool view: all heights" not in err and time.monotonic() < deadline and proc.poll() is None:
            err += proc.stderr.readline()
        if proc.poll() is not None:
            rest = proc.stderr.read()
            if "cannot open a window" in err + rest:
                pytest.skip(f"no OpenGL window under Xvfb here: {(err + rest).strip().splitlines()[-1]}")
            pytest.fail(f"view ended before its window showed: {err + rest}")
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        finally:
            proc.kill()
        assert proc.returncode == 130, proc.stderr.read()
    finally:
        server.terminate()
        server.wait()


def test_a_point_cloud_is_viewed_as_the_voxels_it_fills(sample_map, tmp_path):
    """`view` opens .ply/.pcd (clean's outputs): the voxel centres a map exports, viewed at the
    map's resolution, are exactly the map's occupied voxels (drawn as a map's are: the screenshot
    test above)."""
    from voxtool.viewer import cloud_scene

    for suffix in (".ply", ".pcd"):
        cloud = tmp_path / f"occ{suffix}"
        assert cli("export", sample_map[0], "-o", cloud)[0] == 0
        scene, whole = cloud_scene(cloud, 0.2), load_scene(sample_map[0])
        middle = np.round(np.median(whole.occupied[:, :2], axis=0)).astype(np.int64) - 32768  # shown about it
        assert np.array_equal(np.unique(scene.occupied + [*middle, 0], axis=0), np.unique(whole.occupied, axis=0))
