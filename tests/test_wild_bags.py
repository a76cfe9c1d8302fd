"""Bags as other people record them: every real bag of ../shared/data/bags gives a map or one
line that says what to do (exit 3), never a traceback; and a generated sweep over the structural
cases real bags show (no /tf, only /odom, only /tf_static, legacy tf, a frame missing from the
tree, scans before the first transform, an empty bag, a truncated recording, a pre-2.0 bag),
each bag written by rosbags' own writer."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from bag_writer import _store, _transform, cloud
from conftest import cli
from scenes import box_scene, yaw_quat

# what each real bag needs, as its PROVENANCE.md says: the options that build it (None: it
# cannot be built, and the one line must say what to do)
REAL_BAGS = {
    "johnny5_data.bag": ([], "left out 2 scans (0, 1) taken before the first transform"),
    "robo_lape_2018-09-25-21-42-18.bag": ([], "left out scan 0 taken before the first transform"),
    "robo_lape_2018-09-20-19-57-08.bag": (None, "pose them with --pose-topic /odom"),
    "lidarme_lidar.bag": (None, "pose them with --world-frame laser"),
    "sick_rms_1xxx_lms_1xx_movement_off.bag": (None, "choose one with --topic"),
    "scan_tools_laser_scan_matcher_demo.bag": (None, "--bad-scans skip"),
    "scan_tools_laser_scan_splitter_demo.bag": (None, "older than format 2.0"),
}
# and what builds the ones that need an option, as the one line told
REAL_BAG_FIXES = {
    "robo_lape_2018-09-20-19-57-08.bag": ["--pose-topic", "/odom"],
    "lidarme_lidar.bag": ["--world-frame", "laser"],
    "sick_rms_1xxx_lms_1xx_movement_off.bag": ["--topic", "/sick_lms_1xx/scan"],
    "scan_tools_laser_scan_matcher_demo.bag": ["--bad-scans", "skip", "--world-frame", "laser"],
}


def _build(tmp_path, path, *options):
    out = tmp_path / "m.vxm"
    out.unlink(missing_ok=True)
    code, text, err = cli("build", path, "-o", out, "--no-progress", "--json", *options)
    return code, (json.loads(text) if code == 0 else None), err, out


def _one_error_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if not ln.startswith("voxtool: warning:")]
    assert len(lines) == 1 and lines[0].startswith("voxtool: error: "), err
    return lines[0]


def _corpus_bags(shared_data):
    folder = shared_data / "bags"
    found = sorted(p.name for p in folder.glob("*.bag")) if folder.is_dir() else []
    if not found:
        pytest.skip("no bags in ../shared/data/bags")
    return folder, found


def test_every_real_bag_gives_a_map_or_one_line_that_says_what_to_do(tmp_path, shared_data):
    folder, found = _corpus_bags(shared_data)
    for name in found:
        options, says = REAL_BAGS.get(name, ([], ""))
        code, report, err, out = _build(tmp_path, folder / name, *(options or []))
        if options is None:
            assert code == 3 and not out.exists(), (name, err)
            assert says in _one_error_line(err), (name, err)
            if name not in REAL_BAG_FIXES:  # (a pre-2.0 bag: only ROS 1 itself rewrites it)
                continue
            code, report, err, out = _build(tmp_path, folder / name, *REAL_BAG_FIXES[name])
        assert code == 0, (name, err)
        assert "Traceback" not in err
        assert report["scans"] > 0 and report["occupied_voxels"] > 0 and out.exists(), name
        if says and options is not None:
            assert says in err, (name, err)


def test_a_damaged_index_is_read_record_by_record_with_skip(tmp_path, shared_data):
    """The 2010 demo bag's index records declare lengths that do not match their counts:
    rosbags cannot open it. Read record by record, it gives every scan its index lists."""
    from rosbags.rosbag1 import Reader

    folder, found = _corpus_bags(shared_data)
    name = "scan_tools_laser_scan_matcher_demo.bag"
    if name not in found:
        pytest.skip(f"{name} absent")
    with pytest.raises(AssertionError):
        Reader(folder / name).open()
    code, report, err, _ = _build(tmp_path, folder / name, "--bad-scans", "skip", "--world-frame", "laser")
    assert code == 0, err
    # every message the bag's two index records list (278 + 82), each message record once
    data = (folder / name).read_bytes()
    assert report["scans"] == 278 + 82 == data.count(b"op=\x02")
    assert "2 damaged records were passed over (0 bytes lost" in err


# ---- the generated sweep -------------------------------------------------------------------------

LEGACY_TF = "tf/msg/tfMessage"


def _legacy_store():
    from rosbags.typesys import get_types_from_msg

    store = _store("ros1")
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", LEGACY_TF))
    return store


def write_wild_bag(path, scans, *, tf: str = "tf", tf_from: int = 0, scan_frame: str = "lidar",
                   tf_child: str = "lidar", static_only: bool = False, odom: bool = False, chunk: int = 1 << 20,
                   late_stamps: bool = False, odom_from: int = 0, odom_stamp_ns: int | None = None):
    """A ROS 1 bag of PointCloud2 scans at 10 Hz: tf "tf" (tf2), "legacy" (tf/tfMessage), "mixed"
    (both, on two connections of /tf, scan by scan in turn, as a bag of several nodes has them) or
    "none"; `odom_from`: the Odometry topic from that scan on; `odom_stamp_ns`: its stamps start
    there instead of at the scans' (a simulator's clock beside the sensor's); `late_stamps`: every transform also sent again 0.2 s late (out of order) and once
    more with its own stamp (repeated), as several publishers of one edge give; transforms from scan `tf_from` on (scans before it precede the first transform);
    `static_only`: one /tf_static message holds the sensor pose; `odom`: an Odometry topic too;
    chunks of about `chunk` bytes (ROS's recorder: 768 KiB)."""
    from bag_writer import _odometry
    from rosbags.rosbag1 import Writer

    store = _legacy_store()
    T = store.types
    tf_type = LEGACY_TF if tf == "legacy" else "tf2_msgs/msg/TFMessage"
    writer = Writer(path)
    writer.chunk_threshold = chunk
    with writer:
        c_scan = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        c_tf = writer.add_connection("/tf_static" if static_only else "/tf", tf_type, typestore=store) \
            if tf != "none" else None
        c_legacy = writer.add_connection("/tf", LEGACY_TF, typestore=store) if tf == "mixed" else None
        c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store) if odom else None
        for i, (pts, origin, q) in enumerate(scans):
            ns = 1_000_000_000 + i * 100_000_000
            if c_tf is not None and i >= tf_from and (not static_only or i == tf_from):
                msg = _transform(T, "ros1", "odom", tf_child, ns, origin, q)
                if tf == "legacy":
                    msg = T[LEGACY_TF](transforms=msg.transforms)
                if tf == "mixed" and i % 2:
                    writer.write(c_legacy, ns, store.serialize_ros1(T[LEGACY_TF](transforms=msg.transforms), LEGACY_TF))
                else:
                    writer.write(c_tf, ns, store.serialize_ros1(msg, tf_type))
                if late_stamps and i >= 2:  # scan i-2's transform again, now: a stamp older than the last
                    p, o, qq = scans[i - 2]
                    old = _transform(T, "ros1", "odom", tf_child, ns - 200_000_000, o, qq)
                    writer.write(c_tf, ns, store.serialize_ros1(old, tf_type))
                if late_stamps:
                    writer.write(c_tf, ns, store.serialize_ros1(msg if tf != "legacy" else
                                                                _transform(T, "ros1", "odom", tf_child, ns, origin, q),
                                                                tf_type))
            if c_odom is not None and i >= odom_from:
                stamp = ns if odom_stamp_ns is None else odom_stamp_ns + i * 100_000_000
                writer.write(c_odom, ns, store.serialize_ros1(_odometry(T, "ros1", stamp, origin, q), "nav_msgs/msg/Odometry"))
            writer.write(c_scan, ns + 50_000_000 * (i < tf_from),
                         store.serialize_ros1(cloud(T, "ros1", pts, ns, scan_frame), "sensor_msgs/msg/PointCloud2"))
    return path


