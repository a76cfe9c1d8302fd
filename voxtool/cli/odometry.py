"""`voxtool odometry`: a pose file for scans that have no poses (LiDAR odometry: a grid matcher for 2D
scans, KISS-ICP for 3D ones)."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import dropped_text, ego_box_option, emit, handle_errors, parse_box, resolve_source


@click.command("odometry")
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool as SOURCE.")
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path), metavar="POSES.txt",
              help="The pose file to write (atomically): TUM rows where the scans have times, KITTI rows otherwise.")
@click.option("--max-range", default=None, type=float,
              help="Points farther than this (metres) are not registered (KISS-ICP's max_range; its local map's voxel "
                   "is a hundredth of it). Default: from the data, a LaserScan's range_max, else the 99.5th percentile "
                   "range of the first scans.")
@click.option("--planar/--no-planar", default=None,
              help="Register in the plane (z, roll and pitch held at 0). Default: when the scans are 2D (every z 0).")
@click.option("--min-range", default=0.0, show_default=True, type=float,
              help="Points nearer than this (metres: the vehicle itself) are not registered.")
@click.option("--voxel-size", default=None, type=float,
              help="The local map's cell in metres: KISS-ICP's voxel (default: max range / 100, its own default); "
                   "the grid matcher's finest cell (default: max range / 140, 2.5 cm for a 3.5 m scanner).")
@click.option("--matcher", type=click.Choice(["grid", "kiss-icp"]), default=None,
              help="grid: 2D scans aligned to an occupancy grid of the scans before them (Hector SLAM's matcher); "
                   "kiss-icp: KISS-ICP's point-to-point local map. Default: grid for 2D scans, KISS-ICP for 3D ones.")
@click.option("--topic", help="MCAP/bag PointCloud2 topic (default: the only one).")
@click.option("--world-frame", default=None,
              help="A log's /tf frame to compare the odometry with (--json's against_source_poses: ATE and drift "
                   "against the log's own poses in that frame; default: the frame build would pose the scans in). "
                   "The scans are registered in their sensor frame either way.")
@ego_box_option()
@click.option("--bad-scans", type=click.Choice(["fail", "skip"]), default="fail", show_default=True,
              help="skip: read a truncated bag record by record (every scan file must still be readable).")
@click.option("--json", "as_json", is_flag=True, help="Print figures and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def odometry(source, sample, output, max_range, planar, min_range, voxel_size, matcher, topic, world_frame, ego_box,
             bad_scans, as_json, progress):
    """Estimate the sensor's pose for every scan of SOURCE by LiDAR odometry, and write them as a
    pose file that `build`, `clean` and `eval` take with --poses.

    For scans that carry no poses: a driver's PCD dump, a dataset sample, a KITTI sequence without
    poses.txt, a 2D LaserScan log. The poses are in the first scan's sensor frame. Odometry drifts
    (about 1 % of the distance on KITTI); a map from it is locally consistent, not surveyed. 3D
    scans are registered by KISS-ICP, an optional extra: pip install 'voxtool-lidar[odometry]'; 2D
    scans by a grid matcher that needs nothing more (--matcher kiss-icp for KISS-ICP).

    \b
    Examples:
      voxtool odometry scans/ -o poses.txt && voxtool build scans/ --poses poses.txt -o map.vxm
      voxtool odometry sequences/00 -o odom.txt --max-range 80 --json
      voxtool odometry robot.bag -o poses.txt    a 2D LaserScan log: its range_max, in the plane

    A run that looks diverged (steps faster than the sensor moves, scans with almost nothing to
    register, 2D scans that see one wall or a featureless corridor and so cannot measure motion
    along it) says so on one warning line and in --json's plausibility."""
    from voxtool.odometry import OdometryParams, estimate_poses, write_pose_file
    from voxtool.sources import SourceOptions

    source = resolve_source(source, sample)
    from voxtool.atomic import check_writable

    check_writable(output)
    params = OdometryParams(max_range=max_range, min_range=min_range, voxel_size=voxel_size, planar=planar,
                            matcher=matcher)
    result = estimate_poses(source, SourceOptions(topic=topic, bad_scans=bad_scans, world_frame=world_frame,
                                                 ego_box=parse_box(ego_box, "--ego-box", "in the sensor's frame")),
                            params, progress)
    kind = write_pose_file(output, result["poses"], result["stamps_ns"])
    figures = {**result["figures"], "format": kind}
    t = figures["timings_s"]
    rows = [("scans", f"{figures['scans']:,} ({figures['points']:,} points registered; {dropped_text(figures)})"),
            ("path", f"{figures['path_m']:.2f} m travelled (first scan's frame)"),
            ("registered", f"within {figures['params']['max_range']:g} m ({figures['params']['max_range_from']}), "
                           + (f"to a grid of {figures['params']['voxel_size']:g} m cells (2D scans, in the plane)"
                              if figures["params"]["matcher"] == "grid" else
                              f"by KISS-ICP, {figures['params']['voxel_size']:g} m voxels"
                              + (", in the plane" if figures["params"]["planar"] else ""))),
            ("format", "TUM (t x y z qx qy qz qw)" if kind == "tum" else "KITTI rows (the scans have no times)"),
            ("time", f"{t['total']:.2f} s, {t['per_scan_ms']:.1f} ms a scan")]
    a = figures.get("against_source_poses")
    if a:
        rows.insert(2, ("vs the source's poses", f"ATE {a['ate_rmse_m']:.3f} m RMSE (max {a['ate_max_m']:.3f} m) after a "
                                                 f"rigid fit; the end {a['end_drift_m']:.3f} m off "
                                                 + (f"({a['end_drift_percent_of_path']:.2f} % of the path)"
                                                    if a["end_drift_percent_of_path"] is not None else "(it stood still)")))
    emit(figures, as_json, rows, written=output)
