"""`voxtool odometry`: sensor poses for scans that have none, by LiDAR odometry.

2D scans (LaserScans) are registered to an occupancy grid of the scans before them
(voxtool.grid_matcher, after Hector SLAM's matcher): within a few centimetres of a simulator's
truth where KISS-ICP's point-to-point local map drifts by decimetres (docs/design/odometry.md).
3D scans go to KISS-ICP.

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
from voxtool.errors import ParameterError, SourceError
from voxtool.geometry import planar_pose
from voxtool.grid_matcher import CELLS_PER_RANGE, GridMatcher
from voxtool.sources import SourceOptions, detect_kind, open_source
from voxtool.sources.scan import add_drop_counts

EXTRA = f"pip install '{DISTRIBUTION}[odometry]' (KISS-ICP LiDAR odometry)"


PEEK_SCANS = 10  # scans read before registering: what the sensor's range and kind are
MIN_POINTS = 30  # a scan with fewer points left to register than this is degenerate (a wall, no returns)
SPEED_LIMIT = {True: 5.0, False: 60.0}  # m/s: faster is implausible for a planar (indoor) scanner / a 3D one
# a planar scan whose surface normals put less than this share of their weight in its least
# constrained direction sees a single wall or a featureless corridor: motion along it is unmeasured
# (two parallel walls with 1 cm noise: 0.04; a room's scans: 0.2-0.4)
MIN_SUPPORT = 0.05
DEGENERATE_SHARE = 0.05  # a run with this share of such scans is flagged (0-4 % in the well-registered logs measured)


@dataclass(frozen=True)
class OdometryParams:
    # metres: KISS-ICP's data.max_range (points beyond are not registered); None: from the data,
    # a LaserScan's range_max, else the 99.5th percentile range of the first scans. Its local map
    # voxel is a hundredth of it: 1 m for 100 m, far too coarse for a 3.5-12 m indoor scanner
    max_range: float | None = None
    min_range: float = 0.0
    # the local map's cell: KISS-ICP's voxel (None: max_range / 100, its default), the grid's finest cell
    # (None: max_range / 140)
    voxel_size: float | None = None
    planar: bool | None = None  # register in the plane (z, roll, pitch held at 0); None: 2D scans (every z 0)
    # "grid" (2D scans: voxtool.grid_matcher) or "kiss-icp"; None: the grid for 2D scans, KISS-ICP otherwise
    matcher: str | None = None

    def __post_init__(self) -> None:
        if self.max_range is not None and not (self.max_range > 0 and np.isfinite(self.max_range)):
            raise ParameterError(f"--max-range {self.max_range}: odometry needs a finite range > 0 (metres)")
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ParameterError(f"--voxel-size {self.voxel_size}: give a size > 0 (metres)")
        if self.matcher not in (None, *MATCHERS):
            raise ParameterError(f"--matcher {self.matcher!r}: one of {', '.join(MATCHERS)}")


MATCHERS = ("grid", "kiss-icp")


def _import_kiss_icp():
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise ParameterError(f"voxtool odometry needs KISS-ICP: {EXTRA}") from None
    return KISSConfig, KissICP


def _kiss_icp(max_range: float, min_range: float, voxel_size: float, planar: bool):
    KISSConfig, KissICP = _import_kiss_icp()
    config = KISSConfig()
    config.data.max_range = max_range
    config.data.min_range = min_range
    config.data.deskew = False  # scans carry no per-point times here
    config.mapping.voxel_size = voxel_size
    if not planar:
        return KissICP(config)

    class PlanarKissICP(KissICP):
        """KISS-ICP's register_frame with each pose held in the plane: a 2D scan constrains x, y
        and yaw only, and ICP left free drifts in z, roll and pitch."""

        def register_frame(self, frame, timestamps):
            frame = self.preprocessor.preprocess(frame, timestamps, self.last_delta)
            source, frame_downsample = self.voxelize(frame)
            sigma = self.adaptive_threshold.get_threshold()
            initial_guess = self.last_pose @ self.last_delta
            new_pose = in_plane(self.registration.align_points_to_map(
                points=source, voxel_map=self.local_map, initial_guess=initial_guess,
                max_correspondance_distance=3 * sigma, kernel=sigma))
            self.adaptive_threshold.update_model_deviation(np.linalg.inv(initial_guess) @ new_pose)
            self.local_map.update(frame_downsample, new_pose)
            self.last_delta = np.linalg.inv(self.last_pose) @ new_pose
            self.last_pose = new_pose
            return frame, source

    return PlanarKissICP(config)


class _KissOdometry:
    """KISS-ICP behind GridMatcher's two calls: register a scan, the last pose."""

    def __init__(self, kiss):
        self.kiss = kiss

    def register(self, cloud: np.ndarray) -> int:
        _, used = self.kiss.register_frame(cloud, np.empty(0))
        return len(used)

    def pose_matrix(self) -> np.ndarray:
        return self.kiss.last_pose.copy()


