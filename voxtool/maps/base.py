"""The contract every map backend meets, and the leaf table they all share."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.sources.scan import Scan


@dataclass
class Leaves:
    """A map as Morton-ordered leaves: first covered voxel's code, depth (16 = one voxel), log-odds."""

    codes: np.ndarray  # int64
    depths: np.ndarray  # uint8
    values: np.ndarray  # float32

    def __len__(self) -> int:
        return int(self.codes.shape[0])


def join_leaves(parts: list[Leaves], consume: bool = False) -> Leaves:
    """Leaf sets that do not overlap (a map's parts, pieces of a crop) as one, in Morton order.
    `consume`: empty the list once its arrays are copied, so that the parts' memory can go
    before the sort (a whole map's leaves: 29 bytes a leaf at the peak instead of 50)."""
    codes, depths, values = (np.concatenate([getattr(p, f) for p in parts]) for f in ("codes", "depths", "values"))
    if consume:
        parts.clear()
    order = np.argsort(codes, kind="stable")
    codes = codes[order]  # one array reordered at a time: each original goes as its copy is made
    depths = depths[order]
    values = values[order]
    return Leaves(codes, depths, values)


@dataclass
class IntegrateTiming:
    """Seconds spent in one scan's integration, split by phase."""

    raycast: float = 0.0
    update: float = 0.0
    voxel_updates: int = 0
    ray_steps: int = 0
    rays: int = 0
    merged_rays: int = 0


@dataclass
class PreparedScan:
    """A scan's voxel updates computed ahead of the map update (ray casting is map-independent)."""

    packed: np.ndarray | None  # Morton-sorted code << 1 | occupied; None while kept as `bricks` (updates())
    steps: int
    seconds: float
    rays: int = 0
    merged_rays: int = 0  # rays skipped because another ray of the scan has the same voxel path
    stamp_ns: int = 0  # scan time (backends that keep time, e.g. the hash map's history)
    origin: np.ndarray | None = None  # sensor origin (the hash map's inflation range)
    scan: Scan | None = None  # for backends whose ray casting depends on the map (hash map)
    index: int = -1  # the scan's index (parameter schedules), -1 when not from a scan stream
    brick_runs: tuple | None = None  # (distinct 8^3-brick codes, where each one's updates start) in packed
    source: str = ""  # where the scan came from (for messages)
    near_hits: tuple | None = None  # clean's rays' stop and skip table (kernels.clean.near_hits_table)
    bricks: Any = None  # the octree's: the updates as merged brick masks (maps.octree.ScanBricks)
    threads: int = 1  # threads to expand `bricks` on

    def updates(self) -> np.ndarray:
        """`packed`, expanded from `bricks` the first time it is asked for."""
        if self.packed is None:
            self.packed, starts = self.bricks.updates(self.threads)
            self.brick_runs = (self.bricks.distinct, starts)
        return self.packed


class MapBackend(Protocol):
    """What the pipeline, the snapshot writer and the exporters need from a backend."""

    name: str
    params: MapParams
    sensor: SensorModel

    def warm_up(self) -> None:
        """Load the compiled kernels (JIT) before timing starts."""

    def prepare(self, scan: Scan) -> PreparedScan:
        """Compute a scan's voxel updates without touching the map (may run on another thread)."""

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        """Fold prepared updates into the map, in scan order."""

    def integrate(self, scan: Scan) -> IntegrateTiming:
        """Fold one scan into the map (prepare + apply)."""

    def query(self, codes: np.ndarray) -> np.ndarray:
        """Log-odds at finest-level Morton codes; NaN where unknown."""

    def leaves(self) -> Leaves:
        """All known leaves in Morton order."""

    def node_counts(self) -> tuple[int, int]:
        """(leaf nodes, inner nodes)."""

    def memory_bytes(self) -> int:
        """Bytes the map's storage has allocated (room to grow included)."""

    def used_bytes(self) -> int:
        """Bytes of that storage holding the map's content."""

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Arrays that make the map lossless in a snapshot."""

    def extra_meta(self) -> dict[str, Any]:
        """Backend parameters to record in a snapshot."""

    def extra_stats(self) -> dict[str, Any]:
        """Backend-specific figures for `stats` (pool usage, cache counters...)."""


def update_codes(backend: MapBackend, prepared: PreparedScan) -> np.ndarray:
    """Morton codes (sorted) whose state the next backend.apply(prepared) updates. A backend
    that casts rays against its own map (the hash map) computes them here, at the last moment."""
    own = getattr(backend, "update_codes", None)
    return own(prepared) if own is not None else prepared.updates() >> 1


def removed_voxels(backend: MapBackend) -> tuple[np.ndarray, np.ndarray] | None:
    """Voxels the last apply() dropped beyond its updated codes (the hash map's voxel limit and
    time-to-live): Morton codes and log-odds before they left; None for backends that never drop."""
    own = getattr(backend, "removed_voxels", None)
    return own() if own is not None else None
