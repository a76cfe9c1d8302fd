"""`voxtool odometry` on 2D LaserScans against a simulator's truth: a TurtleBot3-like scanner
(360 beams, range_max 3.5 m, 1 cm noise) driving a loop through a room with boxes, its scans
ray-cast here against the room's walls (the truth is the path they were cast from), written as a
ROS 1 bag by rosbags. At its defaults (the scan's range_max, registration in the plane) the
odometry stays within 3 cm ATE; at the old fixed 100 m range (1 m voxels) it does not."""

from __future__ import annotations

import json

import numpy as np
import pytest
from bag_writer import _store, laser
from conftest import cli

RANGE_MAX = 3.5
BEAMS = 360

# the room (6 m x 5 m) and three boxes, as wall segments (x0, y0, x1, y1)
_BOXES = [(1.0, 1.0, 1.6, 1.5), (4.2, 3.4, 4.8, 4.2), (3.0, 0.6, 3.4, 1.0)]
WALLS = np.array([(0, 0, 6, 0), (6, 0, 6, 5), (6, 5, 0, 5), (0, 5, 0, 0)]
                 + [seg for x0, y0, x1, y1 in _BOXES
                    for seg in ((x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0))], dtype=float)


def cast(x: float, y: float, yaw: float, walls: np.ndarray = WALLS) -> np.ndarray:
    """Each beam's range to the nearest wall (inf beyond RANGE_MAX), by ray-segment intersection."""
    angles = yaw + np.arange(BEAMS) * 2 * np.pi / BEAMS
    d = np.stack([np.cos(angles), np.sin(angles)], 1)[:, None, :]  # (beams, 1, 2)
    p0, p1 = walls[None, :, :2], walls[None, :, 2:]
    e = p1 - p0
    w = p0 - np.array([x, y])
    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / den
        u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / den
    hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
    r = np.where(hit, t, np.inf).min(axis=1)
    return np.where(r <= RANGE_MAX, r, np.inf)


def loop(n: int) -> np.ndarray:
    """(x, y, yaw) of a 0.2 m/s loop around the room's middle, 10 Hz."""
    s = np.arange(n) * 0.02  # metres along an ellipse-ish path
    a = s / 1.9
    x, y = 3.0 + 1.6 * np.cos(a), 2.5 + 1.2 * np.sin(a)
    yaw = np.arctan2(1.2 * np.cos(a), -1.6 * np.sin(a))
    return np.stack([x, y, yaw], 1)


def write_scans(path, truth: np.ndarray, walls=WALLS, seed: int = 4) -> None:
    """A ROS 1 bag of the LaserScans cast from each (x, y, yaw) of `truth`, 1 cm noise, 10 Hz
    (stamps 1 s + i / 10 s). `walls`: the wall segments, or a function of the scan's index that
    gives them (a scene that moves)."""
    from rosbags.rosbag1 import Writer

    store = _store("ros1")
    T = store.types
    rng = np.random.default_rng(seed)
    with Writer(path) as writer:
        c = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for i, (x, y, yaw) in enumerate(truth):
            ranges = cast(x, y, yaw, walls(i) if callable(walls) else walls)
            ranges = np.where(np.isfinite(ranges), ranges + rng.normal(0.0, 0.01, BEAMS), np.inf)
            ns = 1_000_000_000 + i * 100_000_000
            msg = laser(T, "ros1", ranges.astype(np.float32), 0.0, 2 * np.pi / BEAMS, ns, "base_scan", RANGE_MAX)
            writer.write(c, ns, store.serialize_ros1(msg, "sensor_msgs/msg/LaserScan"))


def write_truth_poses(path, truth: np.ndarray) -> None:
    """TUM rows of the scanner's true poses, 0.2 m up, at write_scans' stamps: a --poses file."""
    path.write_text("".join(f"{1 + i / 10:.1f} {x:.6f} {y:.6f} 0.2 0 0 {np.sin(a / 2):.9f} {np.cos(a / 2):.9f}\n"
                            for i, (x, y, a) in enumerate(truth)))


@pytest.fixture(scope="module")
def room_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("room") / "room.bag"
    truth = loop(400)
    write_scans(path, truth)
    return path, truth


def _ate(result, truth) -> float:
    from voxtool.odometry import ate_rmse

    return ate_rmse(result["poses"][:, :3, 3], np.c_[truth[:, :2], np.zeros(len(truth))])


