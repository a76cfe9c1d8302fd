"""`voxtool build`: scans to an occupancy map snapshot."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import (
    backend_options,
    backend_setup,
    emit,
    handle_errors,
    resolve_source,
    scan_options,
    scan_setup,
    summary_rows,
    warn_dropped,
)


@click.command()
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool (norlab, BSD-3) as SOURCE.")
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the map snapshot (.vxm) here (atomically).")
@backend_options
@scan_options
@click.option("--share", type=click.Path(path_type=Path), help="hashmap: write newly occupied voxels (ring buffer) as a packet log.")
@click.option("--ring", default=3, show_default=True, type=int, help="hashmap --share: frames per broadcast (k).")
@click.option("--json", "as_json", is_flag=True, help="Print statistics and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def build(source, sample, output, share, ring, as_json, progress, **kw):
    """Build an occupancy map from SOURCE: a directory of PCD (or PLY + --poses) scans, a single
    PCD/PLY file, a ROS 2 .mcap file, or an OctoMap .graph file."""
    from voxtool.api import build_map

    options, params, sensor = scan_setup(kw)
    backend, extra = backend_setup(kw)
    result = build_map(resolve_source(source, sample), options, params, sensor, backend, output, progress, extra,
                       share, ring)
    warn_dropped(source or "sample", result)
    emit(result, as_json, summary_rows(result), written=output)
