"""The ground under a 3D map, and the 2D grid of what stands on it (`export --above-ground`).

Outdoors a grid cut at fixed heights is wrong wherever the ground slopes: the road uphill is an
obstacle, the road downhill is out of range. What a navigation stack needs is height above the
ground under each cell. The ground here comes from the map itself: each column's lowest
occupied voxel (the floor), filtered by a progressive morphological filter (Zhang et al., 2003):
the floor is opened (a minimum then a maximum over a square window) with windows that double, and
a column whose floor stands above the opened surface by more than the window's allowed rise
(a fixed step plus a slope times the window) is not ground: a car, a wall, a roof. Columns
without ground (under a car, behind a wall) take the height of the nearest ground around them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from voxtool.errors import ParameterError
from voxtool.grid import FREE, OCCUPIED, UNKNOWN, Grid2D
from voxtool.keys import TREE_MAX_VAL, expand_leaves, morton_decode
from voxtool.maps.base import Leaves

NONE = np.iinfo(np.int32).max  # a column without an occupied voxel


@dataclass(frozen=True)
class GroundParams:
    max_window_m: float = 16.0  # the largest object the filter removes (its footprint, metres)
    slope: float = 0.3  # the steepest ground (rise over run)
    step_m: float = 0.3  # the highest kerb or step that is still ground (metres)
    fill_m: float = 3.0  # how far a column without ground looks for ground around it (metres)


def parse_above_ground(text: str | None) -> tuple[float, float] | None:
    """--above-ground MIN,MAX (metres above the ground) as a pair, checked."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ParameterError(f"--above-ground {text}: give two numbers MIN,MAX (metres above the ground)") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 <= lo <= hi):
        raise ParameterError(f"--above-ground {text}: need 0 <= MIN <= MAX (metres above the ground)")
    return lo, hi


@njit(cache=True, nogil=True)
def _filter_rows(a, half, take_min, out):
    """out[r, c]: the minimum (or maximum) of a[r, c - half .. c + half], in time linear in the
    row whatever the window (a monotonic queue of candidates)."""
    rows, cols = a.shape
    queue = np.empty(cols, dtype=np.int64)
    for r in range(rows):
        head = tail = 0
        for i in range(cols + half):
            if i < cols:
                v = a[r, i]
                while tail > head and ((a[r, queue[tail - 1]] >= v) if take_min else (a[r, queue[tail - 1]] <= v)):
                    tail -= 1
                queue[tail] = i
                tail += 1
            c = i - half
            if c < 0:
                continue
            while queue[head] < c - half:
                head += 1
            out[r, c] = a[r, queue[head]]


def _filter(a: np.ndarray, half: int, take_min: bool) -> np.ndarray:
    """A square window's minimum or maximum of the columns that have a floor (separable: rows,
    then columns). Columns without one (NONE) never win: NONE is above every key for a minimum,
    and is made -1 (below every key) for a maximum."""
    work = a if take_min else np.where(a == NONE, -1, a).astype(np.int32)
    rows = np.empty_like(work)
    _filter_rows(work, half, take_min, rows)
    columns = np.ascontiguousarray(rows.T)
    out = np.empty_like(columns)
    _filter_rows(columns, half, take_min, out)
    out = np.ascontiguousarray(out.T)
    return out if take_min else np.where(out == -1, NONE, out).astype(np.int32)


@njit(cache=True, nogil=True)
def _fill(ground, known, rounds):
    """Spread known ground into unknown cells, ring by ring (the mean of known 8-neighbours),
    for `rounds` rings."""
    rows, cols = ground.shape
    for _ in range(rounds):
        new_ground = ground.copy()
        new_known = known.copy()
        changed = False
        for r in range(rows):
            for c in range(cols):
                if known[r, c]:
                    continue
                total = 0.0
                n = 0
                for dr in range(-1, 2):
                    for dc in range(-1, 2):
                        rr, cc = r + dr, c + dc
                        if 0 <= rr < rows and 0 <= cc < cols and known[rr, cc]:
                            total += ground[rr, cc]
                            n += 1
                if n:
                    new_ground[r, c] = total / n
                    new_known[r, c] = True
                    changed = True
        ground[:, :] = new_ground
        known[:, :] = new_known
        if not changed:
            break