def in_plane(pose: np.ndarray) -> np.ndarray:
    """A 4x4 pose projected to the plane: its yaw and x, y kept; z, roll and pitch 0."""
    return planar_pose(pose[0, 3], pose[1, 3], np.arctan2(pose[1, 0], pose[0, 0]))


def sensor_range(scans: list) -> float:
    """The range to register within, from the first scans (sensor frame): a LaserScan's range_max,
    else the 99.5th percentile of the points' ranges, rounded up to 0.5 m (at least 1 m)."""
    declared = [s.miss_range for s in scans if s.miss_range > 0]
    if declared:
        return float(max(declared))
    ranges = np.concatenate([np.linalg.norm(s.points.astype(np.float64), axis=1) for s in scans] or [np.zeros(0)])
    if ranges.size == 0:
        return 100.0
    return max(1.0, float(np.ceil(np.percentile(ranges, 99.5) * 2.0) / 2.0))


def weak_direction_support(points: np.ndarray, min_range: float, max_range: float) -> float:
    """How well a planar scan (sensor frame) fixes motion in its least constrained direction: the
    share of its surface normals' weight there, the smaller eigenvalue of the sum of n n^T over its
    points' normals over their sum (0 along a straight wall, 0.5 where walls face every way). A
    normal comes from a point's neighbours in bearing, two either side on the same surface (no
    range jump), where they lie on a line."""
    p = points[:, :2].astype(np.float64)
    r = np.hypot(p[:, 0], p[:, 1])
    keep = (r < max_range) & (r > min_range)
    p, r = p[keep], r[keep]
    n = len(p)
    if n < 5:
        return 0.0
    order = np.argsort(np.arctan2(p[:, 1], p[:, 0]))
    p, r = p[order], r[order]
    around = (np.arange(n)[:, None] + np.arange(-2, 3)[None, :]) % n  # a full turn wraps round
    same = np.abs(r[around] - r[:, None]) < 0.1 * r[:, None] + 0.05
    count = same.sum(axis=1)
    mean = (p[around] * same[..., None]).sum(axis=1) / count[:, None]
    offsets = (p[around] - mean[:, None, :]) * same[..., None]
    spread, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", offsets, offsets))
    line = (count >= 4) & (spread[:, 0] < 0.1 * spread[:, 1])
    normals = axes[line, :, 0]
    if not len(normals):
        return 0.0
    weak, strong = np.linalg.eigvalsh(normals.T @ normals)
    return float(weak / (weak + strong))


def path_length(positions: np.ndarray, step: float) -> float:
    """The distance travelled, counted from one kept position to the next once they are `step`
    apart: a standing sensor's jitter (millimetres a scan, hundreds of scans) adds nothing."""
    total, anchor = 0.0, positions[0] if len(positions) else None
    for p in positions[1:]:
        d = float(np.linalg.norm(p - anchor))
        if d >= step:
            total += d
            anchor = p
    return total


def _one_direction_run(weak: int, scans: int) -> bool:
    """Whether a run's scans that fix one direction only are enough to flag it."""
    return weak > 0 and weak >= DEGENERATE_SHARE * scans


