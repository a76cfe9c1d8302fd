"""The KITTI / SemanticKITTI layout as a source, `clean --truth` with its labels, and `voxtool
odometry` (KISS-ICP) for scans without poses, on real KITTI frames (skipped without them)."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest
from conftest import cli

from voxtool.geometry import Pose
from voxtool.sources.kitti import MOVING_CLASSES, lidar_poses
from voxtool.sources.poses import read_poses


def relative(poses: list[Pose]) -> list[Pose]:
    """The poses in the first one's frame."""
    first = poses[0]
    return [Pose(first.rotation.T @ p.rotation, first.rotation.T @ (p.translation - first.translation)) for p in poses]


def errors(a: list[Pose], b: list[Pose]) -> tuple[float, float]:
    """Largest translation (m) and rotation (degrees) difference between two trajectories."""
    t = max(float(np.linalg.norm(p.translation - q.translation)) for p, q in zip(a, b))
    r = max(float(np.degrees(np.arccos(np.clip((np.trace(p.rotation.T @ q.rotation) - 1) / 2, -1, 1))))
            for p, q in zip(a, b))
    return t, r


@pytest.fixture
def sequences(kitti_sample, tmp_path):
    for seq in ("00", "05"):
        shutil.copytree(kitti_sample / seq, tmp_path / seq)
    return tmp_path


@pytest.mark.parametrize("seq", ["00", "05"])
def test_odometry_agrees_with_kittis_lidar_poses(sequences, tmp_path, seq):
    """KISS-ICP on the raw scans (no pose read) and KITTI's survey poses moved into the LiDAR
    frame through calib.txt's Tr agree within odometry's drift (about 1 % of 5-7 m). Two
    independent paths: a wrong Tr (the camera's axes taken as the LiDAR's) would differ by metres."""
    pytest.importorskip("kiss_icp")
    out = tmp_path / f"odom{seq}.txt"
    code, text, err = cli("odometry", sequences / seq, "-o", out, "--json", "--no-progress")
    assert code == 0, err
    report = json.loads(text)
    assert report["scans"] == 10 and report["format"] == "tum"  # times.txt gives times
    rows = read_poses(out)
    assert [round(t, 6) for t, _ in rows] == pytest.approx(np.loadtxt(sequences / seq / "times.txt")[:10], abs=1e-6)
    truth = relative(lidar_poses(sequences / seq, list(range(10))))
    odometry = [pose for _, pose in rows]
    trans, rot = errors(odometry, truth)
    # the command says how far it is from the sequence's own poses: an ATE under the largest error here
    against = report["against_source_poses"]
    assert 0 < against["ate_max_m"] <= trans + 1e-6 and against["end_drift_percent_of_path"] < 3
    assert np.linalg.norm(truth[-1].translation) > 4.0  # the car moved
    assert trans < 0.15 and rot < 0.5, (trans, rot)
    camera_axes = relative([Pose(np.eye(3), p.translation) for p in lidar_poses(sequences / seq, list(range(10)))])
    wrong = [Pose(p.rotation, np.array([p.translation[2], -p.translation[0], -p.translation[1]])) for p in camera_axes]
    assert errors(odometry, wrong)[0] > 1.0 or errors(odometry, camera_axes)[0] > 1.0


def test_a_kitti_sequence_builds_and_the_odometry_map_matches_the_survey_map(sequences, tmp_path):
    """`build sequences/05` poses the scans by poses.txt and Tr; the map built from the odometry's
    pose file shares most occupied voxels with it (0.2 m voxels, 10 scans)."""
    pytest.importorskip("kiss_icp")
    seq = sequences / "05"
    code, text, err = cli("build", seq, "-o", tmp_path / "survey.vxm", "--json", "--no-progress")
    assert code == 0, err
    report = json.loads(text)
    assert report["scans"] == 10 and report["points"] == sum(
        (seq / "velodyne" / f"{i:06d}.bin").stat().st_size // 16 for i in range(10))
    assert cli("odometry", seq, "-o", tmp_path / "odom.txt", "--no-progress")[0] == 0
    code, _, err = cli("build", seq, "--poses", tmp_path / "odom.txt", "-o", tmp_path / "odom.vxm", "--no-progress")
    assert code == 0, err
    from voxtool.api import load_leaves
    from voxtool.keys import expand_leaves, morton_decode

    def occupied(path):  # the occupied voxels' keys as one integer each
        leaves, _, thr, _ = load_leaves(path)
        occ = leaves.values > np.float32(thr)
        k = morton_decode(expand_leaves(leaves.codes[occ], leaves.depths[occ])).astype(np.int64)
        return k, (k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2]

    # the odometry map is in the first scan's frame: the survey poses, moved to it, build the reference
    survey = relative(lidar_poses(seq, list(range(10))))
    rows = [" ".join(f"{v:.9e}" for v in np.c_[p.rotation, p.translation].ravel()) for p in survey]
    (tmp_path / "survey.txt").write_text("\n".join(rows) + "\n")
    assert cli("build", seq, "--poses", tmp_path / "survey.txt", "-o", tmp_path / "s0.vxm", "--no-progress")[0] == 0
    (_, a), (kb, _) = occupied(tmp_path / "s0.vxm"), occupied(tmp_path / "odom.vxm")
    near = np.zeros(len(kb), bool)  # an odometry voxel with a survey voxel in its 3x3x3 neighbourhood
    for d in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1]), -1).reshape(-1, 3):
        k = kb + d
        near |= np.isin((k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2], a)
    assert len(a) > 50_000 and near.mean() > 0.95, near.mean()


