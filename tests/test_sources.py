"""Every source form of the same scans gives the same map; readers handle real PCL files."""

from __future__ import annotations

import numpy as np
import pytest
from ros2_writer import write_graph, write_mcap
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.api import build_map
from voxtool.config import MapParams, SensorModel
from voxtool.errors import SourceError
from voxtool.geometry import quat_to_matrix
from voxtool.sources import SourceOptions, open_source
from voxtool.sources.pcd import read_pcd
from voxtool.sources.poses import read_poses


@pytest.fixture(scope="module")
def scans():
    return [(pts, origin, yaw_quat(yaw)) for pts, origin, yaw in box_scene(4, 300, seed=21)]


def build_leaves(src, **opts):
    from voxtool.maps import make_backend
    from voxtool.pipeline import build

    stream = open_source(src, SourceOptions(**opts))
    m = make_backend("octree", MapParams(resolution=0.2), SensorModel())
    report = build(stream, m, progress=False)
    lv = m.leaves()
    return (lv.codes.tolist(), lv.depths.tolist(), lv.values.tolist()), report


def write_tum(path, scans, indexed=False):
    rows = []
    for i, (_, o, q) in enumerate(scans):
        o, q = [float(v) for v in o], [float(v) for v in q]
        prefix = f"{i} " if indexed else ""
        rows.append(f"{prefix}{i * 0.1:.3f} {o[0]!r} {o[1]!r} {o[2]!r} {q[1]!r} {q[2]!r} {q[3]!r} {q[0]!r}")
    path.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")


def write_ply(path, pts, fmt="binary_little_endian"):
    pts = np.asarray(pts, dtype="<f4")
    head = f"ply\nformat {fmt} 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    if fmt == "ascii":
        body = "".join(f"{p[0]!r} {p[1]!r} {p[2]!r}\n" for p in pts.astype(float).tolist()).encode()
    else:
        body = pts.astype(">f4" if "big" in fmt else "<f4").tobytes()
    path.write_bytes(head.encode() + body)


@pytest.fixture(scope="module")
def pcd_map(tmp_path_factory, scans):
    d = tmp_path_factory.mktemp("pcd")
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(d / f"{i}.pcd", pts, (*o, *q))
    return build_leaves(d)[0]


@pytest.mark.parametrize("kind", ["ascii", "binary_compressed"])
def test_pcd_data_kinds_give_the_same_map(tmp_path, scans, pcd_map, kind):
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(tmp_path / f"{i:03d}.pcd", pts, (*o, *q), kind=kind)
    assert build_leaves(tmp_path)[0] == pcd_map


def test_pcd_files_are_taken_in_numeric_order(tmp_path, scans, pcd_map):
    # names 9.pcd, 10.pcd sort wrongly as strings; scan order matters for the log-odds
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(tmp_path / f"{i + 8}.pcd", pts, (*o, *q))
    assert build_leaves(tmp_path)[0] == pcd_map


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_with_tum_poses_gives_the_same_map(tmp_path, scans, pcd_map, fmt):
    for i, (pts, _, _) in enumerate(scans):
        write_ply(tmp_path / f"{i}.ply", pts, fmt)
    write_tum(tmp_path / "poses.tum", scans)
    assert build_leaves(tmp_path, poses=str(tmp_path / "poses.tum"))[0] == pcd_map


def test_kitti_poses_equal_tum_poses(tmp_path, scans):
    rows = []
    for _, o, q in scans:
        m = np.hstack([quat_to_matrix(*q), np.asarray(o)[:, None]])
        rows.append(" ".join(repr(float(v)) for v in m.ravel()))
    (tmp_path / "k.txt").write_text("\n".join(rows) + "\n")
    write_tum(tmp_path / "t.txt", scans, indexed=True)
    kitti, tum = read_poses(tmp_path / "k.txt"), read_poses(tmp_path / "t.txt")
    for (_, a), (_, b) in zip(kitti, tum):
        assert np.allclose(a.rotation, b.rotation, atol=1e-12) and np.array_equal(a.translation, b.translation)


@pytest.mark.parametrize("mode", ["tf", "odom", "pose"])
def test_mcap_gives_the_same_map(tmp_path, scans, pcd_map, mode):
    path = tmp_path / "s.mcap"
    write_mcap(path, scans, mode)
    leaves, report = build_leaves(path, pose_topic={"odom": "/odom", "pose": "/pose"}.get(mode))
    assert leaves == pcd_map
    assert report.scans == len(scans) and report.first_stamp_ns == 1_000_000_000


