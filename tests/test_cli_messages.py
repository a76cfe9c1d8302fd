"""What a user sees: one-line errors that name the file, warnings whenever data is dropped,
comparisons with a direction, figures named for what they count, the same confirmation from
every command that writes, and progress on long work."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from voxtool.cli import main


def run(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="module")
def logs(sample_logs):
    """The folder of the session's sample logs (a.mcap, b.mcap, fine.mcap, ...)."""
    return sample_logs["a"][0].parent


def test_the_same_log_twice_is_refused(logs, tmp_path):
    code, out, err = run("merge", logs / "a.mcap", logs / "a.mcap")
    assert code == 2 and err.strip().endswith("given twice (a log fused with itself would count its packets twice)")
    (tmp_path / "copy.mcap").write_bytes((logs / "a.mcap").read_bytes())
    code, out, err = run("merge", logs / "a.mcap", tmp_path / "copy.mcap")
    assert code == 2 and "copy.mcap: packet 0 of robot 'a' is also in" in err and err.count("\n") == 1


def test_a_resolution_mismatch_names_both_files(logs):
    code, _, err = run("merge", logs / "a.mcap", logs / "fine.mcap")
    assert code == 5 and err.count("\n") == 1
    assert "fine.mcap: packet 0 of robot 'f' has resolution 0.1 m, but" in err and "a.mcap has 0.2 m" in err


