"""A map as a Python object (`voxtool.load`): occupancy and state at world coordinates, its
leaves, statistics and exports. Any map voxtool reads: a snapshot (.vxm), a sharded map (a
directory) or an OctoMap .bt."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from voxtool.keys import keys_inside, morton_encode
from voxtool.maps.base import Leaves

UNKNOWN, FREE, OCCUPIED = 0, 1, 2
STATE_NAMES = ("unknown", "free", "occupied")


class VoxelMap:
    """An occupancy map loaded for queries (see docs/python.md)."""

    def __init__(self, leaves: Leaves, resolution: float, threshold_log: float, path: str | None = None,
                 origin=(0.0, 0.0, 0.0)) -> None:
        from voxtool.maps.shards import ShardedOctree

        self.path = path
        self.origin = np.asarray(origin if origin is not None else (0.0, 0.0, 0.0), dtype=np.float64)  # --origin
        self.resolution = float(resolution)
        self.threshold_log = float(threshold_log)
        self._leaves = leaves
        self._tree = ShardedOctree()
        self._tree.load(leaves)

    def __repr__(self) -> str:
        return f"VoxelMap({self.path or 'in memory'}, resolution={self.resolution:g} m, {len(self._leaves):,} leaves)"

    def _codes(self, xyz) -> tuple[np.ndarray, np.ndarray]:
        """Morton codes of points (N x 3, metres in the scans' frame) and which points lie inside
        the key range."""
        pts = np.atleast_2d(np.asarray(xyz, dtype=np.float64))
        if pts.shape[-1] != 3:
            raise ValueError(f"points must be N x 3 coordinates, not shape {pts.shape}")
        if self.origin.any():
            pts = pts - self.origin  # a map built about a local origin holds the scans moved by it
        keys, inside = keys_inside(pts, self.resolution)  # NaN compares false: outside
        return morton_encode(keys), inside

    def query(self, xyz) -> dict[str, np.ndarray]:
        """Per point: `state` (0 unknown, 1 free, 2 occupied), `probability` (NaN where unknown),
        `log_odds` and `depth` of the leaf that answered (-1 where unknown); vectorized."""
        codes, inside = self._codes(xyz)
        log_odds, depth = self._tree.query(codes)
        log_odds[~inside], depth[~inside] = np.nan, -1
        known = ~np.isnan(log_odds)
        state = np.zeros(codes.shape[0], np.uint8)
        state[known] = np.where(log_odds[known] > np.float32(self.threshold_log), OCCUPIED, FREE)
        with np.errstate(over="ignore"):
            probability = 1.0 - 1.0 / (1.0 + np.exp(log_odds.astype(np.float64)))
        return {"state": state, "probability": probability, "log_odds": log_odds, "depth": depth}

    def occupancy(self, xyz) -> np.ndarray:
        """Occupancy probability at each point (NaN where unknown)."""
        return self.query(xyz)["probability"]

    def state(self, xyz) -> np.ndarray:
        """'occupied', 'free' or 'unknown' at each point."""
        return np.array(STATE_NAMES)[self.query(xyz)["state"]]

    def leaves(self) -> Leaves:
        """The map's leaves (Morton codes, depths, log-odds), Morton order."""
        return self._leaves

    def stats(self) -> dict:
        from voxtool.stats import tree_stats

        return {"resolution": self.resolution, **tree_stats(self._leaves, self.resolution, self.threshold_log, False)}

    def export(self, path: str | os.PathLike, include_free: bool = False) -> dict:
        """Write as .bt, .ply, .pcd, .png or .mcap (the suffix decides); returns what was written."""
        from voxtool.api import exporter
        from voxtool.io.export import TAKES_ORIGIN

        extra = {"origin": tuple(self.origin)} if self.origin.any() and Path(path).suffix.lower() in TAKES_ORIGIN else {}
        return exporter(Path(path))(Path(path), self._leaves, self.resolution, self.threshold_log, include_free, **extra)


def load(path: str | os.PathLike) -> VoxelMap:
    from voxtool.api import load_leaves

    leaves, resolution, threshold_log, meta = load_leaves(path)
    return VoxelMap(leaves, resolution, threshold_log, str(path), meta.get("info", {}).get("origin"))