def test_graph_gives_the_same_map(tmp_path, scans, pcd_map):
    path = tmp_path / "s.graph"
    write_graph(path, scans)
    assert build_leaves(path)[0] == pcd_map


def test_slicing_start_stop_every(tmp_path, scans):
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(tmp_path / f"{i}.pcd", pts, (*o, *q))
    stream = open_source(tmp_path, SourceOptions(start=1, stop=4, every=2))
    assert stream.count == 2
    assert [s.index for s in stream.scans] == [1, 3]


@pytest.mark.parametrize("mode,chunk,ties", [("tf", 1 << 20, False), ("odom", 1 << 20, False), ("tf", 1, False),
                                              ("odom", 1, True)])
def test_a_sliced_mcap_gives_the_whole_reads_scans(tmp_path, scans, mode, chunk, ties):
    """Slices start at the chunk the message index points to and reuse the file's poses: each
    scan is still the one the whole read gives at that index (points, pose, stamp), with one
    message per chunk, with clouds sharing a log time, and from a second open of the file."""
    path = tmp_path / "s.mcap"
    log_times = [1_000_000_000 + (i // 2) * 200_000_000 for i in range(len(scans))] if ties else None
    write_mcap(path, scans, mode, chunk_size=chunk, cloud_log_times=log_times)
    pose_topic = "/odom" if mode == "odom" else None
    whole = list(open_source(path, SourceOptions(pose_topic=pose_topic)).scans)
    assert len(whole) == len(scans) >= 4
    for start, stop, every in ((1, None, 2), (2, 3, 1), (0, None, 3), (3, None, 1)):
        got = list(open_source(path, SourceOptions(start=start, stop=stop, every=every, pose_topic=pose_topic)).scans)
        want = whole[start:stop:every]
        assert [s.index for s in got] == [s.index for s in want] and len(got) > 0
        for a, b in zip(got, want):
            assert np.array_equal(a.points, b.points) and np.array_equal(a.origin, b.origin) and a.stamp_ns == b.stamp_ns
    # the same path rewritten with other poses (same size): the new poses, not the remembered ones
    write_mcap(path, [(pts, (o[0] + 1.0, *o[1:]), q) for pts, o, q in scans], mode, chunk_size=chunk,
               cloud_log_times=log_times)
    moved = list(open_source(path, SourceOptions(start=1, pose_topic=pose_topic)).scans)
    assert np.allclose([s.origin[0] for s in moved], [s.origin[0] + 1.0 for s in whole[1:]])


@pytest.mark.parametrize("kind", ["pcd", "mcap", "graph"])
def test_a_slice_that_selects_no_scan_is_an_error(tmp_path, scans, kind):
    """Slicing past the end gives a clear error naming the source, not an empty map."""
    from voxtool.errors import ParameterError

    if kind == "pcd":
        for i, (pts, o, q) in enumerate(scans):
            write_pcd(tmp_path / f"{i}.pcd", pts, (*o, *q))
        path = tmp_path
    else:
        path = tmp_path / f"s.{kind}"
        (write_mcap if kind == "mcap" else write_graph)(path, scans)
    assert open_source(path, SourceOptions(start=len(scans) - 1)).count == 1
    with pytest.raises(ParameterError, match=f"{path.name}: --start {len(scans)} .* selects none of its {len(scans)} scans"):
        open_source(path, SourceOptions(start=len(scans)))


def test_nan_points_are_dropped_and_counted(tmp_path, scans):
    pts, o, q = scans[0]
    bad = pts.copy()
    bad[:5] = np.nan
    bad[5] = np.inf
    write_pcd(tmp_path / "0.pcd", bad, (*o, *q))
    r = build_map(tmp_path, SourceOptions(), MapParams(0.2), SensorModel(), progress=False)
    assert r["points"] == len(pts) and r["points_dropped"] == 6 and r["points_dropped_nonfinite"] == 6


def test_a_signalling_nan_in_a_binary_pcd_is_a_nan_without_a_warning():
    """A float32 signalling NaN widened beside a float64 field raises the FPU's invalid flag: it
    reads as a NaN point (dropped and counted later), with no RuntimeWarning on the way."""
    import warnings

    from voxtool.sources.pcd import parse_pcd

    for kind in ("binary", "binary_compressed"):
        head = (b"VERSION 0.7\nFIELDS x y z\nSIZE 8 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
                b"POINTS 2\nDATA " + kind.encode() + b"\n")
        x, y, z = np.array([1.0, 2.0]), np.array([0x7FA00000, 0x40400000], np.uint32).view(np.float32), np.ones(2, np.float32)
        if kind == "binary":
            body = np.rec.fromarrays([x, y, z], names="x,y,z").tobytes()
        else:  # column-major, stored uncompressed: an LZF stream of literal runs
            raw = x.tobytes() + y.tobytes() + z.tobytes()
            lzf = b"".join(bytes([len(raw[k:k + 32]) - 1]) + raw[k:k + 32] for k in range(0, len(raw), 32))
            body = np.array([len(lzf), len(raw)], "<u4").tobytes() + lzf
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            xyz = parse_pcd(head + body).xyz
        assert np.isnan(xyz[0, 1]) and np.array_equal(xyz[1], [2.0, 3.0, 1.0])


def test_min_range_drops_near_points(tmp_path, scans):
    pts, o, q = scans[0]
    write_pcd(tmp_path / "0.pcd", pts, (*o, *q))
    near = int((np.linalg.norm(pts.astype(np.float64), axis=1) < 1.0).sum())
    assert near > 0
    r = build_map(tmp_path, SourceOptions(min_range=1.0), MapParams(0.2, min_range=1.0), SensorModel(), progress=False)
    assert r["points_dropped_min_range"] == near


def test_no_viewpoint_treats_points_as_world_frame(tmp_path):
    pts = np.array([[1.0, 0.0, 0.0]], dtype=np.float32)
    write_pcd(tmp_path / "0.pcd", pts, (0, 0, 0, 0, 1, 0, 0))  # OpenNI's 180-degree VIEWPOINT
    flipped = next(open_source(tmp_path).scans).points
    kept = next(open_source(tmp_path, SourceOptions(no_viewpoint=True)).scans).points
    assert np.array_equal(kept, pts)
    assert np.allclose(flipped, [[1.0, 0.0, 0.0]])  # x unchanged by a rotation about x
    pts2 = np.array([[0.0, 1.0, 0.0]], dtype=np.float32)
    write_pcd(tmp_path / "0.pcd", pts2, (0, 0, 0, 0, 1, 0, 0))
    assert np.allclose(next(open_source(tmp_path).scans).points, [[0.0, -1.0, 0.0]])


def test_pose_file_row_count_must_match(tmp_path, scans):
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(tmp_path / f"{i}.pcd", pts, (*o, *q))
    write_tum(tmp_path / "p.txt", scans[:2])
    with pytest.raises(SourceError, match=r"p.txt: pose file has 2 poses for 4 scans"):
        open_source(tmp_path, SourceOptions(poses=str(tmp_path / "p.txt")))


def test_non_unit_quaternion_is_refused(tmp_path):
    (tmp_path / "p.txt").write_text("0 1 2 3 0 0 0 2\n")
    with pytest.raises(SourceError, match=r"p.txt:1: quaternion has norm 2.000000"):
        read_poses(tmp_path / "p.txt")


def test_real_pcl_fixtures_decode(shared_data):
    fixtures = shared_data / "pcl_format_fixtures"
    finite = {"frame_20121214T142255.814212.pcd": 271575, "table_scene_mug_stereo_textured.pcd": 209280,
              "cturtle.pcd": 167198, "bun0.pcd": 397, "colored_cloud.pcd": 1000}
    for name, n in finite.items():
        path = next(fixtures.rglob(name))
        cloud = read_pcd(path)
        assert int(np.isfinite(cloud.xyz).all(axis=1).sum()) == n
    assert read_pcd(fixtures / "pcl_logo.pcd").viewpoint == (0.0, 0.0, -2.0, 0.0, 1.0, 0.0, 0.0)
    assert not read_pcd(fixtures / "nhood_test.pcd").has_viewpoint


def test_rosbag2_written_mcap_decodes(shared_data):
    from voxtool.sources.mcap_ros2 import McapCloudSource

    src = McapCloudSource(shared_data / "mcap_format_fixtures" / "truck_icp_test_default_conf_0.mcap",
                          "cloud_2", "test", None)
    assert src.count == 1
    index, points, pose, stamp, _, _ = next(src.scans())
    assert index == 0
    assert points.shape == (34894, 3) and pose.is_identity() and stamp == 0


def test_tf_is_interpolated_at_the_cloud_stamp():
    from voxtool.geometry import matrix_to_quat
    from voxtool.sources.tf import STAMP_TOLERANCE_NS, StampedPoses

    series = StampedPoses()  # (x, y, z, qw, qx, qy, qz) at each stamp
    series.add(1_000, (0, 0, 0, 1, 0, 0, 0))
    series.add(3_000, (2, 0, 0, np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)))  # yaw 90 deg
    mid = series.at(2_000)
    assert np.allclose(mid.translation, [1, 0, 0])
    q = matrix_to_quat(mid.rotation)
    assert np.isclose(2 * np.arctan2(q[3], q[0]), np.pi / 4)  # slerp: yaw 45 deg
    assert series.at(3_000 + STAMP_TOLERANCE_NS) is not None
    assert series.at(3_000 + STAMP_TOLERANCE_NS + 1) is None
    assert series.at(1_000 - STAMP_TOLERANCE_NS - 1) is None


def test_pcd_directory_takes_its_scan_times_from_poses_txt_beside(tmp_path):
    """Without --poses, a PCD directory's scans keep their VIEWPOINT poses and take their times
    from the poses.txt beside them; a poses.txt that does not fit is a warning, not times."""
    import json

    from conftest import cli

    from voxtool.synthetic import Lidar, street, write_pcd_scans

    d = tmp_path / "scans"
    write_pcd_scans(street(3, seed=4, lidar=Lidar(beams=4, columns=64)), d)
    rows = (d / "poses.txt").read_text().splitlines()
    times = [1690309709.25, 1690309709.5, 1690309710.0]  # epoch seconds, not 10 Hz
    # poses in the file moved 5 m: the scans' poses must still be their VIEWPOINTs
    (d / "poses.txt").write_text("".join(
        f"{t} {float(r.split()[1]) + 5} {' '.join(r.split()[2:])}\n" for t, r in zip(times, rows)))
    viewpoint = [read_pcd(d / f"{i:06d}.pcd").viewpoint[:3] for i in range(3)]
    scans = list(open_source(d).scans)
    assert [s.stamp_ns for s in scans] == [int(round(t * 1e9)) for t in times]
    for s, vp in zip(scans, viewpoint):
        assert np.allclose(s.origin, vp, atol=1e-6)
    # a packet log of the directory is stamped with them
    code, out, err = cli("encode", d, "-o", tmp_path / "r.mcap", "--max-changes", 500, "--json", "--no-progress")
    assert code == 0, err
    assert json.loads(out)["packets"] >= 3
    from voxtool.codec.fusion import packets_of

    assert {p.stamp_ns for p in packets_of(tmp_path / "r.mcap")} == {int(round(t * 1e9)) for t in times}
    # a file with a row too few: a warning naming it, the scans without times
    (d / "poses.txt").write_text("".join(f"{t} 0 0 0 0 0 0 1\n" for t in times[:2]))
    with pytest.warns(UserWarning, match="poses.txt: 2 rows for 3 scans"):
        assert [s.stamp_ns for s in open_source(d).scans] == [0, 0, 0]
    code, _, err = cli("build", d, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 0 and err.count("voxtool: warning:") == 1 and "2 rows for 3 scans" in err, err


def test_outputs_are_named_by_the_path_ends_that_tell_sources_apart(tmp_path, scans):
    """`build data/*/pcd -o maps/` (the shared data's layout) once refused: every output would
    be pcd.vxm. Now each is named by the shortest end of its path that differs."""
    import json

    from conftest import cli

    from voxtool.sources import source_names

    for name in ("alpha", "beta"):
        d = tmp_path / "data" / name / "pcd"
        d.mkdir(parents=True)
        for i, (pts, o, q) in enumerate(scans):
            write_pcd(d / f"{i}.pcd", pts, (*o, *q))
    sources = [tmp_path / "data" / n / "pcd" for n in ("alpha", "beta")]
    code, text, err = cli("build", *sources, "-o", tmp_path / "maps", "--json", "--no-progress")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "maps").iterdir()) == ["alpha-pcd.vxm", "beta-pcd.vxm"]
    assert json.loads(text)["totals"]["ok"] == 2
    assert source_names([sources[0]]) == ["alpha-pcd"]  # a lone pcd/ folder: its dataset's name too (plot titles)
    assert source_names([tmp_path / "x" / "run.mcap", tmp_path / "y" / "run.mcap"]) == ["x-run", "y-run"]
    assert source_names([tmp_path / "a.mcap", tmp_path / "b.mcap"]) == ["a", "b"]
