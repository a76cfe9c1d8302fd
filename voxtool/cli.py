"""voxtool command line: a thin layer over the library. Heavy imports stay inside commands."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

from voxtool import __version__
from voxtool.errors import VoxtoolError

SAMPLE_DIR = Path(__file__).parent / "data" / "sample"


def handle_errors(func):
    """Turn VoxtoolError into one line on stderr and its exit code; Ctrl-C into exit 130."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except VoxtoolError as err:
            click.echo(f"voxtool: error: {err}", err=True)
            sys.exit(err.exit_code)
        except KeyboardInterrupt:
            click.echo("voxtool: interrupted; no output written", err=True)
            sys.exit(130)
        except MemoryError:
            click.echo("voxtool: error: out of memory", err=True)
            sys.exit(1)

    return wrapper


def emit(data: dict, as_json: bool, rows: list[tuple[str, str]]) -> None:
    if as_json:
        click.echo(json.dumps(data, indent=2, sort_keys=True))
    else:
        width = max(len(k) for k, _ in rows)
        for key, value in rows:
            click.echo(f"{key:<{width}}  {value}")


def summary_rows(stats: dict) -> list[tuple[str, str]]:
    bbox = stats.get("occupied_bbox")
    rows = [
        ("backend", str(stats.get("backend"))),
        ("resolution", f"{stats.get('resolution')} m"),
        ("occupied voxels", f"{stats['occupied_voxels']:,}"),
        ("free voxels", f"{stats['free_voxels']:,}"),
        ("nodes (leaf/inner)", f"{stats['leaf_nodes']:,} / {stats['inner_nodes']:,}"),
        ("memory", f"{stats['memory_bytes'] / 2**20:.1f} MiB"),
        ("occupied bbox", f"{bbox['min']} .. {bbox['max']}" if bbox else "(empty)"),
    ]
    if "scans" in stats:
        rows += [("scans", f"{stats['scans']:,}"), ("points", f"{stats['points']:,} ({stats['points_dropped']:,} dropped)")]
    if "timings_s" in stats:
        t = stats["timings_s"]
        lat = stats["scan_latency_ms"]
        rows += [
            ("time total", f"{t['total']:.3f} s (read {t['read']:.3f}, raycast {t['raycast']:.3f}, update {t['update']:.3f})"),
            ("scan latency", f"p50 {lat['p50']:.1f} ms, p95 {lat['p95']:.1f} ms, max {lat['max']:.1f} ms"),
        ]
    return rows


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="voxtool")
def main() -> None:
    """Turn LiDAR scan streams into 3D occupancy voxel maps, measure and share them.

    Exit codes: 0 ok, 1 error, 2 bad parameter, 3 bad source, 4 point outside the key range,
    5 bad map/packet file, 6 regression found by `stats --compare`, 130 interrupted.
    """


@main.command()
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool (norlab, BSD-3) as SOURCE.")
@click.option("-o", "--output", type=click.Path(path_type=Path), help="Write the map snapshot (.vxm) here (atomically).")
@click.option("--backend", default="octree", show_default=True, help="Map backend (see docs/backends.md).")
@click.option("--resolution", default=0.2, show_default=True, type=float, help="Voxel edge length in metres.")
@click.option("--max-range", default=-1.0, show_default=True, type=float,
              help="Rays longer than this are cut here and mark no hit (OctoMap maxrange); < 0 = unlimited.")
@click.option("--min-range", default=0.0, show_default=True, type=float, help="Drop points closer than this to the sensor.")
@click.option("--poses", type=click.Path(path_type=Path), help="Pose file (TUM, index+TUM or KITTI), one row per scan file.")
@click.option("--no-viewpoint", is_flag=True, help="PCD points are already in the world frame; take only the ray origin from VIEWPOINT/--poses.")
@click.option("--topic", help="MCAP PointCloud2 topic (default: the only one).")
@click.option("--world-frame", default="map", show_default=True, help="MCAP /tf frame the map is built in.")
@click.option("--pose-topic", help="MCAP Odometry/PoseStamped topic giving the sensor pose (instead of /tf).")
@click.option("--start", default=0, show_default=True, type=int, help="First scan index to use.")
@click.option("--stop", default=None, type=int, help="Stop before this scan index.")
@click.option("--every", default=1, show_default=True, type=int, help="Use every n-th scan.")
@click.option("--prob-hit", default=0.7, show_default=True, type=float)
@click.option("--prob-miss", default=0.4, show_default=True, type=float)
@click.option("--clamp-min", default=0.1192, show_default=True, type=float)
@click.option("--clamp-max", default=0.971, show_default=True, type=float)
@click.option("--threshold", default=0.5, show_default=True, type=float, help="Occupancy probability threshold.")
@click.option("--json", "as_json", is_flag=True, help="Print statistics and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def build(source, sample, output, backend, resolution, max_range, min_range, poses, no_viewpoint, topic, world_frame,
          pose_topic, start, stop, every, prob_hit, prob_miss, clamp_min, clamp_max, threshold, as_json, progress):
    """Build an occupancy map from SOURCE: a directory of PCD (or PLY + --poses) scans, a single
    PCD/PLY file, a ROS 2 .mcap file, or an OctoMap .graph file."""
    from voxtool.api import build_map
    from voxtool.config import MapParams, SensorModel
    from voxtool.errors import ParameterError
    from voxtool.sources import SourceOptions

    if sample == (source is not None):
        raise ParameterError("give exactly one of SOURCE or --sample")
    src = SAMPLE_DIR if sample else source
    options = SourceOptions(poses=str(poses) if poses else None, no_viewpoint=no_viewpoint, topic=topic,
                            world_frame=world_frame, pose_topic=pose_topic, start=start, stop=stop, every=every,
                            min_range=min_range)
    params = MapParams(resolution=resolution, max_range=max_range, min_range=min_range)
    sensor = SensorModel(prob_hit, prob_miss, clamp_min, clamp_max, threshold)
    result = build_map(src, options, params, sensor, backend, output, progress)
    emit(result, as_json, summary_rows(result) + ([("written", str(output))] if output else []))


@main.command()
@click.argument("map_file", type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
@click.option("--compare", "baseline", type=click.Path(path_type=Path),
              help="Baseline JSON (from `stats --json`); exit 6 when a figure drifts beyond --tolerance.")
@click.option("--tolerance", default=0.0, show_default=True, type=float, help="Relative tolerance for --compare.")
@handle_errors
def stats(map_file, as_json, baseline, tolerance):
    """Statistics of a map snapshot (.vxm) or an OctoMap .bt file."""
    from voxtool.api import map_stats
    from voxtool.stats import compare

    result = map_stats(map_file)
    if baseline is not None:
        compare(result, baseline, tolerance)
    emit(result, as_json, summary_rows(result))


@main.command()
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


if __name__ == "__main__":  # pragma: no cover
    main()
