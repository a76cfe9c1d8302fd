"""ROS logs whose clouds nothing poses (no /tf, no pose topic): `voxtool odometry` registers them
without reading a transform, and `--poses` poses a log's scans by message order. The logs are
written by rosbags' own writers from real scans (kaist03, sensor frame); the map they build with
the odometry's pose file equals the map of the same scans as PCD files posed by that file (another
reader, one pose file), and the odometry's track follows kaist03's own survey poses."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from bag_writer import write_bag
from conftest import cli
from scenes import write_pcd

from voxtool.io.mapfile import read_leaves
from voxtool.sources.pcd import read_pcd
from voxtool.sources.poses import read_poses

SCANS = 8
LOG_KINDS = ("ros1", "ros2-db3", "ros2-mcap", "mcap file")


@pytest.fixture(scope="module")
def kaist_scans(shared_data):
    """kaist03's first scans: (sensor-frame points, survey position) each."""
    files = sorted((shared_data / "kaist03" / "pcd").glob("*.pcd"))[:SCANS]
    clouds = [read_pcd(f) for f in files]
    return [(c.xyz.astype(np.float32), np.array(c.viewpoint[:3])) for c in clouds]


def unposed_log(tmp_path, kind, kaist_scans):
    """The scans as a log of PointCloud2 messages alone, 10 Hz from 1 s; 'mcap file': a ROS 2
    bag's storage file taken out of its folder (read by voxtool's MCAP reader, not rosbags)."""
    scans = [(pts, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)) for pts, _ in kaist_scans]
    if kind == "mcap file":
        folder = write_bag(tmp_path / "folder", scans, "ros2-mcap", mode="none")
        return shutil.copy(next(folder.glob("*.mcap")), tmp_path / "clouds.mcap")
    return write_bag(tmp_path / ("clouds.bag" if kind == "ros1" else "clouds"), scans, kind, mode="none")


def leaves(path):
    lv = read_leaves(path)[0]
    return lv.codes, lv.depths, lv.values


@pytest.mark.parametrize("kind", LOG_KINDS)
def test_odometry_poses_a_log_without_transforms_and_build_takes_its_file(tmp_path, kaist_scans, kind):
    pytest.importorskip("kiss_icp")
    log = unposed_log(tmp_path, kind, kaist_scans)
    code, _, err = cli("build", log, "-o", tmp_path / "unposed.vxm", "--no-progress")
    assert code == 3 and f"voxtool odometry {log} -o poses.txt" in err, err  # the hint names the way out
    code, _, err = cli("odometry", log, "-o", tmp_path / "poses.txt", "--no-progress")
    assert code == 0, err
    rows = read_poses(tmp_path / "poses.txt")
    assert [round(stamp, 6) for stamp, _ in rows] == [round(1.0 + 0.1 * i, 6) for i in range(SCANS)]
    # the track against the survey's, without any fit: each scan's distance from the first, within
    # 0.2 m over the 7.8 m travelled (the first registrations are off by 0.11 m at most)
    track = np.array([pose.translation for _, pose in rows])
    survey = np.array([where for _, where in kaist_scans])
    gap = np.abs(np.linalg.norm(track - track[0], axis=1) - np.linalg.norm(survey - survey[0], axis=1))
    assert np.linalg.norm(survey[-1] - survey[0]) > 7.0 and gap.max() < 0.2, gap

    code, _, err = cli("build", log, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "log.vxm", "--no-progress")
    assert code == 0, err
    pcd = tmp_path / "pcd"
    pcd.mkdir()
    for i, (pts, _) in enumerate(kaist_scans):
        write_pcd(pcd / f"{i:06d}.pcd", pts)
    code, _, err = cli("build", pcd, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "pcd.vxm", "--no-progress")
    assert code == 0, err
    got, want = leaves(tmp_path / "log.vxm"), leaves(tmp_path / "pcd.vxm")
    assert want[0].shape[0] > 10_000 and all(np.array_equal(a, b) for a, b in zip(got, want))


@pytest.mark.parametrize("kind", ["ros2-mcap", "mcap file"])
def test_a_pose_file_that_does_not_fit_the_log_is_refused_in_one_line(tmp_path, kaist_scans, kind):
    """Fewer rows than scan messages, or rows stamped apart from the messages (another log's
    file): one line naming the file, exit 3, no map; with a pose topic too: exit 2."""
    log = unposed_log(tmp_path, kind, kaist_scans)
    rows = [f"{1.0 + 0.1 * i:.6f} {0.5 * i} 0 0 0 0 0 1" for i in range(SCANS)]
    cases = {"short.txt": (rows[:-1], f"pose file has {SCANS - 1} poses"),
             "late.txt": ([f"{1.5 + 0.1 * i:.6f} {0.5 * i} 0 0 0 0 0 1" for i in range(SCANS)],
                          "a pose file of another log or topic")}
    for name, (lines, message) in cases.items():
        (tmp_path / name).write_text("\n".join(lines) + "\n")
        out = tmp_path / f"{name}.vxm"
        code, _, err = cli("build", log, "--poses", tmp_path / name, "-o", out, "--no-progress")
        assert code == 3 and message in err and str(tmp_path / name) in err and not out.exists(), err
        assert len(err.strip().splitlines()) == 1, err
    (tmp_path / "fits.txt").write_text("\n".join(rows) + "\n")
    code, _, err = cli("build", log, "--poses", tmp_path / "fits.txt", "--pose-topic", "/odom", "-o",
                       tmp_path / "both.vxm", "--no-progress")
    assert code == 2 and "--poses poses a log's scans by message order" in err, err
    code, _, err = cli("build", log, "--poses", tmp_path / "fits.txt", "-o", tmp_path / "fits.vxm", "--no-progress")
    assert code == 0, err


def test_a_graph_refuses_a_pose_file_instead_of_ignoring_it(tmp_path, shared_data):
    graph = shared_data / "kaist03" / "kaist03_21scans.graph"
    (tmp_path / "poses.txt").write_text("".join(f"{i} 0 0 0 0 0 0 1\n" for i in range(21)))
    code, _, err = cli("build", graph, "--poses", tmp_path / "poses.txt", "-o", tmp_path / "g.vxm", "--no-progress")
    assert code == 2 and "an OctoMap graph holds its scans' poses" in err and not (tmp_path / "g.vxm").exists(), err
