"""`voxtool encode`: map a scan stream and write its voxel changes as a packet log."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import (
    backend_options,
    backend_setup,
    cluster_options,
    dropped_text,
    emit,
    emit_fleet,
    handle_errors,
    origin_option,
    resolve_source,
    scan_options,
    scan_setup,
    warn_dropped,
)


@click.command()
@click.argument("sources", nargs=-1, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the shipped sample as SOURCE.")
@click.option("-o", "--output", required=True, type=click.Path(),
              help="Packet log to write (.mcap); a directory (several SOURCES, or a name ending in /): one log per "
                   "source, named after it.")
@click.option("--robot", default=None,
              help="Robot id (1..16 bytes) stamped on every packet. Default: the log's file name (r2.mcap: r2), so "
                   "that the logs of two robots fuse as two robots.")
@backend_options
@scan_options
@origin_option
@click.option("--scheme", type=click.Choice(["hilbert", "nested", "racer", "occupied"]), default=None,
              help="What a packet holds (docs/packets.md).  [default: hilbert; nested with --codec cm]")
@click.option("--codec", type=click.Choice(["zstd", "zlib", "cm", "none"]), default="zstd", show_default=True,
              help="Payload compression. cm: a 3D context model with a range coder, 40-60 % smaller than "
                   "zstd; codes boxes in x-y-z order, so only with the nested scheme (docs/packets.md).")
@click.option("--max-changes", default=50_000, show_default=True, type=int, help="Emit a packet once this many voxels changed state (d).")
@click.option("--max-interval", default=0.5, show_default=True, type=float, help="...or this many seconds of scan time passed (t).")
@click.option("--ring", default=3, show_default=True, type=int, help="Frames per packet of the 'occupied' scheme (k).")
@click.option("--keyframe-every", default=0, show_default=True, type=click.IntRange(min=0),
              help="Also emit a full-state keyframe every n packets (0: never).")
@click.option("--rate", "rate_hz", default=10.0, show_default=True, type=float, help="Scan rate (Hz) assumed when the source has no stamps.")
@click.option("--json", "as_json", is_flag=True, help="Print the encoding report as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@cluster_options
@handle_errors
def encode(sources, sample, output, robot, scheme, codec, max_changes, max_interval, ring, keyframe_every,
           rate_hz, as_json, progress, workers, scheduler, **kw):
    """Map SOURCE and write the voxel state changes as packets to an MCAP packet log."""
    from voxtool.api import encode_log
    from voxtool.cluster import wanted
    from voxtool.codec.encode import EncodeOptions

    dask = wanted(workers, scheduler)
    to_dir = len(sources) > 1 or output.endswith("/") or Path(output).is_dir()
    output = Path(output)
    options, params, sensor = scan_setup(kw)
    backend, extra = backend_setup(kw)
    if scheme is None:
        scheme = "nested" if codec == "cm" else "hilbert"
    opts = EncodeOptions(robot, scheme, codec, max_changes, max_interval, ring, keyframe_every, rate_hz)
    if (to_dir or dask) and not sample:
        from voxtool.fleet import fleet_job, run_fleet_on

        # one source with --workers: one task, writing the log named by -o
        report = run_fleet_on("encode", list(sources), fleet_job(options, params, sensor, backend, extra, encode=opts),
                              output if to_dir else None, workers, scheduler, progress,
                              None if to_dir else [output])
        emit_fleet(report, as_json, lambda r: f"{r['bytes']:,} bytes in {r['packets']:,} packets")
        return
    src = resolve_source(sources[0] if sources else None, sample)
    result = encode_log(src, output, options, params, sensor, backend, extra, opts, progress)
    warn_dropped(src, result)
    emit(result, as_json, encode_rows(result), written=output)


def encode_rows(r: dict) -> list[tuple[str, str]]:
    """An encoding report as people read it (--json keeps the raw figures)."""
    rows = [
        ("robot", f"{r['robot']} ({r['scheme']} order, {r['codec']} payloads)"),
        ("scans", f"{r['scans']:,} over {r['duration_s']:.2f} s of scan time"),
        *([("points", dropped_text(r))] if r.get("points_dropped") else []),
        ("packets", f"{r['packets']:,}" + (f" ({r['keyframes']:,} keyframes)" if r.get("keyframes") else "")),
        ("log size", f"{r['bytes']:,} bytes for {r['changed_voxels']:,} voxel changes "
                     f"({r['bytes_per_changed_voxel']:.3f} bytes a change)"),
        ("bandwidth", f"{r['avg_bandwidth_Bps'] / 1e3:,.1f} kB/s on average, against {r['raw_sensor_Bps'] / 1e3:,.1f} kB/s "
                      "of raw sensor data"),
        ("time", f"mapping {r['time_map_s']:.3f} s, encoding {r['time_encode_s']:.3f} s "
                 f"({r['encode_cells_per_s'] / 1e6:,.1f} M cells/s)"),
    ]
    return rows
