"""`voxtool eval`: hold scans out of a map and count how their voxels agree with it, as OctoMap's
eval_octree_accuracy does; a CI gate with --min-correct."""

from __future__ import annotations

from pathlib import Path

import click

from voxtool.cli.common import (
    dropped_text,
    emit,
    handle_errors,
    int_list,
    origin_option,
    resolve_source,
    scan_options,
    scan_setup,
    threads_option,
)


@click.command("eval")
@click.argument("source", required=False, type=click.Path(path_type=Path))
@click.option("--sample", is_flag=True, help="Use the small real sample shipped with voxtool as SOURCE.")
@click.option("--holdout-every", type=int, default=None, metavar="N",
              help="Hold out every N-th scan counted from 1 (scans N, 2N, ...: indices N-1, 2N-1, ...), as "
                   "eval_octree_accuracy does with N = 5. Default: 5, unless --holdout is given.")
@click.option("--holdout", metavar="I,J,...", help="Hold out these scans (indices from 0) instead.")
@scan_options
@origin_option
@threads_option
@click.option("--min-correct", type=click.FloatRange(0, 100), metavar="PCT",
              help="For CI: exit 8 when held-out voxels agree with the map less than PCT percent of the time.")
@click.option("--png", type=click.Path(path_type=Path), metavar="OUT.png",
              help="Draw where held-out scans disagree with the map (wrong: red, unknown: orange) over the map.")
@click.option("--view", type=click.Choice(["top", "front", "side"]), default="top", show_default=True,
              help="--png: the direction of the picture.")
@click.option("--json", "as_json", is_flag=True, help="Print the totals and every held-out scan's figures as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def eval_cmd(source, sample, holdout_every, holdout, threads, min_correct, png, view, as_json, progress, **kw):
    """How well a map built from SOURCE predicts scans it was not built from (OctoMap's
    eval_octree_accuracy): the map is built from every scan but the held-out ones; each held-out
    scan's voxels (those its rays pass through: free; its end points: occupied) are looked up in
    it: correct, wrong, or unknown. % correct = correct / (correct + wrong).

    \b
    Examples:
      voxtool eval kaist03.graph --resolution 0.2                  eval_octree_accuracy's figures
      voxtool eval scans/ --holdout 3,7 --json                     chosen scans, per scan in JSON
      voxtool eval scans/ --min-correct 98 --png where.png          a CI gate and a picture"""
    from voxtool.evaluate import check_min_correct, evaluate

    source = resolve_source(source, sample)
    if png is not None:
        from voxtool.plots import check_png

        check_png(png, "--png")
    listed = int_list(holdout) if holdout else None
    every = holdout_every if holdout_every is not None or listed else 5
    options, params, sensor = scan_setup(kw)
    from voxtool.api import origin_hint

    with origin_hint(options):
        figures, disagree, map_leaves = evaluate(source, options, params, sensor, every, listed, threads, progress)
    written = None
    if png is not None:
        figures["png"] = _draw(png, disagree, map_leaves, params.resolution, sensor.threshold_log, view, source,
                               figures["total"], figures["origin"])
        written = png
    rows = [(f"scan {r['index']}", _counts(r)) for r in figures["per_scan"]]
    rows += [("held out", f"{len(figures['held_out'])} of {figures['scans']} scans (map of the other "
                          f"{figures['scans_built']})"),
             ("total", _counts(figures["total"]))]
    if figures.get("points_dropped"):
        rows.append(("points", dropped_text(figures) + " on reading"))
    emit(figures, as_json, rows, written=written)
    check_min_correct(figures, min_correct)


def _counts(row: dict) -> str:
    pct = "-" if row["percent_correct"] is None else f"{row['percent_correct']:.2f} %"
    return f"correct {row['correct']:,}, wrong {row['wrong']:,}, unknown {row['unknown']:,}: {pct} correct"


def _draw(png, disagree, map_leaves, resolution, threshold_log, view, source, total, origin):
    """The held-out points' disagreements as voxels over the map. The totals count points, scan by
    scan; the picture shows each voxel once (many points fall in one voxel; a voxel some scan got
    wrong and another found unknown is drawn as wrong), so the legend gives both."""
    from voxtool.api import local_frame_note
    from voxtool.errors import ParameterError
    from voxtool.io.picture import write_overlay_png
    from voxtool.maps.base import Leaves

    if disagree is None:
        raise ParameterError(f"{png}: the held-out scans agree with the map everywhere: nothing to draw")
    wrong = disagree.values > 0
    layers = [(name, Leaves(disagree.codes[m], disagree.depths[m], disagree.values[m]), rgb, int(m.sum()),
               f"{name}: {total[key]:,} points in {int(m.sum()):,} voxels")
              for name, key, m, rgb in (("unknown to the map", "unknown", ~wrong, (0.95, 0.60, 0.15)),
                                        ("wrong", "wrong", wrong, (0.85, 0.10, 0.10)))]
    return write_overlay_png(png, [(map_leaves, threshold_log)], layers, resolution, view,
                             f"held-out scans of {source.name} against the map of the others "
                             "(points counted scan by scan, voxels once; a voxel wrong in any scan is drawn wrong)"
                             + local_frame_note(origin))