def test_clean_truth_scores_against_the_semantickitti_labels(sequences, tmp_path):
    """SA, DA and AA of `clean --truth` equal the scores counted here from its --labels output and
    the .label files read directly (moving classes 252-259)."""
    seq = sequences / "05"
    code, text, err = cli("clean", seq, "--labels", tmp_path / "l.npy", "--truth", seq / "labels", "--json",
                          "--no-progress")
    assert code == 0, err
    got = json.loads(text)["accuracy"]
    labels = np.load(tmp_path / "l.npy").astype(bool)
    semantic = np.concatenate([np.fromfile(seq / "labels" / f"{i:06d}.label", np.uint32) & 0xFFFF for i in range(10)])
    truth = (semantic >= MOVING_CLASSES.start) & (semantic <= 259)
    assert labels.shape == truth.shape and truth.sum() == got["dynamic_points"] > 1000
    sa = 100 * (~labels & ~truth).sum() / (~truth).sum()
    da = 100 * (labels & truth).sum() / truth.sum()
    assert got["SA"] == pytest.approx(sa, abs=1e-3) and got["DA"] == pytest.approx(da, abs=1e-3)
    assert got["AA"] == pytest.approx(np.sqrt(sa * da), abs=1e-3)
    assert got["SA"] > 99 and got["DA"] > 80  # real movers in the first second of sequence 05
    # the same truth as one .npy of per-point labels (--labels' layout): the same scores, in the summary's row
    # (a truth of the wrong length: test_clean.test_a_static_world_loses_no_point)
    np.save(tmp_path / "truth.npy", truth.astype(np.uint8))
    code, text, err = cli("clean", seq, "-o", tmp_path / "s.pcd", "--truth", tmp_path / "truth.npy", "--no-progress")
    assert code == 0, err
    assert (f"against --truth    SA {got['SA']:.2f} % of {got['static_points']:,} static points kept, DA "
            f"{got['DA']:.2f} % of {got['dynamic_points']:,} dynamic removed, AA {got['AA']:.2f}\n") in text, text


@pytest.mark.parametrize("breakage, says", [
    (lambda s: (s / "poses.txt").unlink(), "no poses.txt (nor ../../poses/05.txt): the scans have no poses; estimate "
                                           "them with `voxtool odometry"),
    (lambda s: (s / "calib.txt").write_text((s / "calib.txt").read_text().split("Tr:")[0]), "calib.txt: no Tr line"),
    (lambda s: (s / "velodyne" / "000003.bin").write_bytes(b"x" * 30), "000003.bin: 30 bytes is not a whole number"),
    (lambda s: (s / "labels" / "000002.label").write_bytes(b"\0" * 40), "000002.label: 10 labels for a scan of"),
])
def test_a_broken_sequence_is_one_line(sequences, tmp_path, breakage, says):
    seq = sequences / "05"
    breakage(seq)
    code, _, err = cli("clean", seq, "-o", tmp_path / "s.pcd", "--truth", seq / "labels", "--no-progress")
    assert code == 3 and err.count("\n") == 1 and says in err, err
    assert not (tmp_path / "s.pcd").exists()


