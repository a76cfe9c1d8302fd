"""`voxtool cache-bench`: the plain octree against OctoCache settings."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from voxtool.cli.common import (
    check_plot,
    handle_errors,
    int_list,
    origin_option,
    plot_option,
    resolve_source,
    scan_options,
    scan_setup,
    threads_option,
)


@click.command("cache-bench")
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the shipped sample as SOURCE.")
@scan_options
@origin_option
@click.option("--tau", default="4", show_default=True, help="Bucket threshold(s) after eviction, comma-separated sweep.")
@click.option("--buckets", default="", help="Bucket count(s) (powers of two), comma-separated; default: the paper's rule.")
@click.option("--order", default="morton", show_default=True,
              help="Write-back order(s) of evicted voxels: morton, xyz, random, bucket (comma-separated sweep).")
@click.option("--overlap", default="0,1", show_default=True,
              help="0 (write-back on the calling thread) and/or 1 (on its own thread, the paper's two threads).")
@threads_option
@click.option("--json", "as_json", is_flag=True, help="Print all rows as JSON.")
@plot_option("each configuration's time decomposition and cache hit ratio")
@handle_errors
def cache_bench_cmd(source, sample, tau, buckets, order, overlap, threads, as_json, plot, **kw):
    """Run the same scans through the plain octree and through OctoCache settings; report time and
    where it goes, cache hit ratio, octree writes saved, memory, and check the maps are identical
    (exit 1 when any differs)."""
    from voxtool.cachebench import cache_bench
    from voxtool.errors import ParameterError, VoxtoolError

    options, params, sensor = scan_setup(kw)
    source = resolve_source(source, sample)
    from voxtool.sources import resolve_origin

    options = resolve_origin(source, options, params.resolution)  # once, here: every configuration reads the same
    orders = [o.strip() for o in order.split(",") if o.strip()]
    try:
        taus, bucket_list, overlaps = int_list(tau), int_list(buckets) or [None], int_list(overlap)
    except ValueError:
        raise ParameterError("--tau, --buckets and --overlap take comma-separated integers") from None

    def progress(k, n, backend, cfg):
        click.echo(f"[{k + 1}/{n}] {backend} {cfg}", err=True)

    check_plot(plot)
    from voxtool.api import origin_hint

    with origin_hint(options):
        result = cache_bench(source, options.__dict__, params.to_dict(), sensor.to_dict(),
                             taus, bucket_list, orders, overlaps, threads, progress if sys.stderr.isatty() else None)
    rows = result["rows"]
    if plot is not None:
        from voxtool.plots import cache_figure, write_plot

        result.update(write_plot(cache_figure(result), plot))
    if as_json:
        click.echo(json.dumps(result, indent=2))
    else:
        head = f"{'backend':<9} {'ovl':>3} {'tau':>3} {'buckets':>8} {'order':<7} {'total s':>8} {'raycast':>8} {'insert':>7} {'evict':>6} {'octree':>7} {'wait':>6} {'hit %':>6} {'written/updates':>17} {'speedup':>7} {'peak MiB':>8} {'same':>4}"
        click.echo(head)
        for r in rows:
            cache = r["backend"] == "octocache"
            click.echo(
                f"{r['backend']:<9} {r.get('overlap', '-')!s:>3} {r.get('tau', '-')!s:>3} {r.get('buckets', '-')!s:>8} "
                f"{r.get('order', '-'):<7} {r['total_s']:>8.3f} {r['raycast_s']:>8.3f} {r.get('insert_s', 0):>7.3f} "
                f"{r.get('evict_s', 0):>6.3f} {r['octree_update_s']:>7.3f} {r.get('wait_s', 0):>6.3f} "
                f"{(100 * r['hit_ratio'] if cache else 0):>6.1f} "
                f"{(str(r['written_to_octree']) + '/' + str(r['voxel_updates'])) if cache else '-':>17} "
                f"{r['speedup']:>7.2f} {(r['peak_rss_bytes'] or 0) / 2**20:>8.1f} {'yes' if r['identical_to_octree'] else 'NO':>4}")
        if plot is not None:
            click.echo(f"plot written to {plot}")
    bad = [r for r in rows if not r["identical_to_octree"]]
    if bad:
        raise VoxtoolError(f"{source or 'sample'}: {len(bad)} OctoCache configuration(s) built a map different from the octree")