@pytest.fixture(scope="module")
def scans():
    return [(pts, origin, yaw_quat(yaw)) for pts, origin, yaw in box_scene(6, 300, seed=41)]


def _map_of(tmp_path, path, *options):
    code, report, err, out = _build(tmp_path, path, *options)
    assert code == 0, err
    from voxtool.io.mapfile import load_map

    return report, load_map(out)[0], err


@pytest.mark.parametrize("case", ["legacy", "mixed", "late"])
def test_tf_as_tf2_reads_it(tmp_path, scans, case):
    """tf/tfMessage (bags recorded before tf2), /tf on connections of both it and
    tf2_msgs/TFMessage, and transforms stamped out of order or twice (several publishers of one
    edge): tf2 keeps each edge's buffer sorted by stamp, and so does voxtool: the same map as the
    clean tf2 bag's, and info names the tree."""
    a = write_wild_bag(tmp_path / "tf2.bag", scans)
    b = write_wild_bag(tmp_path / f"{case}.bag", scans, tf="tf" if case == "late" else case,
                       late_stamps=case == "late")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    ra, ma, _ = _map_of(tmp_path / "a", a)
    rb, mb, _ = _map_of(tmp_path / "b", b)
    assert ra["scans"] == rb["scans"] == len(scans)
    la, lb = ma.leaves(), mb.leaves()
    assert np.array_equal(la.codes, lb.codes) and np.array_equal(la.values, lb.values)
    code, text, err = cli("info", b, "--json")
    assert code == 0, err
    got = json.loads(text)
    assert [(e["parent"], e["child"]) for e in got["tf"]] == [("odom", "lidar")]


