"""Scan sources: every supported input turned into a stream of world-frame `Scan`s.

SOURCES maps a kind to its opener; `open_source` picks the kind from the path.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

import numpy as np

from voxtool.errors import ParameterError, SourceError, VoxtoolWarning
from voxtool.geometry import Pose
from voxtool.sources.scan import Scan

BAD_SCAN_POLICIES = ("fail", "skip")


@dataclass(frozen=True)
class SourceOptions:
    poses: str | None = None  # pose file (TUM / indexed TUM / KITTI)
    no_viewpoint: bool = False  # PCD points are world-frame; only the origin comes from a pose
    topic: str | None = None
    world_frame: str | None = None  # None: the root of the /tf tree above the cloud's frame
    pose_topic: str | None = None
    start: int = 0
    stop: int | None = None
    every: int = 1
    min_range: float = 0.0
    bad_scans: str = "fail"  # a scan that cannot be read: "fail" (stop with its error) or "skip" (warn, go on)
    # the map's local origin in the source's frame (subtracted from every point and sensor origin
    # in float64, before the float32 rounding); "auto": resolve_origin() picks one
    origin: tuple[float, float, float] | str | None = None
    # a folder of per-scan ground-truth labels (SemanticKITTI NNNNNN.label beside each scan file's
    # number or name): each scan carries its points' dynamic flags as extra["truth"] (clean --truth)
    truth: str | None = None
    # the points in the sensor's own frame, every pose the identity: what odometry registers
    sensor_frame: bool = False
    # (xmin, ymin, zmin, xmax, ymax, zmax) in the sensor's frame, metres: the vehicle's own body, whose
    # returns are dropped (PCL's CropBox, negative); they would leave a trail of obstacles along the path
    ego_box: tuple[float, ...] | None = None
    # a KITTI sequence's Tr (LiDAR to camera: 12 numbers, row-major [R|t]) where its calib.txt has none
    kitti_tr: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.bad_scans not in BAD_SCAN_POLICIES:
            raise ParameterError(f"--bad-scans {self.bad_scans!r}: one of {', '.join(BAD_SCAN_POLICIES)}")
        if self.start < 0 or (self.stop is not None and self.stop < self.start) or self.every < 1:
            raise ParameterError(f"scan slice start={self.start} stop={self.stop} every={self.every} is invalid")
        if self.ego_box is not None:
            box = np.asarray(self.ego_box, dtype=np.float64)
            if box.shape != (6,) or not np.all(np.isfinite(box)) or np.any(box[:3] > box[3:]):
                raise ParameterError(f"--ego-box {','.join(f'{v:g}' for v in np.ravel(box))}: give xmin,ymin,zmin,"
                                     "xmax,ymax,zmax in metres in the sensor's frame, each min at most its max")


class BadScans:
    """What a source does with a scan it cannot read (--bad-scans): 'fail' raises the scan's
    error; 'skip' warns on one line, records the scan and its reason, and reading goes on."""

    def __init__(self, policy: str) -> None:
        self.policy = policy
        self.skipped: list[dict] = []
        self.unposed = 0  # scans left out for want of a transform at their time (before the first, after the last)

    def unposed_scans(self, before: list[int], after: list[int]) -> None:
        self.unposed += len(before) + len(after)

    def __call__(self, index: int, err: SourceError) -> None:
        if self.policy == "fail":
            if "--bad-scans" in str(err):
                raise err
            import copy

            named = copy.copy(err)  # the same error (class, exit code), its line naming the way on
            named.args = (f"{err}; --bad-scans skip leaves out the scans that cannot be read, with a warning",)
            raise named from err
        import warnings

        from voxtool.errors import VoxtoolWarning

        self.skipped.append({"index": index, "reason": str(err)})
        warnings.warn(f"skipped scan {index}: {err}", VoxtoolWarning, stacklevel=2)


@dataclass
class ScanStream:
    """A source opened for reading: how many scans it will yield (if known), the scans, and
    those skipped as unreadable so far (bad.skipped, with --bad-scans skip)."""

    kind: str
    path: Path
    count: int | None
    scans: Iterator[Scan]
    bad: BadScans = field(default_factory=lambda: BadScans("fail"))


def _selected(path: Path, total: int, options: SourceOptions) -> int:
    """How many of a source's `total` scans the slice options select; none of some is an error
    (a script slicing past the end should not get an empty map and exit 0)."""
    n = len(range(total)[options.start:options.stop:options.every])
    if n == 0 and total > 0:
        stop = f" --stop {options.stop}" if options.stop is not None else ""
        raise ParameterError(f"{path}: --start {options.start}{stop} --every {options.every} selects none of its "
                             f"{total} scans (indices 0..{total - 1})")
    return n


def _numeric_key(path: Path) -> tuple:
    """Sort scan files by the numbers in their names, never as strings of unequal length."""
    return tuple(int(n) for n in re.findall(r"\d+", path.stem)), path.name


def make_scan(points: np.ndarray, pose: Pose, index: int, stamp_ns: int, source: str, raw_bytes: int,
              options: SourceOptions, world_frame_points: bool = False, misses: tuple | None = None,
              per_point: dict | None = None) -> Scan:
    """Drop non-finite points, move sensor-frame points to the world (about the local origin,
    if any), drop those below min range. misses: (sensor-frame no-return beams, their range),
    whose NaN places in `points` are not counted as dropped (ros_msgs.decode_laserscan).
    per_point: arrays of one value per point (ground-truth labels), kept for the same points
    and put in the scan's `extra`."""
    if options.sensor_frame:
        pose = Pose.identity()
    finite = np.isfinite(points).all(axis=1)
    # a point exactly at the sensor's position is no surface: drivers write "no return" as (0, 0, 0)
    # in organized clouds, and one such point per scan marks the sensor's own voxel as a hit
    sensor = pose.translation.astype(points.dtype) if world_frame_points else np.zeros(3, points.dtype)
    at_origin = finite & (points == sensor).all(axis=1)
    on_vehicle = _in_ego_box(points, pose, world_frame_points, options.ego_box) & finite & ~at_origin
    keep = finite & ~at_origin & ~on_vehicle
    kept = points[keep]
    extra = {name: values[keep] for name, values in (per_point or {}).items()}
    if options.origin is not None:
        if isinstance(options.origin, str):
            raise ParameterError(f"--origin {options.origin} was not resolved (resolve_origin) before reading {source}")
        shift = np.asarray(options.origin, dtype=np.float64)
        pose = Pose(np.eye(3), -shift).compose(pose)  # world - origin, all in float64
        if world_frame_points:
            kept = np.asarray(kept, dtype=np.float64) - shift
    world = np.asarray(kept, dtype=np.float32) if world_frame_points else pose.apply(kept)
    origin = pose.translation.astype(np.float32)
    miss_points, miss_range = (None, -1.0) if misses is None else misses
    if miss_points is not None:
        miss_points = pose.apply(miss_points)
    if options.min_range > 0 and world.shape[0]:
        d = np.linalg.norm(world.astype(np.float64) - origin.astype(np.float64), axis=1)
        near = d < options.min_range
        dropped_min = int(near.sum())
        world = world[~near]
        extra = {name: values[~near] for name, values in extra.items()}
    else:
        dropped_min = 0
    return Scan(
        points=np.ascontiguousarray(world, dtype=np.float32),
        origin=origin,
        index=index,
        stamp_ns=stamp_ns,
        source=source,
        points_read=int(points.shape[0]),
        dropped_nonfinite=int((~finite).sum()) - (0 if miss_points is None else int(miss_points.shape[0])),
        dropped_at_origin=int(at_origin.sum()),
        dropped_ego_box=int(on_vehicle.sum()),
        dropped_min_range=dropped_min,
        raw_bytes=raw_bytes,
        misses=None if miss_points is None else np.ascontiguousarray(miss_points, dtype=np.float32),
        miss_range=float(miss_range),
        extra=extra,
    )


