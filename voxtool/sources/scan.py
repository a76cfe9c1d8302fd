"""One scan as voxtool integrates it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Scan:
    """World-frame points (float32, as OctoMap's point3d) and the sensor origin rays start from."""

    points: np.ndarray  # (N, 3) float32, world frame
    origin: np.ndarray  # (3,) float32, world frame
    index: int = 0
    stamp_ns: int = 0
    source: str = ""
    points_read: int = 0  # points in the file before filtering
    dropped_nonfinite: int = 0
    dropped_min_range: int = 0
    raw_bytes: int = 0  # bytes of sensor data this scan came from (bandwidth accounting)
    # beams that saw nothing (a LaserScan's range_max / +Inf readings): world-frame points beyond
    # miss_range along each beam; their rays clear free space up to miss_range and mark no hit
    misses: np.ndarray | None = None
    miss_range: float = -1.0
    extra: dict = field(default_factory=dict)

    @property
    def no_returns(self) -> int:
        return 0 if self.misses is None else int(self.misses.shape[0])

    @property
    def points_dropped(self) -> int:
        return self.dropped_nonfinite + self.dropped_min_range
