"""Library entry points behind the CLI commands (usable from Python directly)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from voxtool.config import MapParams, SensorModel
from voxtool.errors import ParameterError
from voxtool.maps.base import Leaves, MapBackend
from voxtool.sources import SourceOptions, open_source


def backend_stats(backend: MapBackend) -> dict:
    from voxtool.stats import leaf_stats

    leaf_nodes, inner_nodes = backend.node_counts()
    out = {"backend": backend.name, "resolution": backend.params.resolution,
           "leaf_nodes": leaf_nodes, "inner_nodes": inner_nodes, "memory_bytes": backend.memory_bytes()}
    out.update(leaf_stats(backend.leaves(), backend.params.resolution, backend.sensor.threshold_log))
    out.update(backend.extra_stats())
    return out


def build_map(source: str | os.PathLike, options: SourceOptions, params: MapParams, sensor: SensorModel,
              backend_name: str = "octree", output: str | os.PathLike | None = None,
              progress: bool | None = None, backend_options: dict | None = None,
              share: str | os.PathLike | None = None, share_ring: int = 3, robot: str = "r1") -> dict:
    """Build a map from a source; write a snapshot if `output` is given. Returns stats + timings.
    `share` (hashmap backend): write each scan's newly occupied voxels, ring of `share_ring`
    frames, as a packet log."""
    from voxtool.atomic import check_writable
    from voxtool.io.mapfile import save_map
    from voxtool.maps import make_backend
    from voxtool.pipeline import build

    if output is not None and Path(output).suffix.lower() != ".vxm":
        raise ParameterError(f"{output}: map snapshots are written as .vxm (use `voxtool export` for .bt/.ply/.pcd/.png)")
    for path in (output, share):
        if path is not None:
            check_writable(path)
    stream = open_source(source, options)
    backend = make_backend(backend_name, params, sensor, **(backend_options or {}))
    writer = None
    if share is not None:
        from voxtool.codec.share import ShareWriter

        if backend_name != "hashmap":
            raise ParameterError("--share needs --backend hashmap (it shares the hash map's newly occupied voxels)")
        writer = ShareWriter(share, robot, share_ring, "zstd", params.resolution)
    ok = False
    try:
        report = build(stream, backend, progress, writer)
        ok = True
    finally:
        if writer is not None:
            writer.close(ok)
    result = backend_stats(backend)
    result.update(report.to_dict())
    result["threads"] = backend.threads
    if writer is not None:
        result["shared_bytes"] = writer.bytes
        result["shared_packets"] = writer.seq
    if output is not None:
        info = {"source": str(source), "source_kind": stream.kind, "source_options": options.__dict__,
                **{k: result[k] for k in ("scans", "points", "points_dropped", "raw_bytes")}}
        save_map(output, backend, info)
    return result


def load_leaves(path: str | os.PathLike) -> tuple[Leaves, float, float, dict]:
    """(leaves, resolution, threshold log-odds, info) of a .vxm snapshot or an OctoMap .bt file."""
    path = Path(path)
    if path.suffix.lower() == ".bt":
        from voxtool.io.bt import read_bt

        tree = read_bt(path)
        sensor = SensorModel()
        values = np.where(tree.occupied, np.float32(sensor.clamp_max_log), np.float32(sensor.clamp_min_log))
        return Leaves(tree.codes, tree.depths, values.astype(np.float32)), tree.resolution, sensor.threshold_log, {
            "backend": "octomap-bt", "declared_nodes": tree.declared_size}
    from voxtool.io.mapfile import load_map

    backend, snap = load_map(path)
    return backend.leaves(), backend.params.resolution, backend.sensor.threshold_log, snap.header


def map_stats(path: str | os.PathLike) -> dict:
    """Statistics of a snapshot (with the build counts recorded in it) or of a .bt file."""
    from voxtool.stats import leaf_stats

    path = Path(path)
    if path.suffix.lower() == ".bt":
        leaves, res, thr, meta = load_leaves(path)
        n_leaves = len(leaves)
        out = {"backend": meta["backend"], "resolution": res, "leaf_nodes": n_leaves,
               "inner_nodes": meta["declared_nodes"] - n_leaves, "memory_bytes": 0}
        out.update(leaf_stats(leaves, res, thr))
        return out
    from voxtool.io.mapfile import load_map

    backend, snap = load_map(path)
    out = backend_stats(backend)
    info = snap.header.get("info", {})
    for key in ("scans", "points", "points_dropped"):
        if key in info:
            out[key] = info[key]
    out["voxtool_version"] = snap.header.get("voxtool_version")
    out["source"] = info.get("source")
    return out


def export_map(path: str | os.PathLike, output: str | os.PathLike, include_free: bool = False) -> int:
    from voxtool.io.export import EXPORTERS

    output = Path(output)
    writer = EXPORTERS.get(output.suffix.lower())
    if writer is None:
        raise ParameterError(f"{output}: unknown export type '{output.suffix}' (use {', '.join(sorted(EXPORTERS))})")
    leaves, res, thr, _ = load_leaves(path)
    return writer(output, leaves, res, thr, include_free)


