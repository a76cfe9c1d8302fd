"""`voxtool odometry`: sensor poses for scans that have none, by KISS-ICP LiDAR odometry.

KISS-ICP (PyPI `kiss-icp`, MIT; Vizzo et al., RA-L 2023) registers each scan to a local map of
the scans before it: point-to-point ICP with an adaptive threshold, a constant-velocity guess,
voxel-downsampled points. It is an optional extra (`pip install 'voxtool-lidar[odometry]'`): its
compiled core is what makes this practical, and it is maintained by its authors. The poses are
of the first scan's sensor frame, written as a pose file that `build`, `clean` and `eval` read
with `--poses` (TUM rows with times where the source has them, KITTI rows otherwise).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import ParameterError
from voxtool.sources import SourceOptions, open_source
from voxtool.sources.scan import add_drop_counts

EXTRA = f"pip install '{DISTRIBUTION}[odometry]' (KISS-ICP LiDAR odometry)"


@dataclass(frozen=True)
class OdometryParams:
    max_range: float = 100.0  # metres: KISS-ICP's data.max_range (points beyond are not registered)
    min_range: float = 0.0
    voxel_size: float | None = None  # KISS-ICP's local map voxel; None: max_range / 100, its default

    def __post_init__(self) -> None:
        if not (self.max_range > 0 and np.isfinite(self.max_range)):
            raise ParameterError(f"--max-range {self.max_range}: odometry needs a finite range > 0 (metres)")
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ParameterError(f"--voxel-size {self.voxel_size}: give a size > 0 (metres)")


def _kiss_icp(params: OdometryParams):
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise ParameterError(f"voxtool odometry needs KISS-ICP: {EXTRA}") from None
    config = KISSConfig()
    config.data.max_range = params.max_range
    config.data.min_range = params.min_range
    config.data.deskew = False  # scans carry no per-point times here
    config.mapping.voxel_size = params.voxel_size or params.max_range / 100.0
    return KissICP(config)


def estimate_poses(source: str | os.PathLike, options: SourceOptions, params: OdometryParams,
                   progress: bool | None = None) -> dict:
    """Register every scan of `source` in its sensor frame; returns the poses (4x4, the first
    scan's frame), the scans' stamps (ns, 0 where unknown), and figures."""
    from voxtool.progress import track

    odometry = _kiss_icp(params)
    stream = open_source(source, replace(options, sensor_frame=True, origin=None))
    poses, stamps, points, dropped = [], [], 0, {}
    t0 = time.perf_counter()
    for scan in track(stream.scans, stream.count, "odometry", progress, unit="scan"):
        cloud = scan.points.astype(np.float64)
        odometry.register_frame(cloud, np.empty(0))
        poses.append(odometry.last_pose.copy())
        stamps.append(scan.stamp_ns)
        points += cloud.shape[0]
        add_drop_counts(dropped, scan)
    seconds = time.perf_counter() - t0
    if not poses:
        raise ParameterError(f"{source}: no scan to register")
    skipped = stream.bad.skipped
    if skipped:
        # a pose file has one row per scan file: a skipped scan would shift every later row
        raise ParameterError(f"{source}: {len(skipped)} scans could not be read (first: {skipped[0]['reason']}); "
                             "a pose file needs a pose for every scan")
    path_m = float(sum(np.linalg.norm(b[:3, 3] - a[:3, 3]) for a, b in zip(poses, poses[1:])))
    against = against_source_poses(source, options, np.array([m[:3, 3] for m in poses]), path_m)
    return {"poses": np.array(poses), "stamps_ns": np.array(stamps, dtype=np.int64),
            "figures": {"source": str(source), "scans": len(poses), "points": points, **dropped, "path_m": round(path_m, 6),
                        "against_source_poses": against,
                        "params": {"max_range": params.max_range, "min_range": params.min_range,
                                   "voxel_size": params.voxel_size or params.max_range / 100.0},
                        "timings_s": {"total": round(seconds, 6),
                                      "per_scan_ms": round(1000 * seconds / len(poses), 3)}}}


def rigid_fit(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising |R a + t - b| over point pairs (Kabsch; no scale): the alignment under
    which a trajectory's absolute error (ATE) is measured."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def against_source_poses(source, options: SourceOptions, estimated: np.ndarray, path_m: float) -> dict | None:
    """How far the odometry's sensor positions are from the source's own poses, where it has
    them (a KITTI poses.txt, PCD VIEWPOINTs, a pose file): ATE RMSE and largest error after a
    rigid alignment, and the end's drift in % of the path. None where the source has none."""
    import warnings

    from voxtool.errors import SourceError, VoxtoolWarning

    try:
        with warnings.catch_warnings():  # what reading its poses says (no poses: run odometry) is not news here
            warnings.simplefilter("ignore", VoxtoolWarning)
            truth = np.array([scan.origin for scan in open_source(source, replace(options, origin=None)).scans],
                             dtype=np.float64)
    except SourceError:
        return None  # the source cannot pose its scans (what odometry is for)
    if truth.shape[0] != estimated.shape[0] or truth.shape[0] < 3 or np.ptp(truth, axis=0).max() < 1e-6:
        return None  # no poses (every scan at the origin), or not one per scan
    r, t = rigid_fit(estimated, truth)
    error = np.linalg.norm(estimated @ r.T + t - truth, axis=1)
    # the end's drift with the start pinned: both trajectories from their first position
    end = np.linalg.norm((estimated[-1] - estimated[0]) @ r.T - (truth[-1] - truth[0]))
    return {"ate_rmse_m": round(float(np.sqrt(np.mean(error ** 2))), 6), "ate_max_m": round(float(error.max()), 6),
            "end_drift_m": round(float(end), 6), "end_drift_percent_of_path": round(100 * float(end) / max(path_m, 1e-9), 3)}


def pose_rows(poses: np.ndarray, stamps_ns: np.ndarray) -> tuple[str, list[str]]:
    """('tum' or 'kitti', one text row per pose): TUM `t x y z qx qy qz qw` where every scan has
    a time, KITTI's row-major 3x4 [R|t] otherwise."""
    from voxtool.geometry import matrix_to_quat

    if stamps_ns.size and np.all(stamps_ns > 0) or (stamps_ns.size > 1 and np.all(np.diff(stamps_ns) > 0)):
        rows = []
        for m, ns in zip(poses, stamps_ns):
            qw, qx, qy, qz = matrix_to_quat(m[:3, :3])
            x, y, z = m[:3, 3]
            rows.append(f"{ns / 1e9:.9f} {x:.9f} {y:.9f} {z:.9f} {qx:.9f} {qy:.9f} {qz:.9f} {qw:.9f}")
        return "tum", rows
    return "kitti", [" ".join(f"{v:.9e}" for v in m[:3].ravel()) for m in poses]


def write_pose_file(path: str | os.PathLike, poses: np.ndarray, stamps_ns: np.ndarray) -> str:
    """Write the poses atomically; returns the format written."""
    from voxtool.atomic import atomic_writer

    kind, rows = pose_rows(poses, stamps_ns)
    header = ("# voxtool odometry (KISS-ICP): the sensor's pose per scan, in the first scan's frame; "
              + ("t x y z qx qy qz qw\n" if kind == "tum" else "KITTI rows (3x4 [R|t], row-major)\n"))
    with atomic_writer(Path(path)) as handle:
        handle.write((header + "\n".join(rows) + "\n").encode())
    return kind