def test_odometry_at_its_defaults_follows_a_2d_scanner_within_3_cm(room_bag):
    pytest.importorskip("kiss_icp")
    from voxtool.errors import VoxtoolWarning
    from voxtool.odometry import OdometryParams, estimate_poses
    from voxtool.sources import SourceOptions

    path, truth = room_bag
    result = estimate_poses(path, SourceOptions(), OdometryParams(), progress=False)
    params = result["figures"]["params"]
    assert params["max_range"] == pytest.approx(RANGE_MAX) and params["planar"]
    assert np.all(result["poses"][:, 2, 3] == 0.0)  # in the plane
    assert _ate(result, truth) < 0.03
    travelled = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1).sum()
    assert abs(result["figures"]["path_m"] - travelled) < 0.05 * travelled
    assert not result["figures"]["plausibility"]["suspect"]
    # the old defaults: a 1 m voxel for a 3.5 m scanner, a few points a scan left to register: flagged
    with pytest.warns(VoxtoolWarning, match="may have diverged: .* scans with fewer than 30 points"):
        old = estimate_poses(path, SourceOptions(), OdometryParams(max_range=100.0, planar=False), progress=False)
    assert _ate(old, truth) > 2 * _ate(result, truth)


def test_a_featureless_corridor_is_flagged_as_one_direction_only(tmp_path):
    """A 2D scanner driven 20 m down a straight corridor 2 m wide whose ends lie beyond its 3.5 m
    range: every scan is two parallel walls, so motion along them is not measured (the odometry
    covers a fraction of the way). It says so: each scan is counted as fixing one direction only,
    and the run is flagged, though no step is too fast and no scan too sparse."""
    pytest.importorskip("kiss_icp")
    from voxtool.errors import VoxtoolWarning
    from voxtool.odometry import OdometryParams, estimate_poses
    from voxtool.sources import SourceOptions

    corridor = np.array([(-10.0, 0.0, 40.0, 0.0), (-10.0, 2.0, 40.0, 2.0)])
    truth = np.stack([np.arange(200) * 0.1, np.ones(200), np.zeros(200)], 1)  # 1 m/s
    path = tmp_path / "corridor.bag"
    write_scans(path, truth, corridor)
    with pytest.warns(VoxtoolWarning, match=r"200 scans \(100 %\) fix the motion in one direction only"):
        result = estimate_poses(path, SourceOptions(), OdometryParams(), progress=False)
    check = result["figures"]["plausibility"]
    assert check["suspect"] and check["one_direction_scans"] == 200 and check["first_one_direction_scan"] == 0
    assert check["implausible_steps"] == 0 and check["sparse_scans"] == 0
    assert result["figures"]["path_m"] < 0.8 * 19.9  # what the flag is for: the way is not measured


def test_the_room_s_scans_each_fix_every_direction(room_bag):
    """The flag's other side: in the room (corners and boxes always in range) no scan is counted."""
    from voxtool.odometry import weak_direction_support
    from voxtool.sources import SourceOptions, open_source

    path, _ = room_bag
    support = [weak_direction_support(s.points, 0.0, RANGE_MAX)
               for s in open_source(path, SourceOptions(sensor_frame=True)).scans]
    assert len(support) == 400 and min(support) >= 0.1, min(support)


