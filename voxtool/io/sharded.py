"""Sharded map snapshots (formats/sharded.md): a directory of part snapshots, one per partition
of the map's Morton-prefix shards, each written by the worker that holds it, and a manifest
written last. A directory without its manifest is never taken for a map.

Readers go part by part, so memory is bounded by the largest part, not the map.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

from voxtool.atomic import atomic_writer
from voxtool.errors import FormatError, VoxtoolError
from voxtool.io.sharded_tree import Units, add_part, join_counts

MANIFEST = "manifest.json"
FORMAT = "voxtool-sharded-map"
VERSION = 1
STAGING = ".voxtool-staging-"


def part_name(p: int) -> str:
    return f"part-{p:05d}.vxm"


def is_sharded(path: str | os.PathLike) -> bool:
    return Path(path).is_dir()


def staging_dir(target: str | os.PathLike) -> Path:
    """A fresh directory beside `target` that the parts are written into (on the file system
    every worker sees)."""
    target = Path(target)
    if target.exists() and not (target / MANIFEST).is_file():
        if not target.is_dir() or any(target.iterdir()):
            raise VoxtoolError(f"{target}: exists and is not a sharded map; give a new directory")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise VoxtoolError(f"{target}: output directory {parent} does not exist")
    staging = parent / f"{STAGING}{target.name}-{uuid.uuid4().hex[:8]}"
    staging.mkdir()
    return staging


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def write_part(part, staging: str, p: int, params, info: dict | None = None) -> dict:
    """Write partition `p` (a distbuild.Partition) as a snapshot (a Dask task on the worker that
    holds it); returns its manifest entry."""
    from voxtool.io.mapfile import save_map
    from voxtool.maps.octree import OctreeMap
    from voxtool.stats import leaf_stats

    backend = OctreeMap(params, part.sensor, threads=1, shard_depth=part.tree.depth)
    backend.tree = part.tree
    path = Path(staging) / part_name(p)
    save_map(path, backend, {**(info or {}), "partition": p})
    leaves = backend.leaves()  # the leaves the file was written from: the tree keeps them until its next update
    entry = {"file": path.name, "bytes": path.stat().st_size, "sha256": _sha256(path), "leaves": len(leaves)}
    entry.update(leaf_stats(leaves, params.resolution, part.sensor.threshold_log))
    return entry


def finish(staging: Path, target: str | os.PathLike, header: dict, parts: list[dict]) -> dict:
    """Write the manifest (last), then put the directory in place of `target` (an older sharded
    map there is replaced only now); returns the manifest."""
    target = Path(target)
    manifest = {"format": FORMAT, "version": VERSION, **header, "parts": parts}
    with atomic_writer(staging / MANIFEST) as f:
        f.write(json.dumps(manifest, indent=1, sort_keys=True).encode())
    old = None
    if target.exists():
        old = target.parent / f"{STAGING}old-{uuid.uuid4().hex[:8]}"
        target.rename(old)
    staging.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
    return manifest


def abandon(staging: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        shutil.rmtree(staging)


def read_manifest(path: str | os.PathLike) -> dict:
    path = Path(path)
    file = path / MANIFEST
    if not file.is_file():
        raise FormatError(f"{path}: a directory without {MANIFEST} is not a (complete) sharded map")
    try:
        manifest = json.loads(file.read_text())
    except (OSError, ValueError) as err:
        raise FormatError(f"{file}: cannot read the manifest ({err})") from err
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise FormatError(f"{file}: not a voxtool sharded map manifest")
    if manifest.get("version") != VERSION:
        raise FormatError(f"{file}: sharded map version {manifest.get('version')} is not supported (this voxtool "
                          f"reads {VERSION})")
    parts = manifest.get("parts")
    if not isinstance(parts, list) or len(parts) != manifest.get("partitions"):
        raise FormatError(f"{file}: the manifest lists {len(parts) if isinstance(parts, list) else 'no'} parts for "
                          f"{manifest.get('partitions')} partitions")
    for entry in parts:
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or "/" in name or name.startswith("."):
            raise FormatError(f"{file}: the manifest names a bad part file {name!r}")
    return manifest


def _part_files(path: Path, check_hash: bool) -> Iterator[tuple[dict, Path]]:
    """(manifest entry, file) of every part in turn, each checked against the manifest (size,
    SHA-256) before it is read."""
    for entry in read_manifest(path)["parts"]:
        file = path / entry["file"]
        if not file.is_file():
            raise FormatError(f"{file}: a part the manifest lists is missing")
        if file.stat().st_size != entry.get("bytes"):
            raise FormatError(f"{file}: {file.stat().st_size} bytes, the manifest says {entry.get('bytes')}")
        if check_hash and _sha256(file) != entry.get("sha256"):
            raise FormatError(f"{file}: content differs from the manifest's SHA-256")
        yield entry, file


def iter_parts(path: str | os.PathLike, check_hash: bool = True) -> Iterator[tuple[dict, object]]:
    """(manifest entry, loaded OctreeMap) of every part in turn, each checked against the
    manifest (size, SHA-256) before it is read."""
    from voxtool.io.mapfile import load_map

    for entry, file in _part_files(Path(path), check_hash):
        backend, _ = load_map(file)
        yield entry, backend


def iter_part_leaves(path: str | os.PathLike, check_hash: bool = True) -> Iterator[tuple[dict, object, float]]:
    """(manifest entry, leaves, threshold log-odds) of every part in turn, checked as
    iter_parts checks them, without rebuilding each part's tree (mapfile.read_leaves)."""
    from voxtool.io.mapfile import read_leaves

    for entry, file in _part_files(Path(path), check_hash):
        leaves, _, threshold, _ = read_leaves(file)
        yield entry, leaves, threshold


