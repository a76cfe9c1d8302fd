"""A 3D map projected to the 2D occupancy grid a navigation stack plans on, as octomap_server's
`projected_map` does it: a cell is occupied where any occupied voxel of its column lies in the
height range, free where only free ones do, unknown where none is known.

The grid's cells are the map's voxel columns (same resolution, same origin grid), so every
voxel falls in exactly one cell. Pruned leaves cover squares of cells, painted whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from voxtool.errors import ParameterError
from voxtool.keys import TREE_MAX_VAL, centre_key_range, leaf_edge, morton_decode
from voxtool.maps.base import Leaves

UNKNOWN, FREE, OCCUPIED = -1, 0, 100  # nav_msgs/OccupancyGrid's cell values
_PAINT_CELLS = 1 << 22  # cells painted per numpy step (bounded memory for large leaves)


@dataclass
class Grid2D:
    """cells[row, col]: row 0 is the lowest y, col 0 the lowest x (OccupancyGrid's order);
    origin: the (x, y) of cell (0, 0)'s outer corner, metres."""

    cells: np.ndarray  # int8: UNKNOWN, FREE or OCCUPIED
    resolution: float
    origin: tuple[float, float]
    z_range: tuple[float, float] | None

    def counts(self) -> dict:
        return {"cells": int(self.cells.size), "width": int(self.cells.shape[1]), "height": int(self.cells.shape[0]),
                "occupied_cells": int((self.cells == OCCUPIED).sum()), "free_cells": int((self.cells == FREE).sum()),
                "unknown_cells": int((self.cells == UNKNOWN).sum())}


def parse_range(text: str | None, option: str, unit: str, rule: str,
                lowest: float | None = None) -> tuple[float, float] | None:
    """`option` MIN,MAX as a pair of finite numbers, MIN <= MAX (and `lowest` <= MIN where
    given); None when the option is not given. `rule`: what the error line says they must be."""
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise ParameterError(f"{option} {text}: give two numbers MIN,MAX ({unit})") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi and (lowest is None or lowest <= lo)):
        raise ParameterError(f"{option} {text}: {rule}")
    return lo, hi


def parse_z_range(text: str | None) -> tuple[float, float] | None:
    """--z-range MIN,MAX (metres) as a pair, checked; None for the whole height."""
    return parse_range(text, "--z-range", "metres", "MIN must be at most MAX, both finite")


def project(leaves: Leaves, resolution: float, threshold_log: float,
            z_range: tuple[float, float] | None = None) -> Grid2D:
    """The 2D grid of the voxels whose centres lie in z_range (inclusive; None: all). Heights
    above the ground: voxtool.ground.project_grid."""
    return project_sets(lambda: [(leaves, threshold_log)], resolution, z_range)


def _in_range(leaves: Leaves, resolution: float, z_range):
    """(keys, edges, values) of the leaves whose voxels reach into z_range."""
    keys = morton_decode(leaves.codes).astype(np.int64)
    edge = leaf_edge(leaves.depths)
    if z_range is None:
        return keys, edge, leaves.values
    z_lo, z_hi = (int(k) for k in centre_key_range(z_range[0], z_range[1], resolution))  # --crop's rule
    inside = (keys[:, 2] <= z_hi) & (keys[:, 2] + edge - 1 >= z_lo)
    return keys[inside], edge[inside], leaves.values[inside]


def footprint(leaf_sets) -> tuple[int, int, int, int]:
    """(x0, y0, width, height) in keys of the columns a map's voxels (free ones too) cover: every
    2D grid of one map spans it, whatever its band, so that grids of one map lie on each other."""
    lo = hi = None
    for leaves, _ in leaf_sets():
        if leaves.codes.shape[0]:
            keys, edge = morton_decode(leaves.codes).astype(np.int64), leaf_edge(leaves.depths)
            a, b = keys[:, :2].min(axis=0), (keys[:, :2] + edge[:, None]).max(axis=0)
            lo, hi = (a, b) if lo is None else (np.minimum(lo, a), np.maximum(hi, b))
    if lo is None:
        raise ParameterError("the map holds no voxel")
    return int(lo[0]), int(lo[1]), int(hi[0]) - int(lo[0]), int(hi[1]) - int(lo[1])


