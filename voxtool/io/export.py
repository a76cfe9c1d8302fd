"""Exports of a map: .bt (OctoMap), .ply / .pcd (voxel centres), .png (top-down picture)."""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from voxtool.atomic import atomic_writer
from voxtool.errors import ParameterError
from voxtool.keys import expand_leaves, keys_to_coords, leaf_edge, leaf_span, morton_decode
from voxtool.maps.base import Leaves

MAX_EXPORT_VOXELS = 200_000_000
OCCUPIED_RGB = (220, 60, 40)
FREE_RGB = (170, 210, 170)
UNKNOWN_RGB = (40, 40, 48)


def voxel_centres(leaves: Leaves, mask: np.ndarray, resolution: float) -> np.ndarray:
    """Centres (float32) of every finest-level voxel of the selected leaves (pruned ones expanded)."""
    total = int(leaf_span(leaves.depths[mask]).sum())
    if total > MAX_EXPORT_VOXELS:
        raise ParameterError(f"export would write {total} voxels (limit {MAX_EXPORT_VOXELS})")
    codes = expand_leaves(leaves.codes[mask], leaves.depths[mask])
    return keys_to_coords(morton_decode(codes), resolution).astype(np.float32)


def _cloud(leaves: Leaves, resolution: float, threshold_log: float, include_free: bool):
    occupied = leaves.values > np.float32(threshold_log)
    pts = voxel_centres(leaves, occupied, resolution)
    if not include_free:
        return pts, None
    free = voxel_centres(leaves, ~occupied, resolution)
    colors = np.concatenate([np.tile(np.array(OCCUPIED_RGB, np.uint8), (len(pts), 1)),
                             np.tile(np.array(FREE_RGB, np.uint8), (len(free), 1))])
    return np.concatenate([pts, free]), colors


def _cloud_figures(fmt: str, pts: np.ndarray, colors, occupied: int) -> dict:
    return {"format": fmt, "points": int(len(pts)), "occupied_voxels": occupied,
            "free_voxels": int(len(pts) - occupied) if colors is not None else None}