def plausibility(positions: np.ndarray, stamps_ns: np.ndarray, registered: np.ndarray, planar: bool,
                 max_range: float, support: np.ndarray | None = None) -> dict:
    """What says a run diverged or had too little to go on: steps faster than a sensor of its
    kind moves (or, without times, longer than a quarter of its range), scans with fewer than
    MIN_POINTS points to register, and (planar runs, `support` from weak_direction_support) a
    DEGENERATE_SHARE of scans that cannot fix motion along one direction."""
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    dt = np.diff(stamps_ns.astype(np.float64)) / 1e9
    timed = bool(len(dt)) and bool(np.all(dt > 0))
    limit = SPEED_LIMIT[planar]
    if timed:
        speeds = steps / dt
        bad = np.flatnonzero(speeds > limit)
        worst = float(speeds.max()) if len(speeds) else 0.0
    else:
        bad = np.flatnonzero(steps > max_range / 4.0)
        worst = float(steps.max()) if len(steps) else 0.0
    sparse = np.flatnonzero(registered < MIN_POINTS)
    # a scan too sparse to register is counted as sparse, not again as degenerate
    weak = np.flatnonzero((support < MIN_SUPPORT) & (registered >= MIN_POINTS)) if support is not None else np.zeros(0, int)
    degenerate = _one_direction_run(weak.size, len(registered))
    return {"implausible_steps": int(bad.size), "first_implausible_scan": int(bad[0] + 1) if bad.size else None,
            "max_speed_m_s" if timed else "max_step_m": round(worst, 3),
            "limit": f"{limit} m/s" if timed else f"{max_range / 4.0:g} m a scan",
            "sparse_scans": int(sparse.size), "first_sparse_scan": int(sparse[0]) if sparse.size else None,
            "one_direction_scans": int(weak.size) if support is not None else None,
            "first_one_direction_scan": int(weak[0]) if weak.size else None,
            "suspect": bool(bad.size or sparse.size or degenerate)}


