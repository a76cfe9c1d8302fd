"""Map statistics as OctoMap users count them, and regression comparison for CI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from voxtool.errors import FormatError, RegressionError
from voxtool.keys import keys_to_coords, leaf_span, morton_decode
from voxtool.maps.base import Leaves

# figures `stats --compare` checks; timings are machine-dependent and never compared
COMPARED = ("occupied_voxels", "free_voxels", "leaf_nodes", "inner_nodes", "scans", "points", "points_dropped")


def leaf_stats(leaves: Leaves, resolution: float, threshold_log: float) -> dict:
    """Occupied/free voxel counts at the finest resolution (pruned leaves expanded) and the
    metric bounding box of the occupied voxels (outer corners, as OctoMap's getMetricMin/Max)."""
    occupied = leaves.values > np.float32(threshold_log)
    spans = leaf_span(leaves.depths)
    out = {
        "occupied_voxels": int(spans[occupied].sum()),
        "free_voxels": int(spans[~occupied].sum()),
        "occupied_bbox": None,
    }
    if occupied.any():
        first = morton_decode(leaves.codes[occupied])
        last = morton_decode(leaves.codes[occupied] + spans[occupied] - 1)
        lo = keys_to_coords(first.min(axis=0), resolution) - resolution / 2
        hi = keys_to_coords(last.max(axis=0), resolution) + resolution / 2
        out["occupied_bbox"] = {"min": [round(float(v), 9) for v in lo], "max": [round(float(v), 9) for v in hi]}
    return out


def compare(current: dict, baseline_path: str | Path, tolerance: float) -> list[str]:
    """Figures that drifted beyond a relative tolerance; raises RegressionError listing them."""
    path = Path(baseline_path)
    try:
        baseline = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise FormatError(f"{path}: cannot read baseline JSON ({err})") from err
    if not isinstance(baseline, dict):
        raise FormatError(f"{path}: baseline JSON is not an object")
    drifted = []
    for name in COMPARED:
        if name not in baseline or name not in current:
            continue
        old, new = float(baseline[name]), float(current[name])
        rel = abs(new - old) / max(abs(old), 1.0)
        if rel > tolerance or math.isnan(rel):
            drifted.append(f"{name}: {old:g} -> {new:g} ({rel:.2%} > {tolerance:.2%})")
    if drifted:
        raise RegressionError(f"{path}: {len(drifted)} figure(s) drifted: " + "; ".join(drifted))
    return drifted