def _in_ego_box(points: np.ndarray, pose: Pose, world_frame_points: bool, box) -> np.ndarray:
    """Which points lie in the vehicle's box (sensor frame, inclusive); none without a box."""
    if box is None or points.shape[0] == 0:
        return np.zeros(points.shape[0], bool)
    local = np.asarray(points, dtype=np.float64)
    if world_frame_points:
        local = (local - pose.translation) @ pose.rotation  # R^T (p - t), row by row
    lo, hi = np.asarray(box[:3]), np.asarray(box[3:])
    with np.errstate(invalid="ignore"):  # NaN points: in no box
        return ((local >= lo) & (local <= hi)).all(axis=1)


def _pose_rows(options: SourceOptions, n_scans: int | None, scans: str = "scans") -> list | None:
    """The --poses rows, one per scan (`scans` says what a scan is in the message); None without
    --poses. n_scans None: not known before reading (a log read from its start), not checked."""
    if options.poses is None:
        return None
    from voxtool.sources.poses import read_poses

    rows = read_poses(options.poses)
    if n_scans is not None and len(rows) != n_scans:
        longer = (" (a whole sequence's or a longer run's file? --poses takes one row per scan read, in order: "
                  "cut it to the scans read)" if len(rows) > n_scans else "")
        raise SourceError(f"{options.poses}: pose file has {len(rows)} poses for {n_scans} {scans}{longer}")
    return rows


