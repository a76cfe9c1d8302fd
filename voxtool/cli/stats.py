"""`voxtool stats`: statistics of a map or a packet log, and regression checks for CI."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import emit, handle_errors, summary_rows


@click.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
@click.option("--compare", "baseline", type=click.Path(path_type=Path),
              help="Baseline JSON (from `stats --json`); exit 6 when a figure drifts beyond --tolerance "
                   "(maps: voxel, node, scan and point counts; packet logs: packets, bytes, bandwidth).")
@click.option("--tolerance", default=0.0, show_default=True, type=float, help="Relative tolerance for --compare.")
@handle_errors
def stats(map_file, as_json, baseline, tolerance):
    """Statistics of a map snapshot (.vxm), an OctoMap .bt file, or a packet log (.mcap)."""
    from voxtool.api import map_stats
    from voxtool.stats import LOG_COMPARED, compare

    if map_file.suffix.lower() == ".mcap":
        from voxtool.codec.logstats import log_stats

        result = log_stats(map_file)
        rows = [("packets", str(result["packets"])), ("bytes", f"{result['bytes']:,}"),
                ("total bandwidth", f"avg {result['total']['avg_Bps']:,.0f} B/s, max {result['total']['max_Bps']:,.0f} B/s")]
        for robot, r in result["robots"].items():
            rows.append((f"robot {robot}", f"{r['scheme']}/{r['codec']}: avg {r['avg_Bps']:,.0f} B/s, max {r['max_Bps']:,.0f} B/s, "
                                           f"{r['bytes_per_changed_voxel']} B/changed voxel, x{r['compression_ratio']} compression, "
                                           f"{r['ratio_to_raw_sensor']} of raw sensor B/s"))
        if baseline is not None:
            compare(result, baseline, tolerance, LOG_COMPARED)
        emit(result, as_json, rows)
        return
    result = map_stats(map_file)
    if baseline is not None:
        compare(result, baseline, tolerance)
    emit(result, as_json, summary_rows(result))
