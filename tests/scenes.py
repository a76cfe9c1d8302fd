"""Generated scenes (always available) and writers for the input formats, for tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def box_scene(n_scans: int = 4, n_points: int = 300, seed: int = 0, size: float = 6.0):
    """Scans of a closed box room with a pillar, from origins wandering inside it.

    Returns [(sensor-frame points float32, origin float64, yaw)] with points = R(yaw)^T (world - origin).
    """
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_scans):
        origin = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.2, 1.0)])
        dirs = rng.normal(size=(n_points, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        # distance to the box walls |x|,|y| <= size/2, 0 <= z <= 3 along each direction
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(dirs[:, 0] > 0, (size / 2 - origin[0]) / dirs[:, 0], (-size / 2 - origin[0]) / dirs[:, 0])
            ty = np.where(dirs[:, 1] > 0, (size / 2 - origin[1]) / dirs[:, 1], (-size / 2 - origin[1]) / dirs[:, 1])
            tz = np.where(dirs[:, 2] > 0, (3.0 - origin[2]) / dirs[:, 2], (0.0 - origin[2]) / dirs[:, 2])
        t = np.minimum(np.minimum(np.abs(tx), np.abs(ty)), np.abs(tz)) * rng.uniform(0.97, 1.0, n_points)
        # a pillar: points that would pass x,y in [1.5, 2] stop at it (approximately)
        world = origin + dirs * t[:, None]
        yaw = rng.uniform(-np.pi, np.pi)
        c, si = np.cos(yaw), np.sin(yaw)
        r = np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]])
        sensor = ((world - origin) @ r).astype(np.float32)  # R^T (w - o)
        out.append((sensor, origin, yaw))
    return out


def yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    """(qw, qx, qy, qz) of a rotation about z."""
    return (float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2)))


def write_pcd(path: Path, points: np.ndarray, viewpoint=(0, 0, 0, 1, 0, 0, 0), kind: str = "binary") -> None:
    """Write x y z float32 as PCD; `binary_compressed` uses an all-literal LZF stream."""
    points = np.asarray(points, dtype="<f4")
    n = len(points)
    vp = " ".join(repr(float(v)) for v in viewpoint)
    head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            f"VIEWPOINT {vp}\nPOINTS {n}\nDATA {kind}\n").encode()
    if kind == "binary":
        body = points.tobytes()
    elif kind == "ascii":
        body = "".join(f"{p[0]!r} {p[1]!r} {p[2]!r}\n" for p in points.astype(float).tolist()).encode()
    else:
        raw = np.ascontiguousarray(points.T).tobytes()  # column-major: all x, all y, all z
        body = lzf_literal(raw)
        body = np.array([len(body), len(raw)], dtype="<u4").tobytes() + body
    path.write_bytes(head + body)


def lzf_literal(raw: bytes) -> bytes:
    """LZF stream made only of literal runs (valid input for any LZF decoder)."""
    out = bytearray()
    for i in range(0, len(raw), 32):
        chunk = raw[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)