BESIDE_POSES = "poses.txt"  # a PCD directory's own pose file: its times are the scans' times


def _times_beside(path: Path, n_scans: int) -> list | None:
    """Scan times (seconds) from the `poses.txt` beside a PCD directory's scans, when it gives
    one time per scan; None (with a warning when the file is there but does not fit)."""
    import warnings

    from voxtool.errors import VoxtoolWarning
    from voxtool.sources.poses import read_poses

    file = path / BESIDE_POSES
    if not file.is_file():
        return None
    try:
        rows = read_poses(file)
    except SourceError as err:
        warnings.warn(f"{err}; the scans have no times (pass --poses to use a pose file)", VoxtoolWarning,
                      stacklevel=2)
        return None
    if len(rows) != n_scans or any(stamp is None for stamp, _ in rows):
        why = f"{len(rows)} rows for {n_scans} scans" if len(rows) != n_scans else "no times (KITTI rows)"
        warnings.warn(f"{file}: {why}; the scans have no times", VoxtoolWarning, stacklevel=2)
        return None
    return [stamp for stamp, _ in rows]


def _open_cloud_files(path: Path, options: SourceOptions, suffix: str) -> ScanStream:
    files = sorted(path.glob(f"*{suffix}"), key=_numeric_key) if path.is_dir() else [path]
    if not files:
        raise SourceError(f"{path}: directory holds no {suffix} files")
    rows = _pose_rows(options, len(files))
    # without --poses, a PCD directory's poses come from VIEWPOINT and its times from poses.txt
    times = _times_beside(path, len(files)) if rows is None and suffix == ".pcd" and path.is_dir() else None
    if suffix == ".ply" and rows is None and not options.sensor_frame:
        raise SourceError(f"{path}: PLY scans need a pose file (--poses); `voxtool odometry` estimates one")

    bad = BadScans(options.bad_scans)
    unposed: list[int] = []  # scans with neither a VIEWPOINT nor a pose row: one warning for them all

    def read(i: int, f: Path) -> Scan:
        from voxtool.sources.pcd import read_pcd
        from voxtool.sources.ply import read_ply

        stamp = 0
        if suffix == ".pcd":
            cloud = read_pcd(f)
            points = cloud.xyz
            vp = cloud.viewpoint
            pose = Pose.from_quat(vp[:3], vp[3], vp[4], vp[5], vp[6])
            # no VIEWPOINT, or PCL's default one (the identity): what a driver's dump holds
            if pose.is_identity() and rows is None and not options.sensor_frame and not options.no_viewpoint:
                unposed.append(i)
        else:
            points = read_ply(f)
            pose = Pose.identity()
        if rows is not None:
            stamp_s, pose = rows[i]
            stamp = int(round(stamp_s * 1e9)) if stamp_s is not None else 0
        elif times is not None:
            stamp = int(round(times[i] * 1e9))
        if options.no_viewpoint:
            pose = Pose(np.eye(3), pose.translation)
        return make_scan(points, pose, i, stamp, str(f), f.stat().st_size, options, options.no_viewpoint,
                         per_point=truth_of(f, points.shape[0], options))

    def scans() -> Iterator[Scan]:
        read_count = 0
        for scan in _file_scans(files, options, read, bad):
            read_count += 1
            yield scan
        if len(unposed) > 1 and len(unposed) == read_count:  # all at the origin: a static sensor, or a dump without poses
            import warnings

            from voxtool.errors import VoxtoolWarning

            warnings.warn(f"{path}: none of its {len(unposed)} scans has a pose (no VIEWPOINT, or the identity, and no "
                          "--poses): all were taken as seen from the origin, as a static sensor's; for a moving "
                          "one, `voxtool odometry` estimates poses", VoxtoolWarning, stacklevel=2)

    return ScanStream(suffix.lstrip("."), path, _selected(path, len(files), options), scans(), bad)


