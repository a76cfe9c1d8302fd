"""`voxtool clean`: remove what moved from a scan sequence, keeping a static point map."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import (
    emit,
    handle_errors,
    origin_option,
    resolve_source,
    source_options,
    source_setup,
    threads_option,
    with_origin,
)


@click.command()
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool as SOURCE.")
@click.option("-o", "--output", type=click.Path(path_type=Path), metavar="STATIC.pcd|.ply",
              help="Write the static points (world frame, scan order) here, atomically.")
@click.option("--map", "map_output", type=click.Path(path_type=Path), metavar="STATIC.vxm",
              help="Write the occupancy map of the static points here, atomically: every scan's rays cast to its kept "
                   "points (octree, OctoMap's sensor model, at --resolution); the removed points mark nothing. Its grid "
                   "(voxtool export STATIC.vxm -o grid.pgm --above-ground 0.3,2) has no movers; --grid also marks "
                   "the hedges and fences rays pass through.")
@click.option("--grid", type=click.Path(path_type=Path), metavar="GRID.pgm|.mcap",
              help="Write a planner's grid of the static points here, atomically (nav2's .pgm and .yaml, or a .mcap "
                   "holding a nav_msgs/OccupancyGrid on /projected_map, stamped with the last scan), a cell "
                   "per voxel: occupied where something stands --above-ground (default 0.3,2 m) over the ground: a "
                   "voxel the map of the kept points holds occupied, or one holding a kept return from 3.5 m or more "
                   "off its sensor that the map has not cleared to its floor (hedges, fences, railings that rays "
                   "pass through; a grid of the --map alone leaves them free). Free where the ground is known.")
@click.option("--labels", type=click.Path(path_type=Path), metavar="LABELS.npy",
              help="Write one uint8 per point voxtool read (0 static, 1 dynamic), in scan order; points dropped "
                   "as non-finite or below --min-range have none.")
@click.option("--dynamic", type=click.Path(path_type=Path), metavar="REMOVED.pcd|.ply",
              help="Write the removed (dynamic) points here, atomically (in the scans' frame, as -o).")
@click.option("--png", type=click.Path(path_type=Path), metavar="OUT.png",
              help="Draw what was removed: every point with the removed ones in red, then the kept ones alone.")
@click.option("--view", type=click.Choice(["top", "front", "side"]), default="top", show_default=True,
              help="--png: look from above, from the front (along +y) or the side (along -x).")
@click.option("--above-ground", metavar="MIN,MAX",
              help="--grid: what stands MIN..MAX metres over the ground is an obstacle (default 0.3,2). --png (top "
                   "view): colour the points by height above the ground found in the static points, on that scale.")
@click.option("--resolution", default=0.1, show_default=True, type=float, help="Voxel edge of the void map, metres.")
@click.option("--sensor-noise", default=0.2, show_default=True, type=float,
              help="d_s: each ray gives no evidence of empty space over its last d_s metres (range noise).")
@click.option("--pose-error", default=1, show_default=True, type=int,
              help="d_p: a voxel is void when one scan saw through it and every voxel within d_p of it "
                   "(pose error); 0: its own voxel only.")
@click.option("--group-share", default=0.15, show_default=True, type=click.FloatRange(0.0, 1.0),
              help="A group of points (connected voxels some ray crossed) is removed when this share of its "
                   "points lie in void voxels.")
@click.option("--max-range", default=-1.0, show_default=True, type=float,
              help="Rays are cut here and give no evidence beyond; < 0 = unlimited.")
@click.option("--ground-band", default=0.3, show_default=True, type=float, metavar="METRES",
              help="Points up to this far above the ground (found in all the scans' points together) are no "
                   "evidence of a mover, and go only with a moving group above them (wheels, feet): under pose "
                   "error of a few centimetres rays graze the road another scan saw, and the road would go. "
                   "< 0: judge the ground as any other surface.")
@click.option("--truth", type=click.Path(path_type=Path, exists=True), metavar="LABELS_DIR|TRUTH.npy",
              help="Score the result against ground truth: a folder of SemanticKITTI .label files, one per scan "
                   "file (000123.label for 000123.bin/.pcd; moving classes 252-259 are dynamic), or a .npy of "
                   "one label per judged point in --labels' layout (non-zero: dynamic): SA, DA, AA.")
@source_options
@origin_option
@threads_option
@click.option("--json", "as_json", is_flag=True, help="Print figures and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def clean(source, sample, output, map_output, grid, labels, dynamic, png, view, above_ground, resolution, sensor_noise, pose_error,
          group_share, max_range, ground_band, truth, origin, threads, as_json, progress, **kw):
    """Judge every point of SOURCE static or dynamic and write the static points (-o), their map
    (--map), a planner's grid of them (--grid) and/or the labels.

    A point is dynamic when another scan saw through the space it occupies: its voxel is void
    (one scan's rays crossed it and every voxel within --pose-error of it), or it belongs to a
    group of its scan's points around such voxels of which --group-share lie in them. A car, a
    person, a door that moved. Works on every source `build` reads; the sensor poses must be
    good (docs/cleaning.md says how to tune).

    \b
    Examples:
      voxtool clean scans/ -o static.pcd
      voxtool clean drive.bag --grid grid.pgm --resolution 0.2        a planner's grid without the movers
      voxtool clean drive.bag --map static.vxm && voxtool export static.vxm -o grid.pgm --above-ground 0.3,2
      voxtool clean drive.mcap -o static.ply --labels labels.npy --json
      voxtool clean scans/ -o static.pcd --resolution 0.2 --sensor-noise 0.3
      voxtool clean sequences/08 -o static.pcd --truth sequences/08/labels   SemanticKITTI: SA, DA, AA"""
    from voxtool.clean import CleanParams, clean_source

    source = resolve_source(source, sample)
    options = with_origin(source_setup(kw), origin)
    truth_npy = truth if truth is not None and truth.is_file() else None
    if truth is not None and truth_npy is None:
        from dataclasses import replace

        options = replace(options, truth=str(truth))
    params = CleanParams(resolution=resolution, sensor_noise=sensor_noise, pose_error=pose_error, max_range=max_range,
                         group_share=group_share, ground_band=ground_band)
    from voxtool.ground import parse_above_ground

    band = parse_above_ground(above_ground)
    if band is not None and png is None and grid is None:
        from voxtool.errors import ParameterError

        raise ParameterError("--above-ground sets the --grid's band and colours the --png picture: give --grid GRID.pgm "
                             "or --png OUT.png")
    if band is not None and png is not None and view != "top":
        from voxtool.errors import ParameterError

        raise ParameterError("--above-ground colours a top view by height above the ground: not with --view")
    from voxtool.clean import GRID_BAND

    result = clean_source(source, options, params, output, labels, threads, progress, dynamic, png, view, truth_npy,
                          band if png is not None else None, map_output, grid, band or GRID_BAND)
    t = result["timings_s"]
    removed = result["points_removed"]
    share = removed / max(result["points_in"], 1)
    rows = [
        ("scans", f"{result['scans']:,}"),
        ("points", f"{result['points_in']:,} judged ({result['points_dropped']:,} dropped on reading)"),
        ("kept (static)", f"{result['points_kept']:,}"),
        ("removed (dynamic)", f"{removed:,} ({share:.2%})"),
        ("ground", "none in 2D scans: judged in the scan plane, the pose error a square in it" if result["planar"]
                   else f"{result['ground_points']:,} points within {ground_band} m of the ground: evidence of no mover"
                   if ground_band >= 0 else "judged as any other surface (--ground-band < 0)"),
        ("maps", f"{result['void_map_bytes'] / 2**20:.1f} MiB at {resolution} m (crossed, void, holding points)"),
        ("time", f"{t['scans_total']:.3f} s for the scans on {result['threads']} threads (ray casting "
                 f"{t['raycast']:.3f} s, void map {t['void_update']:.3f} s), judging {t['classify']:.3f} s, "
                 f"writing {t['write']:.3f} s"),
    ]
    if "accuracy" in result:
        a = result["accuracy"]
        def score(v, unit=" %"):
            return "n/a" if v is None else f"{v:.2f}{unit}"

        rows.append(("against --truth", f"SA {score(a['SA'])} of {a['static_points']:,} static points kept, DA "
                                        f"{score(a['DA'])} of {a['dynamic_points']:,} dynamic removed, AA "
                                        f"{score(a['AA'], '')}" + (" (no moving point in the truth: nothing to "
                                                                   "find, so DA and AA are not known)"
                                                                   if a["DA"] is None else "")))
    if "map" in result:
        rows.append(("static map", f"{result['map']['occupied_voxels']:,} occupied, {result['map']['free_voxels']:,} free "
                                   f"voxels at {resolution} m, the removed points left out"))
    if "grid" in result:
        g = result["grid"]
        rows.append(("grid", f"{g['occupied_cells']:,} occupied ({g['cells_by_returns']:,} by returns the map leaves "
                             f"under its threshold), {g['free_cells']:,} free, {g['unknown_cells']:,} unknown cells of "
                             f"{g['resolution']:g} m: what stands {g['above_ground'][0]:g}-{g['above_ground'][1]:g} m "
                             "over the ground"))
    written = [p for p in (output, map_output, grid, labels, dynamic, png) if p is not None]
    emit(result, as_json, rows, written=written if len(written) > 1 else written[0])
