"""Exports of a map: .bt (OctoMap), .ply / .pcd (voxel centres), .png (a picture), .mcap, .vxm, .pgm (a 2D grid)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from voxtool.atomic import atomic_writer
from voxtool.errors import ParameterError
from voxtool.keys import expand_leaves, keys_to_coords, leaf_span, morton_decode
from voxtool.maps.base import Leaves

MAX_EXPORT_VOXELS = 200_000_000
OCCUPIED_RGB = (220, 60, 40)
FREE_RGB = (170, 210, 170)


def voxel_centres(leaves: Leaves, mask: np.ndarray, resolution: float) -> np.ndarray:
    """Centres (float32) of every finest-level voxel of the selected leaves (pruned ones expanded)."""
    total = int(leaf_span(leaves.depths[mask]).sum())
    if total > MAX_EXPORT_VOXELS:
        raise ParameterError(f"export would write {total} voxels (limit {MAX_EXPORT_VOXELS})")
    codes = expand_leaves(leaves.codes[mask], leaves.depths[mask])
    return keys_to_coords(morton_decode(codes), resolution).astype(np.float32)


def in_source_frame(points: np.ndarray, origin, resolution: float) -> np.ndarray:
    """Local-frame points moved back to the scans' frame by the map's origin (--origin): float32
    while that keeps every point within a thousandth of a voxel, else float64 (float32 steps
    0.25 m at 4,000 km, 0.5 mm at 5 km)."""
    if origin is None or not np.any(origin):
        return points
    moved = np.asarray(points, dtype=np.float64) + np.asarray(origin, dtype=np.float64)
    largest = float(np.abs(moved).max()) if moved.size else 0.0
    return moved if needs_double(largest, resolution) else moved.astype(np.float32)


def needs_double(largest: float, resolution: float) -> bool:
    """Whether coordinates up to `largest` metres need float64 to stay within a thousandth of a voxel."""
    return bool(np.spacing(np.float32(largest)) > resolution * 1e-3)


def _cloud(leaves: Leaves, resolution: float, threshold_log: float, include_free: bool, origin=None):
    occupied = leaves.values > np.float32(threshold_log)
    pts = in_source_frame(voxel_centres(leaves, occupied, resolution), origin, resolution)
    if not include_free:
        return pts, None
    free = in_source_frame(voxel_centres(leaves, ~occupied, resolution), origin, resolution).astype(pts.dtype)
    colors = np.concatenate([np.tile(np.array(OCCUPIED_RGB, np.uint8), (len(pts), 1)),
                             np.tile(np.array(FREE_RGB, np.uint8), (len(free), 1))])
    return np.concatenate([pts, free]), colors


def _cloud_figures(fmt: str, pts: np.ndarray, colors, occupied: int) -> dict:
    return {"format": fmt, "points": int(len(pts)), "occupied_voxels": occupied,
            "free_voxels": int(len(pts) - occupied) if colors is not None else None}


def ply_header(points: int, coloured: bool, double: bool = False) -> bytes:
    kind = "double" if double else "float"
    props = f"property {kind} x\nproperty {kind} y\nproperty {kind} z\n"
    if coloured:
        props += "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    return (f"ply\nformat binary_little_endian 1.0\ncomment voxtool voxel centres\nelement vertex {points}\n"
            f"{props}end_header\n").encode()


def ply_rows(pts: np.ndarray, colors) -> bytes:
    f = "<f8" if pts.dtype == np.float64 else "<f4"
    fields = [("x", f), ("y", f), ("z", f)]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    return rec.tobytes()


def pcd_header(points: int, coloured: bool, double: bool = False, viewpoint: tuple | None = None) -> bytes:
    """A binary PCD header (x y z float32, or float64 when `double`; rgb packed in a float32);
    `viewpoint` (tx ty tz qw qx qy qz): the sensor pose, identity if None."""
    w = "8" if double else "4"
    fields, sizes, types = ("x y z rgb", f"{w} {w} {w} 4", "F F F F") if coloured else ("x y z", f"{w} {w} {w}", "F F F")
    vp = "0 0 0 1 0 0 0" if viewpoint is None else " ".join(repr(float(v)) for v in viewpoint)
    return (f"# .PCD v0.7 - voxtool\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\n"
            f"COUNT {' '.join('1' * len(fields.split()))}\nWIDTH {points}\nHEIGHT 1\n"
            f"VIEWPOINT {vp}\nPOINTS {points}\nDATA binary\n").encode()


def pcd_rows(pts: np.ndarray, colors) -> bytes:
    f = "<f8" if pts.dtype == np.float64 else "<f4"
    if colors is None:
        return np.ascontiguousarray(pts, dtype=f).tobytes()
    rgb = (colors[:, 0].astype(np.uint32) << 16) | (colors[:, 1].astype(np.uint32) << 8) | colors[:, 2]
    rec = np.empty(len(pts), dtype=[("xyz", f, (3,)), ("rgb", "<u4")])
    rec["xyz"] = pts
    rec["rgb"] = rgb
    return rec.tobytes()


# a point cloud format: (header for n points, coloured or not; the bytes of some points)
CLOUD_FORMATS = {"ply": (ply_header, ply_rows), "pcd": (pcd_header, pcd_rows)}


def write_cloud(fmt: str, path: Path, leaves: Leaves, resolution: float, threshold_log: float,
                include_free: bool, origin=None) -> dict:
    """Voxel centres (in the scans' frame when the map has an origin) as .ply or .pcd."""
    header, rows = CLOUD_FORMATS[fmt]
    pts, colors = _cloud(leaves, resolution, threshold_log, include_free, origin)
    with atomic_writer(path) as handle:
        handle.write(header(len(pts), colors is not None, pts.dtype == np.float64))
        handle.write(rows(pts, colors))
    return _cloud_figures(fmt, pts, colors, occupied_count(leaves, threshold_log))


def write_ply(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
              origin=None) -> dict:
    return write_cloud("ply", path, leaves, resolution, threshold_log, include_free, origin)


def write_pcd(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
              origin=None) -> dict:
    return write_cloud("pcd", path, leaves, resolution, threshold_log, include_free, origin)


def occupied_count(leaves: Leaves, threshold_log: float) -> int:
    return int(leaf_span(leaves.depths[leaves.values > np.float32(threshold_log)]).sum())


def write_png(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
              **picture) -> dict:
    """A picture with legend, scale and axes (io.picture; matplotlib is imported only here)."""
    from voxtool.io.picture import write_png as draw

    return draw(path, leaves, resolution, threshold_log, include_free, **picture)


def write_bt_export(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    """OctoMap's .bt: the max-likelihood tree (free and occupied voxels always)."""
    from voxtool.io.bt import write_bt

    if include_free:
        raise ParameterError(f"{path}: a .bt always holds free and occupied voxels; --free is for .ply/.pcd")
    leaf_nodes, inner_nodes = write_bt(path, leaves, resolution, threshold_log)
    return {"format": "bt", "bt_leaf_nodes": leaf_nodes, "bt_inner_nodes": inner_nodes}


def write_vxm(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    """A snapshot of the leaves (an OctoMap .bt imported: occupied leaves at the upper clamp,
    free ones at the lower, as OctoMap reads a .bt), with the default sensor model."""
    from voxtool.config import MapParams, SensorModel
    from voxtool.io.mapfile import save_map
    from voxtool.maps.octree import OctreeMap

    if include_free:
        raise ParameterError(f"{path}: a snapshot always holds free and occupied voxels; --free is for .ply/.pcd")
    sensor = SensorModel()
    if not np.isclose(threshold_log, sensor.threshold_log):
        raise ParameterError(f"{path}: a map with threshold log-odds {threshold_log:g} is already a snapshot")
    backend = OctreeMap(MapParams(resolution=resolution), sensor)
    backend.load_state({"leaf_codes": leaves.codes, "leaf_depths": leaves.depths, "leaf_values": leaves.values})
    save_map(path, backend, {"source": "OctoMap .bt (imported)"})
    return {"format": "vxm", "leaves": len(leaves), "occupied_voxels": occupied_count(leaves, threshold_log)}


def write_mcap(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
               stamp_ns: int = 0, z_range: tuple | None = None, origin=None, above_ground: tuple | None = None,
               obstacle_log: float | None = None) -> dict:
    from voxtool.io.viewer_mcap import write_map_mcap

    return write_map_mcap(path, leaves, resolution, threshold_log, include_free, stamp_ns, z_range, origin,
                          above_ground, obstacle_log)


def grid_yaml_path(path: Path) -> Path:
    """The nav2 map YAML written beside a .pgm grid (map.pgm -> map.yaml)."""
    return path.with_suffix(".yaml")


def write_pgm(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool,
              z_range: tuple | None = None, origin=None, above_ground: tuple | None = None,
              obstacle_log: float | None = None) -> dict:
    """A 2D occupancy grid for nav2's map_server: the image and its YAML beside it (voxtool.grid).
    The YAML's origin is in the scans' frame (a map built about --origin is shifted back, as the
    .mcap's OccupancyGrid is), and says so; --z-range stays in the map's local heights."""
    from voxtool.ground import project_grid

    if include_free:
        raise ParameterError(f"{path}: a grid always holds free, occupied and unknown cells; --free is for .ply/.pcd")
    check_grid_writable(path)
    grid = project_grid(leaves, resolution, threshold_log, z_range, above_ground, obstacle_log)
    return {**write_grid_pgm(path, grid, origin), "z_range": list(z_range) if z_range else None,
            "above_ground": list(above_ground) if above_ground else None}


def check_grid_writable(path: Path) -> None:
    """Refuse a .pgm grid, or the YAML beside it, that cannot be written, before any work."""
    from voxtool.atomic import check_writable

    check_writable(path)
    check_writable(grid_yaml_path(path))


def write_grid_pgm(path: Path, grid, origin=None) -> dict:
    """A Grid2D as nav2's map_server reads it: the .pgm and the YAML beside it, each atomically;
    the YAML's origin shifted back by a map's --origin into the scans' frame."""
    from voxtool.grid import map_yaml, pgm_bytes

    yaml_path = grid_yaml_path(path)
    with atomic_writer(path) as handle:
        handle.write(pgm_bytes(grid))
    with atomic_writer(yaml_path) as handle:
        handle.write(map_yaml(grid, path.name, origin).encode())
    shift = (0.0, 0.0) if origin is None else (float(origin[0]), float(origin[1]))
    return {"format": "pgm", "yaml": str(yaml_path), "origin": [grid.origin[0] + shift[0], grid.origin[1] + shift[1]],
            **grid.counts()}


# each writes the file and returns what it wrote (format, counts)
EXPORTERS: dict[str, Callable[[Path, Leaves, float, float, bool], dict]] = {
    ".bt": write_bt_export,
    ".ply": write_ply,
    ".pcd": write_pcd,
    ".png": write_png,
    ".vxm": write_vxm,
    ".mcap": write_mcap,
    ".pgm": write_pgm,
}
TAKES_Z_RANGE = (".pgm", ".mcap")  # outputs with a 2D grid projected in --z-range
TAKES_ORIGIN = (".ply", ".pcd", ".mcap", ".pgm")  # outputs written in the scans' frame of a map built about --origin
