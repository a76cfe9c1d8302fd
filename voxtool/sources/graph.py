"""OctoMap ScanGraph (.graph) reader.

Layout (little endian): uint32 n_nodes; per node: uint32 n_points, n_points x Vector3, Pose6D
(Vector3 translation + Quaternion), uint32 id; then uint32 n_edges and the edges (ignored).
Vector3 = int32 3 + 3 float64; Quaternion = int32 4 + w x y z float64. Node points are in the
sensor frame. Node ids written by OctoMap's log2graph are uninitialised: nodes are taken in file
order.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from voxtool.errors import SourceError
from voxtool.geometry import Pose
from voxtool.sources.pcd import MAX_POINTS


def count_graph_nodes(path: Path) -> int:
    with open(path, "rb") as handle:
        head = handle.read(4)
    if len(head) < 4:
        raise SourceError(f"{path}: ScanGraph is shorter than its 4-byte node count")
    return struct.unpack("<I", head)[0]


def iter_graph(path: str | Path) -> Iterator[tuple[np.ndarray, Pose, int]]:
    """(sensor-frame points float64, pose, raw bytes) per node, streamed."""
    path = Path(path)
    try:
        handle = open(path, "rb")
    except OSError as err:
        raise SourceError(f"{path}: cannot read: {err.strerror}") from err
    with handle:
        size = path.stat().st_size
        head = handle.read(4)
        if len(head) < 4:
            raise SourceError(f"{path}: ScanGraph is shorter than its 4-byte node count")
        (n_nodes,) = struct.unpack("<I", head)
        if n_nodes * 72 > size:
            raise SourceError(f"{path}: ScanGraph declares {n_nodes} nodes, more than its {size} bytes can hold")
        for node in range(n_nodes):
            raw = handle.read(4)
            if len(raw) < 4:
                raise SourceError(f"{path}: ScanGraph truncated in node {node} (point count)")
            (npts,) = struct.unpack("<I", raw)
            if npts > MAX_POINTS or handle.tell() + npts * 28 > size:
                raise SourceError(f"{path}: ScanGraph node {node} declares {npts} points, beyond the file or the limit")
            data = handle.read(npts * 28)
            rec = np.frombuffer(data, dtype=np.dtype([("n", "<i4"), ("xyz", "<f8", (3,))]), count=npts)
            if npts and not np.all(rec["n"] == 3):
                raise SourceError(f"{path}: ScanGraph node {node} has a point whose Vector3 size field is not 3")
            pose_raw = handle.read(28 + 36 + 4)
            if len(pose_raw) < 68:
                raise SourceError(f"{path}: ScanGraph truncated in node {node} (pose)")
            n3, tx, ty, tz = struct.unpack("<i3d", pose_raw[:28])
            n4, qw, qx, qy, qz = struct.unpack("<i4d", pose_raw[28:64])
            if n3 != 3 or n4 != 4:
                raise SourceError(f"{path}: ScanGraph node {node} pose has bad size fields ({n3}, {n4})")
            if not np.all(np.isfinite([tx, ty, tz, qw, qx, qy, qz])) or np.linalg.norm([qw, qx, qy, qz]) < 1e-6:
                raise SourceError(f"{path}: ScanGraph node {node} pose is not finite or its quaternion is zero")
            yield rec["xyz"], Pose.from_quat((tx, ty, tz), qw, qx, qy, qz), 4 + npts * 28 + 68


def write_graph(path: str | Path, stream, progress: bool | None = None) -> dict:
    """A scan source as an OctoMap ScanGraph, atomically, so that OctoMap's own tools
    (eval_octree_accuracy, graph2tree) read the same scans. Each node holds its scan in a frame
    parallel to the world at the sensor origin: points = world - origin (float64), pose = the
    origin with no rotation (voxtool's scans are world-frame float32 points and an origin); OctoMap
    adds the two back in float32. Node ids are the scan indices; no edges."""
    from voxtool.atomic import atomic_writer
    from voxtool.progress import track

    nodes = points = 0
    point = np.dtype([("n", "<i4"), ("xyz", "<f8", (3,))])
    with atomic_writer(path) as handle:
        handle.write(struct.pack("<I", 0))  # the node count, filled in at the end
        for scan in track(stream.scans, stream.count, "graph", progress, "scan"):
            origin = scan.origin.astype(np.float64)
            rec = np.empty(scan.points.shape[0], dtype=point)
            rec["n"] = 3
            rec["xyz"] = scan.points.astype(np.float64) - origin
            handle.write(struct.pack("<I", rec.shape[0]) + rec.tobytes())
            handle.write(struct.pack("<i3d", 3, *origin.tolist()) + struct.pack("<i4d", 4, 1.0, 0.0, 0.0, 0.0))
            handle.write(struct.pack("<I", scan.index & 0xFFFFFFFF))
            nodes += 1
            points += rec.shape[0]
        handle.write(struct.pack("<I", 0))  # no edges
        handle.seek(0)
        handle.write(struct.pack("<I", nodes))
    return {"format": "graph", "nodes": nodes, "points": points}
