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
    dropped_at_origin: int = 0  # exactly at the sensor's own position: a driver's "no return", not a surface
    dropped_ego_box: int = 0  # the vehicle's own body (--ego-box)
    dropped_min_range: int = 0
    raw_bytes: int = 0  # bytes of sensor data this scan came from (bandwidth accounting)
    # beams that saw nothing (a LaserScan's range_max / +Inf readings): world-frame points beyond
    # miss_range along each beam; their rays clear free space up to miss_range and mark no hit
    misses: np.ndarray | None = None
    miss_range: float = -1.0
    # no sensor origin (a survey tile): the points mark their voxels occupied and no ray clears
    # free space (`origin` is then only a place in the tile, for --origin auto)
    hits_only: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def no_returns(self) -> int:
        return 0 if self.misses is None else int(self.misses.shape[0])

    @property
    def points_dropped(self) -> int:
        return self.dropped_nonfinite + self.dropped_at_origin + self.dropped_ego_box + self.dropped_min_range

    def drop_counts(self) -> dict[str, int]:
        """The points dropped on reading, in total and by reason, as every command's --json counts them."""
        return {"points_dropped": self.points_dropped, "points_dropped_nonfinite": self.dropped_nonfinite,
                "points_dropped_at_origin": self.dropped_at_origin, "points_dropped_ego_box": self.dropped_ego_box,
                "points_dropped_min_range": self.dropped_min_range}


# why points were dropped on reading, as the summaries say it (keys of Scan.drop_counts)
DROP_REASONS = {"points_dropped_nonfinite": "not finite (NaN/Inf) or below a LaserScan's range_min",
                "points_dropped_at_origin": "at the sensor's own position (a driver's \"no return\")",
                "points_dropped_ego_box": "on the vehicle (--ego-box)",
                "points_dropped_min_range": "nearer than --min-range"}


def add_drop_counts(totals: dict, scan: Scan) -> None:
    """Add a scan's drop_counts() into `totals` (a dict of the same keys, or an empty one)."""
    for key, n in scan.drop_counts().items():
        totals[key] = totals.get(key, 0) + n
