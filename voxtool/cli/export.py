"""`voxtool export`: a map as OctoMap .bt, point clouds or a picture."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors, origin_option, parse_box, source_options, source_setup


@click.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="Output file; its suffix picks the format: .bt, .ply, .pcd, .png, .mcap (ROS 2: a "
                   "foxglove_msgs/SceneUpdate, an octomap_msgs/Octomap and a nav_msgs/OccupancyGrid), .pgm (a 2D "
                   "occupancy grid + nav2 map_server's .yaml beside it) or .vxm (an OctoMap .bt imported).")
@click.option("--free", "include_free", is_flag=True,
              help="Also write free voxels (.ply/.pcd, coloured; a .bt and a picture always hold them).")
@click.option("--ros2-only", is_flag=True, hidden=True,
              help="Changes nothing: every .mcap export is ROS 2 (kept for scripts that pass it).")
@click.option("--view", type=click.Choice(["top", "front", "side"]), default=None,
              help=".png: look from above (default), from the front (along +y) or the side (along -x).")
@click.option("--slice", "slice_z", type=float, default=None, metavar="Z",
              help=".png: only the voxel layer holding height Z (metres), seen from above.")
@click.option("--crop", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
              help="Only the voxels whose centres lie in this box (metres, edges inclusive: an edge on a voxel "
                   "centre keeps that voxel), for every output type; a leaf across the box's faces is split. A "
                   "sharded map is then read whole. (OctoMap 1.10's edit_octree has no crop: its --bb is not "
                   "implemented.)")
@click.option("--z-range", metavar="MIN,MAX",
              help=".pgm/.mcap 2D grid: project the voxels whose centres lie at these heights (metres; default: all): "
                   "a cell is occupied where any of them is occupied, free where all known ones are free, unknown "
                   "elsewhere (octomap_server's projected_map).")
@click.option("--above-ground", metavar="MIN,MAX",
              help=".pgm/.mcap 2D grid: a cell is occupied where an occupied voxel lies MIN..MAX metres above the "
                   "ground under it (the ground found in the map, docs/viewing.md), free where its ground is known "
                   "and nothing there is occupied, unknown elsewhere: for sloped outdoor ground, instead of --z-range.")
@click.option("--obstacle-threshold", type=float, default=None, metavar="P",
              help="With --above-ground: a voxel in the band is an obstacle where its occupancy probability is over "
                   "P (default: the map's threshold, 0.5). 0.4 also marks voxels hit once and passed through up "
                   "to three times (bushes, fences): more of the objects, at the cost of a few free cells on the "
                   "road (docs/viewing.md).")
@source_options
@origin_option
@click.option("--json", "as_json", is_flag=True, help="Print what was written as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def export(map_file, output, include_free, ros2_only, view, slice_z, crop, z_range, above_ground, obstacle_threshold,  # noqa: ARG001
           as_json, progress, **kw):
    """Export a map snapshot (.vxm) or an OctoMap .bt: .bt (OctoMap binary, the max-likelihood
    tree), .ply/.pcd (voxel centres), .png (a picture with colour bar, legend, scale bar and axes
    in metres; --view, --slice), .mcap (for Foxglove, RViz and rosbags), or import an OctoMap .bt
    as a snapshot (.vxm), or a 2D occupancy grid for navigation (.pgm + .yaml, nav2
    map_server's format; --z-range). A scan source (what `build` reads) exported as an OctoMap
    ScanGraph (.graph) runs in OctoMap's own tools (eval_octree_accuracy, graph2tree); the source
    options below are for it. A sharded map (a directory) is exported part by part (.bt, .ply, .pcd,
    .png), in the memory of its largest part."""
    from voxtool.api import export_map, export_scans
    from voxtool.errors import ParameterError

    options = source_setup(kw)  # only a scan source exported as .graph reads them
    if output.suffix.lower() == ".graph":
        written = export_scans(map_file, output, options, progress)
        emit(written, as_json, [(key.replace("_", " "), value_text(value)) for key, value in written.items()],
             written=output)
        return
    if options.origin is not None:
        raise ParameterError("--origin is for scans exported as .graph: a map keeps the origin it was built about")

    box = parse_box(crop, "--crop")
    from voxtool.grid import parse_z_range
    from voxtool.ground import parse_above_ground

    written = export_map(map_file, output, include_free, progress, view=view, slice_z=slice_z, crop=box,
                         z_range=parse_z_range(z_range), above_ground=parse_above_ground(above_ground),
                         obstacle_threshold=obstacle_threshold)
    rows = [(key.replace("_", " "), value_text(value)) for key, value in written.items() if value is not None]
    emit(written, as_json, rows, written=[output, Path(written["yaml"])] if "yaml" in written else output)


def value_text(value) -> str:
    """A figure as the text summary prints it: thousands separated, lists and nested figures
    as words (not Python's dict and list syntax)."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, list | tuple):
        return ", ".join(value_text(v) for v in value)
    if isinstance(value, dict):
        return ", ".join(f"{key.replace('_', ' ')} {value_text(v)}" for key, v in value.items())
    return str(value)