def project_sets(leaf_sets, resolution: float, z_range: tuple[float, float] | None = None) -> Grid2D:
    """project() of a map given as `leaf_sets()`: a fresh iterator of (leaves, threshold
    log-odds) each call (a sharded map's parts), read three times: for the grid's extent (the
    map's footprint, whatever the band), then to paint free and occupied cells; memory is bounded
    by a set and the grid."""
    x0, y0, width, height = footprint(leaf_sets)
    if width * height > 1 << 31:
        # every grid spans the map's footprint, so a --z-range no longer makes it smaller
        raise ParameterError(f"the grid would have {width} x {height} cells; --crop the map first")
    paint = np.zeros(width * height, dtype=np.uint8)  # 0 unknown, 1 free, 2 occupied: the highest wins
    for state in (1, 2):  # occupied painted last, over every set's free cells: it wins a cell
        for leaves, threshold_log in leaf_sets():
            keys, edge, values = _in_range(leaves, resolution, z_range)
            chosen = (values > np.float32(threshold_log)) == (state == 2)
            for e in np.unique(edge[chosen]).tolist():
                m = chosen & (edge == e)
                base = (keys[m, 1] - y0) * width + (keys[m, 0] - x0)
                square = (np.arange(e)[:, None] * width + np.arange(e)[None, :]).ravel()
                step = max(1, _PAINT_CELLS // square.size)
                for i in range(0, base.shape[0], step):
                    paint[(base[i:i + step, None] + square[None, :]).ravel()] = state
    if z_range is not None and not paint.any():  # every voxel in the band paints its cell
        raise ParameterError("no voxel of the map lies in the --z-range")
    cells = np.array([UNKNOWN, FREE, OCCUPIED], dtype=np.int8)[paint].reshape(height, width)
    origin = ((x0 - TREE_MAX_VAL) * resolution, (y0 - TREE_MAX_VAL) * resolution)
    return Grid2D(cells, resolution, origin, z_range)


# nav2 map_server's trinary image: occ = (255 - pixel) / 255 is occupied above occupied_thresh,
# free below free_thresh, unknown between (ROS map_saver's pixels and thresholds: 0, 254, 205)
PGM_PIXEL = {OCCUPIED: 0, FREE: 254, UNKNOWN: 205}
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


def pgm_bytes(grid: Grid2D) -> bytes:
    """A binary PGM (P5) of the grid, the top row the highest y (an image's first row)."""
    lut = np.full(256, PGM_PIXEL[UNKNOWN], dtype=np.uint8)
    lut[OCCUPIED], lut[FREE] = PGM_PIXEL[OCCUPIED], PGM_PIXEL[FREE]
    image = lut[grid.cells.view(np.uint8)][::-1]
    h, w = image.shape
    return f"P5\n# voxtool occupancy grid, {grid.resolution:g} m\n{w} {h}\n255\n".encode() + image.tobytes()


def map_yaml(grid: Grid2D, image_name: str, local_origin=None) -> str:
    """nav2 map_server's map YAML for the image: the corner of its bottom-left pixel as origin,
    in the scans' frame (a map built about a local origin is shifted back by it, and a comment
    says so)."""
    x, y = grid.origin
    note = ""
    x, y = round(x, 9), round(y, 9)  # key * resolution: -1.7, not -1.7000000000000002
    if local_origin is not None and any(local_origin):
        x, y = round(x + float(local_origin[0]), 9), round(y + float(local_origin[1]), 9)
        note = (f"# voxtool: the map was built about the local origin {list(map(float, local_origin))} "
                "(--origin); this origin is in the scans' frame\n")
    return (f"{note}image: {image_name}\nmode: trinary\nresolution: {grid.resolution!r}\n"
            f"origin: [{x!r}, {y!r}, 0.0]\nnegate: 0\noccupied_thresh: {OCCUPIED_THRESH}\n"
            f"free_thresh: {FREE_THRESH}\n")