MOUNT = np.array([0.1, 0.0, 0.17])  # base_footprint -> lidar, as a TurtleBot3's base_scan sits


def write_mounted_bag(path, scans, mode: str, pose_type: str = "odom"):
    """The scans (lidar poses) as a robot's bag has them: the robot's base_footprint posed by /tf
    (mode "tf": odom -> base_footprint) or by an Odometry topic /odom ("odom", child
    base_footprint; "odom-no-mount": without the /tf_static mount), the lidar on the base by
    /tf_static. pose_type "pose": a PoseStamped /odom instead (it names no frame)."""
    from bag_writer import _odometry, _transform
    from rosbags.rosbag1 import Writer

    from voxtool.geometry import Pose

    store = _legacy_store()
    T = store.types
    with Writer(path) as writer:
        c_scan = writer.add_connection("/points", "sensor_msgs/msg/PointCloud2", typestore=store)
        c_static = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
        c_tf = writer.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=store)
        odom_type = "nav_msgs/msg/Odometry" if pose_type == "odom" else "geometry_msgs/msg/PoseStamped"
        c_odom = writer.add_connection("/odom", odom_type, typestore=store)
        if mode != "odom-no-mount":
            writer.write(c_static, 1, store.serialize_ros1(
                _transform(T, "ros1", "base_footprint", "lidar", 0, MOUNT, (1.0, 0.0, 0.0, 0.0)), "tf2_msgs/msg/TFMessage"))
        for i, (pts, origin, q) in enumerate(scans):
            ns = 1_000_000_000 + i * 100_000_000
            lidar = Pose.from_quat(origin, *q)
            base = lidar.compose(Pose(np.eye(3), -MOUNT))  # world <- base = world <- lidar <- base
            qb = _quat_wxyz(base.rotation)
            if mode == "tf":
                writer.write(c_tf, ns, store.serialize_ros1(_transform(T, "ros1", "odom", "base_footprint", ns,
                                                                       base.translation, qb), "tf2_msgs/msg/TFMessage"))
            else:
                odom = _odometry(T, "ros1", ns, base.translation, qb, child="base_footprint")
                if pose_type == "pose":
                    odom = T["geometry_msgs/msg/PoseStamped"](header=odom.header, pose=odom.pose.pose)
                writer.write(c_odom, ns, store.serialize_ros1(odom, odom_type))
            writer.write(c_scan, ns, store.serialize_ros1(cloud(T, "ros1", pts, ns, "lidar"),
                                                          "sensor_msgs/msg/PointCloud2"))
    return path


def _quat_wxyz(r: np.ndarray) -> tuple:
    """A rotation matrix's unit quaternion (w, x, y, z), w >= 0 (Shepperd's method, trace branch:
    the yaw-only rotations here)."""
    w = np.sqrt(max(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 0.0)) / 2.0
    return (w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w))


