"""Saving a map backend as a snapshot and loading it back (validating untrusted leaves)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import voxtool
from voxtool.config import MapParams, SensorModel
from voxtool.errors import FormatError, VoxtoolError
from voxtool.io.snapshot import Snapshot, read_snapshot, write_snapshot
from voxtool.maps.base import Leaves, MapBackend


def save_map(path: str | Path, backend: MapBackend, info: dict, arrays: dict | None = None) -> None:
    """Write `backend` with its parameters and `info` (source, counts, timings) to a .vxm file;
    `arrays`: its state_arrays(), when the caller has them."""
    header = {
        "voxtool_version": voxtool.__version__,
        "backend": backend.name,
        "map_params": backend.params.to_dict(),
        "sensor_model": backend.sensor.to_dict(),
        "backend_params": backend.extra_meta(),
        "info": info,
    }
    write_snapshot(path, header, backend.state_arrays() if arrays is None else arrays)


def validate_leaves(leaves: Leaves, where: str) -> None:
    """A leaf table must be Morton-sorted, aligned, non-overlapping and finite."""
    n = len(leaves)
    if not (leaves.depths.shape[0] == n and leaves.values.shape[0] == n):
        raise FormatError(f"{where}: leaf arrays differ in length")
    from voxtool.kernels.stats import leaf_problem

    problem, i = leaf_problem(np.ascontiguousarray(leaves.codes, dtype=np.int64), leaves.depths, leaves.values)
    if problem:
        raise FormatError(f"{where}: " + (f"leaf depth {int(leaves.depths[i])} is not 0..16", "leaf code outside the 48-bit key space",
                                          "leaf code not aligned to its depth", "leaves are not sorted or overlap",
                                          "leaf log-odds not finite")[problem - 1])


def read_leaves(path: str | Path) -> tuple[Leaves, float, float, dict]:
    """(leaves, resolution, threshold log-odds, header) of a snapshot, checked as load_map
    checks it. An octree snapshot's leaves are its stored arrays, not rebuilt into a tree
    (kaist03's 30M leaves in 1-2 s instead of 9); other backends' are derived from the backend."""
    snap = read_snapshot(path)
    backend, leaves = _checked(snap, str(path))
    if backend.name != "octree":
        backend.load_state(snap.arrays)
        leaves = backend.leaves()
    return leaves, backend.params.resolution, backend.sensor.threshold_log, snap.header


LEAF_NAMES = ("leaf_codes", "leaf_depths", "leaf_values")


def stream_leaves(path: str | Path, piece: int = 1 << 22):
    """(resolution, threshold log-odds, header, chunks) of an octree snapshot: `chunks()` is a
    fresh iterator of its stored leaves, `piece` at a time, each checked as load_map checks the
    whole table (and where one chunk meets the next), so that a large map is read in the memory
    of a chunk. None for another backend's snapshot (its leaves are derived from its state)."""
    from voxtool.io.snapshot import stream_arrays

    header, pieces = stream_arrays(path, LEAF_NAMES, piece)  # checks the file (CRCs, sizes) once, here
    if header.get("backend") != "octree":
        return None
    try:
        params, sensor = MapParams(**header["map_params"]), SensorModel(**header["sensor_model"])
    except (KeyError, TypeError, VoxtoolError) as err:
        raise FormatError(f"{path}: snapshot header lacks or mangles map parameters ({err})") from err

    def chunks():
        from voxtool.keys import leaf_span

        end = 0
        for k, (codes, depths, values) in enumerate(pieces()):
            chunk = Leaves(codes, depths, values)
            validate_leaves(chunk, f"{path} (leaves {k * piece:,} on)")
            if codes.shape[0] and int(codes[0]) < end:
                raise FormatError(f"{path}: leaves are not sorted or overlap")
            if codes.shape[0]:
                end = int(codes[-1]) + int(leaf_span(depths[-1:])[0])
            yield chunk

    return params.resolution, sensor.threshold_log, header, chunks


def load_map(path: str | Path) -> tuple[MapBackend, Snapshot]:
    """Rebuild the backend stored in a snapshot file."""
    snap = read_snapshot(path)
    return backend_from_snapshot(snap, str(path)), snap


def backend_from_snapshot(snap: Snapshot, path: str) -> MapBackend:
    """The backend a parsed snapshot describes, its state loaded (everything checked first)."""
    backend, _ = _checked(snap, path)
    backend.load_state(snap.arrays)
    return backend


def _checked(snap: Snapshot, path: str) -> tuple[MapBackend, Leaves]:
    """The (empty) backend a snapshot's header describes and its stored leaves, both checked."""
    from voxtool.maps import make_backend

    h = snap.header
    try:
        params = MapParams(**h["map_params"])
        sensor = SensorModel(**h["sensor_model"])
        backend = make_backend(h["backend"], params, sensor, **h.get("backend_params", {}))
    except (KeyError, TypeError) as err:
        raise FormatError(f"{path}: snapshot header lacks or mangles map parameters ({err})") from err
    except VoxtoolError as err:
        raise FormatError(f"{path}: snapshot header holds invalid parameters ({err})") from err
    try:
        leaves = Leaves(snap.arrays["leaf_codes"], snap.arrays["leaf_depths"], snap.arrays["leaf_values"])
    except KeyError as err:
        raise FormatError(f"{path}: snapshot lacks array {err}") from err
    validate_leaves(leaves, path)
    return backend, leaves
