"""`voxtool build`: scans to an occupancy map snapshot."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import (
    backend_options,
    backend_setup,
    check_plot,
    cluster_options,
    emit,
    emit_fleet,
    handle_errors,
    origin_option,
    plot_option,
    resolve_source,
    scan_options,
    scan_setup,
    summary_rows,
    warn_dropped,
    with_origin,
)


@click.command()
@click.argument("sources", nargs=-1, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool (norlab, BSD-3) as SOURCE.")
@click.option("-o", "--output", type=click.Path(),
              help="Write the map snapshot (.vxm) here (atomically). A directory (several SOURCES, or a name ending "
                   "in /): one map per source, named by the shortest end of its path that tells the sources apart "
                   "(data/kaist03/pcd and data/norlab/pcd: kaist03-pcd.vxm, norlab-pcd.vxm). With --sharded: the "
                   "sharded map's directory.")
@backend_options
@scan_options
@origin_option
@click.option("--decay", type=float, metavar="SECONDS",
              help="octree: let the map forget: every voxel's log-odds halve towards unknown over SECONDS of scan "
                   "time, and a voxel within 0.01 log-odds of unknown is forgotten (docs/decay.md). Needs scan "
                   "times. Default: none (the map is OctoMap's).")
@click.option("--share", type=click.Path(path_type=Path), help="hashmap: write newly occupied voxels (ring buffer) as a packet log.")
@click.option("--ring", default=3, show_default=True, type=int, help="hashmap --share: frames per broadcast (k).")
@cluster_options
@click.option("--one-map", is_flag=True,
              help="Build one map from all SOURCES (in scan-timestamp order) instead of one per source.")
@click.option("--sharded", is_flag=True,
              help="Write one map as a sharded snapshot directory, each part by the worker holding it "
                   "(formats/sharded.md); needs --workers or --scheduler.")
@click.option("--json", "as_json", is_flag=True, help="Print statistics and timings as JSON on stdout.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@plot_option("each scan's latency and the map's size over the scans (one map built in this process)")
@handle_errors
def build(sources, sample, output, origin, decay, share, ring, workers, scheduler, one_map, sharded, as_json, progress,
          plot, **kw):
    """Build an occupancy map from SOURCE: a directory of PCD (or PLY + --poses) scans, a single
    PCD/PLY file, a ROS 2 .mcap file, a ROS 1 .bag file, a ROS 2 bag directory (.db3 or .mcap
    storage), an OctoMap .graph file, a KITTI sequence, an .e57 file (the e57 extra), a Velodyne
    .pcap/.pcapng capture (the velodyne extra; with --poses) or a .las/.laz survey tile (the las
    extra; occupied voxels only, --origin auto for projected coordinates). Bags and MCAP files give PointCloud2,
    LaserScan or Velodyne packet (the velodyne extra) scans posed by /tf, --pose-topic, or a pose
    file (--poses: one row per message).

    \b
    Several SOURCES:
      voxtool build runs/*/ -o maps/ --workers 4        one map per source (a fleet)
      voxtool build a.mcap b.mcap -o map.vxm --workers 4 one map of all (scan-timestamp order)
      voxtool build big.mcap -o map/ --sharded --workers 8  one map, written part by part
    With --workers or --scheduler the work runs on Dask (docs/distributed.md)."""
    from voxtool.cluster import wanted
    from voxtool.errors import ParameterError

    dask = wanted(workers, scheduler)
    if sample or not sources:
        sources = (resolve_source(None if not sources else sources[0], sample),)
    options, params, sensor = scan_setup(kw)
    options = with_origin(options, origin)
    backend, extra = backend_setup(kw)
    if decay is not None:
        if backend != "octree":
            raise ParameterError(f"--decay makes the octree forget; backend '{backend}' has no decay (build with "
                                 "--backend octree, the default)")
        extra["decay_half_life"] = decay
    # a trailing slash, an existing directory, or several sources without .vxm: one map per source
    to_dir = output is not None and not sharded and not one_map and (
        output.endswith("/") or Path(output).is_dir() or (len(sources) > 1 and Path(output).suffix.lower() != ".vxm"))
    output = Path(output) if output is not None else None
    if plot is not None and (dask or to_dir or len(sources) > 1 or sharded or one_map):
        raise ParameterError("--plot draws the scans of one map built in this process: one SOURCE, "
                             "without --workers/--scheduler")
    check_plot(plot)
    if sharded or one_map or (not to_dir and (dask or len(sources) > 1)):
        if not dask:
            raise ParameterError("one map from several sources, or a sharded map, is built by Dask workers: "
                                 "give --workers N (a local cluster) or --scheduler ADDRESS")
        if backend != "octree" or share is not None or "decay_half_life" in extra:
            raise ParameterError(f"a map built by Dask workers uses the octree backend (not '{backend}'), without "
                                 "--share or --decay")
        if sharded and output is None:
            raise ParameterError("--sharded needs -o DIRECTORY")
        from voxtool.api import build_one_map
        from voxtool.cluster import dask_client

        with dask_client(workers, scheduler) as client:
            result = build_one_map(list(sources), options, params, sensor, client, output, sharded, progress,
                                   extra.get("shard_depth"))
        emit(result, as_json, summary_rows(result), written=output)
        return
    if to_dir or len(sources) > 1:
        from voxtool.fleet import fleet_job, run_fleet_on

        if output is None:
            raise ParameterError("several SOURCES build one map each: give -o DIRECTORY for them")
        report = run_fleet_on("build", list(sources), fleet_job(options, params, sensor, backend, extra), output,
                              workers, scheduler, progress)
        emit_fleet(report, as_json, lambda r: f"{r['occupied_voxels']:,} occupied voxels, {r['scans']:,} scans")
        return
    from voxtool.api import build_map

    if sources[0].suffix.lower() == ".bt":  # an OctoMap map, imported as it is
        from voxtool.api import export_map

        if output is None:
            raise ParameterError(f"{sources[0]}: an OctoMap .bt is imported with -o MAP.vxm")
        imported = export_map(sources[0], output, False, progress)
        from voxtool.api import map_stats

        result = {**map_stats(output, progress), "imported": imported}
        emit(result, as_json, summary_rows(result), written=output)
        return
    result = build_map(sources[0], options, params, sensor, backend, output, progress, extra, share, ring,
                       per_scan=plot is not None)
    warn_dropped(sources[0], result)
    rows = summary_rows(result)
    if plot is not None:
        from voxtool.plots import build_figure, write_plot
        from voxtool.sources import source_names

        result.update(write_plot(build_figure(result, source_names(sources)[0]), plot))
        del result["per_scan"]
        rows.append(("plot", str(plot)))
    if output is None:  # measured only: say so, or a forgotten -o looks like a map written somewhere
        rows.append(("written", "nothing: no -o given, the map was built and measured only"))
    emit(result, as_json, rows, written=output)
