from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"

# No test may depend on wall-clock speed: Hypothesis' per-example deadline (200 ms by default) failed
# a compiled-kernel property on a busy machine (a first call compiles or loads the kernel). Every
# property test runs under this profile, whatever its own @settings say of the example count.
from hypothesis import settings  # noqa: E402

settings.register_profile("voxtool", deadline=None)
settings.load_profile("voxtool")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED.is_dir():
        pytest.skip("../shared/data is absent (it ships only with the development checkout)")
    return SHARED


FETCHED = Path(__file__).resolve().parents[1] / ".fetched"


def skip_unfetched(why: str, sample: str) -> None:
    """Skip a test whose public sample is not under .fetched/, naming the command that lays it out."""
    pytest.skip(f"{why} (python scripts/fetch_samples.py {sample} GIT_DIR)")


@pytest.fixture(scope="session")
def kitti_sample() -> Path:
    """SemanticKITTI frames 0-9 of sequences 00 and 05 (scripts/fetch_samples.py lays them out
    from a public repository; not in git: KITTI's licence is non-commercial)."""
    root = FETCHED / "mini_kitti" / "sequences"
    if not (root / "00" / "velodyne").is_dir():
        skip_unfetched("the KITTI sample is absent", "kitti")
    return root


@pytest.fixture(scope="session")
def udacity_dump() -> Path:
    """22 real PCD scans from a driving car with no poses (scripts/fetch_samples.py udacity)."""
    root = FETCHED / "udacity_data_1"
    if not any(root.glob("*.pcd")):
        skip_unfetched("the udacity sample is absent", "udacity")
    return root


@pytest.fixture(scope="session")
def nebula_bags() -> Path:
    """ROS 2 bags of real 3D LiDAR (and radar) packets from TIER IV's nebula drivers' tests
    (scripts/fetch_samples.py nebula)."""
    root = FETCHED / "nebula"
    bags = sorted(p for p in root.glob("*") if (p / "metadata.yaml").is_file())
    if not bags:
        skip_unfetched("the nebula bags are absent", "nebula")
    return bags


@pytest.fixture(scope="session")
def tb3_bag() -> Path:
    """A simulated TurtleBot3's LaserScans (Gazebo), no /tf (scripts/fetch_samples.py tb3)."""
    path = FETCHED / "tb3" / "turtlebot3_scan2.bag"
    if not path.is_file():
        skip_unfetched("the TurtleBot3 bag is absent", "tb3")
    return path


@pytest.fixture(scope="session")
def gazebo_bags() -> Path:
    """A course's ROS 2 bags of a simulated TurtleBot3 with /tf, /odom and /scan: Gazebo's driving,
    standing and sparse logs, whose odom -> base_footprint is the simulator's truth, and a Webots
    log whose /tf is wheel odometry (scripts/fetch_samples.py gazebo; not redistributed)."""
    root = FETCHED / "gazebo_tb3"
    if not (root / "driving" / "metadata.yaml").is_file():
        skip_unfetched("the simulated TurtleBot3 bags are absent", "gazebo")
    return root


@pytest.fixture(scope="session")
def e57_files() -> Path:
    """pye57's test inputs: a real terrestrial scan and a posed scan (scripts/fetch_samples.py e57)."""
    root = FETCHED / "e57"
    if not (root / "pumpAVisualReferenceImage.e57").is_file():
        skip_unfetched("the E57 samples are absent", "e57")
    return root


@pytest.fixture(scope="session")
def las_files() -> Path:
    """laspy's test tiles: Autzen in feet, simple.las/.laz/.copc.laz (scripts/fetch_samples.py las)."""
    root = FETCHED / "las"
    if not (root / "autzen_trim.laz").is_file():
        skip_unfetched("the LAS samples are absent", "las")
    return root


def map_voxels(path):
    """(occupied, free) finest-level Morton codes of a map file, each sorted."""
    import numpy as np

    from voxtool.api import load_leaves
    from voxtool.keys import expand_leaves

    leaves, _, thr, _ = load_leaves(path)
    occ = leaves.values > np.float32(thr)
    return (np.sort(expand_leaves(leaves.codes[occ], leaves.depths[occ])),
            np.sort(expand_leaves(leaves.codes[~occ], leaves.depths[~occ])))


def cli(*args):
    """Run the voxtool command line in this process: (exit code, stdout, stderr)."""
    from click.testing import CliRunner

    from voxtool.cli import main

    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="session")
def sample_map(tmp_path_factory):
    """The shipped sample built once for the whole session: (snapshot path, build --json)."""
    import json

    out = tmp_path_factory.mktemp("sample") / "map.vxm"
    code, text, err = cli("build", "--sample", "-o", out, "--json", "--no-progress")
    assert code == 0, err
    return out, json.loads(text)


SAMPLE_LOG_RANGE = "20"  # m: the paper's sensing range; at full range (180 m) a box is mostly unchanged cells


@pytest.fixture(scope="session")
def sample_map_ranged(tmp_path_factory):
    """The sample built at the sample logs' sensing range: (snapshot path, build --json)."""
    import json

    out = tmp_path_factory.mktemp("sample_ranged") / "map.vxm"
    code, text, err = cli("build", "--sample", "-o", out, "--json", "--no-progress", "--max-range", SAMPLE_LOG_RANGE)
    assert code == 0, err
    return out, json.loads(text)


@pytest.fixture(scope="session")
def sample_logs(tmp_path_factory):
    """Packet logs of the sample at a 20 m sensing range, encoded once: r1 (all scans,
    hilbert/zstd), cm (all scans, codec cm), robots a (scans 0-2) and b (scans 3-4), and f (scan 0
    at 0.1 m); each with encode's --json report."""
    import json

    d = tmp_path_factory.mktemp("logs")
    specs = {"r1": ["--robot", "r1"], "cm": ["--robot", "r1", "--codec", "cm"], "a": ["--robot", "a", "--stop", "3"],
             "b": ["--robot", "b", "--start", "3"], "fine": ["--robot", "f", "--resolution", "0.1", "--stop", "1"]}
    logs = {}
    for name, args in specs.items():
        code, text, err = cli("encode", "--sample", "-o", d / f"{name}.mcap", "--json", "--no-progress",
                              "--max-range", SAMPLE_LOG_RANGE, *args)
        assert code == 0, err
        logs[name] = (d / f"{name}.mcap", json.loads(text))
    return logs
