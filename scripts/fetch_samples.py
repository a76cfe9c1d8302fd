"""Lay out the real samples some tests use in .fetched/ (ignored by git; the tests skip without them).

kitti: .fetched/mini_kitti. Source: the public repository rancheng/mini_kitti_dataset (commit 2a361538a576d0c675b537ee3bffecda85905609):
the first 10 frames of each KITTI odometry sequence 00-10 with SemanticKITTI labels, poses.txt and
times.txt. KITTI: CC BY-NC-SA 3.0; SemanticKITTI labels: CC BY-NC-SA 4.0. Neither goes into voxtool's git.

Its calib.txt files lack the Tr line (LiDAR to camera 0) that the poses need. KITTI's odometry calibration
gives one Tr per recording day; this script appends it, as the odometry calibration download's calib.txt
holds it (values as quoted in public KITTI tooling): sequences 00-02 (2011_10_03) and 04-10 (2011_09_30).

udacity: .fetched/udacity_data_1, 22 PCD scans (about 120 k points each) from a driving car, with PCL's
identity VIEWPOINT and no poses: a driver's dump as users have them. Source:
the public repository udacity/SFND_Lidar_Obstacle_Detection (commit
ef15da2bc172359e7d6edfdd156a2a243d10977e), src/sensors/data/pcd/data_1.

nebula: .fetched/nebula/<sensor>/, the ROS 2 bags (sqlite3, with metadata.yaml) of the public repository
tier4/nebula (commit 606ac41f1f136333915f0114736f2f828e9d2789, Apache-2.0), its decoders' test inputs:
real Velodyne VLP-16/VLP-32/VLS-128 and Hesai Pandar 40P/64/QT64/QT128/XT16/XT32/XT32M logs of four
raw packet messages each (velodyne_msgs/VelodyneScan, pandar_msgs/PandarScan: no points until a
driver decodes them), and two Continental radar logs. 3D LiDAR logs as drivers record them. Beside
them, in ground_truth/<sensor>/<log time>.pcd, nebula's own decoder's points of one message of each
Velodyne bag: a decoder other than the one voxtool uses.

tb3: .fetched/tb3/turtlebot3_scan2.bag, a ROS 1 bag of a simulated TurtleBot3 (Gazebo, the
turtlebot3_world arena) driving: 538 LaserScans on /scan, frame base_scan, no /tf. Source: the
public repository samialperen/oko_slam (commit 7136b806bfd13fafee9b7cf9995202ba063a0aca, MIT),
ros_ws/bagfiles/simulation_data/turtlebot3_scan2.bag. A 2D scanner's log that nothing poses.

gazebo: .fetched/gazebo_tb3/<log>/, ROS 2 bags (sqlite3, with metadata.yaml) a robotics course recorded of a
simulated TurtleBot3 burger (360-beam 3.5 m LDS-01): /scan with /tf, /tf_static, /odom and /clock. Source: the
public repository josetamaritfernandez/IR2121 (commit 270b77c93ca615264986f5f338ea95e75594426b; it states no
licence: laid out here for local tests, never redistributed). In Gazebo (driving, standing, sparse) the
diff-drive plugin publishes odom -> base_footprint from the model's world pose (its odometry_source left at
the default, WORLD): the simulator's truth.
  driving: Teleoperation/scripts/rosbag2_2023_10_25-17_10_22.zip, 816 scans over 163 s, 28.4 m along a
  house's corridor (Gazebo).
  standing: Teleoperation/scripts/rosbag2_2023_10_25-16_35_56, 114 scans of a robot that stands still (Gazebo).
  sparse: Worlds/scripts/rosbag2_2023_11_27-18_22_26, 110 scans of a robot standing in a nearly empty world,
  about 20 returns a scan (Gazebo).
  webots: Teleoperation/scripts/rosbag2_2023_09_27-16_31_26.zip, 1,189 scans over 258 s in a furnished room
  (Webots: its odom -> base_link is the wheels' odometry, which drifts).
gazebo-hall: .fetched/gazebo_tb3/hall/, a ROS 2 bag of the same course a year later, from the public
repository Danivfr/IR2121 (commit 2e8a9c18acd22d6e548bfbeaf6b4e56df95f6afd, Worlds/rosbag2_2025_10_06-18_47_53.zip;
no licence stated: local tests only): a Gazebo TurtleBot3 driving 42 m round a 12 m x 15 m hall, 1,046
scans, with the simulator's /tf. With a 3.5 m scanner most of the hall is one wall or none in range.
gazebo-teleop: .fetched/gazebo_tb3/teleop/, a ROS 2 bag of the same course from the public repository
hurtaditoo/IR2121 (commit 920bdfdbbda7fd4ed9263e55a9f0cded5f5fb21c,
Teleoperation/scripts/rosbag2_2023_10_07-02_37_34.zip; no licence stated: local tests only): a Gazebo TurtleBot3
driven 9.1 m through a house's rooms, 333 scans over 67 s, with the simulator's /tf.
gazebo-localization: .fetched/gazebo_tb3/localization/, a ROS 2 bag of the same course from the public
repository mpuigsari/IR2121 (commit 916b75ac105d4d73180fa719ae50abca2e32fb56,
Worlds/rosbags/localization/rosbag2_2023_10_24-12_51_52.zip; no licence stated: local tests only): a Gazebo
TurtleBot3 driven 12.4 m through a house while AMCL localised it, 831 scans over 207 s, with the simulator's
odom -> base_footprint (and AMCL's map -> odom).

e57: .fetched/e57/, the E57 files of the public repository davidcaron/pye57 (commit
b8d20999f3037c580bf1fe1dcb239c50a8f764ad, MIT), its tests' inputs: pumpAVisualReferenceImage.e57 (one real
terrestrial scan of a pump, 155,201 points with intensity and colour), translationWithoutRotation.e57
(a scan with a pose of translation only) and testWithNormals.e57.

ouster: .fetched/ouster/, two Ouster captures with their metadata JSON from the public repository
ouster-lidar/ouster-sdk (commit 46b7bcee, its tests/pcaps; BSD-3): OS-1-32-G and OS-2-128-U1, 1024x10.
Captures voxtool does not decode (docs/sources.md): the tests check the line that says so.

las: .fetched/las/, survey tiles from the public repository laspy/laspy (commit fbc5b37, its tests/data;
BSD-2): autzen_trim.laz (110,000 points of the Autzen stadium in international feet, NAD83 Oregon
Lambert, WKT and GeoTIFF keys), simple.las and simple.laz (the same 1,065 points), simple.copc.laz
(COPC) and file_with_both_wkt_and_geotiff_vlrs.las (US survey feet).

    python scripts/fetch_samples.py kitti GIT_DIR     # a clone or mirror of rancheng/mini_kitti_dataset
    python scripts/fetch_samples.py udacity GIT_DIR   # a clone or mirror of udacity/SFND_Lidar_Obstacle_Detection
    python scripts/fetch_samples.py nebula GIT_DIR    # a clone or mirror of tier4/nebula
    python scripts/fetch_samples.py tb3 GIT_DIR       # a clone or mirror of samialperen/oko_slam
    python scripts/fetch_samples.py gazebo GIT_DIR    # a clone or mirror of josetamaritfernandez/IR2121
    python scripts/fetch_samples.py gazebo-hall GIT_DIR   # a clone or mirror of Danivfr/IR2121
    python scripts/fetch_samples.py gazebo-teleop GIT_DIR   # a clone or mirror of hurtaditoo/IR2121
    python scripts/fetch_samples.py gazebo-localization GIT_DIR   # a clone or mirror of mpuigsari/IR2121
    python scripts/fetch_samples.py e57 GIT_DIR       # a clone or mirror of davidcaron/pye57
    python scripts/fetch_samples.py ouster GIT_DIR    # a clone or mirror of ouster-lidar/ouster-sdk
    python scripts/fetch_samples.py las GIT_DIR       # a clone or mirror of laspy/laspy
"""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile
from pathlib import Path

