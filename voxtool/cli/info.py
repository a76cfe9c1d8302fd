"""`voxtool info`: what a source holds (scans, time span, points per scan; for ROS logs the
topics, the /tf tree and the pose source build would use), before anything is built."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors


@click.command("info")
@click.argument("source", type=click.Path(path_type=Path))
@click.option("--topic", help="The scan topic (a log with several PointCloud2/LaserScan topics).")
@click.option("--world-frame", help="The world frame build would pose the scans in (default: the /tf root).")
@click.option("--pose-topic", help="An Odometry or PoseStamped topic build would pose the scans by.")
@click.option("--poses", type=click.Path(path_type=Path), help="A pose file build would take (PCD/PLY folders).")
@click.option("--bad-scans", type=click.Choice(["fail", "skip"]), default="fail", show_default=True,
              help="skip: read a truncated or index-damaged bag record by record, as build would.")
@click.option("--json", "as_json", is_flag=True, help="Print everything as JSON.")
@handle_errors
def info(source, topic, world_frame, pose_topic, poses, bad_scans, as_json):
    """What SOURCE holds, as `ros2 bag info`, `mcap info` and `pdal info` tell: scans, time span,
    points per scan (min/median/max); for ROS bags and MCAP files their topics with types and
    counts, the /tf tree, and the pose source `build` would use, or why there is none (with the
    option that would pose the scans).

    \b
    Examples:
      voxtool info drive.bag                       topics, /tf tree, what poses the scans
      voxtool info run.mcap --json | jq .pose_source
      voxtool info scans/ --json                   a PCD folder: scans and points per scan"""
    from voxtool.info import describe
    from voxtool.sources import SourceOptions

    options = SourceOptions(poses=str(poses) if poses else None, topic=topic, world_frame=world_frame,
                            pose_topic=pose_topic, bad_scans=bad_scans)
    figures = describe(source, options)
    emit(figures, as_json, _rows(figures))


def _rows(f: dict) -> list[tuple[str, str]]:
    rows = [("source", f"{f['source']} ({f['kind']})")]
    for t in f.get("topics", []):
        count = "?" if t["messages"] is None else f"{t['messages']:,}"
        rows.append(("topic", f"{t['topic']}  {t['type']}  {count} messages"))
    if f.get("scans") is None:
        rows.append(("scans", f"none to build from: {f.get('why', '')}"))
        return rows
    if f.get("scan_topic"):
        frame = "no messages" if f.get("scan_frame") is None else f"frame '{f['scan_frame']}'"
        rows.append(("scan topic", f"{f['scan_topic']} ({f['scan_type'].rsplit('/', 1)[-1]}, {frame})"))
    rows.append(("scans", f"{f['scans']:,}"))
    span = f.get("time_span")
    rows.append(("time span", f"{span['seconds']:.3f} s" if span else "no times"))
    pps = f.get("points_per_scan")
    if pps:
        rows.append(("points per scan", f"min {pps['min']:,}, median {pps['median']:,.0f}, max {pps['max']:,}"))
    if f.get("fields"):
        rows.append(("fields", " ".join(f["fields"])))
    if f.get("units"):
        u = f["units"]
        h, v = u["horizontal"], u["vertical"]
        rows.append(("units", f"horizontal {h['name']} ({h['metres']:g} m), vertical {v['name']} ({v['metres']:g} m), "
                              f"from {u['from']}; read in metres"))
    if f.get("points_invalid"):
        rows.append(("invalid points", f"{f['points_invalid']:,} (a direction only, or no return: build drops them)"))
    if f.get("lidar"):
        lidar = f["lidar"]
        rate = f", {lidar['rate_hz']:g} revolutions a second" if lidar.get("rate_hz") else ""
        rows.append(("sensor", f"{lidar['model']}, return mode {lidar['return_mode']}{rate} (decoded from its packets)"))
    for e in f.get("tf", []):
        how = "static" if e["static"] else f"{e['transforms']:,} transforms"
        rows.append(("tf", f"{e['parent']} -> {e['child']} ({how})"))
    pose = f.get("pose_source")
    if isinstance(pose, dict):
        rows.append(("poses", f"by {pose['by']}" if pose["posed"] else f"none: {pose['why']}"))
        if pose.get("mount"):
            rows.append(("", pose["mount"]))
    elif pose:
        rows.append(("poses", pose))
    if f.get("lost"):
        rows.append(("lost", f["lost"]))
    return rows