def test_a_simulated_turtlebot3_log_others_recorded(tb3_bag, tmp_path):
    """A Gazebo TurtleBot3 bag from a public repository (/scan alone, nothing poses it): `build`
    refuses it in one line naming `voxtool odometry`; odometry at its defaults takes the scanner's
    range_max and the plane, is not flagged, and its poses build a map whose walls are thin."""
    pytest.importorskip("kiss_icp")
    code, _, err = cli("build", tb3_bag, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 3 and "voxtool odometry" in err and not (tmp_path / "m.vxm").exists()
    code, text, err = cli("odometry", tb3_bag, "-o", tmp_path / "p.txt", "--json", "--no-progress")
    assert code == 0 and err == "", err
    got = json.loads(text)
    assert got["scans"] == 538 and got["params"]["planar"] and got["params"]["max_range_from"] == "the data"
    assert not got["plausibility"]["suspect"] and 5.0 < got["path_m"] < 25.0
    code, text, err = cli("build", tb3_bag, "--poses", tmp_path / "p.txt", "-o", tmp_path / "m.vxm",
                          "--resolution", "0.05", "--json", "--no-progress")
    assert code == 0, err
    built = json.loads(text)
    # the arena's walls from 538 scans: 670 occupied voxels here (849 with KISS-ICP's poses); the old
    # fixed 100 m range (1 m voxels, every scan flagged as too sparse to register) smeared them over 1,319
    assert built["scans"] == 538 and 300 < built["occupied_voxels"] < 1100


def _json(*args):
    code, text, err = cli(*args, "--json", "--no-progress")
    assert code == 0, err
    return json.loads(text), err


def test_a_pose_topic_poses_a_gazebo_log_through_its_sensor_mount(gazebo_bags, tmp_path):
    """A course's Gazebo TurtleBot3 log (public, recorded by others): /odom poses base_footprint and
    /tf_static mounts the scanner 18.2 cm above it. `info` names the chain, and the map posed by
    /odom is the map posed by /tf in the odom frame: Gazebo publishes both from one pose (14 of
    104,780 voxels differ, the two topics sampled at slightly different times). Without the mount
    every voxel would sit 18 cm low and 3 cm forward, sharing almost none."""
    bag = gazebo_bags / "driving"
    code, text, err = cli("info", bag, "--pose-topic", "/odom")
    assert code == 0, err
    assert ("'/odom' poses 'base_footprint'; /tf mounts the scan frame 'base_scan' on it at "
            "[-0.032, 0.000, 0.182] m") in text
    _json("build", bag, "--pose-topic", "/odom", "-o", tmp_path / "odom.vxm", "--resolution", "0.05")
    _json("build", bag, "--world-frame", "odom", "-o", tmp_path / "tf.vxm", "--resolution", "0.05")
    diff, _ = _json("diff", tmp_path / "tf.vxm", tmp_path / "odom.vxm")
    known = diff["common_known_voxels"]
    assert known > 100_000 and diff["unchanged"]["occupied"] > 3000
    assert diff["changed_voxels"] < 0.001 * known, diff


def test_odometry_on_a_gazebo_log_against_the_simulator_s_truth(gazebo_bags, tmp_path):
    """`voxtool odometry` at its defaults on the driving log (816 scans, 28.4 m along a house's
    corridor by the simulator's /tf): the scanner's 3.5 m range_max, the plane; its path within
    5 % of the truth's. Its ATE against that truth is 0.25 m here (KISS-ICP: 0.38 m), not 3 cm: the
    corridor's length is not measured at 3.5 m (docs/design/odometry.md): this guards the figure. The
    run is flagged: 77 scans from scan 330 on, where its steps start to go wrong, see only the
    corridor's two walls."""
    pytest.importorskip("kiss_icp")
    got, err = _json("odometry", gazebo_bags / "driving", "-o", tmp_path / "p.txt")
    assert got["params"]["max_range"] == 3.5 and got["params"]["planar"]
    check = got["plausibility"]
    assert check["suspect"] and 0.05 * 816 < check["one_direction_scans"] < 0.15 * 816, check
    assert 300 < check["first_one_direction_scan"] < 360 and "fix the motion in one direction only" in err
    assert check["implausible_steps"] == 0 and check["sparse_scans"] == 0
    assert got["against_source_poses"]["ate_rmse_m"] < 0.5, got["against_source_poses"]
    from voxtool.sources import open_source

    positions = np.array([s.origin for s in open_source(gazebo_bags / "driving").scans], dtype=np.float64)
    travelled = np.linalg.norm(np.diff(positions, axis=0), axis=1).sum()  # 28.39 m
    assert travelled > 25.0 and abs(got["path_m"] - travelled) < 0.05 * travelled, (got["path_m"], travelled)


def test_odometry_of_gazebo_robots_that_stand_still(gazebo_bags, tmp_path):
    """Two Gazebo logs of a robot that never moves: in a house (114 scans) the odometry travels 0 m
    (a standing sensor's jitter is not a path) within 1 cm of the truth; in a nearly empty world
    (110 scans of about 20 returns) it is flagged as having too little to register. The end's drift
    is not given as a share of a path it does not have (it was 271,798,055 %)."""
    got, err = _json("odometry", gazebo_bags / "standing", "-o", tmp_path / "p.txt")
    assert err == "" and got["scans"] == 114 and got["path_m"] == 0.0
    against = got["against_source_poses"]
    assert against["ate_rmse_m"] < 0.01 and not got["plausibility"]["suspect"]
    assert against["end_drift_m"] < 0.01 and against["end_drift_percent_of_path"] is None
    code, text, err = cli("odometry", gazebo_bags / "standing", "-o", tmp_path / "p.txt", "--no-progress")
    assert code == 0 and "m off (it stood still)" in text and "% of the path" not in text, text
    got, err = _json("odometry", gazebo_bags / "sparse", "-o", tmp_path / "p.txt")
    assert got["plausibility"]["suspect"] and got["plausibility"]["sparse_scans"] == 110
    assert "may have diverged: 110 scans with fewer than 30 points to register" in err


def test_odometry_maps_a_webots_room_crisper_than_its_wheel_odometry(gazebo_bags, tmp_path):
    """A Webots TurtleBot3 log (1,189 scans, 258 s in a furnished room) whose /tf is the wheels'
    odometry: its map smears the room's walls as the wheels' heading drifts. The map from
    `voxtool odometry`'s poses holds the same walls in half the occupied voxels (516 against 1,113
    at 0.1 m here; 1,260 against 1,942 at 5 cm; KISS-ICP's poses 525 and 1,281)."""
    pytest.importorskip("kiss_icp")
    bag = gazebo_bags / "webots"
    got, err = _json("odometry", bag, "-o", tmp_path / "p.txt")
    assert got["scans"] == 1189 and not got["plausibility"]["suspect"], err
    by_wheels, _ = _json("build", bag, "-o", tmp_path / "wheels.vxm", "--resolution", "0.1")
    by_odometry, _ = _json("build", bag, "--poses", tmp_path / "p.txt", "-o", tmp_path / "odo.vxm", "--resolution", "0.1")
    assert by_odometry["scans"] == by_wheels["scans"] == 1189
    assert by_odometry["occupied_voxels"] < 0.6 * by_wheels["occupied_voxels"], (by_odometry, by_wheels)
    # nothing moves in the simulated room: with the odometry's poses clean removes almost nothing
    # (66 of 324,275 points here, 0.02 %; 35 % with the drifting wheel odometry, docs/cleaning.md)
    cleaned, _ = _json("clean", bag, "--poses", tmp_path / "p.txt", "-o", tmp_path / "static.pcd")
    assert cleaned["planar"] and cleaned["points_removed"] < 1e-3 * cleaned["points_in"], cleaned


def test_odometry_round_a_gazebo_hall_is_flagged_where_it_cannot_see(gazebo_bags, tmp_path):
    """A course's Gazebo log driving 42 m round a 12 m x 15 m hall with a 3.5 m scanner: 41 % of
    its scans see one wall or a corner-less stretch, and the odometry misses most of the way
    along them (ATE 3.8 m against the simulator's /tf; KISS-ICP 3.7 m). It used to report success; it is flagged."""
    pytest.importorskip("kiss_icp")
    bag = gazebo_bags / "hall"
    if not (bag / "metadata.yaml").is_file():
        from conftest import skip_unfetched

        skip_unfetched("the Gazebo hall bag is absent", "gazebo-hall")
    got, err = _json("odometry", bag, "-o", tmp_path / "p.txt")
    check = got["plausibility"]
    assert check["suspect"] and 0.3 * got["scans"] < check["one_direction_scans"] < 0.5 * got["scans"], check
    assert "fix the motion in one direction only" in err
    assert got["against_source_poses"]["ate_rmse_m"] > 1.0  # the flag is warranted


@pytest.mark.parametrize("log, sample, ate_within", [("teleop", "gazebo-teleop", 0.03),
                                                     ("localization", "gazebo-localization", 0.03)])
def test_odometry_at_its_defaults_within_3_cm_of_the_simulator_on_gazebo_logs(gazebo_bags, tmp_path, log, sample,
                                                                              ate_within):
    """Two more Gazebo TurtleBot3 logs of the course, recorded by others (9.1 m through a house's
    rooms; 12.4 m under AMCL): `voxtool odometry` at its defaults registers the 2D scans to a grid
    of the scans before it and ends within 3 cm ATE of the simulator's odom -> base_scan (1.5 and
    1.1 cm here). KISS-ICP's point-to-point local map on the same scans is decimetres off (0.14 and
    0.15 m): the independent truth tells the two apart."""
    import warnings

    from voxtool.errors import VoxtoolWarning
    from voxtool.odometry import OdometryParams, ate_rmse, estimate_poses
    from voxtool.sources import SourceOptions, open_source

    bag = gazebo_bags / log
    if not (bag / "metadata.yaml").is_file():
        from conftest import skip_unfetched

        skip_unfetched(f"the Gazebo {log} bag is absent", sample)
    truth = np.array([s.origin for s in open_source(bag, SourceOptions(world_frame="odom")).scans], np.float64)

    def ate(matcher):
        with warnings.catch_warnings():  # the teleop log's corridor stretches are flagged (tested above): not news here
            warnings.simplefilter("ignore", VoxtoolWarning)
            result = estimate_poses(bag, SourceOptions(), OdometryParams(matcher=matcher), progress=False)
        ours = result["poses"][:, :3, 3]
        assert ours.shape == truth.shape
        return ate_rmse(ours, truth), result["figures"]

    grid, figures = ate(None)
    assert figures["params"]["matcher"] == "grid" and figures["params"]["voxel_size"] == pytest.approx(0.025)
    assert grid < ate_within, grid
    travelled = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1).sum()
    assert abs(figures["path_m"] - travelled) < 0.08 * travelled, (figures["path_m"], travelled)
    pytest.importorskip("kiss_icp")
    kiss, _ = ate("kiss-icp")
    assert kiss > 3 * grid, (kiss, grid)


