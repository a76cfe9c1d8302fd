"""Map statistics as OctoMap users count them, and regression comparison for CI."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from voxtool.errors import FormatError, ParameterError, RegressionError
from voxtool.keys import keys_to_coords
from voxtool.maps.base import Leaves

# The figures `stats --compare` checks, with the change that counts as a regression: "up" (more
# is worse), "down" (less is worse) or "any" (a change either way needs a look). Timings are
# machine-dependent and never compared. docs/parameters.md lists the reason for each.
COMPARED = {
    "occupied_voxels": "any", "free_voxels": "any",  # the map itself: fewer can be as wrong as more
    "bt_leaf_nodes": "up", "bt_inner_nodes": "up",  # a bigger tree costs more memory, disk and bandwidth
    "logodds_leaf_nodes": "up", "logodds_inner_nodes": "up",
    "scans": "any", "points": "any",  # a different input: the rest is no longer comparable
    "points_dropped": "up",
}
# the names these figures had before 0.2 (a baseline written then still compares)
RENAMED = {"leaf_nodes": "bt_leaf_nodes", "inner_nodes": "bt_inner_nodes",
           "octree_leaf_nodes": "logodds_leaf_nodes", "octree_inner_nodes": "logodds_inner_nodes"}
LOG_COMPARED = {"packets": "up", "bytes": "up", "total.avg_Bps": "up", "total.max_Bps": "up"}  # packet logs


def tree_stats(leaves: Leaves | Iterable[Leaves], resolution: float, threshold_log: float, canonical: bool) -> dict:
    """leaf_stats, and the nodes of OctoMap's two trees of these leaves: `bt_leaf_nodes` /
    `bt_inner_nodes` of the max-likelihood tree a .bt file holds, `logodds_leaf_nodes` /
    `logodds_inner_nodes` of the log-odds tree OctoMap keeps in memory (`canonical`: the leaves are
    that tree's already, else they are pruned first). `leaves` may come in consecutive chunks
    (ShardedOctree.leaf_chunks), each read once."""
    counter = TreeStats(threshold_log, canonical)
    for chunk in [leaves] if isinstance(leaves, Leaves) else leaves:
        counter.add(chunk)
    return counter.result(resolution)


class TreeStats:
    """tree_stats of leaves added chunk by chunk, in Morton order; `seconds` spent adding."""

    def __init__(self, threshold_log: float, canonical: bool) -> None:
        from voxtool.kernels.octree import pruned_tree_state

        self.threshold = np.float32(threshold_log)
        self.canonical = canonical
        self.summary = LeafSummary(threshold_log)
        # counted while pruning, without building the pruned trees (their copies cost a kaist03
        # build 0.3 s, most of it first-touch page faults)
        self.ml, self.octree = pruned_tree_state(), pruned_tree_state()
        self.octree_leaves = self.octree_inner = 0
        self.last = (0, -1)  # the leaf before the next chunk (canonical inner nodes), depth -1: none
        self.seconds = 0.0

    def add(self, chunk: Leaves) -> None:
        from voxtool.kernels.octree import inner_nodes, pruned_tree_feed

        if not len(chunk):
            return
        t0 = time.perf_counter()
        self.summary.add(chunk)
        if self.canonical:
            self.octree_leaves += len(chunk)
            self.octree_inner += int(inner_nodes(chunk.codes, chunk.depths, *self.last))
            self.last = (int(chunk.codes[-1]), int(chunk.depths[-1]))
        else:
            pruned_tree_feed(chunk.codes, chunk.depths, chunk.values, self.threshold, False, *self.octree)
        pruned_tree_feed(chunk.codes, chunk.depths, chunk.values, self.threshold, True, *self.ml)
        self.seconds += time.perf_counter() - t0

    def feed(self, chunks: Iterable[tuple]) -> Iterable[tuple]:
        """The (codes, depths, values) chunks passed on, each added on the way (the leaves a
        snapshot writes, counted in the same pass)."""
        for chunk in chunks:
            self.add(Leaves(*chunk))
            yield chunk

    def result(self, resolution: float) -> dict:
        """The figures, once every leaf is added (closing the counts: ask once)."""
        from voxtool.kernels.octree import pruned_tree_close

        out = self.summary.result(resolution)
        counts = (self.octree_leaves, self.octree_inner) if self.canonical else pruned_tree_close(*self.octree)
        out["logodds_leaf_nodes"], out["logodds_inner_nodes"] = (int(n) for n in counts)
        out["bt_leaf_nodes"], out["bt_inner_nodes"] = (int(n) for n in pruned_tree_close(*self.ml))
        return out


def leaf_stats(leaves: Leaves, resolution: float, threshold_log: float) -> dict:
    """Occupied/free voxel counts at the finest resolution (pruned leaves expanded) and the
    metric bounding box of the occupied voxels (outer corners, as OctoMap's getMetricMin/Max)."""
    summary = LeafSummary(threshold_log)
    summary.add(leaves)
    return summary.result(resolution)


class LeafSummary:
    """leaf_stats of leaves added chunk by chunk."""

    def __init__(self, threshold_log: float) -> None:
        self.threshold = np.float32(threshold_log)
        self.occupied = self.free = 0
        self.lo = self.hi = None

    def add(self, leaves: Leaves) -> None:
        from voxtool.kernels.stats import leaf_summary

        occ, free, lo, hi = leaf_summary(leaves.codes, leaves.depths, leaves.values, self.threshold)
        self.occupied += int(occ)
        self.free += int(free)
        if occ:
            self.lo = lo if self.lo is None else np.minimum(self.lo, lo)
            self.hi = hi if self.hi is None else np.maximum(self.hi, hi)

    def result(self, resolution: float) -> dict:
        out = {"occupied_voxels": self.occupied, "free_voxels": self.free, "occupied_bbox": None}
        if self.occupied:
            lo = keys_to_coords(self.lo, resolution) - resolution / 2
            hi = keys_to_coords(self.hi, resolution) + resolution / 2
            out["occupied_bbox"] = {"min": [round(float(v), 9) for v in lo], "max": [round(float(v), 9) for v in hi]}
        return out


def _figure(d: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def number(value) -> str:
    """One way to print a figure: thousands separated, no exponent, no trailing zeros."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, int):
        return f"{value:,}"
    return f"{value:,.3f}".rstrip("0").rstrip(".")


def compare(current: dict, baseline_path: str | Path, tolerance: float, figures: dict = COMPARED) -> dict:
    """Compare figures (dotted paths into the JSON) with a baseline: per figure the baseline,
    the new value, the relative change, the change allowed and a verdict (ok, improvement,
    regression: a change beyond the tolerance in the direction `figures` names). Never raises
    for a regression: the caller reports it (`stats` exits 6)."""
    path = Path(baseline_path)
    try:
        baseline = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise FormatError(f"{path}: cannot read baseline JSON ({err})") from err
    if not isinstance(baseline, dict):
        raise FormatError(f"{path}: baseline JSON is not an object")
    for old, new in RENAMED.items():
        if old in baseline and new not in baseline:
            baseline[new] = baseline.pop(old)
    if not (0 <= tolerance < math.inf):  # NaN would pass every figure
        raise ParameterError(f"--tolerance {tolerance} must be a finite number >= 0")
    rows = {}
    for name, worse in figures.items():
        value, now = _figure(baseline, name), _figure(current, name)
        if value is None or now is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise FormatError(f"{path}: baseline figure '{name}' is {value!r}, not a number")
        change = (float(now) - float(value)) / max(abs(float(value)), 1.0)
        beyond = abs(change) > tolerance or math.isnan(change)
        bad = beyond and (worse == "any" or (worse == "up") == (change > 0) or math.isnan(change))
        rows[name] = {"base": value, "new": now, "change": round(change, 6), "allowed": tolerance,
                      "regression_if": {"up": "more", "down": "less", "any": "changed"}[worse],
                      "verdict": "regression" if bad else "improvement" if beyond else "ok"}
    if not rows:
        raise FormatError(f"{path}: baseline holds none of the compared figures ({', '.join(figures)})")
    return {"baseline": str(path), "tolerance": tolerance, "figures": rows,
            "regressions": [name for name, r in rows.items() if r["verdict"] == "regression"]}


def comparison_rows(report: dict) -> list[tuple[str, str]]:
    """The comparison as `stats` prints it: one row per figure."""
    out = []
    for name, r in report["figures"].items():
        out.append((f"compare {name}", f"{number(r['base'])} -> {number(r['new'])} ({r['change']:+.2%}, allowed "
                                       f"{r['allowed']:.2%}, worse if {r['regression_if']}): {r['verdict']}"))
    return out


def regression_error(report: dict) -> RegressionError:
    """The one-line error for a comparison with regressions."""
    parts = [f"{name} {number(report['figures'][name]['base'])} -> {number(report['figures'][name]['new'])} "
             f"({report['figures'][name]['change']:+.2%})" for name in report["regressions"]]
    return RegressionError(f"{report['baseline']}: {len(parts)} figure(s) regressed beyond the tolerance of "
                           f"{report['tolerance']:.2%}: " + "; ".join(parts))