COMMIT = "2a361538a576d0c675b537ee3bffecda85905609"
SEQUENCES = ("00", "01", "02", "04", "05", "06", "07", "08", "09", "10")  # 03: its day's Tr is not quoted here
TR = {
    "2011_10_03": "4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 "
                  "-7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 "
                  "9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01",
    "2011_09_30": "-1.857739385241e-03 -9.999659513510e-01 -8.039975204516e-03 -4.784029760483e-03 "
                  "-6.481465826011e-03 8.051860151134e-03 -9.999466081774e-01 -7.337429464231e-02 "
                  "9.999773098287e-01 -1.805528627661e-03 -6.496203536139e-03 -3.339968064433e-01",
}
DAY = {"00": "2011_10_03", "01": "2011_10_03", "02": "2011_10_03", **{f"{n:02d}": "2011_09_30" for n in range(4, 11)}}
FETCHED = Path(__file__).resolve().parents[1] / ".fetched"
DST = FETCHED / "mini_kitti"
UDACITY_COMMIT = "ef15da2bc172359e7d6edfdd156a2a243d10977e"


def _git(git_dir: str):
    def git(*args: str) -> bytes:
        return subprocess.run(["git", "-C", git_dir, *args], check=True, capture_output=True).stdout
    return git


def udacity(git_dir: str) -> None:
    git = _git(git_dir)
    out = FETCHED / "udacity_data_1"
    out.mkdir(parents=True, exist_ok=True)
    names = git("ls-tree", "-r", "--name-only", UDACITY_COMMIT, "src/sensors/data/pcd/data_1").decode().split()
    for name in names:
        (out / Path(name).name).write_bytes(git("show", f"{UDACITY_COMMIT}:{name}"))
    print(f"{out}: {len(names)} scans")