def test_the_grid_matcher_refuses_3d_scans_in_one_line(tmp_path):
    """The grid matcher registers 2D scans: asked for on the shipped sample's 3D scans it says so and
    names the default, writing nothing."""
    code, _, err = cli("odometry", "--sample", "--matcher", "grid", "-o", tmp_path / "p.txt", "--no-progress")
    assert code == 2 and err.count("\n") == 1, err
    assert "--matcher grid registers 2D scans" in err and "KISS-ICP" in err
    assert not (tmp_path / "p.txt").exists()


def test_a_grid_cell_too_small_for_memory_is_refused_in_one_line(room_bag, tmp_path):
    """--voxel-size 1 mm for a 3.5 m scanner would need a 28,000-cell-square grid (3 GB): refused,
    naming the smallest cell that fits, before any pose is written."""
    path, _ = room_bag
    code, _, err = cli("odometry", path, "--voxel-size", "0.001", "-o", tmp_path / "p.txt", "--no-progress")
    assert code == 2 and err.count("\n") == 1, err
    assert "--voxel-size 0.001" in err and "28,000 x 28,000 cells" in err and "give at least 0.00684 m" in err
    assert not (tmp_path / "p.txt").exists()
    code, _, err = cli("odometry", path, "--voxel-size", "0.007", "-o", tmp_path / "p.txt", "--no-progress")
    assert code == 0 and (tmp_path / "p.txt").exists(), err


