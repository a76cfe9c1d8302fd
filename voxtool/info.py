"""`voxtool info SOURCE`: what a source holds before anything is built from it (what `ros2 bag
info`, `mcap info` and `pdal info` give): its scans, time span and points per scan; for ROS logs
its topics, the /tf tree, and the pose source `build` would use, or why there is none."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from voxtool.errors import SourceError, VoxtoolError, VoxtoolWarning
from voxtool.sources import SourceOptions, detect_kind, open_source


def _spread(values: list[int]) -> dict | None:
    if not values:
        return None
    a = np.asarray(values)
    return {"min": int(a.min()), "median": float(np.median(a)), "max": int(a.max())}


def _span(stamps: list[int]) -> dict | None:
    """The stamps' span; None where the scans have no times (every stamp 0). A stamp of 0 among
    others is a time (KITTI's first scan), not a missing one."""
    if not any(stamps):
        return None
    return {"first_ns": min(stamps), "last_ns": max(stamps), "seconds": round((max(stamps) - min(stamps)) * 1e-9, 6)}


def describe(source: str | Path, options: SourceOptions | None = None) -> dict:
    """A dict of what the source holds (see the module's docstring)."""
    path = Path(source)
    options = options or SourceOptions()
    if not path.exists():
        raise SourceError(f"{path}: no such file or directory")
    kind = detect_kind(path)
    if kind in ("bag", "db3"):
        return _describe_bag(path, options)
    if kind == "mcap":
        return _describe_mcap(path, options)
    return _describe_stream(path, kind, options)


def _describe_stream(path: Path, kind: str, options: SourceOptions) -> dict:
    """Files of scans (PCD, PLY, graph): every scan read, as build would read it."""
    if kind in ("las", "laz") and options.poses is None:
        return _describe_tile(path, kind, options)
    unposed = None
    try:
        stream = open_source(path, options)
    except SourceError as err:
        if kind not in ("kitti", "pcap", "pcapng") or options.poses is not None:
            raise
        # a sequence build cannot pose (no Tr, no poses.txt): its scans listed all the same, and why
        from dataclasses import replace

        unposed = str(err)
        stream = open_source(path, replace(options, sensor_frame=True))
    points, stamps, invalid = [], [], []
    for scan in stream.scans:
        points.append(scan.points_read)
        stamps.append(scan.stamp_ns)
        invalid.append(scan.dropped_nonfinite)
    out = {"source": str(path), "kind": stream.kind, "scans": len(points), "points_per_scan": _spread(points),
           "time_span": _span(stamps),
           "pose_source": _file_pose_source(path, kind, options) if unposed is None else f"none: {unposed}"}
    if kind == "pcd":
        first = next(iter(sorted(path.glob("*.pcd"))), None) if path.is_dir() else path
        if first is not None:
            out["fields"] = _pcd_fields(first)
    if kind in ("las", "laz"):
        out.update(_tile_header(path))
    if kind in ("pcap", "pcapng"):
        from voxtool.sources.velodyne import capture_sensor

        with warnings.catch_warnings():  # the scans' read has said what is wrong with the capture
            warnings.simplefilter("ignore", VoxtoolWarning)
            sensor = capture_sensor(path)
        out["lidar"] = {**sensor, "rate_hz": _rate_hz(stamps)}
    if kind == "e57":
        from voxtool.sources.e57 import open_e57

        e57 = open_e57(path)  # held while its header is read (pye57 frees the file with the reader)
        out["fields"] = list(e57.get_header(0).point_fields)
        out["points_invalid"] = int(sum(invalid))  # a direction only, or no return: dropped by build
    return out


def _tile_header(path: Path) -> dict:
    from voxtool.sources.las import check_complete, open_tile, tile_units

    with open_tile(path) as reader:
        check_complete(path, reader.header)
        return {"units": tile_units(reader.header), "points_in_tile": int(reader.header.point_count)}


def _describe_tile(path: Path, kind: str, options: SourceOptions) -> dict:
    """A survey tile without a trajectory, from its header alone: its scans are chunks of its
    points, and reading them all (a LAZ tile of a billion points takes minutes) would tell nothing more."""
    from voxtool.sources.las import CHUNK_POINTS

    tile = _tile_header(path)
    count = tile["points_in_tile"]
    sizes = [min(CHUNK_POINTS, count - start) for start in range(0, count, CHUNK_POINTS)] or [0]
    return {"source": str(path), "kind": "las", "scans": len(sizes), "points_per_scan": _spread(sizes),
            "time_span": None, "pose_source": _file_pose_source(path, kind, options), **tile}


def _rate_hz(stamps: list[int]) -> float | None:
    """Scans a second (a spinning sensor's revolutions): one over the median time between scans,
    so that a revolution cut by where the recording starts or stops does not skew it (a capture
    started a quarter turn late read 12.5/s for a 10/s sensor over the stamps' span); None without
    times."""
    if _span(stamps) is None:
        return None
    gaps = np.diff(np.sort(np.asarray(stamps, np.int64)))
    gap_s = float(np.median(gaps)) * 1e-9 if gaps.size else 0.0
    return round(1.0 / gap_s, 2) if gap_s > 0 else None


def _pcd_fields(path: Path) -> list[str]:
    with open(path, "rb") as f:
        for line in f.read(4096).split(b"\n"):
            if line.upper().startswith(b"FIELDS"):
                return line.decode("ascii", "replace").split()[1:]
    return []


def _file_pose_source(path: Path, kind: str, options: SourceOptions) -> str:
    if options.poses:
        return f"pose file {options.poses}"
    if kind == "pcd":
        return "each PCD's VIEWPOINT (times from the poses.txt beside the scans, when there is one)"
    if kind == "graph":
        return "the graph's node poses"
    if kind == "kitti":
        from voxtool.sources.kitti import pose_file, sequence_dir

        found = pose_file(sequence_dir(path))
        if found is None:
            return "none: no poses.txt (voxtool odometry estimates them)"
        return f"{found.name}, the camera's poses moved to the LiDAR by calib.txt's Tr (times from times.txt)"
    if kind == "ply":
        return "none: PLY scans need --poses (voxtool odometry estimates them)"
    if kind in ("las", "laz"):
        return "none: a survey tile has no sensor origin (its points mark occupied voxels; free space stays unknown)"
    if kind == "e57":
        from voxtool.sources.e57 import open_e57

        e57 = open_e57(path)
        posed = sum(e57.get_header(i).has_pose() for i in range(e57.scan_count))
        return f"each scan's header pose ({posed} of {e57.scan_count} scans have one; the others sit at the origin)"
    return "none"


def _scan_counts(msgtype: str, msg, found: dict) -> int:
    """Points (or beams) of a scan message; a VelodyneScan is decoded, and what its decoder
    found (model, return mode) is put in `found`."""
    from voxtool.sources.ros_msgs import LASER, VELODYNE

    if msgtype == VELODYNE:
        from voxtool.sources.velodyne import decode_revolution

        points, what = decode_revolution("info", msg)
        found.update(what)
        return int(points.shape[0])
    return len(msg.ranges) if msgtype == LASER else int(msg.width) * int(msg.height)


def _pose_source(poses, frame: str | None, stamps: list[int]) -> dict:
    """Whether `build` can pose the scans, and by what: tried at the middle scan's stamp."""
    if frame is None or not stamps:
        return {"posed": False, "why": "no scan"}
    stamp = sorted(stamps)[len(stamps) // 2]
    try:
        poses.pose_at(frame, stamp)
    except VoxtoolError as err:
        text = str(err)
        return {"posed": False, "why": text.split(": ", 1)[1] if ": " in text else text}
    if poses.pose_topic is not None:
        return {"posed": True, "by": f"pose topic {poses.pose_topic}", "mount": poses.mount_note}
    return {"posed": True, "by": f"/tf: scan frame '{frame.lstrip('/')}' in world frame '{poses.world_frame}'"}


def _log_figures(kind: str, path: Path, topics: list[dict], topic: str, msgtype: str, messages, poses,
                 problem: str | None) -> dict:
    """What a ROS log (bag or MCAP) holds: `messages` are its scan topic's decoded messages,
    `poses` its tf.SensorPoses as read (`problem`: why they could not be)."""
    from voxtool.sources.tf import header_stamp

    points, stamps, frame, found = [], [], None, {}
    for msg in messages:
        points.append(_scan_counts(msgtype, msg, found))
        stamps.append(header_stamp(msg.header))
        frame = frame or msg.header.frame_id
    edges = [] if poses is None else sorted(poses.edges.items())
    if found:  # driver packets: the sensor as its decoder found it, and its revolutions per second
        found["rate_hz"] = _rate_hz(stamps)
    return {"source": str(path), "kind": kind, "topics": topics, "scan_topic": topic, "scan_type": msgtype,
            **({"lidar": found} if found else {}),
            "scans": len(points), "points_per_scan": _spread(points), "time_span": _span(stamps), "scan_frame": frame,
            "tf": [{"parent": p, "child": c, "static": e.static, "transforms": len(e.stamps)} for (p, c), e in edges],
            "pose_source": {"posed": False, "why": problem} if problem else _pose_source(poses, frame, stamps)}


def _describe_bag(path: Path, options: SourceOptions) -> dict:
    from voxtool.sources.bag_limits import bag_errors
    from voxtool.sources.ros_msgs import SCAN_TYPES
    from voxtool.sources.rosbag import BagCloudSource, open_bag

    recover = options.bad_scans == "skip"
    bag = open_bag(path, recover)
    kind = "rosbag1" if path.suffix.lower() == ".bag" else "rosbag2"
    topics = [{"topic": t, "type": s, "messages": bag.count(t)} for t, s in sorted(bag.topics.items())]
    try:
        src = BagCloudSource(path, options.topic, options.world_frame, options.pose_topic, recover, bag=bag)
    except SourceError as err:
        return {"source": str(path), "kind": kind, "topics": topics, "scans": None, "scan_topic": None,
                "why": str(err), "scan_topics": sorted(t for t, s in bag.topics.items() if s in SCAN_TYPES)}
    try:
        src._read_poses()
        problem = None
    except SourceError as err:
        problem = str(err)
    read_error = []

    def messages():
        try:
            for _, msgtype, raw in bag.messages([src.topic]):
                yield bag.deserialize(raw, msgtype)
        except bag_errors() as err:  # a bag that cannot be read on: what was read is described
            read_error.append(f"{type(err).__name__}: {err}")

    out = _log_figures(kind, path, topics, src.topic, src._msgtype, messages(), src._poses, problem)
    if read_error:
        out["read_error"] = read_error[0]
    if src.lost():
        out["lost"] = src.lost()
    return out


def _describe_mcap(path: Path, options: SourceOptions) -> dict:
    from voxtool.sources.mcap_ros2 import McapCloudSource

    src = McapCloudSource(path, options.topic, options.world_frame, options.pose_topic,
                          recover=options.bad_scans == "skip")
    topics = src.topic_table()
    try:
        src._load_poses()
        problem = None
    except SourceError as err:
        problem = str(err)
    extra = {} if src._linear is None else {"decoder_factory": src._decoders}
    messages = (msg for *_, msg in src._reader.iter_decoded_messages(topics=[src.topic], log_time_order=True, **extra))
    out = _log_figures("mcap", path, topics, src.topic, src._msgtype, messages, src._poses, problem)
    if src.lost():
        out["lost"] = src.lost()
    return out