NEBULA_COMMIT = "606ac41f1f136333915f0114736f2f828e9d2789"


def nebula(git_dir: str) -> None:
    git = _git(git_dir)
    out = FETCHED / "nebula"
    names = git("ls-tree", "-r", "--name-only", NEBULA_COMMIT, "src").decode().split()
    bags = sorted({n.rsplit("/", 1)[0] for n in names if "/decoder_ground_truth/" in n and n.endswith(".db3")})
    laid = 0
    for bag in bags:
        sensor = bag.split("/decoder_ground_truth/")[1].split("/")[0]
        folder = out / (sensor if not bag.endswith("all_points") else f"{sensor}_all_points")
        try:
            files = {n.rsplit("/", 1)[1]: git("show", f"{NEBULA_COMMIT}:{n}") for n in names if n.rsplit("/", 1)[0] == bag}
        except subprocess.CalledProcessError:  # a Git LFS file the copy does not hold
            print(f"{bag}: not in this copy, left out")
            continue
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (folder / name).write_bytes(data)
        laid += 1
    # nebula's own decoder's output for one message of each Velodyne bag (named by its log time)
    truths = [n for n in names if "/nebula_velodyne/" in n and "/decoder_ground_truth/" in n and n.endswith(".pcd")]
    for name in truths:
        sensor = name.split("/decoder_ground_truth/")[1].split("/")[0]
        (out / "ground_truth" / sensor).mkdir(parents=True, exist_ok=True)
        (out / "ground_truth" / sensor / name.rsplit("/", 1)[1]).write_bytes(git("show", f"{NEBULA_COMMIT}:{name}"))
    (out / "PROVENANCE.md").write_text(__doc__)
    print(f"{out}: {laid} bags, {len(truths)} decoded clouds")


TB3_COMMIT = "7136b806bfd13fafee9b7cf9995202ba063a0aca"
TB3_BAG = "ros_ws/bagfiles/simulation_data/turtlebot3_scan2.bag"


def tb3(git_dir: str) -> None:
    out = FETCHED / "tb3"
    out.mkdir(parents=True, exist_ok=True)
    (out / "turtlebot3_scan2.bag").write_bytes(_git(git_dir)("show", f"{TB3_COMMIT}:{TB3_BAG}"))
    print(f"{out}: turtlebot3_scan2.bag")


GAZEBO_COMMIT = "270b77c93ca615264986f5f338ea95e75594426b"
GAZEBO_LOGS = {"driving": "Teleoperation/scripts/rosbag2_2023_10_25-17_10_22.zip",
               "standing": "Teleoperation/scripts/rosbag2_2023_10_25-16_35_56",
               "sparse": "Worlds/scripts/rosbag2_2023_11_27-18_22_26",
               "webots": "Teleoperation/scripts/rosbag2_2023_09_27-16_31_26.zip"}


HALL_COMMIT = "2e8a9c18acd22d6e548bfbeaf6b4e56df95f6afd"
HALL_LOGS = {"hall": "Worlds/rosbag2_2025_10_06-18_47_53.zip"}
TELEOP_COMMIT = "920bdfdbbda7fd4ed9263e55a9f0cded5f5fb21c"
TELEOP_LOGS = {"teleop": "Teleoperation/scripts/rosbag2_2023_10_07-02_37_34.zip"}
LOCALIZATION_COMMIT = "916b75ac105d4d73180fa719ae50abca2e32fb56"
LOCALIZATION_LOGS = {"localization": "Worlds/rosbags/localization/rosbag2_2023_10_24-12_51_52.zip"}


