"""2D scans registered to an occupancy grid of every scan before them (`voxtool odometry` on LaserScans).

After the scan matcher of Hector SLAM (Kohlbrecher et al., SSRR 2011): each scan's points are
aligned to the grid of the scans before it by Gauss-Newton on the grid's bilinearly interpolated
occupancy, coarse level first (three levels, each cell half the one before); then its points mark
their cells. The map persists where the robot has been (a window of 8 ranges round it), so a
room or an arena seen again pins the pose again, where a point-to-point local map (KISS-ICP) lets
small biases add up: docs/design/odometry.md has the figures on nine simulated logs.

A direction the scan hardly constrains (a corridor's length: the Gauss-Newton system's eigenvalue
under 1 % of its largest) keeps the constant-velocity guess instead of following noise, and a
correction larger than two coarse cells is taken for a false match (the guess is kept).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.errors import ParameterError
from voxtool.geometry import planar_pose

CELLS_PER_RANGE = 140  # the finest cell: range / 140 (2.5 cm for a 3.5 m scanner whose 1-degree beams lie 6 cm apart)
LEVELS = 3  # cells of 4, 2 and 1 finest cells: the coarse ones widen the basin, the fine one sets the pose
ITERATIONS = 20  # Gauss-Newton steps a level at most (it stops once a step is under 10 um)
WEAK = 0.01  # a direction whose eigenvalue is under this share of the largest keeps the guess
WINDOW_RANGES = 8  # the grid's side, in ranges; recentred on the robot when it nears an edge
MAX_CELLS_A_SIDE = 4096  # the finest grid's side at most (64 MiB of float32): a --voxel-size far under the default


@njit(cache=True, nogil=True)
def _sample(grid, cell, x, y):
    """The grid's occupancy at (x, y) (grid coordinates: metres from its corner), bilinearly
    interpolated between cell centres, and its gradient; 0 outside."""
    gx, gy = x / cell - 0.5, y / cell - 0.5
    ix, iy = int(np.floor(gx)), int(np.floor(gy))
    if ix < 0 or iy < 0 or ix + 1 >= grid.shape[1] or iy + 1 >= grid.shape[0]:
        return 0.0, 0.0, 0.0
    fx, fy = gx - ix, gy - iy
    m00, m10, m01, m11 = grid[iy, ix], grid[iy, ix + 1], grid[iy + 1, ix], grid[iy + 1, ix + 1]
    value = (1 - fy) * ((1 - fx) * m00 + fx * m10) + fy * ((1 - fx) * m01 + fx * m11)
    dx = ((1 - fy) * (m10 - m00) + fy * (m11 - m01)) / cell
    dy = ((1 - fx) * (m01 - m00) + fx * (m11 - m10)) / cell
    return value, dx, dy


@njit(cache=True, nogil=True)
def _eigen3(a):
    """Eigenvalues and eigenvectors (columns) of a symmetric 3 x 3 matrix, by Jacobi rotations."""
    a = a.copy()
    v = np.eye(3)
    for _ in range(30):
        off = abs(a[0, 1]) + abs(a[0, 2]) + abs(a[1, 2])
        if off < 1e-15 * (abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2]) + 1e-300):
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            if a[p, q] == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * a[p, q])
            t = np.sign(theta) / (abs(theta) + np.sqrt(theta * theta + 1.0)) if theta != 0.0 else 1.0
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # a <- a J
                akp, akq = a[k, p], a[k, q]
                a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
            for k in range(3):  # a <- J^T a
                apk, aqk = a[p, k], a[q, k]
                a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
            for k in range(3):
                vkp, vkq = v[k, p], v[k, q]
                v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    return np.array([a[0, 0], a[1, 1], a[2, 2]]), v


@njit(cache=True, nogil=True)
def _align(grid, cell, points, x, y, yaw, iterations, weak):
    """(x, y, yaw) of the scan (sensor-frame points, N x 2) that best fits the grid (coordinates
    from its corner), by Gauss-Newton from the given pose; weak directions are not moved."""
    for _ in range(iterations):
        h = np.zeros((3, 3))
        b = np.zeros(3)
        c, s = np.cos(yaw), np.sin(yaw)
        for i in range(points.shape[0]):
            px, py = points[i, 0], points[i, 1]
            value, dx, dy = _sample(grid, cell, c * px - s * py + x, s * px + c * py + y)
            j2 = dx * (-s * px - c * py) + dy * (c * px - s * py)
            e = 1.0 - value
            h[0, 0] += dx * dx
            h[0, 1] += dx * dy
            h[0, 2] += dx * j2
            h[1, 1] += dy * dy
            h[1, 2] += dy * j2
            h[2, 2] += j2 * j2
            b[0] += dx * e
            b[1] += dy * e
            b[2] += j2 * e
        h[1, 0], h[2, 0], h[2, 1] = h[0, 1], h[0, 2], h[1, 2]
        w, v = _eigen3(h)
        top = w.max()
        if not top > 0.0:
            break
        step = np.zeros(3)
        for k in range(3):
            if w[k] > weak * top:
                along = v[0, k] * b[0] + v[1, k] * b[1] + v[2, k] * b[2]
                step += v[:, k] * (along / w[k])
        x, y, yaw = x + step[0], y + step[1], yaw + step[2]
        if abs(step[0]) < 1e-5 and abs(step[1]) < 1e-5 and abs(step[2]) < 1e-5:
            break
    return x, y, yaw


@njit(cache=True, nogil=True)
def _mark(grid, cell, points, x, y, yaw):
    """Mark the cells the scan's points fall in (coordinates from the grid's corner) occupied."""
    c, s = np.cos(yaw), np.sin(yaw)
    for i in range(points.shape[0]):
        ix = int(np.floor((c * points[i, 0] - s * points[i, 1] + x) / cell))
        iy = int(np.floor((s * points[i, 0] + c * points[i, 1] + y) / cell))
        if 0 <= ix < grid.shape[1] and 0 <= iy < grid.shape[0]:
            grid[iy, ix] = 1.0


class GridMatcher:
    """Registers 2D scans one after another; `pose` is the last scan's (x, y, yaw) in the first
    scan's frame."""

    def __init__(self, max_range: float, min_range: float = 0.0, finest_cell: float | None = None,
                 min_points: int = 30):
        self.max_range, self.min_range, self.min_points = max_range, min_range, min_points
        self.finest = finest_cell or max_range / CELLS_PER_RANGE
        self.cells = [self.finest * 2 ** k for k in reversed(range(LEVELS))]  # coarse first
        coarse = self.cells[0]
        self.side = int(np.ceil(WINDOW_RANGES * max_range / coarse)) * coarse  # whole coarse cells
        if self.side / self.finest > MAX_CELLS_A_SIDE:
            raise ParameterError(f"--voxel-size {self.finest:g}: a grid cell that small for a {max_range:g} m range "
                                 f"needs {self.side / self.finest:,.0f} x {self.side / self.finest:,.0f} cells; give at "
                                 f"least {WINDOW_RANGES * max_range / MAX_CELLS_A_SIDE:.3g} m (default: range / "
                                 f"{CELLS_PER_RANGE}, {max_range / CELLS_PER_RANGE:.3g} m)")
        self.grids = [np.zeros((int(round(self.side / c)),) * 2, np.float32) for c in self.cells]
        # the grids' corner (world position), on whole coarse cells, so that moving the window shifts
        # every level by whole cells
        self.corner = np.full(2, np.floor(-self.side / 2 / coarse) * coarse)
        self.pose = np.zeros(3)
        self.last_delta = np.zeros(3)  # the last step, in the robot's frame (the constant-velocity guess)
        self.scans = 0

    def _guess(self) -> np.ndarray:
        x, y, yaw = self.pose
        dx, dy, dyaw = self.last_delta
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([x + c * dx - s * dy, y + s * dx + c * dy, yaw + dyaw])

    def _keep_in_window(self, position: np.ndarray) -> None:
        """Recentre the grids on `position` when it nears their edge (within 2 ranges): what
        lies beyond the window is forgotten, as a local map does."""
        margin = 2 * self.max_range
        if np.all(position - self.corner > margin) and np.all(self.corner + self.side - position > margin):
            return
        coarse = self.cells[0]
        corner = np.floor((position - self.side / 2) / coarse) * coarse
        for level, cell in enumerate(self.cells):
            old = self.grids[level]
            new = np.zeros_like(old)
            shift = np.round((corner - self.corner) / cell).astype(np.int64)  # in cells, (x, y)
            n = old.shape[0]
            xs, ys = slice(max(shift[0], 0), min(n + shift[0], n)), slice(max(shift[1], 0), min(n + shift[1], n))
            if xs.start < xs.stop and ys.start < ys.stop:
                new[ys.start - shift[1]:ys.stop - shift[1], xs.start - shift[0]:xs.stop - shift[0]] = old[ys, xs]
            self.grids[level] = new
        self.corner = corner

    def register(self, points: np.ndarray) -> int:
        """Align one scan (sensor-frame points, N x 2 or N x 3 with z 0), add it to the map, and
        return how many of its points were registered (within range)."""
        xy = np.ascontiguousarray(points[:, :2], dtype=np.float64)
        r = np.hypot(xy[:, 0], xy[:, 1])
        xy = xy[(r <= self.max_range) & (r >= self.min_range)]
        if self.scans:
            guess = self._guess()
            self._keep_in_window(guess[:2])
            pose = guess
            if len(xy) >= self.min_points:
                for grid, cell in zip(self.grids, self.cells):
                    x, y, yaw = _align(grid, cell, xy, pose[0] - self.corner[0], pose[1] - self.corner[1], pose[2],
                                       ITERATIONS, WEAK)
                    pose = np.array([x + self.corner[0], y + self.corner[1], yaw])
                if np.hypot(*(pose[:2] - guess[:2])) > 2 * self.cells[0]:
                    pose = guess  # a correction beyond the coarse level's reach: a false match
            previous, self.pose = self.pose, pose
            c, s = np.cos(previous[2]), np.sin(previous[2])
            d = pose - previous
            self.last_delta = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
        for grid, cell in zip(self.grids, self.cells):
            _mark(grid, cell, xy, self.pose[0] - self.corner[0], self.pose[1] - self.corner[1], self.pose[2])
        self.scans += 1
        return len(xy)

    def pose_matrix(self) -> np.ndarray:
        """The last scan's pose as a 4 x 4 matrix (z, roll and pitch 0)."""
        return planar_pose(*self.pose)