def load_sharded(path: str | os.PathLike):
    """The whole map of a sharded snapshot as one OctreeMap (memory: the whole map)."""
    from voxtool.maps.base import join_leaves
    from voxtool.maps.octree import OctreeMap

    parts = []
    first = None
    for _, backend in iter_parts(path):
        first = first or backend
        parts.append(backend.leaves())
    leaves = join_leaves(parts)
    whole = OctreeMap(first.params, first.sensor, shard_depth=first.shard_depth)
    whole.load_state({"leaf_codes": leaves.codes, "leaf_depths": leaves.depths, "leaf_values": leaves.values})
    return whole


def combined_stats(parts: list[dict], manifest: dict) -> dict:
    """A sharded map's statistics from its parts' (leaf_stats of each, with its `leaves`): voxel
    counts and the bounding box; node counts need the tree across the parts (None here; see
    sharded_stats)."""
    out = {"backend": "octree", "sharded": True, "partitions": manifest["partitions"],
           "resolution": manifest["map_params"]["resolution"], "occupied_voxels": 0, "free_voxels": 0,
           "occupied_bbox": None, "part_leaves_max": 0, "bt_leaf_nodes": None, "bt_inner_nodes": None,
           "logodds_leaf_nodes": None, "logodds_inner_nodes": None}
    lo = hi = None
    for part in parts:
        out["occupied_voxels"] += part["occupied_voxels"]
        out["free_voxels"] += part["free_voxels"]
        out["part_leaves_max"] = max(out["part_leaves_max"], part["leaves"])
        box = part["occupied_bbox"]
        if box:
            lo = box["min"] if lo is None else [min(a, b) for a, b in zip(lo, box["min"])]
            hi = box["max"] if hi is None else [max(a, b) for a, b in zip(hi, box["max"])]
    if lo is not None:
        out["occupied_bbox"] = {"min": lo, "max": hi}
    info = manifest.get("info", {})
    for key in ("scans", "points", "points_dropped"):
        if key in info:
            out[key] = info[key]
    out["source"] = info.get("source")
    return out


def sharded_stats(path: str | os.PathLike, progress: bool | None = False) -> dict:
    """Statistics of a sharded snapshot, read part by part (each part's figures computed from
    its leaves, not taken from the manifest), with the node counts of the whole map's trees."""
    from voxtool.maps.tree import max_likelihood
    from voxtool.progress import track
    from voxtool.stats import leaf_stats

    manifest = read_manifest(path)
    parts = []
    ml, lo = Units(), Units()
    for _, backend in track(iter_parts(path), len(manifest["parts"]), "stats", progress, "part"):
        leaves = backend.leaves()
        parts.append({**leaf_stats(leaves, backend.params.resolution, backend.sensor.threshold_log),
                      "leaves": len(leaves)})
        add_part(lo, leaves, backend.shard_depth)
        add_part(ml, max_likelihood(leaves, backend.sensor.threshold_log), backend.shard_depth)
    return {**combined_stats(parts, manifest), **join_counts(ml, lo)}