def _file_scans(files: list[Path], options: SourceOptions, read, bad: BadScans) -> Iterator[Scan]:
    """read(i, file) of the scan files the slice options select; one that cannot be read goes
    to `bad` (which raises, or records it and reading goes on)."""
    for i, f in islice(enumerate(files), options.start, options.stop, options.every):
        try:
            scan = read(i, f)
        except SourceError as err:
            bad(i, err)
            continue
        yield scan


def truth_of(scan_file: Path, points: int, options: SourceOptions) -> dict | None:
    """The scan's ground-truth dynamic flags (--truth DIR: the .label of the scan file's name)."""
    if options.truth is None:
        return None
    from voxtool.sources.kitti import read_truth

    return {"truth": read_truth(Path(options.truth) / f"{scan_file.stem}.label", points)}


def _open_kitti(path: Path, options: SourceOptions) -> ScanStream:
    """A KITTI / SemanticKITTI sequence (voxtool/sources/kitti.py): LiDAR poses from its camera
    poses and calib.txt's Tr, or --poses (LiDAR poses, one row per scan file)."""
    from voxtool.sources import kitti

    sequence = kitti.sequence_dir(path)
    files = kitti.scan_files(sequence)
    frames = [int(f.stem) for f in files]
    own = kitti.pose_file(sequence)
    if options.poses is not None and own is not None and Path(options.poses).resolve() == own.resolve():
        raise SourceError(f"{options.poses}: the sequence's own poses, the camera's: --poses takes LiDAR poses; leave "
                          "it out, and the scans are posed by these moved to the LiDAR with calib.txt's Tr "
                          "(or --kitti-tr)")
    rows = _pose_rows(options, len(files))
    tr = None if options.kitti_tr is None else kitti.tr_matrix(options.kitti_tr, "--kitti-tr")
    poses = None if rows is not None or options.sensor_frame else kitti.lidar_poses(sequence, frames, tr)
    times = kitti.frame_times(sequence, frames)
    bad = BadScans(options.bad_scans)

    def read(i: int, f: Path) -> Scan:
        points = kitti.read_bin(f)
        stamp = times[i] if times is not None else 0
        if rows is not None:
            stamp_s, pose = rows[i]
            stamp = int(round(stamp_s * 1e9)) if stamp_s is not None else stamp
        else:
            pose = Pose.identity() if poses is None else poses[i]
        return make_scan(points, pose, i, stamp, str(f), f.stat().st_size, options,
                         per_point=truth_of(f, points.shape[0], options))

    return ScanStream("kitti", sequence, _selected(sequence, len(files), options),
                      _file_scans(files, options, read, bad), bad)


def _open_pcd(path: Path, options: SourceOptions) -> ScanStream:
    return _open_cloud_files(path, options, ".pcd")


def _open_ply(path: Path, options: SourceOptions) -> ScanStream:
    return _open_cloud_files(path, options, ".ply")


