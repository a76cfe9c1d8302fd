"""Regenerate formats/vectors: small snapshots (.vxm) and their JSON description."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from voxtool.io.snapshot import snapshot_bytes

OUT = Path(__file__).resolve().parents[1] / "formats" / "vectors"


def describe(header: dict, arrays: dict) -> dict:
    return {"header": header, "arrays": {k: {"dtype": v.dtype.name, "shape": list(v.shape), "values": v.ravel().tolist()}
                                         for k, v in arrays.items()}}


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    base = {"voxtool_version": "0.1.0", "backend": "octree",
            "map_params": {"resolution": 0.2, "max_range": -1.0, "min_range": 0.0},
            "sensor_model": {"prob_hit": 0.7, "prob_miss": 0.4, "clamp_min": 0.1192, "clamp_max": 0.971,
                             "occupancy_threshold": 0.5},
            "backend_params": {}, "info": {"source": "golden", "scans": 1, "points": 2, "points_dropped": 0}}
    cases = {
        "snapshot_empty": {"leaf_codes": np.zeros(0, np.int64), "leaf_depths": np.zeros(0, np.uint8),
                           "leaf_values": np.zeros(0, np.float32)},
        # key (32768, 32768, 32768) = voxel [0, 0.2)^3 has Morton code 7 << 45 = 0xE00000000000; its +x
        # neighbour is code + 1; the depth-15 leaf covers the 2x2x2 voxels from code + 8
        "snapshot_three_leaves": {
            "leaf_codes": np.array([0xE00000000000, 0xE00000000001, 0xE00000000008], np.int64),
            "leaf_depths": np.array([16, 16, 15], np.uint8),
            "leaf_values": np.array([-0.4054651, 0.8472979, -1.9924302], np.float32)},
    }
    for name, arrays in cases.items():
        (OUT / f"{name}.vxm").write_bytes(snapshot_bytes(base, arrays, codec="raw"))
        (OUT / f"{name}.json").write_text(json.dumps(describe(base, arrays), indent=1) + "\n")


if __name__ == "__main__":
    main()
