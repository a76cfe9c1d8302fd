"""`voxtool diff`: where two maps differ, for people and for CI."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors


@click.command()
@click.argument("map_a", type=click.Path(path_type=Path))
@click.argument("map_b", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the counts, KL divergence and bounding box as JSON.")
@click.option("--png", type=click.Path(path_type=Path), metavar="OUT.png",
              help="Draw where the maps differ over map B (export .png's conventions), coloured by change, with a "
                   "legend.")
@click.option("--view", type=click.Choice(["top", "front", "side"]), default="top", show_default=True,
              help="--png: the direction of the picture.")
@click.option("--crop", metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
              help="--png: only the voxels whose centres lie in this box (metres, as export --crop); the counts "
                   "above are of the whole maps.")
@click.option("--ply", type=click.Path(path_type=Path), metavar="OUT.ply|OUT.pcd",
              help="Write the changed voxels' centres as a point cloud coloured as the picture's legend.")
@click.option("--max-changed", type=click.IntRange(min=0), metavar="N",
              help="For CI: exit 7 when more than N voxels changed state (the outputs are still written).")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def diff(map_a, map_b, as_json, png, view, crop, ply, max_changed, progress):
    """Compare MAP_A with MAP_B (.vxm, OctoMap .bt or sharded map directories, one resolution):
    voxels that changed state (occupied, free, unknown; each map by its own threshold), OctoMap
    compare_octrees' KL divergence over the voxels known in both, and the changes' bounding box.
    A sharded map is compared part by part (memory: its largest part). docs/diff.md.

    \b
    Examples:
      voxtool diff base.vxm new.vxm                       counts per change
      voxtool diff base.vxm new.vxm --max-changed 1000    exit 7 past 1,000 changed voxels
      voxtool diff base.vxm new.vxm --png where.png --ply changed.ply"""
    from voxtool.atomic import check_writable
    from voxtool.diff import diff_maps, write_changed_cloud, write_diff_png
    from voxtool.errors import ChangeLimitError, ParameterError

    for out in (png, ply):
        if out is not None:
            check_writable(out)
    if png is not None and png.suffix.lower() != ".png":
        raise ParameterError(f"{png}: --png writes a .png picture")
    box = None
    if crop is not None:
        from voxtool.api import crop_keys

        if png is None:
            raise ParameterError("--crop frames the --png picture: give --png OUT.png")
        try:
            box = tuple(float(v) for v in crop.split(","))
        except ValueError:
            box = ()
        crop_keys(box, 1.0)  # six numbers, each min at most its max: refused before the maps are read
    if ply is not None and ply.suffix.lower() not in (".ply", ".pcd"):
        raise ParameterError(f"{ply}: --ply writes the changed voxels as .ply or .pcd")
    result = diff_maps(map_a, map_b, progress)
    report = result.to_dict()
    written = []
    if ply is not None:
        report["ply"] = write_changed_cloud(ply, result)
        written.append(ply)
    if png is not None and result.changed_voxels:
        report["png"] = write_diff_png(png, result, view, f"{map_a.name} -> {map_b.name}", box)
        written.append(png)
    elif png is not None:
        click.echo(f"voxtool: warning: {png}: the maps do not differ; no picture written", err=True)
    rows = [("changed voxels", f"{report['changed_voxels']:,}")]
    rows += [(name.replace("_", " "), f"{count:,}") for name, count in report["changes"].items() if count]
    rows += [("unchanged", f"{report['unchanged']['occupied']:,} occupied, {report['unchanged']['free']:,} free"),
             ("same state, other log-odds", f"{report['same_state_other_log_odds']:,}"),
             ("KL divergence", f"{report['kl_divergence']:.6g} over {report['common_known_voxels']:,} voxels known "
                               "in both")]
    if report["state_maps"]:  # a decoded packet log: its voxels sit at one log-odds per state
        rows.append(("", f"{' and '.join(report['state_maps'])} holds states (decoded from packets), each voxel at "
                         "its state's log-odds: the log-odds and KL figures measure that, not a change; "
                         "compare the states above"))
    if report["changed_bbox"]:
        box = report["changed_bbox"]
        rows.append(("changes within", f"{box['min']} .. {box['max']} m"))
    if max_changed is not None:
        report["max_changed"] = max_changed
        rows.append(("max changed", f"{max_changed:,}: {'EXCEEDED' if report['changed_voxels'] > max_changed else 'ok'}"))
    emit(report, as_json, rows, written=written or None)
    if max_changed is not None and report["changed_voxels"] > max_changed:
        raise ChangeLimitError(f"{map_b}: {report['changed_voxels']:,} voxels changed state from {map_a}, more than "
                               f"--max-changed {max_changed:,}")