def estimate_poses(source: str | os.PathLike, options: SourceOptions, params: OdometryParams,
                   progress: bool | None = None) -> dict:
    """Register every scan of `source` in its sensor frame; returns the poses (4x4, the first
    scan's frame), the scans' stamps (ns, 0 where unknown), and figures."""
    import warnings
    from itertools import chain, islice

    from voxtool.errors import VoxtoolWarning
    from voxtool.progress import track

    if detect_kind(Path(source)) in ("las", "laz"):
        raise SourceError(f"{source}: a survey tile's points are already placed in the tile's frame, with no sensor "
                          "scans to register: odometry estimates a moving sensor's poses from its scans (a tile's rays "
                          "come from the sensor's trajectory by GPS time: build it with --poses)")
    if params.matcher == "kiss-icp":
        _import_kiss_icp()  # the extra's one line before any reading
    stream = open_source(source, replace(options, sensor_frame=True, origin=None))
    scans = iter(stream.scans)
    first = list(islice(scans, PEEK_SCANS))
    max_range = params.max_range or sensor_range(first)
    flat = bool(first) and all(s.points.shape[0] == 0 or not np.any(s.points[:, 2]) for s in first)
    planar = params.planar if params.planar is not None else flat
    matcher = params.matcher or ("grid" if flat and planar else "kiss-icp")
    if matcher == "grid" and not (flat and planar):
        raise ParameterError(f"{source}: --matcher grid registers 2D scans (every point at z 0 in the sensor's "
                             "frame, in the plane); these are 3D: leave --matcher to its default (KISS-ICP)")
    if matcher == "grid":
        voxel_size = params.voxel_size or max_range / CELLS_PER_RANGE
        odometry = GridMatcher(max_range, params.min_range, voxel_size, MIN_POINTS)
    else:
        voxel_size = params.voxel_size or max_range / 100.0
        odometry = _KissOdometry(_kiss_icp(max_range, params.min_range, voxel_size, planar))
    poses, stamps, points, dropped, registered, support = [], [], 0, {}, [], []
    t0 = time.perf_counter()
    for scan in track(chain(first, scans), stream.count, "odometry", progress, unit="scan"):
        cloud = scan.points.astype(np.float64)
        registered.append(odometry.register(cloud))
        poses.append(odometry.pose_matrix())
        stamps.append(scan.stamp_ns)
        if planar:
            support.append(weak_direction_support(scan.points, params.min_range, max_range))
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
    positions = np.array([m[:3, 3] for m in poses])
    # a standing sensor's registration jitter is no path: a move counts once the position is half a
    # KISS-ICP voxel, or a whole grid cell (range / 140, finer than the voxel), from the last counted one
    # (a standing 12 m RPLidar's grid poses wander 3-6 cm: 0.23 m of path at half a cell, 0 at one)
    path_m = path_length(positions, voxel_size if matcher == "grid" else voxel_size / 2.0)
    check = plausibility(positions, np.array(stamps, dtype=np.int64), np.array(registered), planar, max_range,
                         np.array(support) if planar else None)
    if check["suspect"]:
        said = []
        if check["implausible_steps"]:
            worst = (f"{check['max_speed_m_s']:.1f} m/s" if "max_speed_m_s" in check else f"{check['max_step_m']:.2f} m")
            said.append(f"{check['implausible_steps']} steps beyond {check['limit']} (the worst {worst}; the "
                        f"first at scan {check['first_implausible_scan']})")
        if check["sparse_scans"]:
            said.append(f"{check['sparse_scans']} scans with fewer than {MIN_POINTS} points to register (the first: "
                        f"scan {check['first_sparse_scan']})")
        weak = check["one_direction_scans"] or 0
        if _one_direction_run(weak, len(poses)):
            said.append(f"{weak} scans ({100 * weak / len(poses):.0f} %) fix the motion in one direction only, a single "
                        "wall or a featureless corridor in range: motion along it is not measured (the first: scan "
                        f"{check['first_one_direction_scan']})")
        warnings.warn(f"{source}: the odometry may have diverged: {'; '.join(said)}; check the poses (build a map "
                      "and look) before trusting them", VoxtoolWarning, stacklevel=2)
    against = against_source_poses(source, options, positions, path_m)
    return {"poses": np.array(poses), "stamps_ns": np.array(stamps, dtype=np.int64),
            "figures": {"source": str(source), "scans": len(poses), "points": points, **dropped, "path_m": round(path_m, 6),
                        "against_source_poses": against, "plausibility": check,
                        "params": {"max_range": max_range, "max_range_from": "given" if params.max_range else "the data",
                                   "min_range": params.min_range, "voxel_size": voxel_size, "planar": planar,
                                   "matcher": matcher},
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


def aligned_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each estimated position's distance from the truth's after one rigid fit of the whole
    trajectory onto the truth (rigid_fit), and the fit's rotation."""
    r, t = rigid_fit(estimated, truth)
    return np.linalg.norm(estimated @ r.T + t - truth, axis=1), r


def ate_rmse(estimated: np.ndarray, truth: np.ndarray) -> float:
    """A trajectory's absolute error (ATE RMSE, metres) against the truth, after one rigid fit."""
    return float(np.sqrt(np.mean(aligned_errors(estimated, truth)[0] ** 2)))


def against_source_poses(source, options: SourceOptions, estimated: np.ndarray, path_m: float) -> dict | None:
    """How far the odometry's sensor positions are from the source's own poses, where it has
    them (a KITTI poses.txt, PCD VIEWPOINTs, a pose file): ATE RMSE and largest error after a
    rigid alignment, and the end's drift in % of the path. None where the source has none."""
    import warnings

    from voxtool.errors import VoxtoolWarning

    frame = options.world_frame

    def not_compared(why: str) -> None:
        warnings.warn(f"{source}: the odometry is not compared with the log's poses in --world-frame {frame}: {why}",
                      VoxtoolWarning, stacklevel=4)

    try:
        with warnings.catch_warnings():  # what reading its poses says (no poses: run odometry) is not news here
            warnings.simplefilter("ignore", VoxtoolWarning)
            truth = np.array([scan.origin for scan in open_source(source, replace(options, origin=None)).scans],
                             dtype=np.float64)
    except SourceError as error:
        if frame is not None:  # asked for by name: say why there is no comparison (not how to build)
            why = str(error).removeprefix(f"{source}: ").split("; or ")[0]
            not_compared(why.replace(f"--world-frame {frame} ", f"{frame!r} ", 1))
        return None  # the source cannot pose its scans (what odometry is for)
    if truth.shape[0] != estimated.shape[0] and frame is not None:
        not_compared(f"{truth.shape[0]} of its {estimated.shape[0]} scans have a pose in it")
    if truth.shape[0] != estimated.shape[0] or truth.shape[0] < 3 or np.ptp(truth, axis=0).max() < 1e-6:
        return None  # no poses (every scan at the origin), or not one per scan
    error, r = aligned_errors(estimated, truth)
    # the end's drift with the start pinned: both trajectories from their first position
    end = np.linalg.norm((estimated[-1] - estimated[0]) @ r.T - (truth[-1] - truth[0]))
    return {"ate_rmse_m": round(float(np.sqrt(np.mean(error ** 2))), 6), "ate_max_m": round(float(error.max()), 6),
            "end_drift_m": round(float(end), 6),
            # a standing sensor has no path to take a share of (null, not a drift of millions of %)
            "end_drift_percent_of_path": round(100 * float(end) / path_m, 3) if path_m > 0 else None}


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
