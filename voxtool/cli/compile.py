"""`voxtool compile`: voxtool's kernels compiled ahead of their first use.

numba compiles a kernel the first time it is called and keeps the machine code in its cache
(`__pycache__` beside the source, or NUMBA_CACHE_DIR), so every command pays its kernels'
compilation once per install: 3.4 s of a first `build`, 2.2 s of a first `encode --codec cm`.
The cache is keyed by each source file's modification time, so it cannot ship inside the
package (a new clone or install has new times). What can be done is to fill it once, at
install: `compile_ahead` runs every command on two scans of the shipped sample, in this process,
so each kernel is compiled with exactly the argument types the commands give it.
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import click

from voxtool.cli.common import SAMPLE_DIR, emit, handle_errors
from voxtool.errors import VoxtoolError


def _steps(d: Path) -> list[tuple[str, list[str]]]:
    """Every command on a sliver of the sample (the kernels' types do not depend on the size)."""
    one = ["--sample", "--stop", "2", "--max-range", "8"]
    return [
        ("build", ["build", *one, "-o", str(d / "map.vxm")]),
        ("build --stop 1", ["build", "--sample", "--stop", "1", "--max-range", "8", "-o", str(d / "less.vxm")]),
        ("build --decay", ["build", *one, "--decay", "5", "--poses", "SAMPLE/poses.txt", "-o", str(d / "decay.vxm")]),
        ("build --backend octocache", ["build", *one, "--backend", "octocache", "-o", str(d / "cache.vxm")]),
        ("build --backend hashmap", ["build", *one, "--backend", "hashmap", "-o", str(d / "hash.vxm")]),
        ("build --backend tiny", ["build", *one, "--backend", "tiny", "-o", str(d / "tiny.vxm")]),
        ("stats", ["stats", str(d / "map.vxm"), "--json"]),
        ("query", ["query", str(d / "map.vxm"), "--json", "--", "0", "0", "0"]),
        ("diff", ["diff", str(d / "less.vxm"), str(d / "map.vxm"), "--png", str(d / "diff.png"),
                  "--ply", str(d / "diff.ply")]),
        ("export .bt", ["export", str(d / "map.vxm"), "-o", str(d / "map.bt")]),
        ("build .bt", ["build", str(d / "map.bt"), "-o", str(d / "from_bt.vxm")]),
        ("export .ply", ["export", str(d / "map.vxm"), "-o", str(d / "map.ply"), "--free"]),
        ("export .pcd", ["export", str(d / "map.vxm"), "-o", str(d / "map.pcd")]),
        ("export .png", ["export", str(d / "map.vxm"), "-o", str(d / "map.png")]),
        ("export .mcap", ["export", str(d / "map.vxm"), "-o", str(d / "map.mcap")]),
        ("export .pgm", ["export", str(d / "map.vxm"), "-o", str(d / "map.pgm")]),
        ("eval", ["eval", *one, "--holdout-every", "2", "--json"]),
        ("encode", ["encode", *one, "-o", str(d / "zstd.mcap")]),
        ("encode --codec cm", ["encode", *one, "--codec", "cm", "--robot", "r2", "-o", str(d / "cm.mcap")]),
        ("merge", ["merge", str(d / "zstd.mcap"), str(d / "cm.mcap"), "-o", str(d / "fused.vxm"),
                   "--view", str(d / "replay.mcap")]),
        ("decode", ["decode", str(d / "zstd.mcap"), "--json"]),
        ("stats .mcap", ["stats", str(d / "zstd.mcap"), "--json"]),
        ("clean", ["clean", *one, "-o", str(d / "static.pcd")]),
        ("odometry 2D", ["odometry", str(d / "planar"), "-o", str(d / "planar_poses.txt")]),
    ]


def _planar_scans(folder: Path) -> None:
    """Two 2D scans (z 0) of a 4 m x 3 m room's walls, as PCD files: `odometry 2D`'s input (the
    shipped sample is 3D), enough points for the grid matcher to align the second to the first."""
    import numpy as np

    from voxtool.io.export import pcd_header, pcd_rows

    folder.mkdir(exist_ok=True)
    t = np.arange(0.0, 1.0, 0.0125)
    room = np.concatenate([np.c_[4 * t - 2, np.full_like(t, -1.5)], np.c_[np.full_like(t, 2.0), 3 * t - 1.5],
                           np.c_[2 - 4 * t, np.full_like(t, 1.5)], np.c_[np.full_like(t, -2.0), 1.5 - 3 * t]])
    for i, shift in enumerate((0.0, 0.05)):
        points = np.c_[room[:, 0] - shift, room[:, 1], np.zeros(len(room))].astype(np.float32)
        (folder / f"{i}.pcd").write_bytes(pcd_header(len(points), False) + pcd_rows(points, None))


# The steps in two groups that share few kernels and no files, one process each: the hash map's kernels (half
# the total) compile beside the octree's. Measured on the 2-core VM from an empty cache: 36.5 s in
# one process, see the README for the two-process figure.
_GROUPS = (
    ("build", "build --stop 1", "build --decay", "build --backend octocache", "build --backend tiny",
     "stats", "query", "export .bt", "build .bt", "export .ply", "export .pcd", "export .png",
     "export .mcap", "export .pgm", "eval", "clean", "diff", "odometry 2D"),
    ("build --backend hashmap", "encode", "encode --codec cm", "merge", "decode", "stats .mcap"),
)


def run_steps(names: list[str], tmp: str) -> dict:
    """Run the named steps in this process (a compile worker): the seconds each took."""
    from voxtool.cli import main  # the group this command belongs to: imported when it runs, not before

    steps = dict(_steps(Path(tmp)))
    if "odometry 2D" in names:
        _planar_scans(Path(tmp) / "planar")
    times: dict[str, float] = {}
    for name in names:
        args = [a.replace("SAMPLE/", f"{SAMPLE_DIR}/") for a in steps[name]]
        out, err = io.StringIO(), io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main.main(args, "voxtool")
                code = 0
            except SystemExit as stop:
                code = stop.code or 0
        if code == 130:  # Ctrl-C inside a step: the whole command was interrupted
            raise KeyboardInterrupt
        if code != 0:
            line = err.getvalue().strip().splitlines()[-1:] or [f"exit {code}"]
            raise VoxtoolError(f"compiling: 'voxtool {name}' on the sample failed: {line[0]}")
        times[name] = round(time.perf_counter() - t0, 3)
    return times


def compile_ahead(progress: bool | None = None, jobs: int | None = None) -> dict:
    """Run every command once on the sample so that numba's cache holds every kernel; returns
    the seconds each step took (compiling, or loading what was already cached).

    With `jobs` > 1 each group of steps runs in its own `voxtool compile --group K` process
    (default: one per group, at most one per core). numba writes each cache file to a temporary
    name and renames it, so two processes that compile the same kernel both leave a whole file."""
    import json
    import os
    import subprocess

    from voxtool.progress import bar

    jobs = jobs or min(len(_GROUPS), os.cpu_count() or 1)
    times: dict[str, float] = {}
    # no bar where stderr is not a terminal (an install log, CI): one line per group instead,
    # so that the half minute this takes is not silent
    lines = progress is None and not sys.stderr.isatty()
    total = sum(len(g) for g in _GROUPS)
    with bar(total, "compiling", progress, unit="command") as done:
        def finished(group_times: dict) -> None:
            times.update(group_times)
            done.update(len(group_times))
            if lines:
                click.echo(f"voxtool compile: {len(times)}/{total} {', '.join(group_times)}: "
                           f"{sum(group_times.values()):.1f} s", err=True)

        if jobs <= 1:
            with tempfile.TemporaryDirectory(prefix="voxtool-compile-") as tmp:
                for group in _GROUPS:
                    finished(run_steps(list(group), tmp))
            return times
        # one process per group (subprocesses, not a multiprocessing pool: Ctrl-C reaches them as
        # it reaches this process, and nothing is left behind)
        procs = [subprocess.Popen([sys.executable, "-m", "voxtool.cli", "compile", "--group", str(k), "--json",
                                   "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for k in range(len(_GROUPS))]
        try:
            for proc in procs:
                out, err = proc.communicate()
                if proc.returncode == 130:
                    raise KeyboardInterrupt
                if proc.returncode != 0:
                    line = err.strip().splitlines()[-1:] or [f"exit {proc.returncode}"]
                    raise VoxtoolError(line[0].removeprefix("voxtool: error: "))
                finished(json.loads(out)["seconds"])
        finally:
            for proc in procs:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
    return times


@click.command("compile")
@click.option("--json", "as_json", is_flag=True, help="Print the seconds each command took as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@click.option("--jobs", type=click.IntRange(1, None), default=None,
              help="Processes compiling at once (default: 2, or 1 on a one-core machine).")
@click.option("--group", type=int, default=None, hidden=True, help="Run one group of steps (a worker of --jobs).")
@handle_errors
def compile_cmd(as_json, progress, jobs, group):
    """Compile every kernel ahead into numba's cache (beside the installed sources, or
    NUMBA_CACHE_DIR), by running each command once on a sliver of the shipped sample.

    Without it, each command's first run after an install compiles the kernels it needs
    (about 3 s for `build`, 2 s for `encode --codec cm`). This takes about half a minute once
    from an empty cache on a 2-core machine, in two processes (23-31 s idle, 46-61 s beside other
    work; 2 s when the cache is full); run it again only after changing voxtool's sources (the
    cache then recompiles by itself). Where stderr is no terminal it prints, instead of a bar, a
    line as each process finishes: how many commands are done, the ones it ran, and the seconds
    they took.

    \b
    Example:
      pip install -e . && voxtool compile
    """
    t0 = time.perf_counter()
    if group is not None:
        with tempfile.TemporaryDirectory(prefix="voxtool-compile-") as tmp:
            times = run_steps(list(_GROUPS[group]), tmp)
    else:
        times = compile_ahead(progress, jobs)
    total = round(time.perf_counter() - t0, 2)
    emit({"seconds": times, "total_s": total}, as_json,
         [("commands", str(len(times))), ("time", f"{total:.1f} s (compiling, or loading the cached kernels)")])
