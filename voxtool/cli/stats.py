"""`voxtool stats`: statistics of a map or a packet log, and regression checks for CI."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import check_plot, cluster_options, emit, emit_fleet, handle_errors, plot_option, summary_rows


@click.command()
@click.argument("map_files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print as JSON.")
@click.option("--compare", "baseline", type=click.Path(path_type=Path),
              help="Baseline JSON (from `stats --json`): print every compared figure and exit 6 when one changes "
                   "beyond --tolerance in its bad direction (maps: voxels either way, more nodes or dropped points; "
                   "packet logs: more packets, bytes or bandwidth). docs/parameters.md lists them.")
@click.option("--tolerance", default=0.0, show_default=True, type=float,
              help="Relative change allowed by --compare (0.01: 1 %).")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@plot_option("a packet log's bandwidth over time per robot (1 s windows, average) and its packet sizes")
@cluster_options
@handle_errors
def stats(map_files, as_json, baseline, tolerance, progress, plot, workers, scheduler):
    """Statistics of a map snapshot (.vxm), a sharded map (a directory), an OctoMap .bt file, or a
    packet log (.mcap). Several files: one row each and the totals (with --workers or --scheduler,
    one Dask task each)."""
    from voxtool.api import any_stats
    from voxtool.cluster import wanted
    from voxtool.stats import COMPARED, LOG_COMPARED, compare, comparison_rows, number, regression_error

    dask = wanted(workers, scheduler)
    if plot is not None and (dask or any(f.suffix.lower() != ".mcap" for f in map_files)):
        from voxtool.errors import ParameterError

        raise ParameterError("--plot draws the bandwidth of packet logs (.mcap), without --workers/--scheduler")
    check_plot(plot)
    if plot is not None and len(map_files) > 1:
        _plot_logs(map_files, plot, as_json, progress)
        return
    if len(map_files) > 1 or dask:
        from voxtool.errors import ParameterError
        from voxtool.fleet import run_fleet_on

        if baseline is not None:
            raise ParameterError("--compare checks one file against its baseline; give one file")
        report = run_fleet_on("stats", list(map_files), {}, None, workers, scheduler, progress)
        emit_fleet(report, as_json, lambda r: f"{number(r['bytes'])} bytes in {number(r['packets'])} packets"
                   if "packets" in r else f"{number(r['occupied_voxels'])} occupied voxels")
        return
    map_file = map_files[0]
    if plot is not None:
        from voxtool.codec.logstats import log_stats
        from voxtool.plots import log_figure, write_plot

        series = {}
        result = log_stats(map_file, progress, series)
        if not result["packets"]:
            from voxtool.errors import ParameterError

            raise ParameterError(f"{map_file}: the log holds no packets: there is nothing to plot")
        result.update(write_plot(log_figure(result, series), plot))
    else:
        result = any_stats(map_file, progress)
    if map_file.suffix.lower() == ".mcap":
        figures = LOG_COMPARED
        rows = [("packets", number(result["packets"])), ("bytes", number(result["bytes"])),
                ("total bandwidth", f"avg {number(result['total']['avg_Bps'])} B/s, max {number(result['total']['max_Bps'])} B/s")]
        for robot, r in result["robots"].items():
            rows.append((f"robot {robot}", f"{r['scheme']}/{r['codec']}: avg {number(r['avg_Bps'])} B/s, max "
                                           f"{number(r['max_Bps'])} B/s over 1 s, {number(r['bytes_per_changed_voxel'])} "
                                           f"B a changed voxel"))
            rows += [("", line) for line in ratio_lines(r)]
        if plot is not None:
            rows.append(("plot", str(plot)))
    else:
        figures = COMPARED
        rows = summary_rows(result)
    report = None
    if baseline is not None:
        report = compare(result, baseline, tolerance, figures)
        result["comparison"] = report
        rows += comparison_rows(report)
    emit(result, as_json, rows)
    if report is not None and report["regressions"]:
        raise regression_error(report)


def _plot_logs(logs: list[Path], plot: Path, as_json: bool, progress) -> None:
    """Several robots' packet logs in one bandwidth plot (a robot name two logs share is told
    apart by its file), and each log's figures."""
    from voxtool.codec.logstats import log_stats
    from voxtool.plots import log_figure, write_plot
    from voxtool.stats import number

    series, robots, results = {}, {}, []
    for log in logs:
        own: dict = {}
        result = log_stats(log, progress, own)
        results.append(result)
        for robot, data in own.items():
            name = robot if robot not in series else f"{robot} ({log.name})"
            series[name], robots[name] = data, result["robots"][robot]
    combined = {"log": " + ".join(log.name for log in logs), "packets": sum(r["packets"] for r in results),
                "bytes": sum(r["bytes"] for r in results), "robots": robots}
    out = {"logs": results, "packets": combined["packets"], "bytes": combined["bytes"],
           **write_plot(log_figure(combined, series), plot)}
    rows = [(str(log), f"{number(r['bytes'])} bytes in {number(r['packets'])} packets, robots "
                       f"{', '.join(r['robots'])}") for log, r in zip(logs, results)]
    rows.append(("plot", f"{plot}: {len(series)} robots"))
    emit(out, as_json, rows, written=plot)


def ratio_lines(r: dict) -> list[str]:
    """Each size ratio of a robot's packets, saying what it is against."""
    from voxtool.stats import number

    lines = []
    if r["scheme"] in ("hilbert", "nested"):
        lines.append(f"payloads x{number(r['compression_ratio'])} smaller than the dense 2-bit boxes they code")
    else:
        lines.append(f"payloads x{number(r['compression_ratio'])} smaller than before compression")
    if r.get("vs_racer"):
        lines.append(f"packets x{number(r['vs_racer'])} smaller than RACER's address + state lists of the same "
                     "changes (addressed in each packet's box: RACER's least)")
    if r.get("ratio_to_raw_sensor"):
        lines.append(f"bandwidth {number(r['ratio_to_raw_sensor'])} of the raw sensor data's "
                     f"({number(r['raw_sensor_Bps'])} B/s)")
    return lines
