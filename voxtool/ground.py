"""The ground under a 3D map, and the 2D grid of what stands on it (`export --above-ground`,
`clean --grid`).

Outdoors a grid cut at fixed heights is wrong wherever the ground slopes: the road uphill is an
obstacle, the road downhill is out of range. What a navigation stack needs is height above the
ground under each cell. The ground here comes from the map itself (docs/design/ground.md):
1. each column's floor: its lowest occupied voxel that is part of a surface (at least `support`
   occupied voxels among the 24 around it), not a lone return under the road;
2. pits: a floor more than `pit_depth_m` below the typical floor around it (a median over the
   3 x 3 blocks of `pit_block_m` around it), whose voxel was hit only a few times, is a reflection (returns from under
   the road: multipath, wet asphalt, glass); that column's floor is its lowest surface no deeper
   than `pit_depth_m` under the typical one;
3. a progressive morphological filter (Zhang et al., 2003): the floor is opened (a minimum then
   a maximum over a square window) with windows that double, and a column whose floor stands
   above the opened surface by more than the window's allowed rise (a fixed step plus a slope
   times the window) is not ground: a car, a wall, a roof;
4. columns without ground (under a car, behind a wall) take the height of the ground around them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit

from voxtool.errors import ParameterError
from voxtool.grid import FREE, OCCUPIED, UNKNOWN, Grid2D, footprint, parse_range, project
from voxtool.keys import TREE_MAX_VAL, expand_leaves, morton_decode
from voxtool.maps.base import Leaves

NONE = np.iinfo(np.int32).max  # a column without an occupied voxel


@dataclass(frozen=True)
class GroundParams:
    max_window_m: float = 16.0  # the largest object the filter removes (its footprint, metres)
    slope: float = 0.3  # the steepest ground (rise over run)
    step_m: float = 0.3  # the highest kerb or step that is still ground (metres)
    fill_m: float = 3.0  # how far a column without ground looks for ground around it (metres)
    support: int = 2  # occupied voxels beside a floor voxel that make it a surface (0: the lowest voxel, whatever)
    pit_block_m: float = 2.0  # the typical floor around a column: over 3 x 3 blocks this wide (0: no pits) ...
    pit_quantile: float = 0.25  # ... the median of their floors' lower quartiles
    pit_depth_m: float = 1.0  # a floor deeper than this under the typical floor around it is not the ground ...
    pit_hits: float = 3.5  # ... where their voxel was hit at most this often (the road is hit again and again)
    # a floor over the surface opened by a window at most this many columns wide is not ground
    # once it stands narrow_step_m over it (None: step_m): such a window lowers a slope's top (a
    # crest, the edge of what was seen) by at most half a layer up to a 25 % grade, so a floor a
    # whole layer over it is an object's base
    narrow_columns: int = 5
    narrow_step_m: float | None = None


# The ground of a map's --above-ground grid and picture: a floor a voxel layer over the floors
# around it, on a patch 5 columns across or less, is not ground. Under a bush, a car's sill, a
# kerb stone, the lowest voxel is the object's base, and taking it for the ground lifted the
# object out of a 0.3 m band; a kerb's top stays ground-level in the grid either way (its surface
# one layer over the road's ground is under the band). `clean` keeps GroundParams(): there the
# points of a kerb must stay ground. Measured: docs/design/ground.md, "Narrow steps".
MAP_GRID_GROUND = GroundParams(narrow_step_m=0.05)


def parse_above_ground(text: str | None) -> tuple[float, float] | None:
    """--above-ground MIN,MAX (metres above the ground) as a pair, checked."""
    return parse_range(text, "--above-ground", "metres above the ground",
                       "need 0 <= MIN <= MAX (metres above the ground)", lowest=0.0)


@njit(cache=True, nogil=True)
def _min_along_rows(a, half):
    """Each cell's minimum over cells c - half .. c + half of its row, in three passes whatever
    the window (van Herk / Gil-Werman: running minima forward and backward within blocks of the
    window's length; any window covers the tail of one block and the head of the next). Cells
    beyond the row's ends never win."""
    rows, cols = a.shape
    w = 2 * half + 1
    size = cols + 2 * half  # padded: cell c is cell c + half here
    forward = np.empty(size, dtype=a.dtype)
    backward = np.empty(size, dtype=a.dtype)
    out = np.empty_like(a)
    for r in range(rows):
        forward[:half] = NONE
        forward[half:half + cols] = a[r]
        forward[half + cols:] = NONE
        backward[:] = forward
        for i in range(1, size):
            if i % w and forward[i - 1] < forward[i]:
                forward[i] = forward[i - 1]
        for i in range(size - 2, -1, -1):
            if (i + 1) % w and backward[i + 1] < backward[i]:
                backward[i] = backward[i + 1]
        for c in range(cols):  # the window c - half .. c + half is padded cells c .. c + 2 half
            out[r, c] = min(backward[c], forward[c + 2 * half])
    return out


@njit(cache=True, nogil=True)
def _min_down_columns(a, half):
    """_min_along_rows down the columns, whole rows at a time (contiguous, no transpose)."""
    rows, cols = a.shape
    w = 2 * half + 1
    size = rows + 2 * half
    forward = np.full((size, cols), NONE, dtype=a.dtype)
    forward[half:half + rows] = a
    backward = forward.copy()
    for i in range(1, size):
        if i % w:
            for c in range(cols):
                if forward[i - 1, c] < forward[i, c]:
                    forward[i, c] = forward[i - 1, c]
    for i in range(size - 2, -1, -1):
        if (i + 1) % w:
            for c in range(cols):
                if backward[i + 1, c] < backward[i, c]:
                    backward[i, c] = backward[i + 1, c]
    return np.minimum(backward[:rows], forward[2 * half:])


def _filter(a: np.ndarray, half: int, take_min: bool) -> np.ndarray:
    """A square window's minimum or maximum of the columns that have a floor (separable: along
    rows, then down columns). Columns without one (NONE) never win a minimum; a maximum is the
    minimum of the negated keys, where a column without a floor is +1, above every negated key."""
    if take_min:
        return _min_down_columns(_min_along_rows(a, half), half)
    negated = np.where(a == NONE, 1, -a).astype(np.int32)
    out = _min_down_columns(_min_along_rows(negated, half), half)
    return np.where(out == 1, NONE, -out).astype(np.int32)


@njit(cache=True, nogil=True)
def _fill(ground, known, rounds):
    """Spread known ground into unknown cells, ring by ring (each new cell the mean of its known
    8-neighbours), for `rounds` rings: each ring is the unknown cells beside the last one (the
    known cells, first), so only those are visited."""
    rows, cols = ground.shape
    queued = known.copy()  # known, or in a ring already
    ring = np.empty(rows * cols, dtype=np.int64)  # the last ring, then the next one after it
    m = 0
    for r in range(rows):
        for c in range(cols):
            if known[r, c]:
                ring[m] = r * cols + c
                m += 1
    values = np.empty(rows * cols)
    for _ in range(rounds):
        n_next = 0
        for k in range(m):  # the next ring: cells beside the last one not yet queued
            r, c = ring[k] // cols, ring[k] % cols
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < rows and 0 <= cc < cols and not queued[rr, cc]:
                        queued[rr, cc] = True
                        ring[m + n_next] = rr * cols + cc
                        n_next += 1
        if n_next == 0:
            break
        ring[:n_next] = ring[m:m + n_next]
        m = n_next
        for k in range(m):  # each from the cells known before this ring
            r, c = ring[k] // cols, ring[k] % cols
            total = 0.0
            n = 0
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    rr, cc = r + dr, c + dc
                    if 0 <= rr < rows and 0 <= cc < cols and known[rr, cc]:
                        total += ground[rr, cc]
                        n += 1
            values[k] = total / n
        for k in range(m):
            r, c = ring[k] // cols, ring[k] % cols
            ground[r, c] = values[k]
            known[r, c] = True


@njit(cache=True, nogil=True)
def _under(kx, ky, height, x0, y0, column):
    out = np.empty(kx.shape[0])
    rows, cols = height.shape
    for i in range(kx.shape[0]):
        r, c = ky[i] // column - y0, kx[i] // column - x0
        out[i] = height[r, c] if 0 <= r < rows and 0 <= c < cols else np.nan
    return out


@njit(cache=True, nogil=True)
def _supported_floor(codes, column, x0, y0, rows, cols, support, lowest):
    """Each column's lowest key z among the sorted unique voxel codes (x << 32 | y << 16 | z)
    that has at least `support` occupied voxels among the 24 beside it (the 8 columns around, one
    layer down to one layer up): a surface, not a lone return below it (reflections and multipath
    put about 0.4 % of a car's points metres under the road, and a lowest voxel would take them
    as the ground). NONE where no voxel of the column is supported."""
    floor = np.full((rows, cols), NONE, dtype=np.int32)
    which = np.full((rows, cols), -1, dtype=np.int64)  # the floor's index in codes
    n = codes.shape[0]
    for i in range(n):
        c = codes[i]
        x, y, z = c >> 32, (c >> 16) & 0xFFFF, c & 0xFFFF
        r, col = y // column - y0, x // column - x0
        if z >= floor[r, col] or z < lowest[r, col]:
            continue
        if support > 0 and _neighbours(codes, x, y, z, support) < support:
            continue
        floor[r, col] = z
        which[r, col] = i
    return floor, which


@njit(cache=True, nogil=True)
def _neighbours(codes, x, y, z, most):
    """How many of the 24 voxels beside (x, y, z) (the 8 columns around, one layer down to one up)
    are among the sorted codes, counted up to `most`."""
    n = codes.shape[0]
    found = 0
    for dx in range(-1, 2):
        for dy in range(-1, 2):
            if dx == 0 and dy == 0:
                continue
            # the three voxels z-1..z+1 of a neighbouring column are consecutive codes
            lo = ((x + dx) << 32) | ((y + dy) << 16) | (z - 1)
            j = np.searchsorted(codes, lo)
            while j < n and codes[j] <= lo + 2:
                found += 1
                j += 1
            if found >= most:
                return found
    return found


def _typical_floor(floor: np.ndarray, block: int, quantile: float) -> np.ndarray:
    """Each column's typical floor around it: the median of the `quantile` floors of the 3 x 3
    blocks of `block` x `block` columns around its own (NONE-free; NONE where none has a floor).
    Quantiles, not a closing: a closing's maximum takes a crown over ground that sparse points left
    unseen in a few columns, and a reflection patch a few columns wide moves no low quantile of a
    block; a low one, since far from the sensor most columns hold walls and crowns, few the ground."""
    rows, cols = floor.shape
    br, bc = (rows + block - 1) // block, (cols + block - 1) // block
    r, c = np.nonzero(floor != NONE)
    ids = (r // block) * bc + c // block
    z = floor[r, c]
    order = np.lexsort((z, ids))
    ids, z = ids[order], z[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    counts = np.diff(np.r_[starts, ids.shape[0]])
    medians = np.full(br * bc, np.nan)
    medians[ids[starts]] = z[starts + (counts * quantile).astype(np.int64)]
    padded = np.pad(medians.reshape(br, bc), 1, constant_values=np.nan)
    around = np.stack([padded[i:i + br, j:j + bc] for i in range(3) for j in range(3)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # no floor in any block around: NaN, NONE below
        typical = np.nanmedian(around, axis=0)
    per_column = np.repeat(np.repeat(typical, block, axis=0), block, axis=1)[:rows, :cols]
    return np.where(np.isnan(per_column), NONE, np.round(per_column)).astype(np.int32)


@dataclass
class Ground:
    """Ground height (metres, at the voxel's bottom face) per column of `column` x `column`
    voxels; NaN where unknown. Row 0 is the lowest y, column 0 the lowest x, of the columns from
    (x0, y0) (keys // column)."""

    height: np.ndarray  # float64 (rows, cols)
    x0: int
    y0: int
    resolution: float
    column: int = 1

    def under(self, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
        """The ground's height under columns (kx, ky) (key arrays of one shape); NaN where it is
        not known or the column lies outside the grid."""
        kx, ky = np.asarray(kx), np.asarray(ky)
        out = _under(kx.astype(np.int64).ravel(), ky.astype(np.int64).ravel(), self.height, self.x0, self.y0,
                     self.column)
        return out.reshape(kx.shape)


def voxel_codes(keys: np.ndarray) -> np.ndarray:
    """Finest keys (N, 3) as the codes ground_from_codes sorts (x << 32 | y << 16 | z)."""
    keys = np.asarray(keys, dtype=np.int64)
    return keys[:, 0] << 32 | keys[:, 1] << 16 | keys[:, 2]


def unique_codes(codes: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The sorted unique codes and how often each was hit: its repeats, or its weights summed
    (pieces of unique_codes joined: their counts as the weights)."""
    if weights is None:
        return np.unique(codes, return_counts=True)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    return codes[starts], np.add.reduceat(np.asarray(weights, dtype=np.float64)[order], starts)


def ground_of(keys: np.ndarray, resolution: float, params: GroundParams = GroundParams(),
              column: int = 1, weights: np.ndarray | None = None) -> Ground:
    """The ground under occupied voxels given as finest keys (N, 3; repeats allowed), per
    column of `column` x `column` voxels (heights stay at the voxels' resolution). `weights`: how
    often each key was hit (a map's occupancy in hits, occupied_voxels); None: once per key, so
    the points of scans count their own repeats."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.shape[0] == 0:
        raise ParameterError("the map holds no occupied voxel: there is no ground to find")
    return ground_from_codes(*unique_codes(voxel_codes(keys), weights), resolution, params, column)


def ground_from_codes(codes: np.ndarray, hits: np.ndarray, resolution: float, params: GroundParams = GroundParams(),
                      column: int = 1) -> Ground:
    """ground_of() of sorted unique voxel codes (voxel_codes) and how often each was hit: what a
    caller holding many points builds piece by piece, never all their keys at once."""
    if codes.shape[0] == 0:
        raise ParameterError("the map holds no occupied voxel: there is no ground to find")
    kx, ky = codes >> 32, (codes >> 16) & 0xFFFF
    x0, y0 = int(kx.min()) // column, int(ky.min()) // column
    cols, rows = int(kx.max()) // column - x0 + 1, int(ky.max()) // column - y0 + 1
    if rows * cols > 1 << 28:
        raise ParameterError(f"the ground grid would have {cols:,} x {rows:,} columns of {resolution * column:g} m, over "
                             f"{1 << 28:,}: export a --crop of the map, or clean --grid fewer scans or a coarser "
                             "--resolution")
    nowhere = np.zeros((rows, cols), np.int32)
    floor, which = _supported_floor(codes, column, x0, y0, rows, cols, params.support, nowhere)
    lowest_voxel, lowest_which = _supported_floor(codes, column, x0, y0, rows, cols, 0, nowhere)
    # a column with no surface (far road: one ring's points, a voxel or more apart) keeps its lowest voxel
    alone = (floor == NONE) & (lowest_voxel != NONE)
    floor[alone], which[alone] = lowest_voxel[alone], lowest_which[alone]
    if params.pit_block_m > 0:
        reference = _typical_floor(lowest_voxel, max(1, int(round(params.pit_block_m / (resolution * column)))),
                                   params.pit_quantile)
        depth = int(round(params.pit_depth_m / resolution))
        pits = (floor != NONE) & (reference != NONE) & (reference - floor > depth)
        pits &= hits[np.maximum(which, 0)] <= params.pit_hits  # a surface hit again and again is ground in a pit
        if pits.any():
            lowest = np.where(pits, reference - depth, np.iinfo(np.int32).max).astype(np.int32)
            lifted = _supported_floor(codes, column, x0, y0, rows, cols, params.support, lowest)[0]
            floor = np.where(pits, lifted, floor)
    width = resolution * column  # of a column, metres
    surface = floor.copy()
    ground = floor != NONE
    window = 1
    previous = 0
    while window * width <= params.max_window_m:
        opened = _filter(_filter(surface, window, True), window, False)
        narrow = params.narrow_step_m is not None and 2 * window + 1 <= params.narrow_columns
        step = params.narrow_step_m if narrow else params.step_m
        rise = (step + params.slope * (window - previous) * width) / resolution
        ground &= ~((surface != NONE) & (opened != NONE) & (surface - opened > rise))
        surface = np.where(opened != NONE, opened, surface)
        previous, window = window, window * 2
    height = np.where(ground, (floor.astype(np.float64) - TREE_MAX_VAL) * resolution, 0.0)
    known = ground.copy()
    _fill(height, known, max(1, int(round(params.fill_m / width))))
    height[~known] = np.nan
    return Ground(height, x0, y0, resolution, column)


HIT_LOG = float(np.log(0.7 / 0.3))  # OctoMap's default hit in log-odds: a map's occupancy in hits


def occupied_voxels(leaves: Leaves, threshold_log: float) -> tuple[np.ndarray, np.ndarray]:
    """The finest keys (N, 3) of the occupied voxels and their occupancy in hits (log-odds over
    a default hit's: clamped maps say 4.1 at most), for ground_of's weights."""
    occupied = leaves.values > np.float32(threshold_log)
    keys = morton_decode(expand_leaves(leaves.codes[occupied], leaves.depths[occupied])).astype(np.int64)
    per_leaf = 8 ** (16 - leaves.depths[occupied].astype(np.int64))  # a coarser leaf: its finest voxels
    return keys, np.repeat(leaves.values[occupied].astype(np.float64) / HIT_LOG, per_leaf)


def check_has_height(where: str, leaves: Leaves, resolution: float, threshold_log: float) -> None:
    """Refuse --above-ground on a map whose occupied voxels lie in two layers or fewer: a level
    2D scanner's map, in which the ground model would take the walls for the floor and drop them
    from the grid (a planner would drive through them)."""
    keys, _ = occupied_voxels(leaves, threshold_log)
    if keys.shape[0] and keys[:, 2].max() - keys[:, 2].min() < 2:
        lo, hi = ((int(keys[:, 2].min()) - TREE_MAX_VAL) * resolution, (int(keys[:, 2].max()) + 1 - TREE_MAX_VAL) * resolution)
        raise ParameterError(f"{where}: --above-ground: its occupied voxels lie in {int(np.ptp(keys[:, 2])) + 1} "
                             f"layer(s) of {resolution:g} m (z {lo:.2f}..{hi:.2f} m), a 2D scanner's map, with no ground "
                             "to measure height from: export it without --above-ground (every occupied voxel an obstacle)")


def project_above_ground(leaves: Leaves, resolution: float, threshold_log: float, band: tuple[float, float],
                         params: GroundParams = MAP_GRID_GROUND, obstacle_log: float | None = None) -> Grid2D:
    """The 2D grid of what stands MIN..MAX metres above the ground: a cell is occupied where an
    occupied voxel's centre lies in that band above the ground under it, free where the ground
    under it is known and nothing in the band is occupied, unknown where its ground is not.
    `obstacle_log`: the log-odds over which a voxel in the band is an obstacle, if not the
    map's occupancy threshold (the ground is found from the occupied voxels either way;
    benchmarks/bench_ground.py measures lower ones: docs/design/ground.md)."""
    keys, hits = occupied_voxels(leaves, threshold_log)
    ground = ground_of(keys, resolution, params, weights=hits)
    if obstacle_log is not None:
        keys, _ = occupied_voxels(leaves, obstacle_log)
    x0, y0, width, height = footprint(lambda: [(leaves, threshold_log)])  # the map's, as --z-range's grid
    cells = np.full((height, width), UNKNOWN, dtype=np.int8)
    rows, cols = ground.height.shape
    r0, c0 = ground.y0 - y0, ground.x0 - x0  # the ground's columns lie within the map's
    cells[r0:r0 + rows, c0:c0 + cols] = np.where(np.isnan(ground.height), UNKNOWN, FREE)
    mark_standing(cells, x0, y0, keys, ground, band)
    origin = ((x0 - TREE_MAX_VAL) * resolution, (y0 - TREE_MAX_VAL) * resolution)
    return Grid2D(cells, resolution, origin, None)


def mark_standing(cells: np.ndarray, x0: int, y0: int, keys: np.ndarray, ground: Ground,
                  band: tuple[float, float]) -> None:
    """Mark OCCUPIED the cells (row key y - y0, column key x - x0) of the voxels (finest keys,
    N x 3) that stand MIN..MAX metres over the ground under them."""
    # a voxel's height above the ground: its bottom face above the floor voxel's (the ground's height),
    # so whole voxel layers over the floor; a road that straddles a voxel boundary fills the floor
    # voxel and the one above it, and that one, at a layer, is still the road and not 0.3 m above it
    above = (keys[:, 2] - TREE_MAX_VAL) * ground.resolution - ground.under(keys[:, 0], keys[:, 1])
    inside = (above >= band[0]) & (above <= band[1])  # NaN (no ground, or outside it) is in no band
    cells[keys[inside, 1] - y0, keys[inside, 0] - x0] = OCCUPIED


# Returns this close to their sensor (metres, level) are no obstacle by themselves: a car's own
# body, its roof rack and mirrors (a KITTI car's: 1.3-2.1 m from its scanner, 0.5-0.9 m under
# it), in a new voxel of the world each scan as the car drives. What stands there is an obstacle
# where a scan from farther off hit it, or the map holds it occupied. docs/design/ground.md, section 4.
NEAR_RETURN_M = 3.5


def return_floor_log(sensor) -> float:
    """The log-odds at or under which a voxel holding returns is no obstacle in the grid of the
    returns: the map's clamp floor, plus half a miss (a voxel rays crossed so often after its
    returns that it reached the floor: what a passing car leaves behind)."""
    return float(sensor.clamp_min_log + 0.5 * abs(sensor.miss_log))


def project_returns_above_ground(points: np.ndarray, scan_starts: np.ndarray, origins: np.ndarray, backend,
                                 band: tuple[float, float], keep: np.ndarray | None = None,
                                 evidence: np.ndarray | None = None, near_m: float = NEAR_RETURN_M,
                                 params: GroundParams = MAP_GRID_GROUND) -> tuple[Grid2D, dict]:
    """The 2D grid of what stands MIN..MAX metres above the ground under a scan sequence's points
    (world frame, scan order; scan i is points[scan_starts[i]:scan_starts[i + 1]], its sensor at
    origins[i]; `keep`: the points to use, if not all) and `backend`, the occupancy map of those
    scans: a cell is occupied where a voxel in that band is occupied in the map, or holds a return
    from at least `near_m` (level) off its sensor that the map has not cleared to its floor
    (return_floor_log) and `evidence` (per point, if given: clean's "not void") allows; free
    where the ground under it is known and nothing in the band is, unknown elsewhere. The ground
    is found as a map's (`params`), in the points' voxels, each weighted by the scans that hit it.

    Unlike a map's grid (project_above_ground), a voxel that more rays pass through than stop in
    stays an obstacle: hedges, fences, railings, thin poles. Give it points without movers (clean's
    kept points, their map): a passing car that the map has not cleared would mark its trail.
    Returns (grid, figures: the cells the returns mark that the map alone leaves free)."""
    from voxtool.keys import coords_to_keys, morton_encode

    resolution = backend.params.resolution
    scan_voxels, far_voxels = [], []  # per scan: its distinct voxels, and those a far return hit
    for i, (a, b) in enumerate(zip(scan_starts[:-1], scan_starts[1:])):
        used = slice(None) if keep is None else keep[a:b]
        scan = points[a:b][used]
        if scan.shape[0] == 0:
            continue
        codes = voxel_codes(coords_to_keys(scan, resolution).astype(np.int64))
        far = np.hypot(scan[:, 0] - origins[i][0], scan[:, 1] - origins[i][1]) >= near_m
        if evidence is not None:
            far &= evidence[a:b][used]
        scan_voxels.append(np.unique(codes))
        far_voxels.append(np.unique(codes[far]))
    if not scan_voxels:
        raise ParameterError("no points to find the ground under: the grid of the returns needs returns")
    ground = ground_from_codes(*unique_codes(np.concatenate(scan_voxels)), resolution, params)  # hits: scans
    del scan_voxels
    returns = np.unique(np.concatenate(far_voxels))
    returns = np.stack([returns >> 32, (returns >> 16) & 0xFFFF, returns & 0xFFFF], 1)
    held = backend.query(morton_encode(returns)) > np.float32(return_floor_log(backend.sensor))  # NaN: not held
    occupied, _ = occupied_voxels(backend.leaves(), backend.sensor.threshold_log)

    cells = np.where(np.isnan(ground.height), UNKNOWN, FREE).astype(np.int8)  # the ground's columns
    mark_standing(cells, ground.x0, ground.y0, occupied, ground, band)
    by_map = int((cells == OCCUPIED).sum())
    mark_standing(cells, ground.x0, ground.y0, returns[held], ground, band)
    origin = ((ground.x0 - TREE_MAX_VAL) * resolution, (ground.y0 - TREE_MAX_VAL) * resolution)
    return Grid2D(cells, resolution, origin, None), {"cells_by_returns": int((cells == OCCUPIED).sum()) - by_map,
                                                     "near_returns_m": near_m}


def project_grid(leaves: Leaves, resolution: float, threshold_log: float, z_range: tuple[float, float] | None = None,
                 above_ground: tuple[float, float] | None = None, obstacle_log: float | None = None) -> Grid2D:
    """The 2D grid of a map: what stands `above_ground` (MIN, MAX metres over the ground) where
    given (obstacles over log-odds `obstacle_log`, project_above_ground), else the voxels in
    z_range (voxtool.grid.project)."""
    if above_ground is not None:
        return project_above_ground(leaves, resolution, threshold_log, above_ground, obstacle_log=obstacle_log)
    return project(leaves, resolution, threshold_log, z_range)
