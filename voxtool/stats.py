"""Map statistics as OctoMap users count them, and regression comparison for CI."""

from __future__ import annotations

import json
import math
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
    "leaf_nodes": "up", "inner_nodes": "up",  # a bigger tree costs more memory, disk and bandwidth
    "octree_leaf_nodes": "up", "octree_inner_nodes": "up",
    "scans": "any", "points": "any",  # a different input: the rest is no longer comparable
    "points_dropped": "up",
}
LOG_COMPARED = {"packets": "up", "bytes": "up", "total.avg_Bps": "up", "total.max_Bps": "up"}  # packet logs


def tree_stats(leaves: Leaves, resolution: float, threshold_log: float, canonical: bool) -> dict:
    """leaf_stats, and the nodes of OctoMap's two trees of these leaves: `leaf_nodes` /
    `inner_nodes` of the max-likelihood tree a .bt file holds, `octree_leaf_nodes` /
    `octree_inner_nodes` of the log-odds tree OctoMap keeps in memory (`canonical`: the leaves are
    that tree's already, else they are pruned first)."""
    from voxtool.kernels.octree import pruned_tree_counts
    from voxtool.maps.tree import node_counts

    out = leaf_stats(leaves, resolution, threshold_log)
    thr = np.float32(threshold_log)
    # counted while pruning, without building the pruned trees (their copies cost a kaist03
    # build 0.3 s, most of it first-touch page faults)
    octree = node_counts(leaves) if canonical else pruned_tree_counts(leaves.codes, leaves.depths, leaves.values,
                                                                        thr, False)
    out["octree_leaf_nodes"], out["octree_inner_nodes"] = (int(n) for n in octree)
    out["leaf_nodes"], out["inner_nodes"] = (int(n) for n in pruned_tree_counts(
        leaves.codes, leaves.depths, leaves.values, thr, True))
    return out


def leaf_stats(leaves: Leaves, resolution: float, threshold_log: float) -> dict:
    """Occupied/free voxel counts at the finest resolution (pruned leaves expanded) and the
    metric bounding box of the occupied voxels (outer corners, as OctoMap's getMetricMin/Max)."""
    from voxtool.kernels.stats import leaf_summary

    occ, free, lo_key, hi_key = leaf_summary(leaves.codes, leaves.depths, leaves.values, np.float32(threshold_log))
    out = {"occupied_voxels": int(occ), "free_voxels": int(free), "occupied_bbox": None}
    if occ:
        lo = keys_to_coords(lo_key, resolution) - resolution / 2
        hi = keys_to_coords(hi_key, resolution) + resolution / 2
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