def _open_mcap(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.mcap_ros2 import McapCloudSource

    src = McapCloudSource(path, options.topic, options.world_frame, options.pose_topic,
                          recover=options.bad_scans == "skip", own_poses=_log_poses_itself(options))
    return _log_stream("mcap", path, src, options)


def _open_bag(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.rosbag import BagCloudSource

    src = BagCloudSource(path, options.topic, options.world_frame, options.pose_topic,
                         recover=options.bad_scans == "skip", own_poses=_log_poses_itself(options))
    return _log_stream("rosbag1" if src.path.suffix.lower() == ".bag" else "rosbag2", path, src, options)


def _log_poses_itself(options: SourceOptions) -> bool:
    """Whether a log's clouds are posed by its own /tf or pose topic: not when odometry reads them
    in their sensor's frame, nor when a pose file (--poses) poses them."""
    if options.poses is not None and (options.pose_topic is not None or options.world_frame is not None):
        raise ParameterError("--poses poses a log's scans by message order: it goes without --pose-topic and "
                             "--world-frame")
    return not options.sensor_frame and options.poses is None


STAMP_MATCH_NS = 1_000_000  # a pose row and its scan message stamped further apart are not of one log


def _log_stream(kind: str, path: Path, src, options: SourceOptions) -> ScanStream:
    """The scans of a log of ROS messages (an MCAP file, a bag): one source per message. With
    --poses, row i of the pose file poses scan message i of the topic (`voxtool odometry` of the
    log writes one row per message, stamped as the message)."""
    bad = BadScans(options.bad_scans)
    rows = _pose_rows(options, src.count, f"scan messages of '{src.topic}' in {path}")

    def posed(i: int, stamp: int) -> Pose:
        if i >= len(rows):
            raise SourceError(f"{options.poses}: pose file has {len(rows)} poses, {path} has more scan messages on "
                              f"'{src.topic}'")
        row_stamp, pose = rows[i]
        if row_stamp is not None and abs(round(row_stamp * 1e9) - stamp) > STAMP_MATCH_NS:
            raise SourceError(f"{options.poses}: row {i + 1} is stamped {row_stamp:.6f} s, scan message {i} of "
                              f"'{src.topic}' {stamp / 1e9:.6f} s: a pose file of another log or topic (KITTI rows, "
                              "without times, pose by order alone)")
        return pose

    def scans() -> Iterator[Scan]:
        read = 0
        for i, points, pose, stamp, nbytes, misses in src.scans(options.start, options.stop, options.every, bad):
            read += 1
            if rows is not None:
                pose = posed(i, stamp)
            yield make_scan(points, pose, i, stamp, f"{path}#{i}", nbytes, options, misses=misses)
        lost = src.lost() if hasattr(src, "lost") else ""
        if lost and not read:
            raise SourceError(f"{path}: no scan can be read: {lost}")
        if not read and not bad.skipped and not lost:  # an empty map with exit 0 would pass for a map
            where = "" if options.start == 0 and options.stop is None else " in the --start/--stop range"
            raise SourceError(f"{path}: its scan topic '{src.topic}' holds no messages{where}: nothing to build from")
        if lost:  # a truncated log read as far as it goes (--bad-scans skip)
            import warnings

            from voxtool.errors import VoxtoolWarning

            warnings.warn(f"{path}: {lost}; the {read} whole scans before it were read", VoxtoolWarning, stacklevel=2)

    count = _selected(path, src.count, options) if src.count is not None else None
    return ScanStream(kind, path, count, scans(), bad)


def _open_graph(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.graph import count_graph_nodes, iter_graph

    if options.poses is not None:  # never silently ignored
        raise ParameterError(f"{path}: an OctoMap graph holds its scans' poses; --poses is for scan folders, KITTI "
                             "sequences and ROS logs")
    n = count_graph_nodes(path)

    def scans() -> Iterator[Scan]:
        for i, (points, pose, nbytes) in islice(enumerate(iter_graph(path)), options.start, options.stop, options.every):
            yield make_scan(points, pose, i, 0, f"{path}#{i}", nbytes, options)

    return ScanStream("graph", path, _selected(path, n, options), scans())


def _open_e57(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.e57 import e57_stream

    return e57_stream(path, options)


def _open_pcap(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.velodyne import pcap_stream

    return pcap_stream(path, options)


def _open_las(path: Path, options: SourceOptions) -> ScanStream:
    from voxtool.sources.las import las_stream

    return las_stream(path, options)


SOURCES: dict[str, Callable[[Path, SourceOptions], ScanStream]] = {
    "pcd": _open_pcd,
    "ply": _open_ply,
    "mcap": _open_mcap,
    "graph": _open_graph,
    "bag": _open_bag,
    "db3": _open_bag,
    "kitti": _open_kitti,
    "e57": _open_e57,
    "pcap": _open_pcap,
    "pcapng": _open_pcap,
    "las": _open_las,
    "laz": _open_las,
}
BAG_DIRECTORY = "metadata.yaml"  # what makes a directory a ROS 2 bag


GENERIC_FOLDERS = {"pcd", "ply", "scans", "scan", "points", "clouds", "lidar", "velodyne", "data", "bag", "bags"}


def source_names(sources: list[str | Path]) -> list[str]:
    """A name per source for outputs and titles: the shortest suffix of its path (parts joined by
    '-', a file without its suffix) that tells the sources apart: data/kaist03/pcd and
    data/norlab/pcd are kaist03-pcd and norlab-pcd. A lone source whose name only says what it
    holds (pcd/, scans/) gets its parent's name too."""
    parts = []
    for s in sources:
        p = Path(s).resolve()
        names = [*p.parent.parts[1:], p.name if p.is_dir() or not p.suffix else p.stem]
        parts.append([n for n in names if n] or ["source"])
    longest = max(len(p) for p in parts)
    for k in range(1, longest + 1):
        names = ["-".join(p[-k:]) for p in parts]
        generic = len(parts) == 1 and parts[0][-1].lower() in GENERIC_FOLDERS and k < min(2, len(parts[0]))
        if len(set(names)) == len(names) and not generic:
            return names
    return ["-".join(p) for p in parts]


def _scan_folders(path: Path, depth: int = 2) -> list[str]:
    """Sub-folders of `path` (down to `depth` levels) that hold scans or are ROS 2 bags."""
    found = []
    for sub in sorted(p for p in path.iterdir() if p.is_dir()):
        if (sub / BAG_DIRECTORY).is_file() or any(p.suffix.lower() in (".pcd", ".ply") for p in sub.iterdir()) \
                or (sub / "velodyne").is_dir():
            found.append(str(sub.relative_to(path)))
        elif depth > 1:
            found += [str(Path(sub.name) / f) for f in _scan_folders(sub, depth - 1)]
    return found


def detect_kind(path: Path) -> str:
    if path.is_dir():
        if (path / BAG_DIRECTORY).is_file():
            return "bag"
        from voxtool.sources.kitti import sequence_dir

        if sequence_dir(path) is not None:
            return "kitti"
        kinds = {p.suffix.lower() for p in path.iterdir() if p.suffix.lower() in (".pcd", ".ply")}
        if len(kinds) != 1:
            folders = _scan_folders(path) if not kinds else []
            if folders:
                shown = ", ".join(folders[:8]) + (f" and {len(folders) - 8} more" if len(folders) > 8 else "")
                raise SourceError(f"{path}: holds no scans itself, but its sub-folders do: {shown} (give one of them, "
                                  "or several with -o DIRECTORY for one map each)")
            raise SourceError(f"{path}: directory must hold .pcd or .ply scans, be a ROS 2 bag ({BAG_DIRECTORY}) or a KITTI sequence (velodyne/*.bin) "
                              f"(found {sorted(kinds) or 'neither'})")
        return kinds.pop().lstrip(".")
    if path.suffix.lower() == ".mcap" and (path.parent / BAG_DIRECTORY).is_file():
        return "bag"  # the storage file of a ROS 2 bag: read through its metadata.yaml
    kind = path.suffix.lower().lstrip(".")
    if kind not in SOURCES:
        raise SourceError(f"{path}: unknown source type '{path.suffix}' (known: {', '.join(sorted(SOURCES))}, or a directory)")
    return kind


def parse_origin(text: str | None) -> tuple[float, float, float] | str | None:
    """--origin auto|X,Y,Z as SourceOptions.origin."""
    if text is None or text == "auto":
        return text
    try:
        xyz = tuple(float(v) for v in text.split(","))
    except ValueError:
        xyz = ()
    if len(xyz) != 3 or not np.all(np.isfinite(xyz)):
        raise ParameterError(f"--origin {text}: give auto or three numbers X,Y,Z (metres, in the scans' frame)")
    return xyz


def resolve_origin(path: str | Path, options: SourceOptions, resolution: float) -> SourceOptions:
    """Options with a usable local origin: X,Y,Z snapped to the voxel grid (a multiple of the
    resolution, so voxels keep their places in the scans' frame and the map is OctoMap's map of
    the shifted scans); "auto": the first scan's sensor position, snapped likewise."""
    from dataclasses import replace

    if options.origin is None:
        return options
    if isinstance(options.origin, str):
        with warnings.catch_warnings():  # what the source says of its scans, it says when they are read
            warnings.simplefilter("ignore", VoxtoolWarning)
            first = next(iter(open_source(path, replace(options, origin=None, start=0, stop=1, every=1)).scans), None)
        if first is None:
            raise SourceError(f"{path}: --origin auto: the source holds no scan to take the origin from")
        where = np.asarray(first.origin, dtype=np.float64)
    else:
        where = np.asarray(options.origin, dtype=np.float64)
    snapped = np.round(where / resolution) * resolution
    return replace(options, origin=tuple(float(v) for v in snapped))


def open_source(path: str | Path, options: SourceOptions | None = None) -> ScanStream:
    path = Path(path)
    options = options or SourceOptions()
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    return SOURCES[detect_kind(path)](path, options)