def test_scans_without_poses_are_warned_and_odometry_writes_kitti_rows_without_times(kitti_sample, tmp_path):
    """A driver's dump (PCD files with PCL's identity VIEWPOINT, no times): build warns that every
    scan was taken at the origin; odometry writes KITTI rows, which build reads back."""
    pytest.importorskip("kiss_icp")
    from scenes import write_pcd

    from voxtool.sources.kitti import read_bin

    d = tmp_path / "dump"
    d.mkdir()
    for i in range(4):
        write_pcd(d / f"{i}.pcd", read_bin(kitti_sample / "05" / "velodyne" / f"{i:06d}.bin"), (0, 0, 0, 1, 0, 0, 0))
    code, _, err = cli("build", d, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 0 and "none of its 4 scans has a pose" in err and "voxtool odometry" in err, err
    code, text, err = cli("odometry", d, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0 and json.loads(text)["format"] == "kitti", err
    rows = read_poses(tmp_path / "p.txt")
    assert len(rows) == 4 and all(t is None for t, _ in rows) and rows[3][1].translation[0] > 1.0
    code, _, err = cli("build", d, "--poses", tmp_path / "p.txt", "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 0 and "has a pose" not in err, err


def test_odometry_without_kiss_icp_names_the_extra(kitti_sample, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "kiss_icp", None)  # an import of it fails, as where it is not installed
    monkeypatch.setitem(sys.modules, "kiss_icp.config", None)
    code, _, err = cli("odometry", kitti_sample / "05", "-o", tmp_path / "p.txt", "--no-progress")
    assert code == 2 and "pip install 'voxtool-lidar[odometry]'" in err and err.count("\n") == 1, err
    assert not (tmp_path / "p.txt").exists()


def test_a_real_drivers_dump_without_poses_is_warned_and_mapped_sharper_with_odometry(udacity_dump, tmp_path):
    """22 real scans from a moving car, saved by PCL with no pose: build warns and maps them as one
    static sensor's (smeared); with the odometry's poses the same scans give a sharper map, fewer
    occupied voxels for the same surfaces, and the car travelled forwards."""
    pytest.importorskip("kiss_icp")
    code, text, err = cli("build", udacity_dump, "-o", tmp_path / "static.vxm", "--json", "--no-progress")
    assert code == 0 and "none of its 22 scans has a pose" in err, err
    smeared = json.loads(text)["occupied_voxels"]
    code, text, err = cli("odometry", udacity_dump, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0, err
    assert json.loads(text)["path_m"] > 10 and json.loads(text)["against_source_poses"] is None  # it has none
    code, text, err = cli("build", udacity_dump, "--poses", tmp_path / "p.txt", "-o", tmp_path / "m.vxm", "--json",
                          "--no-progress")
    assert code == 0 and "has a pose" not in err, err
    assert json.loads(text)["occupied_voxels"] < 0.9 * smeared  # measured: 74,634 against 88,593


def test_a_sequence_without_tr_is_listed_and_builds_with_kitti_tr(sequences, tmp_path):
    """mini-KITTI as published: calib.txt without Tr. info lists the scans and names both ways out;
    build refuses in one line naming them; --kitti-tr (a calib.txt or its 12 numbers) builds the
    map of the sequence with Tr; the sequence's own (camera) poses.txt is refused as --poses."""
    from voxtool.io.mapfile import load_map

    seq = sequences / "00"
    calib = seq / "calib.txt"
    with_tr = tmp_path / "calib_with_tr.txt"
    shutil.copy(calib, with_tr)
    tr_line = next(ln for ln in calib.read_text().splitlines() if ln.startswith("Tr:"))
    calib.write_text("".join(ln + "\n" for ln in calib.read_text().splitlines() if not ln.startswith("Tr:")))
    code, text, err = cli("info", seq, "--json")
    assert code == 0, err
    got = json.loads(text)
    assert got["scans"] == 10 and got["pose_source"].startswith("none: ")
    assert "voxtool odometry" in got["pose_source"] and "--kitti-tr" in got["pose_source"]
    code, _, err = cli("build", seq, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 3 and "voxtool odometry" in err and "--kitti-tr" in err and err.count("\n") == 1, err
    numbers = ",".join(tr_line.split(":")[1].split())
    maps = []
    for tr in (str(with_tr), numbers):
        out = tmp_path / f"m{len(maps)}.vxm"
        code, _, err = cli("build", seq, "-o", out, "--kitti-tr", tr, "--no-progress")
        assert code == 0, err
        maps.append(load_map(out)[0].leaves())
    shutil.copy(with_tr, calib)
    assert cli("build", seq, "-o", tmp_path / "ref.vxm", "--no-progress")[0] == 0
    ref = load_map(tmp_path / "ref.vxm")[0].leaves()
    for got_map in maps:
        assert np.array_equal(got_map.codes, ref.codes) and np.array_equal(got_map.values, ref.values)
    code, _, err = cli("build", seq, "-o", tmp_path / "c.vxm", "--poses", seq / "poses.txt", "--no-progress")
    assert code == 3 and "the sequence's own poses, the camera's" in err
    longer = tmp_path / "longer.txt"
    longer.write_text((seq / "poses.txt").read_text())
    code, _, err = cli("build", seq, "-o", tmp_path / "c.vxm", "--poses", longer, "--no-progress")
    assert code == 3 and "for 10 scans (a whole sequence's or a longer run's file?" in err, err


def test_info_spans_the_times_from_kittis_first_scan_at_zero(sequences):
    times = np.loadtxt(sequences / "00" / "times.txt")[:10]
    assert times[0] == 0.0
    code, text, err = cli("info", sequences / "00", "--json")
    assert code == 0, err
    assert json.loads(text)["time_span"]["seconds"] == pytest.approx(times[-1] - times[0], abs=1e-6)