def _course_logs(git_dir: str, commit: str, logs: dict[str, str]) -> None:
    """ROS 2 bags of a course's repository, each a folder or a zip of one, laid out in
    .fetched/gazebo_tb3/<log>/ (metadata.yaml and the .db3: not sqlite's empty -shm/-wal files)."""
    git = _git(git_dir)
    for log, path in logs.items():
        out = FETCHED / "gazebo_tb3" / log
        out.mkdir(parents=True, exist_ok=True)
        if path.endswith(".zip"):
            with zipfile.ZipFile(io.BytesIO(git("show", f"{commit}:{path}"))) as archive:
                files = {Path(n).name: archive.read(n) for n in archive.namelist()}
        else:
            names = git("ls-tree", "--name-only", commit, f"{path}/").decode().split("\n")
            files = {Path(n).name: git("show", f"{commit}:{n}") for n in names if n}
        for name, data in files.items():
            if name == "metadata.yaml" or name.endswith(".db3"):
                (out / name).write_bytes(data)
    (FETCHED / "gazebo_tb3" / "PROVENANCE.md").write_text(__doc__)
    print(f"{FETCHED / 'gazebo_tb3'}: {', '.join(logs)}")


def gazebo(git_dir: str) -> None:
    _course_logs(git_dir, GAZEBO_COMMIT, GAZEBO_LOGS)


def gazebo_hall(git_dir: str) -> None:
    _course_logs(git_dir, HALL_COMMIT, HALL_LOGS)


def gazebo_teleop(git_dir: str) -> None:
    _course_logs(git_dir, TELEOP_COMMIT, TELEOP_LOGS)


def gazebo_localization(git_dir: str) -> None:
    _course_logs(git_dir, LOCALIZATION_COMMIT, LOCALIZATION_LOGS)


def _lay_out(git_dir: str, commit: str, folder: str, names, sample: str) -> None:
    """Files `names` of `folder` at `commit` of a repository, copied to .fetched/<sample>/."""
    out = FETCHED / sample
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        (out / name).write_bytes(_git(git_dir)("show", f"{commit}:{folder}/{name}"))
    print(f"{out}: {', '.join(names)}")


E57_COMMIT = "b8d20999f3037c580bf1fe1dcb239c50a8f764ad"
E57_FILES = ("pumpAVisualReferenceImage.e57", "translationWithoutRotation.e57", "testWithNormals.e57")
OUSTER_COMMIT = "46b7bcee"
OUSTER_FILES = tuple(f"{name}{suffix}" for name in ("OS-1-32-G_v2.1.1_1024x10", "OS-2-128-U1_v2.3.0_1024x10")
                     for suffix in (".pcap", ".json"))
LAS_COMMIT = "fbc5b37"
LAS_FILES = ("autzen_trim.laz", "simple.las", "simple.laz", "simple.copc.laz", "file_with_both_wkt_and_geotiff_vlrs.las")


def e57(git_dir: str) -> None:
    _lay_out(git_dir, E57_COMMIT, "tests/test_data", E57_FILES, "e57")


def ouster(git_dir: str) -> None:
    _lay_out(git_dir, OUSTER_COMMIT, "tests/pcaps", OUSTER_FILES, "ouster")


def las(git_dir: str) -> None:
    _lay_out(git_dir, LAS_COMMIT, "tests/data", LAS_FILES, "las")


def kitti(git_dir: str) -> None:
    git = _git(git_dir)

    for seq in SEQUENCES:
        names = git("ls-tree", "-r", "--name-only", COMMIT, f"dataset/sequences/{seq}").decode().split()
        for name in names:
            if "/image_" in name or "/voxels/" in name:
                continue
            out = DST / name.removeprefix("dataset/")
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(git("show", f"{COMMIT}:{name}"))
        calib = DST / "sequences" / seq / "calib.txt"
        if "Tr:" not in calib.read_text():
            calib.write_text(calib.read_text().rstrip("\n") + f"\nTr: {TR[DAY[seq]]}\n")
    (DST / "PROVENANCE.md").write_text(__doc__)
    print(f"{DST}: sequences {', '.join(SEQUENCES)}")


if __name__ == "__main__":
    {"kitti": kitti, "udacity": udacity, "nebula": nebula, "tb3": tb3, "gazebo": gazebo, "gazebo-hall": gazebo_hall,
     "gazebo-teleop": gazebo_teleop, "gazebo-localization": gazebo_localization, "e57": e57, "ouster": ouster, "las": las}[sys.argv[1]](sys.argv[2])
