"""Dask: one map from many workers, sharded snapshots, fleets, a killed worker and Ctrl-C, on a
real LocalCluster of 2 worker processes (never a mock)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import SAMPLE_LOG_RANGE, cli

from voxtool.api import build_map
from voxtool.config import MapParams, SensorModel
from voxtool.distbuild import cast_batch, distributed_build, order_scans, partition_of
from voxtool.errors import FormatError
from voxtool.io import sharded
from voxtool.io.mapfile import load_map
from voxtool.sources import SourceOptions, open_source

distributed = pytest.importorskip("dask.distributed")
SAMPLE = Path(__file__).resolve().parents[1] / "voxtool" / "data" / "sample"


@pytest.fixture(scope="module")
def client():
    from dask.distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        with Client(cluster) as c:
            yield c


def same_leaves(a, b):
    la, lb = a.leaves(), b.leaves()
    return (np.array_equal(la.codes, lb.codes) and np.array_equal(la.depths, lb.depths)
            and np.array_equal(la.values, lb.values))


def single_map(source, resolution=0.2, options=SourceOptions(), tmp=None):
    out = Path(tmp) / "single.vxm"
    build_map(source, options, MapParams(resolution), SensorModel(), output=out, progress=False)
    return load_map(out)[0]


def test_order_is_stamp_then_source_then_index():
    stamps = [np.array([5, 1, 1]), np.array([1, 0]), np.array([5])]
    got = order_scans(stamps)
    want = sorted(((int(t), s, p) for s, st in enumerate(stamps) for p, t in enumerate(st)))
    assert got == [(s, p) for _, s, p in want]


def test_partitions_hold_whole_shards_and_spread_them():
    rng = np.random.default_rng(3)
    codes = rng.integers(0, 1 << 48, 50_000)
    part = partition_of(codes, 10, 7)
    prefix = codes >> 18
    # one partition per shard, whatever voxel of it is asked
    assert np.array_equal(partition_of(prefix << 18, 10, 7), part)
    assert np.bincount(part, minlength=7).min() > 50_000 / 7 * 0.8


@pytest.mark.parametrize("depth,partitions,picks", [(8, 1, [(0, 0)]), (10, 3, [(0, 1)]), (13, 16, [(0, 2), (0, 4)])])
def test_a_cast_gives_each_partition_its_updates_in_scan_order(depth, partitions, picks):
    """A cast task's pieces against the brute force: each scan's single-process updates (Morton
    order) filtered by partition, scan after scan."""
    from voxtool.maps.octree import scan_updates

    params = MapParams(0.2)
    *pieces, counts = cast_batch([str(SAMPLE)], SourceOptions(), params, picks, partitions, depth)
    scans = list(open_source(SAMPLE, SourceOptions()).scans)
    whole = [scan_updates(scans[p], params)[0] for _, p in picks]
    for p in range(partitions):
        expect = np.concatenate([u[partition_of(u >> 1, depth, partitions) == p] for u in whole])
        assert np.array_equal(pieces[p], expect)
    assert counts["voxel_updates"] == sum(len(u) for u in whole) == sum(len(x) for x in pieces) > 0


def test_one_map_from_workers_equals_the_single_process_map(client, tmp_path):
    one, report = distributed_build(client, [str(SAMPLE)], SourceOptions(), MapParams(0.2), SensorModel(),
                                    progress=False)
    assert same_leaves(one, single_map(SAMPLE, tmp=tmp_path))
    assert report["scans"] == 5 and report["workers"] == 2 and report["partitions"] == 4


def test_several_sources_make_one_map_in_order(client, tmp_path):
    # the sample split in two sources (no stamps: the first source's scans, then the second's)
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    for i, f in enumerate(sorted(SAMPLE.glob("*.pcd"))):
        shutil.copy(f, (a if i < 3 else b) / f.name)
    one, report = distributed_build(client, [str(b), str(a)], SourceOptions(), MapParams(0.2), SensorModel(),
                                    progress=False)
    assert report["scans"] == 5
    # b's scans come first: the same as a directory holding them in that order
    both = tmp_path / "both"
    both.mkdir()
    for k, f in enumerate(sorted(b.glob("*.pcd")) + sorted(a.glob("*.pcd"))):
        shutil.copy(f, both / f"{k:03d}.pcd")
    assert same_leaves(one, single_map(both, tmp=tmp_path))


def test_one_map_equals_octomap_reference_on_shared_data(client, shared_data, tmp_path):
    from test_parity_shared import voxel_sets_of_bt

    from voxtool.keys import expand_leaves

    one, _ = distributed_build(client, [str(shared_data / "norlab" / "pcd")], SourceOptions(), MapParams(0.2),
                               SensorModel(), progress=False)
    ref_occ, ref_free = voxel_sets_of_bt(next((shared_data / "norlab" / "reference").glob("*.bt")))
    lv = one.leaves()
    occ = lv.values > 0
    assert np.array_equal(np.sort(expand_leaves(lv.codes[occ], lv.depths[occ])), ref_occ)
    assert np.array_equal(np.sort(expand_leaves(lv.codes[~occ], lv.depths[~occ])), ref_free)


def test_sharded_snapshot_round_trips_and_is_checked(client, tmp_path):
    from voxtool.api import build_one_map

    out, first = tmp_path / "map", SourceOptions(stop=2)  # two scans: every part holds voxels, exports stay small
    result = build_one_map([SAMPLE], first, MapParams(0.2), SensorModel(), client, out, sharded=True,
                           progress=False)
    single = single_map(SAMPLE, options=first, tmp=tmp_path)
    assert same_leaves(sharded.load_sharded(out), single)
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["parts"]) == manifest["partitions"] == 4
    assert not list(tmp_path.glob(".voxtool-staging-*"))
    code, text, _ = cli("stats", out, "--json")
    assert code == 0
    streamed = json.loads(text)
    whole = json.loads(cli("stats", tmp_path / "single.vxm", "--json")[1])
    for key in ("occupied_voxels", "free_voxels", "occupied_bbox", "scans", "points"):
        assert streamed[key] == whole[key] == (result[key] if key in result else whole[key])
    # node counts of the whole tree, joined from the parts
    for key in ("bt_leaf_nodes", "bt_inner_nodes", "logodds_leaf_nodes", "logodds_inner_nodes"):
        assert streamed[key] == whole[key] > 0, key
    # exported part by part: the same .bt, byte for byte, and the same voxel centres
    assert cli("export", out, "-o", tmp_path / "a.bt")[0] == 0
    assert cli("export", tmp_path / "single.vxm", "-o", tmp_path / "b.bt")[0] == 0
    assert (tmp_path / "a.bt").read_bytes() == (tmp_path / "b.bt").read_bytes()
    o3d = pytest.importorskip("open3d")
    for suffix in (".ply", ".pcd"):
        clouds = []
        for src, name in ((out, "a"), (tmp_path / "single.vxm", "b")):
            assert cli("export", src, "-o", tmp_path / f"{name}{suffix}", "--free")[0] == 0
            pts = np.asarray(o3d.io.read_point_cloud(str(tmp_path / f"{name}{suffix}")).points)
            clouds.append(pts[np.lexsort(pts.T)])
        assert len(clouds[0]) == whole["occupied_voxels"] + whole["free_voxels"]
        assert np.array_equal(clouds[0], clouds[1]), suffix
    # the viewer's scene, read part by part, is the single snapshot's
    from voxtool.viewer import load_scene

    parted, whole_scene = load_scene(out), load_scene(tmp_path / "single.vxm")
    assert np.array_equal(np.unique(parted.occupied, axis=0), np.unique(whole_scene.occupied, axis=0))
    assert np.array_equal(parted.free, whole_scene.free) and parted.free_shift == whole_scene.free_shift
    # a part that changed, or a manifest that is missing, is an error naming the file
    part = out / manifest["parts"][1]["file"]
    blob = bytearray(part.read_bytes())
    blob[100] ^= 1
    part.write_bytes(bytes(blob))
    with pytest.raises(FormatError, match="part-00001.vxm"):
        sharded.load_sharded(out)
    (out / "manifest.json").unlink()
    code, _, err = cli("stats", out)
    assert code == 5 and "manifest.json" in err and err.count("\n") == 1


def test_fleet_rows_equal_per_source_runs(client, tmp_path):
    from voxtool.fleet import run_fleet

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "x.pcd").write_text("not a pcd\n")
    small = tmp_path / "small"
    small.mkdir()
    for f in sorted(SAMPLE.glob("*.pcd"))[:2]:
        shutil.copy(f, small / f.name)
    job = {"options": SourceOptions(), "params": MapParams(0.2), "sensor": SensorModel(), "backend": "octree",
           "backend_options": {}}
    out = tmp_path / "maps"
    out.mkdir()
    report = run_fleet("build", [SAMPLE, bad, small], job, out, client, progress=False)
    rows = {Path(r["source"]).name: r for r in report["rows"]}
    assert rows["bad"]["exit_code"] == 3 and "x.pcd" in rows["bad"]["error"]
    for name, src in (("sample", SAMPLE), ("small", small)):
        alone = build_map(src, SourceOptions(), MapParams(0.2), SensorModel(), progress=False)
        got = rows[name]["result"]
        for key in ("occupied_voxels", "free_voxels", "bt_leaf_nodes", "bt_inner_nodes", "scans", "points", "voxel_updates"):
            assert got[key] == alone[key], key
        assert (out / f"{name}.vxm").is_file()
    assert report["totals"]["ok"] == 2 and report["totals"]["failed"] == 1
    assert report["totals"]["occupied_voxels"] == rows["sample"]["result"]["occupied_voxels"] + \
        rows["small"]["result"]["occupied_voxels"]
    assert not (out / "bad.vxm").exists()


def test_stats_fleet_on_the_cli_exits_with_the_failure(sample_map, tmp_path):
    path, built = sample_map
    code, text, err = cli("stats", path, tmp_path / "missing.vxm", path, "--json")
    report = json.loads(text)
    assert code == 5 and "1 of 3 sources failed" in err
    assert [r["exit_code"] for r in report["rows"]] == [0, 5, 0]
    assert report["rows"][0]["result"]["occupied_voxels"] == built["occupied_voxels"]


def _worker_pids(client):
    return list(client.run(os.getpid).values())


def test_a_killed_worker_gives_the_same_map_or_a_clear_error(client, tmp_path, shared_data):
    from voxtool.cluster import ClusterError

    source = shared_data / "quick_shack" / "pcd"  # 241 scans: long enough to kill a worker mid-build
    out = {}

    def run():
        try:
            out["map"] = distributed_build(client, [str(source)], SourceOptions(), MapParams(0.1), SensorModel(),
                                           progress=False)[0]
        except ClusterError as err:
            out["error"] = err

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.time() + 60
    while time.time() < deadline and not any("cast" in str(k) for k in client.who_has()):
        time.sleep(0.05)
    victim = _worker_pids(client)[0]
    os.kill(victim, signal.SIGKILL)
    thread.join(180)
    assert not thread.is_alive()
    if "error" in out:  # allowed: one line, no output
        assert "\n" not in str(out["error"])
        print("killed worker: clear error:", out["error"])
    else:
        assert same_leaves(out["map"], single_map(source, 0.1, tmp=tmp_path))
        print("killed worker: the same map (recomputed from lineage)")
    client.wait_for_workers(2, timeout=60)  # the nanny restarts the worker for the other tests


def test_ctrl_c_stops_the_cluster_and_writes_nothing(tmp_path):
    import psutil

    out = tmp_path / "map.vxm"
    proc = subprocess.Popen([sys.executable, "-m", "voxtool.cli", "build", "--sample", "-o", str(out), "--workers",
                             "2", "--resolution", "0.05"], stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    line = proc.stderr.readline()  # the cluster is up once it prints its dashboard
    assert "dashboard" in line, line
    children = psutil.Process(proc.pid).children(recursive=True)
    assert children, "a local cluster runs worker processes"
    time.sleep(1.0)  # tasks are running (at 0.05 m the sample takes ~10 s on the cluster)
    proc.send_signal(signal.SIGINT)
    rest = proc.stderr.read()
    assert proc.wait(60) == 130, rest
    assert "interrupted" in rest
    assert not out.exists() and not list(tmp_path.iterdir())
    gone, alive = psutil.wait_procs(children, timeout=20)
    assert not alive, f"orphaned worker processes: {[p.pid for p in alive]}"


def test_one_source_encoded_on_workers_is_the_log_named(tmp_path):
    """`encode SRC -o r1.mcap --workers 1` writes that one log (not a directory of that name),
    packet for packet the log written without Dask."""
    from voxtool.codec.log import read_log

    here, there = tmp_path / "here" / "r1.mcap", tmp_path / "r1.mcap"  # one name: the robot is named after it
    here.parent.mkdir()
    short = ["--stop", 2, "--max-range", SAMPLE_LOG_RANGE, "--no-progress"]
    assert cli("encode", SAMPLE, "-o", here, *short)[0] == 0
    code, text, err = cli("encode", SAMPLE, "-o", there, *short, "--workers", "1", "--json")
    assert code == 0, err
    assert there.is_file() and json.loads(text)["rows"][0]["output"] == str(there)
    packets = [list(read_log(p)[1]) for p in (here, there)]
    assert len(packets[0]) > 0 and packets[0] == packets[1]


def test_scheduler_address_runs_on_a_cluster_started_by_dask_commands(tmp_path, monkeypatch):
    """The README's second way: `dask scheduler` and `dask worker ADDRESS` started apart (real
    processes), then `voxtool ... --scheduler ADDRESS`: one map equal to the single-process map,
    a fleet's rows, and an address nobody listens on as one line and exit 1."""
    info = tmp_path / "scheduler.json"
    dask = [sys.executable, "-m", "dask"]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen(dask + ["scheduler", "--port", "0", "--dashboard-address", ":0", "--scheduler-file",
                                      str(info)], **quiet)]
    try:
        deadline, address = time.time() + 60, None
        while address is None and time.time() < deadline:  # the file may be seen half written
            try:
                address = json.loads(info.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        assert address, "dask scheduler did not start"
        procs.append(subprocess.Popen(dask + ["worker", address, "--nworkers", "2", "--nthreads", "1"], **quiet))
        from dask.distributed import Client

        with Client(address, timeout="30s") as watcher:
            watcher.wait_for_workers(2, timeout=60)
        code, text, err = cli("build", SAMPLE, "-o", tmp_path / "map.vxm", "--scheduler", address, "--json",
                              "--no-progress")
        assert code == 0, err
        assert f"dask: {address}" in err
        built = json.loads(text)
        assert same_leaves(load_map(tmp_path / "map.vxm")[0], single_map(SAMPLE, tmp=tmp_path))
        # a fleet on the same cluster: a row per map
        code, text, err = cli("stats", tmp_path / "map.vxm", tmp_path / "single.vxm", "--scheduler", address, "--json")
        rows = json.loads(text)["rows"]
        assert code == 0 and [r["result"]["occupied_voxels"] for r in rows] == [built["occupied_voxels"]] * 2
    finally:
        # the workers first: without their scheduler they retry to reach it for seconds
        for p in reversed(procs):
            p.terminate()
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    # addresses that are not addresses, and nobody listening (Dask retries until
    # VOXTOOL_CONNECT_TIMEOUT, 10 s by default), last: the Client that failed to connect closes
    # itself later, from the garbage collector, and must not meet another command's Client
    monkeypatch.setenv("VOXTOOL_CONNECT_TIMEOUT", "1")
    for address, exit_code in (("127.0.0.1", 2), ("nonsense://x:1", 2), ("tcp://127.0.0.1:9", 1)):
        code, _, err = cli("build", SAMPLE, "-o", tmp_path / "x.vxm", "--scheduler", address)
        assert code == exit_code and err.count("\n") == 1 and address in err, err
        assert not (tmp_path / "x.vxm").exists()
