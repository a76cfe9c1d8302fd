"""End-to-end CLI: the shipped sample, stats/compare, exports, and bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.cli import SAMPLE_DIR, main
from voxtool.io.bt import read_bt
from voxtool.keys import expand_leaves


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.output


def test_sample_build_equals_real_octomap_reference(sample_map):
    out, stats = sample_map
    ref = read_bt(SAMPLE_DIR / "reference_octomap_res0.2.bt")  # written by OctoMap C++ (pyoctomap)
    code, text = run("export", out, "-o", out.with_suffix(".bt"))
    assert code == 0, text
    ours = read_bt(out.with_suffix(".bt"))
    for occupied in (True, False):
        a = expand_leaves(ref.codes[ref.occupied == occupied], ref.depths[ref.occupied == occupied])
        b = expand_leaves(ours.codes[ours.occupied == occupied], ours.depths[ours.occupied == occupied])
        assert np.array_equal(np.sort(a), np.sort(b))
    assert stats["occupied_voxels"] == int((ref.occupied * (1 << (3 * (16 - ref.depths.astype(np.int64))))).sum())
    assert stats["scans"] == 5 and stats["points"] > 40000
    for key in ("raycast", "update", "total", "jit"):
        assert stats["timings_s"][key] >= 0
    assert stats["scan_latency_ms"]["p95"] >= stats["scan_latency_ms"]["p50"] > 0


def test_stats_json_matches_build_and_compare_detects_drift(sample_map, tmp_path):
    out, built = sample_map
    code, text = run("stats", out, "--json")
    assert code == 0
    stats = json.loads(text)
    for key in ("occupied_voxels", "free_voxels", "bt_leaf_nodes", "bt_inner_nodes", "occupied_bbox", "scans", "points"):
        assert stats[key] == built[key]
    base = tmp_path / "base.json"
    base.write_text(json.dumps(stats))
    assert run("stats", out, "--compare", base)[0] == 0
    stats["occupied_voxels"] = int(stats["occupied_voxels"] * 1.05)
    base.write_text(json.dumps(stats))
    code, text = run("stats", out, "--compare", base, "--tolerance", "0.01")
    assert code == 6 and "1 figure(s) regressed" in text and "occupied_voxels 20,088 -> 19,132 (-4.76%)" in text
    assert run("stats", out, "--compare", base, "--tolerance", "0.1")[0] == 0
    # a baseline that cannot guard anything is an error, not a pass
    code, text = run("stats", out, "--compare", base, "--tolerance", "nan")
    assert code == 2 and "--tolerance nan" in text
    base.write_text(json.dumps({**stats, "occupied_voxels": "many"}))
    code, text = run("stats", out, "--compare", base)
    assert code == 5 and "'occupied_voxels' is 'many', not a number" in text
    base.write_text(json.dumps({"backend": "octree"}))
    code, text = run("stats", out, "--compare", base)
    assert code == 5 and "holds none of the compared figures" in text


def test_stats_compare_guards_packet_log_bandwidth(tmp_path, sample_logs):
    log = sample_logs["r1"][0]
    code, text = run("stats", log, "--json")
    base = tmp_path / "base.json"
    base.write_text(text)
    assert run("stats", log, "--compare", base)[0] == 0
    figures = json.loads(text)
    figures["total"]["avg_Bps"] *= 0.9  # the log now takes 11 % more bandwidth than its baseline
    base.write_text(json.dumps(figures))
    code, text = run("stats", log, "--compare", base, "--tolerance", "0.05")
    assert code == 6 and "total.avg_Bps" in text and "bytes" not in text.split("regressed beyond")[1]


@pytest.mark.parametrize("suffix", [".ply", ".pcd"])
def test_cloud_exports_open_in_open3d(sample_map, tmp_path, suffix):
    import open3d as o3d

    out, stats = sample_map
    path = tmp_path / f"occ{suffix}"
    assert run("export", out, "-o", path)[0] == 0
    cloud = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(cloud.points)
    assert len(pts) == stats["occupied_voxels"]
    assert np.allclose(pts.min(axis=0) - 0.1, stats["occupied_bbox"]["min"], atol=1e-4)  # centres vs corners
    free_path = tmp_path / f"all{suffix}"
    assert run("export", out, "-o", free_path, "--free")[0] == 0
    both = o3d.io.read_point_cloud(str(free_path))
    assert len(both.points) == stats["occupied_voxels"] + stats["free_voxels"] and both.has_colors()


def test_help_is_instant_and_compiles_nothing():
    code = "import sys, voxtool.cli; sys.argv=['voxtool','--help']\ntry:\n    voxtool.cli.main()\nexcept SystemExit: pass\nprint(sorted(m for m in sys.modules if m.startswith(('numba','open3d'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("[]")
    assert "build" in out and "export" in out and "stats" in out


def write_scans(d: Path, n=2):
    for i, (pts, o, yaw) in enumerate(box_scene(n, 100, seed=4)):
        write_pcd(d / f"{i}.pcd", pts, (*o, *yaw_quat(yaw)))


BAD_CASES = {
    "missing source": (lambda d: d / "nope", 3, "nope: no such file or directory"),
    "truncated pcd": (lambda d: _truncate(d / "0.pcd", 100).parent, 3,
                      "PCD binary body has 1100 bytes, header declares 1200; --bad-scans skip leaves out the scans"),
    "pcd without DATA": (lambda d: _rewrite(d / "0.pcd", b"DATA binary\n", b"DATUM binary\n"), 3, "DATA line"),
    "pcd cut in its header": (lambda d: _keep(d / "0.pcd", 60), 3, "the file ends after 60 bytes inside its PCD header"),
    "empty pcd": (lambda d: _keep(d / "0.pcd", 0), 3, "0.pcd: the file is empty (0 bytes)"),
    "pcd bad viewpoint": (lambda d: _rewrite(d / "0.pcd", b"VIEWPOINT ", b"VIEWPOINT 1 "), 3, "VIEWPOINT needs 7 finite numbers"),
    "point outside key range": (lambda d: _far_point(d), 4, "outside the octree key range"),
    "empty directory": (lambda d: _empty(d), 3, "directory must hold .pcd or .ply scans"),
    "pose rows": (lambda d: _poses(d, 1), 3, "pose file has 1 poses for 2 scans"),
    "mcap without the topic": (lambda d: _mcap(d), 3, "topic '/nope' is not a PointCloud2, LaserScan or VelodyneScan topic"),
    "mcap without transform": (lambda d: _mcap(d, skip_tf=True), 3, "no transform chain from 'nowhere' to 'lidar'"),
    "truncated mcap": (lambda d: _truncate(_mcap(d), 700), 3, "s.mcap"),
    "mcap cloud row_step lies": (lambda d: _mcap(d, cloud_overrides={"row_step": 10**6}), 3,
                                 "data has 1200 bytes, row_step x height needs 1000000"),
    "ply short body": (lambda d: _ply(d, cut=40), 3, "PLY body has"),
    "ply bad header": (lambda d: _ply(d, header=b"format binary_middle_endian 1.0"), 3, "PLY format"),
}


def _mcap(d: Path, **kw) -> Path:
    from ros2_writer import write_mcap

    scans = [(pts, o, yaw_quat(yaw)) for pts, o, yaw in box_scene(2, 100, seed=4)]
    write_mcap(d / "s.mcap", scans, **kw)
    return d / "s.mcap"


def _ply(d: Path, cut: int = 0, header: bytes | None = None) -> Path:
    pts = box_scene(1, 50, seed=1)[0][0].astype("<f4")
    head = b"ply\nformat binary_little_endian 1.0\nelement vertex 50\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    if header is not None:
        head = head.replace(b"format binary_little_endian 1.0", header)
    body = pts.tobytes()
    (d / "0.ply").write_bytes(head + (body[:-cut] if cut else body))
    (d / "p.txt").write_text("0 0 0 0 0 0 0 1\n")
    for p in d.glob("*.pcd"):
        p.unlink()
    return d / "0.ply"


def _truncate(p: Path, n: int) -> Path:
    p.write_bytes(p.read_bytes()[:-n])
    return p


def _keep(p: Path, n: int) -> Path:
    p.write_bytes(p.read_bytes()[:n])
    return p.parent


def _rewrite(p: Path, old: bytes, new: bytes) -> Path:
    p.write_bytes(p.read_bytes().replace(old, new, 1))
    return p.parent


def _far_point(d: Path) -> Path:
    write_pcd(d / "0.pcd", np.array([[9000.0, 0, 0]], dtype=np.float32))
    return d


def _empty(d: Path) -> Path:
    for p in d.iterdir():
        p.unlink()
    return d


def _poses(d: Path, n: int) -> Path:
    (d / "p.txt").write_text("0 0 0 0 0 0 0 1\n" * n)
    return d


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_input_one_line_error_exit_code_no_output(tmp_path, case):
    make, exit_code, message = BAD_CASES[case]
    src_dir = tmp_path / "scans"
    src_dir.mkdir()
    write_scans(src_dir)
    source = make(src_dir)
    out = tmp_path / "map.vxm"
    out.write_bytes(b"the user's previous map")
    args = ["build", source, "-o", out]
    if case == "pose rows" or case.startswith("ply"):
        args += ["--poses", src_dir / "p.txt"]
    if case == "mcap without the topic":
        args += ["--topic", "/nope"]
    if case == "mcap without transform":
        args += ["--world-frame", "nowhere"]
    proc = subprocess.run([sys.executable, "-m", "voxtool.cli", *map(str, args)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert proc.returncode == exit_code, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("voxtool: error: ") and message in lines[0], proc.stderr
    assert out.read_bytes() == b"the user's previous map"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".voxtool-tmp-")]


def test_bad_map_files_fail_cleanly(tmp_path, sample_map):
    out, _ = sample_map
    blob = out.read_bytes()
    cases = {
        "trunc.vxm": (blob[: len(blob) // 2], "CRC mismatch"),
        "flip.vxm": (blob[:100] + bytes([blob[100] ^ 1]) + blob[101:], "CRC mismatch"),
        "text.vxm": (b"hello", "too short"),
        "future.vxm": (blob[:8] + (9).to_bytes(2, "little") + blob[10:], "version 9 is newer"),
    }
    for name, (data, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        code, text = run("stats", path)
        assert code == 5 and message in text, (name, text)
        code, text = run("export", path, "-o", tmp_path / f"{name}.bt")
        assert code == 5 and not (tmp_path / f"{name}.bt").exists()


def test_wrong_output_suffixes_are_refused(tmp_path, sample_map):
    out, _ = sample_map
    assert run("export", out, "-o", tmp_path / "x.obj")[0] == 2
    assert run("build", "--sample", "-o", tmp_path / "x.bt")[0] == 2
    assert run("build")[0] == 2


def test_cache_bench_on_sample_reports_consistent_rows(tmp_path):
    # each row is a process of its own (peak memory per configuration): the plain octree and one
    # OctoCache configuration with the write-back on its own thread (test_octocache.py tests the
    # others in this process)
    from matplotlib.image import imread

    from voxtool.plots import PARTS, cache_figure

    plot = tmp_path / "cache.png"
    code, text = run("cache-bench", "--sample", "--overlap", "1", "--order", "random", "--json", "--plot", plot)
    assert code == 0, text
    result = json.loads(text)
    rows = result["rows"]
    assert imread(plot).shape[:2] == (result["height"], result["width"])
    times, hits = cache_figure(result).axes[:2]
    assert len(times.containers) == len(PARTS) and len(times.get_yticklabels()) == len(rows)
    # titled by the dataset, not by its scans' folder ('pcd', 'sample')
    assert cache_figure({**result, "source": "/data/kaist03/pcd"}).axes[0].get_title(loc="left").startswith(
        "kaist03-pcd at")
    stacked = np.sum([[bar.get_width() for bar in c] for c in times.containers], axis=0)
    assert np.allclose(stacked, [r["parts_s"] for r in rows])  # the bars are the measured parts
    assert [bar.get_width() for bar in hits.containers[0]] == pytest.approx([0] + [100 * r["hit_ratio"] for r in rows[1:]])
    assert [r["backend"] for r in rows] == ["octree", "octocache"]
    for r in rows:
        assert r["identical_to_octree"]
        # the parts are timed inside the total, so they cannot exceed it; what they leave out is
        # the scan loop's glue, a few percent idle and more when other tests share the cores
        assert 0 < r["parts_s"] <= r["total_s"]
        assert r["decomposition_error"] == pytest.approx((r["total_s"] - r["parts_s"]) / r["total_s"])
        assert r["decomposition_error"] < 0.25
        assert r["peak_rss_bytes"] > 0
    for r in rows[1:]:
        assert 0 < r["hit_ratio"] < 1
        assert r["written_to_octree"] < r["voxel_updates"]
        assert len(r["hit_ratio_per_scan"]) == 5


def test_encode_decode_merge_stats_on_the_sample(tmp_path, sample_map_ranged, sample_logs):
    built, stats = sample_map_ranged
    log, enc = sample_logs["r1"]
    assert enc["packets"] > 1 and enc["raw_sensor_bytes"] > 0
    code, text = run("stats", log, "--json")
    assert code == 0, text
    st = json.loads(text)["robots"]["r1"]
    assert st["packets"] == enc["packets"] and st["max_Bps"] > 0 and st["compression_ratio"] > 1
    out = tmp_path / "decoded.vxm"
    assert run("decode", log, "-o", out)[0] == 0
    code, text = run("stats", out, "--json")
    decoded = json.loads(text)
    assert decoded["occupied_voxels"] == stats["occupied_voxels"] and decoded["free_voxels"] == stats["free_voxels"]
    # a split stream fuses, and the simulation under loss matches the lossless fusion
    a, b = sample_logs["a"][0], sample_logs["b"][0]
    code, text = run("merge", a, b, "-o", tmp_path / "ab.vxm", "--simulate-loss", "0.3", "--seed", "2", "--json")
    assert code == 0, text
    merged = json.loads(text)
    assert merged["simulation"]["equal_to_lossless"] and merged["simulation"]["lost"] > 0
    assert set(merged["robots"]) == {"a", "b"} and all(not r["gaps"] for r in merged["robots"].values())
    code, text = run("decode", a, "--json")
    assert code == 0 and json.loads(text)["packet_headers"][0]["robot"] == "a"


def test_encode_with_cm_decodes_to_the_built_map_in_fewer_bytes(tmp_path, sample_map_ranged, sample_logs):
    built, stats = sample_map_ranged
    sizes = {}
    for name, codec in (("r1", "zstd"), ("cm", "cm")):  # the scheme follows the codec: hilbert, or nested for cm
        log, enc = sample_logs[name]
        assert enc["scheme"] == ("nested" if codec == "cm" else "hilbert") and enc["codec"] == codec
        sizes[codec] = enc["bytes"]
        out = tmp_path / f"{codec}.vxm"
        assert run("decode", log, "-o", out)[0] == 0
        decoded = json.loads(run("stats", out, "--json")[1])
        assert decoded["occupied_voxels"] == stats["occupied_voxels"] and decoded["free_voxels"] == stats["free_voxels"]
    assert sizes["cm"] < sizes["zstd"]
    log = tmp_path / "refused.mcap"
    code, text = run("encode", "--sample", "-o", log, "--codec", "cm", "--scheme", "hilbert")
    assert code == 2 and "--scheme nested" in text and not log.exists()


def test_bad_packet_logs_fail_cleanly(tmp_path):
    log = tmp_path / "r.mcap"
    assert run("encode", "--sample", "-o", log, "--stop", "1", "--max-range", "20")[0] == 0
    blob = log.read_bytes()
    cases = {"trunc.mcap": blob[: len(blob) // 2], "junk.mcap": b"\x89MCAP0\r\n" + b"\0" * 64}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        for args in (["decode", tmp_path / name, "-o", tmp_path / f"{name}.vxm"], ["stats", tmp_path / name]):
            code, text = run(*args)
            assert code == 5 and "voxtool: error:" in text and name in text, (name, text)
        assert not (tmp_path / f"{name}.vxm").exists()
    # a PointCloud2 bag is not a packet log
    from ros2_writer import write_mcap

    scans = [(pts, o, yaw_quat(yaw)) for pts, o, yaw in box_scene(1, 10, seed=1)]
    write_mcap(tmp_path / "bag.mcap", scans)
    code, text = run("stats", tmp_path / "bag.mcap")
    assert code == 5 and "not a voxtool packet log" in text


def test_hashmap_build_share_and_relay(tmp_path):
    share = tmp_path / "share.mcap"
    code, text = run("build", "--sample", "--backend", "hashmap", "--param", "n_lim=3000", "--schedule", "2:n_lim=2000",
                     "--share", share, "--ring", "2", "--json", "-o", tmp_path / "h.vxm")
    assert code == 0, text
    r = json.loads(text)
    assert r["n_occ"] <= 2000 and r["per_scan_n_occ"]["max"] <= 3000 and r["shared_packets"] == 5
    assert r["per_scan_t_tot_ms"]["p95"] >= r["per_scan_t_tot_ms"]["median"] > 0
    code, text = run("decode", share, "--relay", "--json", "-o", tmp_path / "relayed.vxm")
    assert code == 0, text
    relayed = json.loads(text)
    assert relayed["frames"] == 5 and relayed["n_occ"] >= r["n_occ"]
    assert run("stats", tmp_path / "relayed.vxm")[0] == 0
    assert run("build", "--sample", "--share", share)[0] == 2  # sharing needs the hash map
    for k in (0, -1):  # a broadcast carries at least the last frame
        share.unlink(missing_ok=True)
        code, text = run("build", "--sample", "--backend", "hashmap", "--share", share, "--ring", k)
        assert code == 2 and f"--ring {k}" in text and not share.exists()


def test_cli_backend_choices_match_the_registry():
    from voxtool.cli import BACKEND_NAMES
    from voxtool.maps import BACKENDS

    assert tuple(sorted(BACKENDS)) == BACKEND_NAMES


def test_encode_takes_the_build_backend_options(tmp_path):
    log, out = tmp_path / "h.mcap", tmp_path / "h.vxm"
    code, text = run("encode", "--sample", "-o", log, "--backend", "hashmap", "--param", "n_lim=3000", "--json",
                     "--no-progress")
    assert code == 0, text
    assert json.loads(text)["changed_voxels"] > 3000
    assert run("decode", log, "-o", out)[0] == 0
    code, text = run("stats", out, "--json")
    assert 0 < json.loads(text)["occupied_voxels"] <= 3000  # the limit reached the encoder's map
    code, text = run("encode", "--sample", "-o", log, "--backend", "hashmap", "--param", "bogus=1")
    assert code == 2 and "has no option bogus" in text


@pytest.mark.parametrize("backend, param, message", [
    ("hashmap", "n_lim=abc", "n_lim='abc' must be an integer"),
    ("hashmap", "n_lim=1.5", "n_lim=1.5 must be an integer"),
    ("hashmap", "d_inf=wide", "d_inf='wide' must be a number"),
    ("octocache", "tau=abc", "tau='abc' must be an integer"),
    ("octocache", "order=7", "order=7 must be text"),
    ("tiny", "nodes=5", "has no option nodes (it takes pool_blocks, map_size, hit, miss, prior, threads)"),
])
def test_backend_options_of_the_wrong_kind_are_a_clear_error(tmp_path, backend, param, message):
    out = tmp_path / "m.vxm"
    result = CliRunner().invoke(main, ["build", "--sample", "--backend", backend, "--param", param, "-o", str(out)])
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit), result.output
    assert message in result.output and not out.exists()


def test_an_integral_float_is_an_integer_option(tmp_path):
    from voxtool.io.snapshot import read_snapshot

    out = tmp_path / "m.vxm"
    code, text = run("build", "--sample", "--backend", "hashmap", "--param", "n_lim=2e3", "-o", out, "--no-progress")
    assert code == 0, text
    assert read_snapshot(out).header["backend_params"]["n_lim"] == 2000


def test_more_threads_than_cores_give_the_hash_maps_snapshot(tmp_path):
    """The hash map casts in a numba parallel region, one run of rays per thread: a machine with
    more cores casts in more runs, a path two cores never take (its merge once failed on every
    machine with more than two). Six threads here (numba allows more than the cores) must write
    the bytes one thread writes."""
    from voxtool.io.snapshot import read_snapshot

    one, six = tmp_path / "one.vxm", tmp_path / "six.vxm"
    assert run("build", "--sample", "--backend", "hashmap", "--threads", "1", "-o", one, "--no-progress")[0] == 0
    proc = subprocess.run([sys.executable, "-m", "voxtool.cli", "build", "--sample", "--backend", "hashmap",
                           "--threads", "6", "-o", str(six), "--json", "--no-progress"], capture_output=True, text=True,
                          env={**os.environ, "NUMBA_NUM_THREADS": "6"})
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["threads"] == 6
    assert read_snapshot(one).arrays["leaf_codes"].size > 10_000
    assert one.read_bytes() == six.read_bytes()


def test_thread_counts_write_the_same_snapshot_and_one_core_means_one_thread(tmp_path):
    """--threads 1 and --threads 2 give byte-identical snapshots; run under an affinity mask of
    one core, the default uses that one core (nothing assumes a core count) and agrees too."""
    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this OS")
    outs = {}
    for label, threads in (("one", "1"), ("two", "2"), ("default", "0")):
        out = tmp_path / f"{label}.vxm"
        one_core = (lambda: os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})) if label == "default" else None
        proc = subprocess.run([sys.executable, "-m", "voxtool.cli", "build", "--sample", "-o", str(out), "--threads",
                               threads, "--json", "--no-progress"], capture_output=True, text=True, preexec_fn=one_core)
        assert proc.returncode == 0, proc.stderr
        outs[label] = (json.loads(proc.stdout)["threads"], out.read_bytes())
    assert [outs[k][0] for k in ("one", "two", "default")] == [1, 2, 1]
    assert outs["one"][1] == outs["two"][1] == outs["default"][1]


def test_every_commands_help_renders_its_example_blocks():
    """click keeps a paragraph after a lone \\b line as written; a literal backslash-b (an escaped
    one in a docstring) ran the examples together (issue 26)."""
    import inspect

    for name, command in main.commands.items():
        code, out = run(name, "--help")
        assert code == 0, out
        assert "\\b" not in out and "\b" not in out, name
        doc = inspect.getdoc(command.callback) or ""
        if "\b" in doc:
            block = doc.split("\b", 1)[1].strip("\n").split("\n\n")[0]
            for line in block.splitlines():
                assert line.strip() in {shown.strip() for shown in out.splitlines()}, (name, line)


def test_no_library_module_imports_the_command_line():
    """The CLI is a thin layer over the library: no module outside voxtool/cli imports it (the
    kernels' warm-up did, and the CLI imported it back: a circle)."""
    import re
    from pathlib import Path

    import voxtool

    root = Path(voxtool.__file__).parent
    offenders = [str(p.relative_to(root)) for p in root.rglob("*.py")
                 if "cli" not in p.relative_to(root).parts
                 and re.search(r"^\s*(from voxtool\.cli\b|import voxtool\.cli\b)", p.read_text(), re.M)]
    assert offenders == []
