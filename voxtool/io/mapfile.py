"""Saving a map backend as a snapshot and loading it back (validating untrusted leaves)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import voxtool
from voxtool.config import MapParams, SensorModel
from voxtool.errors import FormatError, VoxtoolError
from voxtool.io.snapshot import Snapshot, read_snapshot, write_snapshot
from voxtool.keys import leaf_span
from voxtool.maps.base import Leaves, MapBackend


def save_map(path: str | Path, backend: MapBackend, info: dict) -> None:
    """Write `backend` with its parameters and `info` (source, counts, timings) to a .vxm file."""
    header = {
        "voxtool_version": voxtool.__version__,
        "backend": backend.name,
        "map_params": backend.params.to_dict(),
        "sensor_model": backend.sensor.to_dict(),
        "backend_params": backend.extra_meta(),
        "info": info,
    }
    write_snapshot(path, header, backend.state_arrays())


def validate_leaves(leaves: Leaves, where: str) -> None:
    """A leaf table must be Morton-sorted, aligned, non-overlapping and finite."""
    n = len(leaves)
    if not (leaves.depths.shape[0] == n and leaves.values.shape[0] == n):
        raise FormatError(f"{where}: leaf arrays differ in length")
    if n == 0:
        return
    if leaves.depths.max() > 16:
        raise FormatError(f"{where}: leaf depth {int(leaves.depths.max())} exceeds 16")
    spans = leaf_span(leaves.depths)
    if np.any(leaves.codes < 0) or np.any(leaves.codes + spans > (1 << 48)):
        raise FormatError(f"{where}: leaf code outside the 48-bit key space")
    if np.any(leaves.codes & (spans - 1)):
        raise FormatError(f"{where}: leaf code not aligned to its depth")
    if np.any(leaves.codes[1:] < leaves.codes[:-1] + spans[:-1]):
        raise FormatError(f"{where}: leaves are not sorted or overlap")
    if not np.all(np.isfinite(leaves.values)):
        raise FormatError(f"{where}: leaf log-odds not finite")


def load_map(path: str | Path) -> tuple[MapBackend, Snapshot]:
    """Rebuild the backend stored in a snapshot file."""
    snap = read_snapshot(path)
    return backend_from_snapshot(snap, str(path)), snap


def backend_from_snapshot(snap: Snapshot, path: str) -> MapBackend:
    """The backend a parsed snapshot describes, its state loaded (everything checked first)."""
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
    backend.load_state(snap.arrays)
    return backend