@dataclass
class Ground:
    """Ground height (metres, at the voxel's bottom face) per map column; NaN where unknown.
    Row 0 is the lowest y, column 0 the lowest x, of the columns from key (x0, y0)."""

    height: np.ndarray  # float64 (rows, cols)
    x0: int
    y0: int
    resolution: float

    def under(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        """The ground's height under columns (kx, ky) (key arrays of one shape); NaN where it is
        not known or the column lies outside the grid."""
        row, col = np.asarray(ky) - self.y0, np.asarray(kx) - self.x0
        inside = (row >= 0) & (row < self.height.shape[0]) & (col >= 0) & (col < self.height.shape[1])
        out = np.full(row.shape, np.nan)
        out[inside] = self.height[row[inside], col[inside]]
        return out


def ground_of(keys: np.ndarray, resolution: float, params: GroundParams = GroundParams()) -> Ground:
    """The ground under occupied voxels given as finest keys (N, 3)."""
    if keys.shape[0] == 0:
        raise ParameterError("the map holds no occupied voxel: there is no ground to find")
    x0, y0 = int(keys[:, 0].min()), int(keys[:, 1].min())
    cols, rows = int(keys[:, 0].max()) - x0 + 1, int(keys[:, 1].max()) - y0 + 1
    if rows * cols > 1 << 28:
        raise ParameterError(f"the ground grid would have {cols} x {rows} columns; --crop the map first")
    floor = np.full(rows * cols, NONE, dtype=np.int32)
    np.minimum.at(floor, (keys[:, 1] - y0) * cols + (keys[:, 0] - x0), keys[:, 2].astype(np.int32))
    floor = floor.reshape(rows, cols)
    surface = floor.copy()
    ground = floor != NONE
    window = 1
    previous = 0
    while window * resolution <= params.max_window_m:
        opened = _filter(_filter(surface, window, True), window, False)
        rise = (params.step_m + params.slope * (window - previous) * resolution) / resolution
        ground &= ~((surface != NONE) & (opened != NONE) & (surface - opened > rise))
        surface = np.where(opened != NONE, opened, surface)
        previous, window = window, window * 2
    height = np.where(ground, (floor.astype(np.float64) - TREE_MAX_VAL) * resolution, 0.0)
    known = ground.copy()
    _fill(height, known, max(1, int(round(params.fill_m / resolution))))
    height[~known] = np.nan
    return Ground(height, x0, y0, resolution)


def occupied_keys(leaves: Leaves, threshold_log: float) -> np.ndarray:
    occupied = leaves.values > np.float32(threshold_log)
    return morton_decode(expand_leaves(leaves.codes[occupied], leaves.depths[occupied])).astype(np.int64)


def project_above_ground(leaves: Leaves, resolution: float, threshold_log: float, band: tuple[float, float],
                         params: GroundParams = GroundParams()) -> Grid2D:
    """The 2D grid of what stands MIN..MAX metres above the ground: a cell is occupied where an
    occupied voxel's centre lies in that band above the ground under it, free where the ground
    under it is known and nothing in the band is occupied, unknown where its ground is not."""
    keys = occupied_keys(leaves, threshold_log)
    ground = ground_of(keys, resolution, params)
    cells = np.where(np.isnan(ground.height), UNKNOWN, FREE).astype(np.int8)
    above = (keys[:, 2] - TREE_MAX_VAL + 0.5) * resolution - ground.under(keys[:, 0], keys[:, 1])
    inside = (above >= band[0]) & (above <= band[1])  # NaN (no ground) is in no band
    cells[keys[inside, 1] - ground.y0, keys[inside, 0] - ground.x0] = OCCUPIED
    origin = ((ground.x0 - TREE_MAX_VAL) * resolution, (ground.y0 - TREE_MAX_VAL) * resolution)
    return Grid2D(cells, resolution, origin, None)
