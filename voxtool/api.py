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
    """A map's figures (docs/parameters.md): voxel counts and bounding box, the nodes of the
    two trees OctoMap has for it, and the bytes of the backend's own storage."""
    from voxtool.stats import tree_stats

    out = {"backend": backend.name, "resolution": backend.params.resolution}
    out.update(tree_stats(backend.leaves(), backend.params.resolution, backend.sensor.threshold_log,
                          getattr(backend, "canonical_leaves", False)))
    out.update(pool_bytes=backend.memory_bytes(), pool_bytes_used=backend.used_bytes())
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


def map_stats(path: str | os.PathLike, progress: bool | None = False) -> dict:
    """Statistics of a snapshot (with the build counts recorded in it) or of a .bt file."""
    from voxtool.progress import bar
    from voxtool.stats import tree_stats

    path = Path(path)
    with bar(2, "stats", progress, "step") as steps:
        if path.suffix.lower() == ".bt":
            leaves, res, thr, meta = load_leaves(path)
            steps.update(1)
            out = {"backend": meta["backend"], "resolution": res}
            out.update(tree_stats(leaves, res, thr, False))
            # a .bt holds only the max-likelihood tree: no log-odds tree, no in-memory pool
            out.update(octree_leaf_nodes=None, octree_inner_nodes=None, pool_bytes=None, pool_bytes_used=None,
                       file_nodes=meta["declared_nodes"])
            return out
        from voxtool.io.mapfile import load_map

        backend, snap = load_map(path)
        steps.update(1)
        out = backend_stats(backend)
    info = snap.header.get("info", {})
    for key in ("scans", "points", "points_dropped"):
        if key in info:
            out[key] = info[key]
    out["voxtool_version"] = snap.header.get("voxtool_version")
    out["source"] = info.get("source")
    return out


def export_map(path: str | os.PathLike, output: str | os.PathLike, include_free: bool = False,
               progress: bool | None = False) -> dict:
    """Write a map (.vxm or .bt) as .bt, .ply, .pcd or .png; returns what was written."""
    from voxtool.atomic import check_writable
    from voxtool.io.export import EXPORTERS
    from voxtool.progress import bar

    output = Path(output)
    writer = EXPORTERS.get(output.suffix.lower())
    if writer is None:
        raise ParameterError(f"{output}: unknown export type '{output.suffix}' (use {', '.join(sorted(EXPORTERS))})")
    check_writable(output)
    with bar(2, f"export {output.suffix}", progress, "step") as steps:
        leaves, res, thr, _ = load_leaves(path)
        steps.update(1)
        written = writer(output, leaves, res, thr, include_free)
        steps.update(1)
    return written


