"""The 2D grid matcher of `voxtool odometry` (voxtool.grid_matcher) against independent truths:
NumPy's eigen-decomposition for its 3 x 3 solver, and scans ray-cast here along a known path for
the matcher itself, over a stretch longer than its grid's window."""

from __future__ import annotations

import numpy as np
from test_odometry_2d import RANGE_MAX, _ate, write_scans


def test_the_3x3_eigen_solver_equals_numpy_s():
    from voxtool.grid_matcher import _eigen3

    rng = np.random.default_rng(3)
    for scale in (1e-6, 1.0, 1e6):
        for _ in range(50):
            a = rng.normal(size=(3, 3)) * scale
            h = a @ a.T  # symmetric, positive semi-definite: a Gauss-Newton system
            w, v = _eigen3(h)
            expected = np.linalg.eigvalsh(h)
            assert np.allclose(np.sort(w), expected, rtol=1e-9, atol=1e-12 * scale ** 2)
            assert np.allclose(v.T @ v, np.eye(3), atol=1e-9)  # orthonormal
            assert np.allclose(h @ v, v * w, rtol=1e-7, atol=1e-9 * scale ** 2)  # each column an eigenvector
    w, v = _eigen3(np.diag([3.0, 1.0, 2.0]))  # already diagonal: nothing to rotate
    assert list(w) == [3.0, 1.0, 2.0] and np.array_equal(v, np.eye(3))


def _corridor_with_boxes(length: float) -> np.ndarray:
    """A corridor 3 m wide and `length` m long with a box on each wall every 2.5 m (wall segments)."""
    walls = [(-5.0, 0.0, length + 5, 0.0), (-5.0, 3.0, length + 5, 3.0)]
    for x in np.arange(-4.0, length + 4, 2.5):
        walls += [(x, 0, x, 0.4), (x, 0.4, x + 0.5, 0.4), (x + 0.5, 0.4, x + 0.5, 0)]
        walls += [(x + 1.2, 3, x + 1.2, 2.6), (x + 1.2, 2.6, x + 1.8, 2.6), (x + 1.8, 2.6, x + 1.8, 3)]
    return np.array(walls, dtype=float)


def test_a_path_longer_than_the_window_is_followed_as_the_grid_moves_with_it(tmp_path):
    """30 m down a corridor whose boxes fix every direction, with a 3.5 m scanner: the grid (a window
    of 8 ranges, 28 m) recentres on the robot on the way, forgetting what lies behind, and the
    poses stay within 1.5 cm ATE of the path the scans were cast from (6 mm here; KISS-ICP 4.3 cm)."""
    from voxtool.grid_matcher import GridMatcher
    from voxtool.odometry import OdometryParams, estimate_poses
    from voxtool.sources import SourceOptions, open_source

    n = 300
    steps = np.arange(n)
    truth = np.stack([steps * 0.1, 1.5 + 0.3 * np.sin(steps / 30), 0.03 * np.cos(steps / 30)], 1)
    path = tmp_path / "corridor.bag"
    write_scans(path, truth, _corridor_with_boxes(30.0))
    result = estimate_poses(path, SourceOptions(), OdometryParams(), progress=False)
    assert result["figures"]["params"]["matcher"] == "grid" and not result["figures"]["plausibility"]["suspect"]
    assert _ate(result, truth) < 0.015
    travelled = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1).sum()
    assert abs(result["figures"]["path_m"] - travelled) < 0.02 * travelled
    # the window did move: its corner is no longer where the first scan put it
    matcher = GridMatcher(RANGE_MAX)
    first_corner = matcher.corner.copy()
    for scan in open_source(path, SourceOptions(sensor_frame=True)).scans:
        matcher.register(scan.points)
    assert matcher.corner[0] - first_corner[0] > 10.0
    assert np.allclose(matcher.pose_matrix()[:3, 3], [result["poses"][-1][0, 3], result["poses"][-1][1, 3], 0.0])