def test_a_truncated_log_says_what_is_wrong_with_the_file(logs, tmp_path):
    blob = (logs / "a.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(blob[: len(blob) // 3])
    for command in ("stats", "decode", "merge"):
        code, _, err = run(command, tmp_path / "cut.mcap")
        assert code == 5 and err.count("\n") == 1 and "cut.mcap: cannot be read as a packet log:" in err, err
        assert "truncated" in err and "RecordLength" not in err and "Exceeded" not in err


def test_usage_mistakes_are_one_line_with_exit_2(tmp_path):
    cases = [(["build", "--sample", "--resolution", "abc"], "'abc' is not a valid float"),
             (["build", "--sample", "--start", "20"], "--start 20 --every 1 selects none of its 5 scans"),
             (["bild"], "No such command 'bild'"),
             (["merge"], "Missing argument 'LOGS...'")]
    for args, message in cases:
        code, out, err = run(*args)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("voxtool: error: ") and message in lines[0], err
        assert "None" not in lines[0] and "Usage:" not in err and out == ""


def test_a_backend_without_options_says_it_takes_none(monkeypatch):
    import voxtool.maps as maps
    from voxtool.config import MapParams, SensorModel
    from voxtool.errors import ParameterError

    class Bare:
        def __init__(self, params, sensor):
            pass

    monkeypatch.setitem(maps.BACKENDS, "bare", Bare)
    with pytest.raises(ParameterError, match=r"backend 'bare' has no option foo \(it takes none\)"):
        maps.make_backend("bare", MapParams(), SensorModel(), foo=1)


def test_compare_knows_which_way_is_worse_and_prints_everything_in_json(logs, tmp_path):
    code, out, _ = run("stats", logs / "a.mcap", "--json")
    figures = json.loads(out)
    bigger = dict(figures, bytes=figures["bytes"] * 2)  # the baseline log was twice as large
    (tmp_path / "bigger.json").write_text(json.dumps(bigger))
    code, out, err = run("stats", logs / "a.mcap", "--compare", tmp_path / "bigger.json", "--json")
    report = json.loads(out)["comparison"]
    assert code == 0 and err == "" and report["regressions"] == []
    assert report["figures"]["bytes"] == {"base": bigger["bytes"], "new": figures["bytes"], "change": -0.5,
                                          "allowed": 0.0, "regression_if": "more", "verdict": "improvement"}
    smaller = dict(figures, bytes=figures["bytes"] // 2)  # the log doubled: a regression
    (tmp_path / "smaller.json").write_text(json.dumps(smaller))
    code, out, err = run("stats", logs / "a.mcap", "--compare", tmp_path / "smaller.json", "--json")
    report = json.loads(out)["comparison"]  # the full comparison is printed when it fails too
    assert code == 6 and report["regressions"] == ["bytes"] and report["figures"]["packets"]["verdict"] == "ok"
    assert err.count("\n") == 1 and f"bytes {smaller['bytes']:,} -> {figures['bytes']:,} (+" in err
    code, out, err = run("stats", logs / "a.mcap", "--compare", tmp_path / "smaller.json")
    assert code == 6 and "e+" not in out + err and f"{figures['bytes']:,}" in out


def test_a_map_that_lost_voxels_is_a_regression_too(tmp_path, sample_map):
    path, built = sample_map
    (tmp_path / "base.json").write_text(json.dumps(dict(built, occupied_voxels=built["occupied_voxels"] + 100,
                                                        bt_leaf_nodes=built["bt_leaf_nodes"] + 100)))
    code, out, err = run("stats", path, "--compare", tmp_path / "base.json", "--json")
    report = json.loads(out)["comparison"]
    assert code == 6 and report["regressions"] == ["occupied_voxels"]  # fewer voxels: changed; fewer nodes: better
    assert report["figures"]["bt_leaf_nodes"]["verdict"] == "improvement"


def test_a_baseline_with_the_old_figure_names_still_compares(tmp_path, sample_map):
    path, built = sample_map
    old = {"leaf_nodes": built["bt_leaf_nodes"] - 100, "octree_leaf_nodes": built["logodds_leaf_nodes"],
           "occupied_voxels": built["occupied_voxels"]}
    (tmp_path / "old.json").write_text(json.dumps(old))
    code, out, _ = run("stats", path, "--compare", tmp_path / "old.json", "--json")
    report = json.loads(out)["comparison"]
    assert code == 6 and report["regressions"] == ["bt_leaf_nodes"]
    assert report["figures"]["logodds_leaf_nodes"]["verdict"] == "ok"


def test_build_and_stats_report_the_same_figures_named_for_what_they_count(tmp_path, sample_map):
    pyoctomap = pytest.importorskip("pyoctomap")
    path, built = sample_map
    code, out, _ = run("stats", path, "--json")
    stats = json.loads(out)
    for key in ("bt_leaf_nodes", "bt_inner_nodes", "logodds_leaf_nodes", "logodds_inner_nodes", "pool_bytes_used",
                "occupied_voxels", "free_voxels"):
        assert stats[key] == built[key], key
    # leaf_nodes / inner_nodes are the tree of the .bt that export writes, as OctoMap reads it
    code, out, _ = run("export", path, "-o", tmp_path / "m.bt", "--json")
    assert code == 0 and json.loads(out)["bt_leaf_nodes"] == stats["bt_leaf_nodes"]
    tree = pyoctomap.OcTree(0.1)
    assert tree.readBinary(str(tmp_path / "m.bt"))
    assert (tree.getNumLeafNodes(), tree.size()) == (stats["bt_leaf_nodes"], stats["bt_leaf_nodes"] + stats["bt_inner_nodes"])
    assert stats["logodds_leaf_nodes"] > stats["bt_leaf_nodes"]  # the log-odds tree prunes less
    code, out, _ = run("stats", tmp_path / "m.bt", "--json")
    from_bt = json.loads(out)
    assert (from_bt["bt_leaf_nodes"], from_bt["bt_inner_nodes"]) == (stats["bt_leaf_nodes"], stats["bt_inner_nodes"])
    assert from_bt["pool_bytes"] is None and from_bt["logodds_leaf_nodes"] is None  # a file has no pool
    code, out, _ = run("stats", tmp_path / "m.bt")
    assert "0.0 MiB" not in out and "memory" not in out


def test_the_build_time_line_says_the_phases_overlap(tmp_path):
    code, out, _ = run("build", "--sample")
    line = next(ln for ln in out.splitlines() if ln.startswith("time per phase"))
    assert "ray casting" in line and "overlap" in line


def test_tiny_builds_a_usable_map_by_default_and_warns_when_a_budget_drops_updates(tmp_path, sample_map):
    code, out, err = run("build", "--sample", "--backend", "tiny", "--json", "--no-progress")
    tiny = json.loads(out)
    octree = sample_map[1]
    assert code == 0 and err == "" and tiny["dropped_updates"] == 0 and tiny["pool_budget"] is None
    assert 0.8 < tiny["occupied_voxels"] / octree["occupied_voxels"] < 1.2  # its own level arithmetic
    code, out, err = run("build", "--sample", "--backend", "tiny", "--pool-blocks", "64", "--json", "--no-progress")
    dropped = json.loads(out)["dropped_updates"]
    lines = err.strip().splitlines()
    assert code == 0 and dropped > 0 and len(lines) == 1 and lines[0].startswith("voxtool: warning: ")
    assert f"{dropped:,} of {tiny['voxel_updates']:,} voxel updates were dropped" in lines[0]
    assert "--pool-blocks" in lines[0]


def test_every_command_that_writes_confirms_it_the_same_way(logs, tmp_path, sample_map):
    share = tmp_path / "share.mcap"
    assert run("build", "--sample", "--backend", "hashmap", "--share", share, "--stop", "2", "--no-progress")[0] == 0
    writes = [["build", "--sample", "-o", tmp_path / "b.vxm", "--stop", "1", "--no-progress"],
              ["encode", "--sample", "-o", tmp_path / "e.mcap", "--stop", "1", "--max-range", "20", "--no-progress"],
              ["decode", logs / "b.mcap", "-o", tmp_path / "d.vxm"],
              ["decode", share, "--relay", "-o", tmp_path / "r.vxm"],
              ["merge", logs / "a.mcap", logs / "b.mcap", "-o", tmp_path / "m.vxm"],
              ["export", sample_map[0], "-o", tmp_path / "x.pcd"]]
    for args in writes:
        target = args[args.index("-o") + 1]
        code, out, err = run(*args)
        assert code == 0, (args, err)
        assert out.splitlines()[-1].split() == ["written", str(target)], args
        code, out, _ = run(*args, "--json")
        assert json.loads(out)["written"] == str(target), args


def test_help_explains_every_option():
    import click

    for name, command in main.commands.items():
        for param in command.params:
            if isinstance(param, click.Option) and not param.hidden:
                assert param.help, f"voxtool {name} {param.opts[0]} has no help text"


@pytest.mark.parametrize("args, desc", [(["decode", "a.mcap"], "fuse"), (["merge", "a.mcap", "b.mcap"], "fuse"),
                                        (["stats", "a.mcap"], "stats")])
def test_long_work_shows_progress_when_asked(logs, args, desc):
    args = [logs / a if a.endswith(".mcap") else a for a in args]
    code, out, err = run(*args, "--progress")
    assert code == 0 and desc in err and "packet" in err
    code, out, err = run(*args, "--no-progress")
    assert err == ""


def test_export_shows_progress_and_refuses_free_where_it_cannot_apply(tmp_path, sample_map):
    path = sample_map[0]
    code, out, err = run("export", path, "-o", tmp_path / "m.bt", "--progress")
    assert code == 0 and "export .bt" in err
    for suffix in (".bt", ".png"):
        code, out, err = run("export", path, "-o", tmp_path / f"f{suffix}", "--free")
        assert code == 2 and "--free is for .ply/.pcd" in err and not (tmp_path / f"f{suffix}").exists()
    assert np.isfinite(json.loads(run("export", path, "-o", tmp_path / "f.ply", "--free", "--json")[1])["free_voxels"])


def test_decay_with_another_backend_names_the_option(tmp_path):
    code, _, err = run("build", "--sample", "-o", tmp_path / "m.vxm", "--decay", "5", "--backend", "hashmap")
    assert code == 2 and "--decay" in err and "decay_half_life" not in err and err.count("\n") == 1, err


def test_importing_a_bt_prints_its_statistics(sample_map, tmp_path):
    path, built = sample_map
    assert run("export", path, "-o", tmp_path / "m.bt")[0] == 0
    code, out, err = run("build", tmp_path / "m.bt", "-o", tmp_path / "back.vxm", "--json")
    got = json.loads(out)
    assert code == 0 and got["occupied_voxels"] == built["occupied_voxels"] and got["imported"]["format"] == "vxm"
    code, out, _ = run("build", tmp_path / "m.bt", "-o", tmp_path / "again.vxm")
    assert f"{built['occupied_voxels']:,}" in out and "occupied voxels" in out


def test_encode_prints_words_not_json_keys(tmp_path):
    code, out, err = run("encode", "--sample", "-o", tmp_path / "r.mcap", "--stop", "2", "--max-range", "20")
    assert code == 0, err
    keys = [line.split()[0] for line in out.splitlines()]
    assert not any("_" in k for k in keys), out
    code, text, _ = run("encode", "--sample", "-o", tmp_path / "r2.mcap", "--stop", "2", "--max-range", "20", "--json")
    report = json.loads(text)
    assert f"{report['bytes']:,} bytes" in out and f"{report['packets']:,}" in out


def test_build_without_output_says_the_map_was_not_written(tmp_path):
    code, out, err = run("build", "--sample", "--no-progress")
    assert code == 0 and "written             nothing: no -o given, the map was built and measured only" in out, out
