"""`voxtool eval`: how well a map predicts scans it was not built from, as OctoMap's
eval_octree_accuracy measures it.

The map is built from every scan but the held-out ones (OctoMap's tool holds out every 5th:
scans 5, 10, ... counted from 1). Each held-out scan is then cast as its own update would be
(OctoMap's computeUpdate: the voxels its rays pass through, and its end points, which win) and
every such voxel is looked up in the map: correct when the map agrees (free where the ray passed,
occupied at an end point), wrong when it disagrees, unknown where the map has no voxel.
% correct = correct / (correct + wrong).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError, VoxtoolError
from voxtool.maps.base import Leaves
from voxtool.sources import ScanStream, SourceOptions, open_source
from voxtool.sources.scan import add_drop_counts


class AccuracyError(VoxtoolError):
    """`eval --min-correct`: the held-out scans agree with the map less than asked."""

    exit_code = 8


def holdout_indices(count: int, every: int | None, listed: list[int] | None) -> np.ndarray:
    """The held-out scan indices (0-based, in the source): every N-th scan counted from 1, as
    eval_octree_accuracy (indices N-1, 2N-1, ...), or the ones listed."""
    if (every is None) == (not listed):
        raise ParameterError("give --holdout-every N or --holdout I,J,... (scan indices from 0)")
    if every is not None:
        if every < 2:
            raise ParameterError(f"--holdout-every {every}: at least 2 (one scan held out of every N)")
        return np.arange(every - 1, count, every, dtype=np.int64)
    chosen = np.unique(np.asarray(listed, dtype=np.int64))
    if chosen.size and (chosen[0] < 0 or chosen[-1] >= count):
        raise ParameterError(f"--holdout {','.join(map(str, listed))}: scan indices are 0..{count - 1}")
    if chosen.size == count:
        raise ParameterError("--holdout names every scan: the map would be empty")
    return chosen


def _without(stream: ScanStream, held: set) -> ScanStream:
    def scans() -> Iterator:
        return (s for s in stream.scans if s.index not in held)

    count = None if stream.count is None else stream.count - len(held)
    return ScanStream(stream.kind, stream.path, count, scans(), stream.bad)


def _count_scans(source, options: SourceOptions) -> int:
    stream = open_source(source, options)
    if stream.count is not None:  # the scans the options select (--stop included)
        return stream.count
    return sum(1 for _ in stream.scans)  # a source that does not say: counted by reading it


def evaluate(source: str | os.PathLike, options: SourceOptions, params: MapParams, sensor: SensorModel,
             every: int | None = 5, listed: list[int] | None = None, threads: int = 0,
             progress: bool | None = None) -> tuple[dict, Leaves | None, Leaves]:
    """(the figures: per held-out scan and in total; the voxels held-out scans disagree on, as
    leaves whose value is 1 wrong, 0 unknown, for a picture; the map's leaves)."""
    from voxtool.maps.octree import OctreeMap, scan_updates
    from voxtool.pipeline import build
    from voxtool.progress import bar

    if options.start or options.every != 1:
        raise ParameterError("eval counts scans from the source's first: use --stop (OctoMap's -n), not --start/--every")
    from voxtool.sources import resolve_origin

    t0 = time.perf_counter()
    options = resolve_origin(source, options, params.resolution)
    count = _count_scans(source, options)
    held = holdout_indices(count, every, listed)
    held_set = set(held.tolist())
    backend = OctreeMap(params, sensor, threads)
    report = build(_without(open_source(source, options), held_set), backend, progress)
    t_build = time.perf_counter() - t0
    rows, wrong_codes, unknown_codes = [], [], []
    thr = np.float32(sensor.threshold_log)
    stream = open_source(source, options)
    dropped = {k: v for k, v in report.to_dict().items() if k.startswith("points_dropped")}  # of the scans built
    with bar(len(held), "eval", progress, "scan") as steps:
        for scan in stream.scans:
            if scan.index not in held_set:
                continue
            add_drop_counts(dropped, scan)
            packed, _, _ = scan_updates(scan, params, backend.threads)
            codes, hit = packed >> 1, (packed & 1).astype(bool)
            log_odds, _ = backend.query_depth(codes)
            known = ~np.isnan(log_odds)
            agrees = (log_odds > thr) == hit
            correct, wrong = int((known & agrees).sum()), int((known & ~agrees).sum())
            rows.append({"index": scan.index, "points": int(scan.points.shape[0]), "correct": correct, "wrong": wrong,
                         "unknown": int((~known).sum()), "percent_correct": _percent(correct, wrong)})
            wrong_codes.append(codes[known & ~agrees])
            unknown_codes.append(codes[~known])
            steps.update(1)
    total = {k: sum(r[k] for r in rows) for k in ("points", "correct", "wrong", "unknown")}
    total["percent_correct"] = _percent(total["correct"], total["wrong"])
    figures = {"source": str(source), "resolution": params.resolution, "max_range": params.max_range,
               "scans": count, "scans_built": report.scans, "held_out": [int(i) for i in held], **dropped,
               "origin": [float(v) for v in options.origin] if options.origin is not None else [0.0, 0.0, 0.0],
               "total": total, "per_scan": rows,
               "timings_s": {"build": round(t_build, 6), "total": round(time.perf_counter() - t0, 6)}}
    return figures, _disagreement(wrong_codes, unknown_codes), backend.leaves()


def _percent(correct: int, wrong: int) -> float | None:
    return round(100.0 * correct / (correct + wrong), 6) if correct + wrong else None


def _disagreement(wrong: list, unknown: list) -> Leaves | None:
    """Finest voxels (depth 16), value 1 where a held-out scan disagreed, 0 where it was unknown
    (a voxel both ways counts as wrong)."""
    from voxtool.keys import unique_codes

    w = unique_codes(np.concatenate(wrong)) if wrong else np.empty(0, np.int64)
    u = unique_codes(np.concatenate(unknown)) if unknown else np.empty(0, np.int64)
    u = u[~np.isin(u, w)]
    codes = np.concatenate([w, u])
    if codes.size == 0:
        return None
    values = np.concatenate([np.ones(w.size, np.float32), np.zeros(u.size, np.float32)])
    order = np.argsort(codes, kind="stable")
    return Leaves(codes[order], np.full(codes.size, 16, np.uint8), values[order])


def check_min_correct(figures: dict, min_correct: float | None) -> None:
    """--min-correct PCT: the CI gate (AccuracyError, exit 8, below it)."""
    got = figures["total"]["percent_correct"]
    if min_correct is not None and (got is None or got < min_correct):
        raise AccuracyError(f"{figures['source']}: held-out scans agree with the map on {got if got is not None else 0:.3f} % "
                            f"of known voxels, below --min-correct {min_correct:g}")
