"""Map statistics as OctoMap users count them, and regression comparison for CI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from voxtool.errors import FormatError, ParameterError, RegressionError
from voxtool.keys import keys_to_coords
from voxtool.maps.base import Leaves

# figures `stats --compare` checks; timings are machine-dependent and never compared
COMPARED = ("occupied_voxels", "free_voxels", "leaf_nodes", "inner_nodes", "scans", "points", "points_dropped")
LOG_COMPARED = ("packets", "bytes", "total.avg_Bps", "total.max_Bps")  # packet logs (`stats LOG.mcap`)


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


def compare(current: dict, baseline_path: str | Path, tolerance: float, figures: tuple = COMPARED) -> list[str]:
    """Figures (dotted paths into the JSON) that drifted beyond a relative tolerance; raises
    RegressionError listing them."""
    path = Path(baseline_path)
    try:
        baseline = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise FormatError(f"{path}: cannot read baseline JSON ({err})") from err
    if not isinstance(baseline, dict):
        raise FormatError(f"{path}: baseline JSON is not an object")
    if not (0 <= tolerance < math.inf):  # NaN would pass every figure
        raise ParameterError(f"--tolerance {tolerance} must be a finite number >= 0")
    drifted, compared = [], 0
    for name in figures:
        value, now = _figure(baseline, name), _figure(current, name)
        if value is None or now is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise FormatError(f"{path}: baseline figure '{name}' is {value!r}, not a number")
        old, new = float(value), float(now)
        compared += 1
        rel = abs(new - old) / max(abs(old), 1.0)
        if rel > tolerance or math.isnan(rel):
            drifted.append(f"{name}: {old:g} -> {new:g} ({rel:.2%} > {tolerance:.2%})")
    if not compared:
        raise FormatError(f"{path}: baseline holds none of the compared figures ({', '.join(figures)})")
    if drifted:
        raise RegressionError(f"{path}: {len(drifted)} figure(s) drifted: " + "; ".join(drifted))
    return drifted
