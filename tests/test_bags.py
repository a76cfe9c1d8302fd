"""ROS 1 bags and ROS 2 bag directories, written by rosbags' own writers, build the same map as
the same scans in PCD files; bad bags and bad scans give one line, or are skipped on request."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from bag_writer import BAG_KINDS, cloud, laser, write_bag
from conftest import cli
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.config import MapParams, SensorModel
from voxtool.errors import SourceError
from voxtool.sources import SourceOptions, open_source


def octree_of(src, **opts):
    """(the octree map of `src` at 0.2 m, the build report)."""
    from voxtool.maps import make_backend
    from voxtool.pipeline import build

    m = make_backend("octree", MapParams(resolution=0.2), SensorModel())
    return m, build(open_source(src, SourceOptions(**opts)), m, progress=False)


def leaves_of(src, **opts):
    m, report = octree_of(src, **opts)
    lv = m.leaves()
    return (lv.codes.tolist(), lv.depths.tolist(), lv.values.tolist()), report


def bag_path(tmp_path, kind):
    return tmp_path / ("s.bag" if kind == "ros1" else "s")


@pytest.fixture(scope="module")
def scans():
    return [(pts, origin, yaw_quat(yaw)) for pts, origin, yaw in box_scene(5, 400, seed=33)]


@pytest.fixture(scope="module")
def pcd_dir(tmp_path_factory, scans):
    d = tmp_path_factory.mktemp("pcd")
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(d / f"{i}.pcd", pts, (*o, *q))
    return d


@pytest.mark.parametrize("mode", ["tf", "odom"])
@pytest.mark.parametrize("kind", BAG_KINDS)
def test_a_bag_gives_the_pcd_map(tmp_path, scans, pcd_dir, kind, mode):
    path = write_bag(bag_path(tmp_path, kind), scans, kind, mode)
    leaves, report = leaves_of(path, pose_topic="/odom" if mode == "odom" else None)
    assert leaves == leaves_of(pcd_dir)[0]
    assert report.scans == len(scans) and report.first_stamp_ns == 1_000_000_000


def test_the_storage_file_of_a_ros2_bag_reads_as_its_bag(tmp_path, scans, pcd_dir):
    path = write_bag(tmp_path / "b", scans, "ros2-mcap")
    storage = next(path.glob("*.mcap"))
    assert open_source(storage).kind == "rosbag2"
    assert leaves_of(storage)[0] == leaves_of(pcd_dir)[0]


@pytest.mark.parametrize("kind", [k for k in BAG_KINDS if k != "ros1"])
def test_a_ros2_bag_with_blank_metadata_fields_reads_as_ros2_bag_reads_it(tmp_path, scans, pcd_dir, kind):
    """Some rosbag2 releases wrote `storage_identifier: ""` or a topic's `serialization_format:
    ""` (TIER IV's published decoder test bags have both): read with the storage the files'
    extension says and CDR, as `ros2 bag` does; the bag's own folder is left as it was."""
    path = write_bag(bag_path(tmp_path, kind), scans, kind)
    meta = path / "metadata.yaml"
    text = meta.read_text()
    blank = re.sub(r"(storage_identifier:) \S+", r'\1 ""', re.sub(r"(serialization_format:) \S+", r'\1 ""', text))
    assert blank != text
    meta.write_text(blank)
    files = sorted(p.name for p in path.iterdir())
    assert leaves_of(path)[0] == leaves_of(pcd_dir)[0]
    assert meta.read_text() == blank and sorted(p.name for p in path.iterdir()) == files


@pytest.mark.parametrize("kind", ["ros1", "ros2-db3"])
def test_laserscans_are_rays_with_no_returns_clearing(tmp_path, kind):
    """A LaserScan's readings become points at their angles in the scan plane. A reading at or
    above range_max, or +Inf, is the scanner's "no return": its beam clears free space up to
    range_max and marks no hit. Below range_min, NaN and -Inf are dropped and counted. Truth:
    the real OctoMap (pyoctomap) inserting the valid points and, for each no-return beam, a point
    beyond range_max with max_range = range_max."""
    pyoctomap = pytest.importorskip("pyoctomap")
    from test_octree import finest_values

    from voxtool.geometry import Pose

    rng = np.random.default_rng(5)
    angle_min, inc, n, range_max, res = -2.0, 0.01, 400, 30.0, 0.2
    rows = [rng.uniform(0.5, 8.0, n) for _ in range(3)]
    for r in rows:
        r[::37] = np.inf
        r[5::41] = 50.0  # beyond range_max: no return
        r[11::47] = range_max  # at range_max: no return
        r[7::43] = np.nan
        r[9::53] = 0.05  # below range_min
    poses = [((0.3 * i, 0.1, 0.5), yaw_quat(0.2 * i)) for i in range(3)]
    path = write_bag(bag_path(tmp_path, kind), [(None, o, q) for o, q in poses], kind,
                     messages=lambda T, k, i, ns: laser(T, k, rows[i], angle_min, inc, ns))
    tree = pyoctomap.OcTree(res)
    expected_dropped = expected_misses = 0
    a = angle_min + inc * np.arange(n)
    for (o, q), r in zip(poses, rows):
        hit = np.isfinite(r) & (r >= 0.1) & (r < range_max)
        miss = (r >= range_max) & ~np.isnan(r)
        expected_dropped += int((~hit & ~miss).sum())
        expected_misses += int(miss.sum())
        far = np.where(miss, 2 * range_max, r)
        sensor = np.stack([far * np.cos(a), far * np.sin(a), np.zeros(n)], axis=1)[hit | miss]
        world = Pose.from_quat(o, *q).apply(sensor.astype(np.float32)).astype(np.float64)
        tree.insertPointCloud(world, np.asarray(o, dtype=np.float64), max_range=range_max)
    m, report = octree_of(path)
    ours = finest_values(m)
    leaves, inner = m.node_counts()
    assert (leaves, leaves + inner) == (tree.getNumLeafNodes(), tree.size())
    for leaf in tree.begin_leafs():  # every OctoMap leaf answers the same log-odds from ours
        c = np.array(leaf.getCoordinate())
        key = tuple(int(v) for v in np.floor(c / res).astype(np.int64) + 32768)
        assert ours[key] == pytest.approx(tree.search(c).getLogOdds(), abs=0)
    assert report.points_dropped_nonfinite == expected_dropped > 0
    assert report.no_returns == expected_misses > 0
    # no phantom arc of walls at range_max, and the cleared beams reach past the hits
    keys = np.array(list(ours.keys()))
    occupied = keys[np.array([ours[tuple(k)] > 0 for k in keys])]
    dist = np.linalg.norm((keys - 32768 + 0.5) * res - np.array([0.3, 0.1, 0.5]), axis=1)
    assert np.linalg.norm((occupied - 32768 + 0.5) * res - np.array([0.3, 0.1, 0.5]), axis=1).max() < 9.0
    assert dist.max() > 25.0


@pytest.mark.parametrize("kind", BAG_KINDS)
def test_bag_problems_are_one_line(tmp_path, scans, kind):
    path = write_bag(bag_path(tmp_path, kind), scans, kind)
    out = tmp_path / "m.vxm"
    code, _, err = cli("build", path, "-o", out, "--topic", "/nope", "--no-progress")
    assert code == 3 and err.count("\n") == 1 and "topic '/nope' is not a PointCloud2, LaserScan or VelodyneScan topic" in err, err
    code, _, err = cli("build", path, "-o", out, "--pose-topic", "/points", "--no-progress")
    assert code == 3 and err.count("\n") == 1 and "pose topic '/points' is not Odometry, PoseStamped, PoseWithCovarianceStamped or TransformStamped" in err, err
    nopose = write_bag(bag_path(tmp_path / "nopose", kind) if kind != "ros1" else tmp_path / "nopose.bag",
                       scans, kind, mode="odom")
    code, _, err = cli("build", nopose, "-o", out, "--no-progress")
    assert code == 3 and err.count("\n") == 1 and "no transform reaches the scan frame 'lidar'" in err, err
    assert not out.exists()


@pytest.mark.parametrize("kind", BAG_KINDS)
def test_a_truncated_bag_is_one_line_naming_it(tmp_path, scans, kind):
    path = write_bag(bag_path(tmp_path, kind), scans, kind)
    data = path if path.is_file() else next(p for p in path.iterdir() if p.suffix in (".db3", ".mcap"))
    data.write_bytes(data.read_bytes()[: data.stat().st_size * 2 // 3])
    out = tmp_path / "m.vxm"
    code, _, err = cli("build", path, "-o", out, "--no-progress")
    assert code == 3 and err.count("\n") == 1 and str(path) in err, err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["ros1", "ros2-mcap"])
def test_bad_scans_skip_gives_the_map_of_the_good_scans(tmp_path, scans, kind):
    """A message that cannot be decoded stops the build by default; with --bad-scans skip it is
    skipped with a warning line and counted, and the map is the map of the other scans."""
    def messages(T, k, i, ns):
        return b"\x00\x01\x02" if i == 2 else cloud(T, k, scans[i][0], ns)

    path = write_bag(bag_path(tmp_path, kind), scans, kind, messages=messages)
    out = tmp_path / "m.vxm"
    code, _, err = cli("build", path, "-o", out, "--no-progress")
    assert code == 3 and err.count("\n") == 1 and "message 2 of '/points'" in err, err
    code, text, err = cli("build", path, "-o", out, "--no-progress", "--bad-scans", "skip", "--json")
    assert code == 0, err
    assert err.count("voxtool: warning: skipped scan 2:") == 1, err
    result = json.loads(text)
    assert result["scans"] == 4 and result["scans_skipped"] == 1 and result["skipped_scans"][0]["index"] == 2
    d = tmp_path / "good"
    d.mkdir()
    for i, (pts, o, q) in enumerate(scans):
        if i != 2:
            write_pcd(d / f"{i}.pcd", pts, (*o, *q))
    from voxtool.io.mapfile import read_leaves

    got = read_leaves(out)[0]
    assert (got.codes.tolist(), got.depths.tolist(), got.values.tolist()) == leaves_of(d)[0]


def test_bad_scans_skip_in_a_pcd_directory(tmp_path, scans, pcd_dir):
    d = tmp_path / "scans"
    d.mkdir()
    for f in pcd_dir.iterdir():
        (d / f.name).write_bytes(f.read_bytes())
    bad = d / "1.pcd"
    bad.write_bytes(bad.read_bytes()[:300])  # truncated inside its data
    with pytest.raises(SourceError, match="1.pcd"):
        leaves_of(d)
    with pytest.warns(UserWarning, match=r"skipped scan 1: .*1\.pcd"):
        leaves, report = leaves_of(d, bad_scans="skip")
    bad.unlink()
    assert leaves == leaves_of(d)[0] and report.scans == len(scans) - 1 and report.skipped[0]["index"] == 1


def test_a_dataset_root_names_its_scan_folders(tmp_path, scans, pcd_dir):
    for name in ("alpha", "beta"):
        (tmp_path / "root" / name / "pcd").mkdir(parents=True)
        for f in pcd_dir.iterdir():
            (tmp_path / "root" / name / "pcd" / f.name).write_bytes(f.read_bytes())
    write_bag(tmp_path / "root" / "gamma", scans[:1], "ros2-db3")
    code, _, err = cli("build", tmp_path / "root", "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 3 and err.count("\n") == 1, err
    assert "its sub-folders do: alpha/pcd, beta/pcd, gamma" in err, err


def test_real_scans_in_bags_equal_the_pcd_build(tmp_path, shared_data):
    """kaist03's real Ouster scans, written into a ROS 1 bag and a ROS 2 (.db3) bag by rosbags
    with their VIEWPOINT poses on /tf, give the PCD directory's map voxel for voxel."""
    from voxtool.sources.pcd import read_pcd

    files = sorted((shared_data / "kaist03" / "pcd").glob("*.pcd"))[:4]
    real = []
    for f in files:
        c = read_pcd(f)
        real.append((c.xyz, c.viewpoint[:3], c.viewpoint[3:]))
    pcd = leaves_of(files[0].parent, stop=4)[0]
    for kind in ("ros1", "ros2-db3"):
        path = write_bag(bag_path(tmp_path / kind, kind) if kind != "ros1" else tmp_path / "k.bag", real, kind)
        assert leaves_of(path)[0] == pcd, kind