def test_a_pose_topic_is_composed_with_the_sensor_mount(tmp_path, scans):
    """--pose-topic /odom (child base_footprint) with /tf_static base_footprint -> lidar: the map
    of the bag posed by /tf through the same mount; without the mount, identity is assumed and
    said on one warning line, and the map sits 0.17 m low."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    (tmp_path / "c").mkdir()
    _, by_tf, _ = _map_of(tmp_path / "a", write_mounted_bag(tmp_path / "tf.bag", scans, "tf"))
    bag = write_mounted_bag(tmp_path / "odom.bag", scans, "odom")
    _, by_odom, err = _map_of(tmp_path / "b", bag, "--pose-topic", "/odom")
    la, lb = by_tf.leaves(), by_odom.leaves()
    assert np.array_equal(la.codes, lb.codes) and np.allclose(la.values, lb.values), err
    assert "identity assumed" not in err
    code, text, err = cli("info", bag, "--pose-topic", "/odom", "--json")
    assert code == 0, err
    assert json.loads(text)["pose_source"]["mount"] == ("'/odom' poses 'base_footprint'; /tf mounts the scan frame "
                                                        "'lidar' on it at [0.100, 0.000, 0.170] m")
    bare = write_mounted_bag(tmp_path / "bare.bag", scans, "odom-no-mount")
    report, by_bare, err = _map_of(tmp_path / "c", bare, "--pose-topic", "/odom")
    assert [ln for ln in err.splitlines() if "identity assumed" in ln] == [
        f"voxtool: warning: {bare}: no /tf or /tf_static chain from '/odom''s frame 'base_footprint' to the scan "
        "frame 'lidar': identity assumed (a sensor mount missing puts the map where the 'base_footprint' frame is)"]
    occupied = [m.leaves().codes[m.leaves().values > 0] for m in (by_tf, by_bare)]
    assert len(np.intersect1d(*occupied)) < 0.5 * len(occupied[0])  # the map is elsewhere


def test_a_pose_stamped_that_names_no_frame_is_said_to_pose_the_sensor(tmp_path, scans):
    bag = write_mounted_bag(tmp_path / "pose.bag", scans, "odom", pose_type="pose")
    code, _, err, _ = _build(tmp_path, bag, "--pose-topic", "/odom")
    assert code == 0, err
    assert [ln for ln in err.splitlines() if "names no frame" in ln] == [
        f"voxtool: warning: {bag}: '/odom' names no frame it poses (no child_frame_id): its poses are taken as the "
        "scan frame 'lidar's, no mount, though /tf mounts 'lidar' on 'base_footprint' (a body's pose used as the "
        "sensor's)"]


def test_a_pose_topic_on_another_clock_poses_nothing_and_says_so(tmp_path, scans):
    """Pose stamps that miss every scan (a simulator's 60 s beside the sensor's 1 s): exit 3 naming
    both spans, no map written; not exit 0 with an empty map."""
    path = write_wild_bag(tmp_path / "b.bag", scans, tf="none", odom=True, odom_stamp_ns=60_000_000_000)
    code, _, err, out = _build(tmp_path, path, "--pose-topic", "/odom")
    assert code == 3 and not out.exists()
    assert (f"none of its {len(scans)} scans on '/points' can be posed: they span 1.000..1.500 s, the pose topic "
            "'/odom' 60.000..60.500 s") in _one_error_line(err), err


def test_scans_before_a_pose_topic_s_first_pose_are_left_out_and_said_so(tmp_path, scans):
    path = write_wild_bag(tmp_path / "b.bag", scans, tf="none", odom=True, odom_from=2)
    code, report, err, _ = _build(tmp_path, path, "--pose-topic", "/odom")
    assert code == 0 and report["scans"] == len(scans) - 2 and report["scans_unposed"] == 2
    assert [ln for ln in err.splitlines() if "left out" in ln] == [
        f"voxtool: warning: {path}: left out 2 scans (0, 1) taken before the first pose of '/odom' that poses them "
        "(topic '/points')"]


def test_scans_before_the_first_transform_are_left_out_counted_and_warned(tmp_path, scans):
    """Scans taken before the first transform are dropped as a tf message filter drops them:
    the map is the map of the later scans alone (built from a bag that holds only those)."""
    early = write_wild_bag(tmp_path / "early.bag", scans, tf_from=2)
    later = write_wild_bag(tmp_path / "later.bag", scans[2:])
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    r1, m1, err = _map_of(tmp_path / "a", early)
    r2, m2, _ = _map_of(tmp_path / "b", later)
    assert r1["scans"] == len(scans) - 2 and r1["scans_unposed"] == 2
    assert [ln for ln in err.splitlines() if "left out" in ln] == [
        f"voxtool: warning: {early}: left out 2 scans (0, 1) taken before the first transform that poses them "
        "(topic '/points'), as a tf message filter drops them"]
    assert np.array_equal(m1.leaves().codes, m2.leaves().codes)


@pytest.mark.parametrize("case, options, says", [
    ("no tf", dict(tf="none"), "the log has no /tf transform); pose them with --world-frame lidar"),
    ("only odom", dict(tf="none", odom=True), "pose them with --pose-topic /odom, or --world-frame lidar"),
    ("frame missing", dict(tf_child="base_laser"), "no transform reaches the scan frame 'lidar' (its /tf frames: "
                                                   "base_laser, odom)"),
    ("empty frame id", dict(tf="none", scan_frame=""), "pose them with --world-frame '' (a static sensor"),
])
def test_a_bag_nothing_poses_is_one_line_naming_what_would(tmp_path, scans, case, options, says):
    path = write_wild_bag(tmp_path / "b.bag", scans, **options)
    code, _, err, out = _build(tmp_path, path)
    assert code == 3 and not out.exists()
    assert says in _one_error_line(err), err
    code, _, err, out = _build(tmp_path, path, "--bad-scans", "skip")  # not a bad scan: the same line
    assert code == 3 and says in _one_error_line(err), err


def test_a_world_frame_the_bag_lacks_lists_its_frames(tmp_path, scans):
    path = write_wild_bag(tmp_path / "b.bag", scans)
    code, _, err, out = _build(tmp_path, path, "--world-frame", "map")
    assert code == 3 and not out.exists()
    assert "--world-frame map is not a frame of its /tf (its frames: lidar, odom)" in _one_error_line(err), err
    assert _build(tmp_path, path, "--world-frame", "odom")[0] == 0


def test_only_odom_builds_with_the_pose_topic_named(tmp_path, scans):
    path = write_wild_bag(tmp_path / "b.bag", scans, tf="none", odom=True)
    with_tf = write_wild_bag(tmp_path / "tf.bag", scans)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    r1, m1, _ = _map_of(tmp_path / "a", path, "--pose-topic", "/odom")
    _, m2, _ = _map_of(tmp_path / "b", with_tf)
    assert r1["scans"] == len(scans) and np.array_equal(m1.leaves().codes, m2.leaves().codes)


def test_only_tf_static_poses_every_scan(tmp_path, scans):
    """A sensor posed by /tf_static alone (a fixed mount): every scan takes that pose."""
    path = write_wild_bag(tmp_path / "b.bag", scans, static_only=True)
    still = [(pts, scans[0][1], scans[0][2]) for pts, _, _ in scans]
    ref = write_wild_bag(tmp_path / "ref.bag", still)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    r1, m1, _ = _map_of(tmp_path / "a", path)
    _, m2, _ = _map_of(tmp_path / "b", ref)
    assert r1["scans"] == len(scans) and np.array_equal(m1.leaves().codes, m2.leaves().codes)


def test_an_empty_bag_is_one_line(tmp_path):
    from rosbags.rosbag1 import Writer

    path = tmp_path / "empty.bag"
    with Writer(path):
        pass
    code, _, err, out = _build(tmp_path, path)
    assert code == 3 and not out.exists()
    assert "no PointCloud2 or LaserScan topic to build from (its topics: none)" in _one_error_line(err)


@pytest.mark.parametrize("command", ["build", "odometry"])
def test_a_scan_topic_without_messages_is_one_line(tmp_path, command):
    """A recording whose /scan connection never got a message (a course's ROS 2 bag has one) used to
    build an empty map with exit 0."""
    from rosbags.rosbag1 import Writer

    path = tmp_path / "silent.bag"
    with Writer(path) as writer:
        writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=_store("ros1"))
    out = tmp_path / ("out.vxm" if command == "build" else "poses.txt")
    code, _, err = cli(command, path, "-o", out, "--no-progress")
    assert code == 3 and not out.exists()
    assert "its scan topic '/scan' holds no messages: nothing to build from" in _one_error_line(err)
    code, text, _ = cli("info", path)
    assert code == 0 and "/scan (LaserScan, no messages)" in text  # was "frame 'None'"


@pytest.mark.parametrize("keep", [0.2, 0.35, 0.7, 0.97])
def test_a_truncated_recording_builds_what_was_recorded_with_skip(tmp_path, scans, keep):
    """A recording killed (or a download cut) at `keep` of its bytes: rosbags cannot open it (its
    index is gone). Without --bad-scans skip: one line naming that option and `rosbag reindex`;
    with it, the scans whose records are whole, the map equal to that of a bag of those alone,
    and one warning that says how much of the file was lost."""
    full = write_wild_bag(tmp_path / "full.bag", scans, chunk=2_000)  # a chunk a scan or so, as a long recording has
    data = full.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: int(len(data) * keep)])
    code, _, err, out = _build(tmp_path, cut)
    assert code == 3 and not out.exists()
    line = _one_error_line(err)
    assert "--bad-scans skip" in line and "rosbag reindex" in line, line
    code, report, err, out = _build(tmp_path, cut, "--bad-scans", "skip")
    assert "Traceback" not in err
    if code != 0:  # cut before the first whole scan: nothing to build
        assert code == 3 and not out.exists() and "no scan" in _one_error_line(err), err
        return
    n = report["scans"]
    assert 0 < n <= len(scans) and (n < len(scans) or keep > 0.9)
    assert any("could not be read" in ln and ln.startswith("voxtool: warning:") for ln in err.splitlines()), err
    (tmp_path / "ref").mkdir()
    _, ref, _ = _map_of(tmp_path / "ref", write_wild_bag(tmp_path / "ref" / "ref.bag", scans[:n]))
    from voxtool.io.mapfile import load_map

    assert np.array_equal(load_map(out)[0].leaves().codes, ref.leaves().codes)


def test_a_pre_2_0_bag_is_one_line(tmp_path):
    path = tmp_path / "old.bag"
    path.write_bytes(b"#ROSRECORD V1.2\n" + bytes(range(256)) * 8)
    code, _, err, out = _build(tmp_path, path)
    assert code == 3 and not out.exists()
    assert "older than format 2.0 (#ROSRECORD V1.2)" in _one_error_line(err)



def test_the_summary_says_why_points_were_dropped_and_which_scans_were_left_out(tmp_path, scans):
    """The text summary names each reason points were dropped, and the scans left out."""
    holed = [(np.vstack([pts, np.full((3, 3), np.nan, np.float32)]), o, q) for pts, o, q in scans]
    path = write_wild_bag(tmp_path / "b.bag", holed, tf_from=1)
    code, text, err = cli("build", path, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 0, err
    points = next(ln for ln in text.splitlines() if ln.startswith("points "))
    assert f"({3 * (len(scans) - 1)} dropped: {3 * (len(scans) - 1)} not finite" in points, points
    assert "scans left out      1 with no pose at their time (before the first transform or pose, or after the last)" \
        in text, text


def test_the_docs_way_to_write_a_ros1_bag_builds(tmp_path, monkeypatch):
    """docs/sources.md's block writing a ROS 1 bag with rosbags (TFMessage registered by hand)
    runs, and the bag it writes builds: the one scan, posed 1 m along x."""
    import re
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "sources.md").read_text()
    block = re.search(r"### Writing a ROS 1 bag.*?```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(block, "docs/sources.md", "exec"), namespace)
    code, report, err, _ = _build(tmp_path, tmp_path / "scans.bag")
    assert code == 0, err
    assert report["scans"] == 1 and report["points"] == 1000
    lo, hi = report["occupied_bbox"]["min"], report["occupied_bbox"]["max"]
    assert lo[0] < -3.5 and hi[0] > 5.5  # the points, -5..5, moved 1 m along x


@pytest.mark.parametrize("keep", [0.3, 0.6])
def test_a_truncated_mcap_builds_the_scans_before_the_cut_with_skip(tmp_path, shared_data, keep):
    """A real MCAP recording (kaist03, 21 Ouster scans) cut short: without --bad-scans skip one
    line naming it and `mcap recover`; with it, read from its start, the map equals the map of the
    original's first N scans (N: the whole scans before the cut) and one warning says how many
    bytes were lost."""
    original = shared_data / "kaist03" / "kaist03_21scans.mcap"
    cut = tmp_path / "cut.mcap"
    data = original.read_bytes()
    cut.write_bytes(data[: int(len(data) * keep)])
    code, _, err, out = _build(tmp_path, cut)
    assert code == 3 and "--bad-scans skip" in _one_error_line(err) and "mcap recover" in err and not out.exists()
    report, cut_map, err = _map_of(tmp_path, cut, "--bad-scans", "skip")
    lost = [ln for ln in err.splitlines() if "could not be read" in ln]
    assert len(lost) == 1 and f"of its {len(data[: int(len(data) * keep)]):,} bytes" in lost[0], err
    n = report["scans"]
    assert 0 < n < 21
    (tmp_path / "whole").mkdir()
    whole, whole_map, _ = _map_of(tmp_path / "whole", original, "--stop", n)
    assert whole["scans"] == n
    a, b = cut_map.leaves(), whole_map.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)


def _declared_topics(bag) -> dict[str, tuple[str, int]]:
    """A ROS 2 bag's topics as its metadata.yaml declares them: name -> (type, messages)."""
    text = (bag / "metadata.yaml").read_text()
    found = re.findall(r"name: (\S+)\s+type: (\S+).*?message_count: (\d+)", text, re.S)
    return {name: (msgtype, int(count)) for name, msgtype, count in found}


def test_logs_of_lidar_packets_are_one_line_that_says_to_decode_them(tmp_path, nebula_bags):
    """Real ROS 2 bags recorded at the driver (Hesai packets, two radars; metadata fields left
    blank in some): `info` lists the topics their metadata declares, and `build` says in one line,
    exit 3, which topic holds packets and what turns them into points. (Velodyne's packets are
    decoded: test_velodyne.)"""
    checked = 0
    for bag in nebula_bags:
        declared = _declared_topics(bag)
        assert declared, bag
        if any(msgtype.endswith("/VelodyneScan") for msgtype, _ in declared.values()):
            continue
        checked += 1
        code, text, err = cli("info", bag, "--json")
        assert code == 0, (bag, err)
        info = json.loads(text)
        assert {t["topic"]: (t["type"], t["messages"]) for t in info["topics"]} == declared, bag
        assert info["scan_topics"] == [] and "raw packets" in info["why"]
        code, report, err, out = _build(tmp_path, bag)
        assert code == 3 and not out.exists(), (bag, err)
        line = _one_error_line(err)
        topic, (msgtype, _) = next(iter(declared.items()))
        assert f"{topic} ({msgtype}) holds the sensor driver's raw packets" in line, line
        assert "turn them into PointCloud2 with that driver" in line
    assert checked >= 8


def _gmapping_share(folder, backend) -> tuple[int, float]:
    """(the authors' gmapping wall cells, the share of them within 0.2 m of a wall of `backend`'s
    map): both grids on one lattice (cell centres at 0.025 + k 0.05 m), so distances are whole cells."""
    from PIL import Image

    from voxtool.keys import TREE_MAX_VAL, expand_leaves, morton_decode

    meta = (folder / "johnny5_gmapping_map.yaml").read_text()
    resolution = float(re.search(r"resolution: (\S+)", meta).group(1))
    x0, y0 = (float(v) for v in re.search(r"origin: \[([^,]+),([^,]+),", meta).groups())
    theirs = (255 - np.asarray(Image.open(folder / "johnny5_gmapping_map.pgm"), dtype=np.float64)) / 255 > 0.65
    rows, cols = theirs.shape
    leaves = backend.leaves()
    occupied = leaves.values > 0
    keys = morton_decode(expand_leaves(leaves.codes[occupied], leaves.depths[occupied])).astype(np.int64)
    col = keys[:, 0] - TREE_MAX_VAL - round(x0 / resolution)  # the gmapping cell of each voxel column
    row = rows - 1 - (keys[:, 1] - TREE_MAX_VAL - round(y0 / resolution))
    inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    ours = np.zeros_like(theirs)
    ours[row[inside], col[inside]] = True
    reach = int(round(0.2 / resolution))  # within 0.2 m (4 cells) of one of our walls
    padded = np.pad(ours, reach)
    near = np.zeros_like(theirs)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            if dr * dr + dc * dc <= reach * reach:
                near |= padded[reach + dr:reach + dr + rows, reach + dc:reach + dc + cols]
    return int(theirs.sum()), float(near[theirs].mean())


def test_johnny5_walls_lie_where_the_authors_gmapping_map_has_them(shared_data):
    """The authors' own gmapping map of johnny5_data.bag (its PGM and YAML, ../shared/data/bags):
    most of its wall cells lie within 0.2 m of a wall voxtool builds from the same bag's
    odometry /tf at 0.05 m (gmapping also corrects the odometry's drift over the 124 s run;
    voxtool does not)."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps import make_backend
    from voxtool.pipeline import build
    from voxtool.sources import open_source

    folder = shared_data / "bags"
    if not (folder / "johnny5_gmapping_map.pgm").is_file():
        pytest.skip("johnny5's gmapping map absent")
    m = make_backend("octree", MapParams(resolution=0.05), SensorModel())
    with pytest.warns(UserWarning, match="before the first transform"):
        build(open_source(folder / "johnny5_data.bag"), m, progress=False)
    walls, share = _gmapping_share(folder, m)
    assert walls > 500 and share >= 0.85, share


def test_johnny5_odometry_at_its_defaults_maps_the_walls_gmapping_has(shared_data, tmp_path):
    """`voxtool odometry` at its defaults on johnny5's 2D LaserScans (a 5 m scanner: its range_max,
    registered in the plane): the path is the wheel odometry's 11.6 m (66 m when KISS-ICP's 100 m
    range made a 1 m voxel), and the map from its poses, after one rigid alignment to the /tf
    trajectory (the odometry's frame is the first scan's), holds gmapping's walls as well as the
    map from /tf does."""
    pytest.importorskip("kiss_icp")
    from voxtool.config import MapParams, SensorModel
    from voxtool.maps import make_backend
    from voxtool.odometry import OdometryParams, estimate_poses, rigid_fit, write_pose_file
    from voxtool.pipeline import build
    from voxtool.sources import SourceOptions, open_source

    folder = shared_data / "bags"
    if not (folder / "johnny5_gmapping_map.pgm").is_file():
        pytest.skip("johnny5's gmapping map absent")
    bag = folder / "johnny5_data.bag"
    result = estimate_poses(bag, SourceOptions(), OdometryParams(), progress=False)
    figures = result["figures"]
    assert figures["params"]["planar"] and figures["params"]["max_range"] == pytest.approx(5.0)
    assert not figures["plausibility"]["suspect"] and 10.5 < figures["path_m"] < 13.0, figures
    with pytest.warns(UserWarning, match="before the first transform"):
        by_tf = {s.index: s.origin.astype(np.float64) for s in open_source(bag).scans}
    ours = result["poses"]
    index = np.array(sorted(by_tf))
    r, t = rigid_fit(ours[index, :3, 3], np.array([by_tf[i] for i in index]))
    aligned = np.array([np.block([[r, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]) @ p for p in ours])
    write_pose_file(tmp_path / "poses.txt", aligned, result["stamps_ns"])
    m = make_backend("octree", MapParams(resolution=0.05), SensorModel())
    build(open_source(bag, SourceOptions(poses=str(tmp_path / "poses.txt"))), m, progress=False)
    walls, share = _gmapping_share(folder, m)
    assert walls > 500 and share >= 0.90, share


COURSE_LOGS = {"driving": (816, "base_scan", "map"), "standing": (114, "base_scan", "odom"),
               "sparse": (110, "base_scan", "odom"), "webots": (1189, "LDS-01", "odom"),
               "hall": (1046, "base_scan", "map"), "teleop": (333, "base_scan", "map"),
               "localization": (831, "base_scan", "map")}


def test_a_course_s_simulated_logs_are_described_and_build(gazebo_bags, tmp_path):
    """The corpus grown by a course's simulated TurtleBot3 logs (ROS 2 sqlite bags with /clock,
    Gazebo's and Webots' /tf trees, scripts/fetch_samples.py gazebo, gazebo-hall, gazebo-teleop and
    gazebo-localization): `info`
    names each one's scans, scan frame and the /tf root that poses them; the short ones build
    every scan with no warning."""
    for log, (scans, frame, root) in COURSE_LOGS.items():
        if not (gazebo_bags / log / "metadata.yaml").is_file():
            continue  # the hall, teleop and localization logs come from other repositories
        code, text, err = cli("info", gazebo_bags / log, "--json")
        assert code == 0 and err == "", (log, err)
        got = json.loads(text)
        assert (got["scans"], got["scan_frame"]) == (scans, frame), log
        assert got["pose_source"]["by"] == f"/tf: scan frame '{frame}' in world frame '{root}'", log
        if scans < 200:
            code, report, err, out = _build(tmp_path, gazebo_bags / log)
            assert code == 0 and err == "" and report["scans"] == scans and report["occupied_voxels"] > 0, (log, err)


def test_odometry_of_a_standing_rplidar_travels_nowhere(shared_data, tmp_path):
    """lidarme's RPLidar (485 LaserScans, range_max 12 m, nothing poses it) stands still: the grid
    matcher's poses wander 3-6 cm within one 8.6 cm cell, and that jitter is no path (0.23 m of it
    when a move counted at half a cell)."""
    bag = shared_data / "bags" / "lidarme_lidar.bag"
    if not bag.is_file():
        pytest.skip("lidarme's bag absent")
    code, text, err = cli("odometry", bag, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0 and err == "", err
    got = json.loads(text)
    assert got["params"]["matcher"] == "grid" and got["params"]["max_range"] == 12.0
    assert got["scans"] == 485 and got["path_m"] == 0.0 and not got["plausibility"]["suspect"]
    rows = np.loadtxt(tmp_path / "p.txt")
    assert np.linalg.norm(rows[:, 1:3], axis=1).max() < got["params"]["voxel_size"]  # within one cell of the start
