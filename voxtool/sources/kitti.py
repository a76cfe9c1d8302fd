"""The KITTI / SemanticKITTI odometry layout as a scan source.

    sequences/NN/velodyne/000000.bin   float32 x, y, z, reflectance per point (LiDAR frame)
    sequences/NN/calib.txt             "Tr:" 12 numbers, the LiDAR-to-left-camera transform [R|t]
    sequences/NN/poses.txt             (SemanticKITTI) or poses/NN.txt (KITTI): one KITTI row per frame,
                                       the left camera's pose in the first camera frame
    sequences/NN/times.txt             seconds since the sequence's start, one row per frame
    sequences/NN/labels/000000.label   (SemanticKITTI) uint32 per point: semantic class in the low 16 bits

Rows are matched to scans by the scan file's number (a sample holding frames 0-9 of a 4,541-row
sequence reads rows 0-9). The LiDAR's pose is Tr^-1 * P * Tr, as SemanticKITTI's own tools do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.errors import SourceError
from voxtool.geometry import Pose

# SemanticKITTI's moving classes (moving-car .. moving-other-vehicle): the dynamic points
MOVING_CLASSES = range(252, 260)


def sequence_dir(path: Path) -> Path | None:
    """The sequence folder when `path` is one (it holds velodyne/*.bin) or is its velodyne/ folder."""
    if path.is_dir() and (path / "velodyne").is_dir() and any((path / "velodyne").glob("*.bin")):
        return path
    if path.is_dir() and path.name == "velodyne" and any(path.glob("*.bin")):
        return path.parent
    return None


def scan_files(sequence: Path) -> list[Path]:
    files = sorted((sequence / "velodyne").glob("*.bin"))
    bad = [f.name for f in files if not f.stem.isdigit()]
    if bad:
        raise SourceError(f"{sequence / 'velodyne'}: scan files are named by frame number (000000.bin); found {bad[0]}")
    return sorted(files, key=lambda f: int(f.stem))


def read_bin(path: Path) -> np.ndarray:
    """(N, 3) float32 points of a velodyne .bin (x, y, z, reflectance per point)."""
    size = path.stat().st_size
    if size % 16:
        raise SourceError(f"{path}: {size:,} bytes is not a whole number of points (16 bytes each: "
                          "float32 x, y, z, reflectance); cut short?")
    return np.fromfile(path, dtype="<f4").reshape(-1, 4)[:, :3]


WAYS_OUT = ("estimate LiDAR poses with `voxtool odometry {seq} -o poses.txt`, then --poses poses.txt; or give the "
            "recording day's Tr with --kitti-tr (its 12 numbers, or a calib.txt that has it: the odometry "
            "calibration download's)")


def tr_matrix(values, where: str) -> np.ndarray:
    """A Tr's 12 numbers (row-major 3x4 [R|t]) as a 4x4 matrix, checked."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size != 12 or not np.all(np.isfinite(values)):
        raise SourceError(f"{where}: Tr needs 12 numbers (a row-major 3x4 [R|t])")
    tr = np.eye(4)
    tr[:3] = values.reshape(3, 4)
    return tr


def read_tr(calib: Path) -> np.ndarray:
    """The 4x4 LiDAR-to-camera transform of calib.txt's Tr line."""
    if not calib.is_file():
        raise SourceError(f"{calib.parent}: no calib.txt beside the scans: KITTI's poses are the camera's and need its "
                          f"Tr (LiDAR to camera); {WAYS_OUT.format(seq=calib.parent)}")
    for line in calib.read_text(errors="replace").splitlines():
        name, _, rest = line.partition(":")
        if name.strip() == "Tr":
            try:
                values = np.array([float(v) for v in rest.split()])
            except ValueError:
                values = np.empty(0)
            return tr_matrix(values, str(calib))
    raise SourceError(f"{calib}: no Tr line (the LiDAR-to-camera transform KITTI's camera poses need; the sequences "
                      f"as SemanticKITTI samples publish them have none): {WAYS_OUT.format(seq=calib.parent)}")


def _rows(path: Path, width: int, what: str) -> np.ndarray:
    try:
        rows = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as err:
        raise SourceError(f"{path}: cannot read {what}: {err}") from err
    if rows.shape[1] != width or not np.all(np.isfinite(rows)):
        raise SourceError(f"{path}: {what} rows need {width} finite numbers, found {rows.shape[1]}")
    return rows


def pose_file(sequence: Path) -> Path | None:
    """SemanticKITTI's poses.txt in the sequence, or KITTI's poses/NN.txt beside sequences/."""
    for candidate in (sequence / "poses.txt", sequence.parent.parent / "poses" / f"{sequence.name}.txt"):
        if candidate.is_file():
            return candidate
    return None


def lidar_poses(sequence: Path, frames: list[int], tr: np.ndarray | None = None) -> list[Pose]:
    """The LiDAR's pose for each frame number: Tr^-1 * P_camera * Tr (`tr`: 4x4, else calib.txt's)."""
    found = pose_file(sequence)
    if found is None:
        raise SourceError(f"{sequence}: no poses.txt (nor ../../poses/{sequence.name}.txt): the scans have no poses; "
                          f"estimate them with `voxtool odometry {sequence} -o poses.txt`, then --poses poses.txt")
    tr = read_tr(sequence / "calib.txt") if tr is None else tr
    rows = _rows(found, 12, "KITTI poses")
    if max(frames) >= rows.shape[0]:
        raise SourceError(f"{found}: {rows.shape[0]} poses, but the scans go up to frame {max(frames)}")
    tr_inv = np.linalg.inv(tr)
    poses = []
    for f in frames:
        camera = np.eye(4)
        camera[:3] = rows[f].reshape(3, 4)
        m = tr_inv @ camera @ tr
        poses.append(Pose(m[:3, :3], m[:3, 3]))
    return poses


def frame_times(sequence: Path, frames: list[int]) -> list[int] | None:
    """Nanoseconds of each frame from times.txt, or None where there is none."""
    path = sequence / "times.txt"
    if not path.is_file():
        return None
    rows = _rows(path, 1, "times")
    if max(frames) >= rows.shape[0]:
        raise SourceError(f"{path}: {rows.shape[0]} times, but the scans go up to frame {max(frames)}")
    return [int(round(rows[f, 0] * 1e9)) for f in frames]


def read_truth(path: Path, points: int) -> np.ndarray:
    """Per-point dynamic flags of a SemanticKITTI .label file (moving classes 252-259)."""
    if not path.is_file():
        raise SourceError(f"{path}: no label file for this scan (--truth)")
    labels = np.fromfile(path, dtype="<u4")
    if labels.size != points:
        raise SourceError(f"{path}: {labels.size:,} labels for a scan of {points:,} points")
    semantic = labels & 0xFFFF
    return (semantic >= MOVING_CLASSES.start) & (semantic < MOVING_CLASSES.stop)