def write_ply(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    pts, colors = _cloud(leaves, resolution, threshold_log, include_free)
    props = "property float x\nproperty float y\nproperty float z\n"
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        props += "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rec = np.empty(len(pts), dtype=fields)
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        rec["red"], rec["green"], rec["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
    header = f"ply\nformat binary_little_endian 1.0\ncomment voxtool voxel centres\nelement vertex {len(pts)}\n{props}end_header\n"
    with atomic_writer(path) as handle:
        handle.write(header.encode())
        handle.write(rec.tobytes())
    return _cloud_figures("ply", pts, colors, occupied_count(leaves, threshold_log))


def write_pcd(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    pts, colors = _cloud(leaves, resolution, threshold_log, include_free)
    if colors is None:
        fields, sizes, types = "x y z", "4 4 4", "F F F"
        rec = np.ascontiguousarray(pts, dtype="<f4")
    else:
        fields, sizes, types = "x y z rgb", "4 4 4 4", "F F F F"
        rgb = (colors[:, 0].astype(np.uint32) << 16) | (colors[:, 1].astype(np.uint32) << 8) | colors[:, 2]
        rec = np.empty((len(pts), 4), dtype="<f4")
        rec[:, :3] = pts
        rec[:, 3] = rgb.astype("<u4").view("<f4")
    header = (f"# .PCD v0.7 - voxtool voxel centres\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\n"
              f"COUNT {' '.join('1' * len(fields.split()))}\nWIDTH {len(pts)}\nHEIGHT 1\n"
              f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(pts)}\nDATA binary\n")
    with atomic_writer(path) as handle:
        handle.write(header.encode())
        handle.write(rec.tobytes())
    return _cloud_figures("pcd", pts, colors, occupied_count(leaves, threshold_log))


def occupied_count(leaves: Leaves, threshold_log: float) -> int:
    return int(leaf_span(leaves.depths[leaves.values > np.float32(threshold_log)]).sum())


def topdown_image(leaves: Leaves, resolution: float, threshold_log: float, max_side: int = 4096) -> np.ndarray:
    """(H, W, 3) uint8 top view: occupied coloured by the height of the highest occupied voxel,
    free in light green, unknown dark. Each pixel covers 2^k voxels per side so the image fits."""
    if len(leaves) == 0:
        return np.zeros((1, 1, 3), dtype=np.uint8) + np.array(UNKNOWN_RGB, np.uint8)
    spans = leaf_span(leaves.depths)
    side = leaf_edge(leaves.depths)
    lo = morton_decode(leaves.codes).astype(np.int64)
    hi = morton_decode(leaves.codes + spans - 1).astype(np.int64)
    kmin, kmax = lo.min(axis=0), hi.max(axis=0)
    shift = 0
    while max(kmax[0] - kmin[0], kmax[1] - kmin[1]) >> shift >= max_side:
        shift += 1
    w = int((kmax[0] - kmin[0]) >> shift) + 1
    h = int((kmax[1] - kmin[1]) >> shift) + 1
    state = np.zeros(h * w, dtype=np.int8)  # 0 unknown, 1 free, 2 occupied
    height = np.full(h * w, -np.inf)
    occupied = leaves.values > np.float32(threshold_log)
    top_z = keys_to_coords(hi[:, 2], resolution)
    for s in np.unique(side):
        sel = side == s
        px0 = (lo[sel, 0] - kmin[0]) >> shift
        py0 = (lo[sel, 1] - kmin[1]) >> shift
        n = max(int(s) >> shift, 1)
        for dx in range(n):
            for dy in range(n):
                flat = (py0 + dy) * w + (px0 + dx)
                np.maximum.at(state, flat, np.where(occupied[sel], 2, 1).astype(np.int8))
                occ_flat = flat[occupied[sel]]
                np.maximum.at(height, occ_flat, top_z[sel][occupied[sel]])
    img = np.empty((h * w, 3), dtype=np.uint8)
    img[:] = UNKNOWN_RGB
    img[state == 1] = FREE_RGB
    occ = state == 2
    if occ.any():
        z = height[occ]
        t = (z - z.min()) / max(z.max() - z.min(), 1e-9)
        img[occ, 0] = (60 + 195 * t).astype(np.uint8)
        img[occ, 1] = (40 + 80 * (1 - t)).astype(np.uint8)
        img[occ, 2] = (200 * (1 - t)).astype(np.uint8)
    # image rows go down; world y goes up
    return img.reshape(h, w, 3)[::-1]


def png_bytes(img: np.ndarray) -> bytes:
    """Minimal PNG encoder (8-bit RGB, filter 0 rows, zlib)."""
    h, w, _ = img.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), img.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def write_png(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    if include_free:
        raise ParameterError(f"{path}: a picture always shows free space (light green); --free is for .ply/.pcd")
    img = topdown_image(leaves, resolution, threshold_log)
    with atomic_writer(path) as handle:
        handle.write(png_bytes(img))
    return {"format": "png", "width": int(img.shape[1]), "height": int(img.shape[0])}


def write_bt_export(path: Path, leaves: Leaves, resolution: float, threshold_log: float, include_free: bool) -> dict:
    """OctoMap's .bt: the max-likelihood tree (free and occupied voxels always)."""
    from voxtool.io.bt import write_bt

    if include_free:
        raise ParameterError(f"{path}: a .bt always holds free and occupied voxels; --free is for .ply/.pcd")
    leaf_nodes, inner_nodes = write_bt(path, leaves, resolution, threshold_log)
    return {"format": "bt", "leaf_nodes": leaf_nodes, "inner_nodes": inner_nodes}


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
               ros2_only: bool = False) -> dict:
    from voxtool.io.viewer_mcap import write_map_mcap

    return write_map_mcap(path, leaves, resolution, threshold_log, include_free, ros2_only)


# each writes the file and returns what it wrote (format, counts)
EXPORTERS: dict[str, Callable[[Path, Leaves, float, float, bool], dict]] = {
    ".bt": write_bt_export,
    ".ply": write_ply,
    ".pcd": write_pcd,
    ".png": write_png,
    ".vxm": write_vxm,
    ".mcap": write_mcap,
}
