"""`voxtool compile` fills numba's cache so that no command compiles on its first run: checked
with numba's own cache log (NUMBA_DEBUG_CACHE) on a cache folder that starts empty, as on a
fresh install."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest


def voxtool(args, env):
    proc = subprocess.run([sys.executable, "-m", "voxtool.cli", *map(str, args), "--no-progress"],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout + proc.stderr


def _planar_room(folder):
    from voxtool.cli.compile import _planar_scans

    _planar_scans(folder / "planar")
    return folder / "planar"


@pytest.mark.sweep  # 25-35 s of compilation from an empty cache: run by .ci/run after the quick suite
def test_first_runs_after_compile_compile_nothing(tmp_path):
    cache = tmp_path / "numba-cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    report = json.loads(voxtool(["compile", "--json"], env))
    assert {"build", "encode --codec cm", "merge", "export .mcap", "clean", "diff", "odometry 2D"} <= set(report["seconds"])
    saved = {p.name for p in cache.rglob("*.nbi")}
    # the kernels of the build, the cm coder, clean (and its ground) and the hash map are in the cache
    for kernel in ("raycast._make_scan_bricks", "octree.apply_bricks", "cm.", "clean.near_hits_table", "hashmap.",
                   "ground._min_along_rows", "grid_matcher._align"):
        assert any(kernel in name for name in saved), kernel

    env["NUMBA_DEBUG_CACHE"] = "1"
    d = tmp_path
    for args in (["build", "--sample", "-o", d / "map.vxm"],
                 ["encode", "--sample", "-o", d / "z.mcap"],
                 ["encode", "--sample", "--codec", "cm", "--robot", "r2", "-o", d / "c.mcap"],
                 ["merge", d / "z.mcap", d / "c.mcap", "-o", d / "fused.vxm"],
                 ["export", d / "map.vxm", "-o", d / "map.mcap"],
                 ["clean", "--sample", "-o", d / "static.pcd"],
                 ["odometry", _planar_room(d), "-o", d / "poses.txt"]):
        log = voxtool(args, env)
        compiled = [line for line in log.splitlines() if "data saved" in line]
        assert not compiled, (args[0], compiled[:3])
        assert "data loaded" in log, args[0]  # numba's log is there: the check above can fail


def test_an_interrupted_compile_exits_130(tmp_path):
    """Ctrl-C during `voxtool compile` (a fresh cache, so it is still compiling) is one line and
    exit 130, as for every command; not a 'step failed' error."""
    import signal
    import time

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.Popen([sys.executable, "-m", "voxtool.cli", "compile", "--no-progress"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while time.time() < deadline and not any((tmp_path / "cache").rglob("*.nbi")):
        time.sleep(0.05)  # the first kernel is in the cache: compiling has begun
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["voxtool: interrupted; no output written"]


def test_compile_prints_its_phases_where_stderr_is_no_terminal(monkeypatch):
    """Piped stderr (an install log, CI) gets no bar: one line per group of commands instead of a
    silent half-minute on a fresh install; --no-progress keeps it quiet. (Three of the steps, in
    this process: the whole list, in two processes, runs in the sweep above.)"""
    from click.testing import CliRunner

    from voxtool.cli import compile as command
    from voxtool.cli import main

    monkeypatch.setattr(command, "_GROUPS", (("build", "stats"), ("query",)))
    result = CliRunner().invoke(main, ["compile", "--jobs", "1"])
    assert result.exit_code == 0, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("voxtool compile: ")]
    assert [line.split(":")[1].strip() for line in lines] == ["2/3 build, stats", "3/3 query"]
    quiet = CliRunner().invoke(main, ["compile", "--jobs", "1", "--no-progress"])
    assert quiet.exit_code == 0 and "voxtool compile:" not in quiet.stderr


def test_the_compile_groups_hold_every_step_once():
    """The two processes' groups together run every step exactly once."""
    from pathlib import Path

    from voxtool.cli.compile import _GROUPS, _steps

    names = [name for group in _GROUPS for name in group]
    assert sorted(names) == sorted(name for name, _ in _steps(Path("/tmp")))