def test_odometry_is_compared_with_the_log_s_poses_in_a_named_frame(gazebo_bags, tmp_path):
    """The AMCL log: build poses its scans in 'map', which AMCL's transform reaches for 687 of the
    831 scans, so by default there is nothing to compare with; --world-frame odom compares with the simulator's odom
    poses (1.1 cm ATE). A named frame that cannot pose every scan says why on one warning line."""
    bag = gazebo_bags / "localization"
    if not (bag / "metadata.yaml").is_file():
        from conftest import skip_unfetched

        skip_unfetched("the Gazebo localization bag is absent", "gazebo-localization")
    got, err = _json("odometry", bag, "-o", tmp_path / "p.txt")
    assert got["against_source_poses"] is None and err == "", err
    got, err = _json("odometry", bag, "-o", tmp_path / "p.txt", "--world-frame", "odom")
    assert got["against_source_poses"]["ate_rmse_m"] < 0.03 and err == "", err
    for frame, says in (("map", "in --world-frame map: 687 of its 831 scans have a pose in it"),
                        ("nowhere", "in --world-frame nowhere: 'nowhere' is not a frame of its /tf (its frames: ")):
        got, err = _json("odometry", bag, "-o", tmp_path / "p.txt", "--world-frame", frame)
        assert got["against_source_poses"] is None and err.count("\n") == 1 and says in err, err
        assert "voxtool odometry" not in err  # no advice to run itself
