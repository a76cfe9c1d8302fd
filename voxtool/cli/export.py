"""`voxtool export`: a map as OctoMap .bt, point clouds or a picture."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors


@click.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("-o", "--output", required=True, type=click.Path(path_type=Path),
              help="Output file; its suffix picks the format: .bt, .ply, .pcd or .png.")
@click.option("--free", "include_free", is_flag=True, help="Also write free voxels (.ply/.pcd, coloured).")
@click.option("--json", "as_json", is_flag=True, help="Print what was written as JSON.")
@handle_errors
def export(map_file, output, include_free, as_json):
    """Export a map snapshot: .bt (OctoMap binary), .ply/.pcd (voxel centres), .png (top view)."""
    from voxtool.api import export_map

    count = export_map(map_file, output, include_free)
    emit({"output": str(output), "items": count}, as_json, [("written", str(output)), ("items", f"{count:,}")])
