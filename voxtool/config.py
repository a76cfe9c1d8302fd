"""Typed, validated configuration: the sensor model and the map parameters.

Both are frozen dataclasses recorded inside every snapshot so a file says how it was made.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from voxtool.errors import ParameterError


def logodds(p: float) -> float:
    """Log-odds of a probability, rounded to float32 as OctoMap stores it."""
    return float(np.float32(math.log(p / (1.0 - p))))


@dataclass(frozen=True)
class SensorModel:
    """OctoMap's occupancy sensor model (probabilities; log-odds are derived, float32)."""

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    occupancy_threshold: float = 0.5

    def __post_init__(self) -> None:
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max", "occupancy_threshold"):
            value = getattr(self, name)
            if not (0.0 < value < 1.0) or not math.isfinite(value):
                raise ParameterError(f"sensor model: {name}={value} must lie strictly between 0 and 1")
        if self.prob_hit <= 0.5:
            raise ParameterError(f"sensor model: prob_hit={self.prob_hit} must be > 0.5")
        if self.prob_miss >= 0.5:
            raise ParameterError(f"sensor model: prob_miss={self.prob_miss} must be < 0.5")
        if not self.clamp_min < self.occupancy_threshold < self.clamp_max:
            raise ParameterError(
                "sensor model: need clamp_min < occupancy_threshold < clamp_max, got "
                f"{self.clamp_min} / {self.occupancy_threshold} / {self.clamp_max}"
            )

    @property
    def hit_log(self) -> float:
        return logodds(self.prob_hit)

    @property
    def miss_log(self) -> float:
        return logodds(self.prob_miss)

    @property
    def clamp_min_log(self) -> float:
        return logodds(self.clamp_min)

    @property
    def clamp_max_log(self) -> float:
        return logodds(self.clamp_max)

    @property
    def threshold_log(self) -> float:
        return logodds(self.occupancy_threshold)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class MapParams:
    """Map-wide parameters shared by every backend."""

    resolution: float = 0.2
    max_range: float = -1.0  # < 0: unlimited, as OctoMap's maxrange=-1
    min_range: float = 0.0  # points closer than this to the sensor are dropped
    merge_rays: bool = False  # integrate rays with identical voxel paths once (TinyOctoMap IV-B)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and 1e-4 <= self.resolution <= 100.0):
            raise ParameterError(f"resolution={self.resolution} must lie in [0.0001, 100] metres")
        if not math.isfinite(self.max_range) or self.max_range == 0.0:
            raise ParameterError(f"max_range={self.max_range} must be > 0, or < 0 for unlimited")
        if not math.isfinite(self.min_range) or self.min_range < 0.0:
            raise ParameterError(f"min_range={self.min_range} must be >= 0")
        if self.max_range > 0 and self.min_range >= self.max_range:
            raise ParameterError(f"min_range={self.min_range} must be below max_range={self.max_range}")

    def to_dict(self) -> dict:
        return asdict(self)
