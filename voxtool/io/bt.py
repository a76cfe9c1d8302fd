"""OctoMap's binary tree file (.bt): read and write.

Writing follows OctoMap's `writeBinary`: every leaf is reduced to its max-likelihood state
(occupied when log-odds > threshold) and the tree is pruned. voxtool prunes fully (OctoMap's own
prune loop stops at the first level where nothing pruned), so a file can be smaller than
OctoMap's but encodes the same voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxtool.atomic import atomic_writer
from voxtool.errors import FormatError
from voxtool.maps.base import Leaves

HEADER = b"# Octomap OcTree binary file"


@dataclass
class BtTree:
    resolution: float
    tree_type: str
    declared_size: int
    codes: np.ndarray
    depths: np.ndarray
    occupied: np.ndarray


def read_bt(path: str | Path) -> BtTree:
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise FormatError(f"{path}: cannot read: {err.strerror}") from err
    return parse_bt_bytes(blob, path)


def parse_bt_bytes(blob: bytes, path: str | Path = "bt") -> BtTree:
    """Decode .bt bytes; `path` only names the input in error messages."""
    from voxtool.kernels.bt import parse_bt

    if not blob.startswith(HEADER):
        raise FormatError(f"{path}: not an OctoMap binary file (first line is not '{HEADER.decode()}')")
    pos = 0
    meta: dict[str, str] = {}
    for _ in range(100):
        end = blob.find(b"\n", pos)
        if end < 0:
            raise FormatError(f"{path}: .bt header has no 'data' line")
        line = blob[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if line == "data":
            break
        if line.startswith("#") or not line:
            continue
        key, _, rest = line.partition(" ")
        meta[key] = rest.strip()
    else:
        raise FormatError(f"{path}: .bt header has no 'data' line within 100 lines")
    try:
        res = float(meta["res"])
        size = int(meta["size"])
    except (KeyError, ValueError):
        raise FormatError(f"{path}: .bt header needs numeric 'res' and 'size'") from None
    if not res > 0 or size < 0:
        raise FormatError(f"{path}: .bt header res {res} / size {size} out of range")
    body = np.frombuffer(blob, dtype=np.uint8, offset=pos)
    if size > 4 * body.shape[0] + 1:
        raise FormatError(f"{path}: .bt declares {size} nodes, far more than its {body.shape[0]} data bytes hold")
    codes, depths, occ, nodes, used, status = parse_bt(body, max(size, 1))
    if status == -1:
        raise FormatError(f"{path}: .bt data is truncated at byte {pos + used}")
    if status == -2:
        raise FormatError(f"{path}: .bt tree is deeper than 16 levels")
    if status == -3 or (size and nodes != size):
        raise FormatError(f"{path}: .bt holds {nodes} nodes, header declares {size}")
    return BtTree(res, meta.get("id", ""), size, codes, depths, occ.astype(bool))


def bt_bytes(leaves: Leaves, resolution: float, threshold_log: float) -> bytes:
    """Encode leaves as a .bt file (max-likelihood, fully pruned)."""
    return _bt(leaves, resolution, threshold_log)[0]


def tree_stream(leaves: Leaves, threshold_log: float) -> tuple[bytes, int, int]:
    """(OctoMap's binary tree stream, leaf nodes, inner nodes) of leaves: max-likelihood, fully
    pruned; what follows a .bt header, and what octomap_msgs/Octomap carries in `data`."""
    from voxtool.kernels.bt import serialize_bt
    from voxtool.maps.tree import max_likelihood

    tree = max_likelihood(leaves, threshold_log)
    occupied = tree.values > 0
    need = serialize_bt(tree.codes, tree.depths, occupied, np.zeros(0, np.uint8))
    data = np.zeros(need, dtype=np.uint8)
    serialize_bt(tree.codes, tree.depths, occupied, data)
    return data.tobytes(), len(tree), need // 2  # one 16-bit word per inner node


def _bt(leaves: Leaves, resolution: float, threshold_log: float) -> tuple[bytes, int, int]:
    """(.bt bytes, leaf nodes, inner nodes) of leaves: max-likelihood, fully pruned."""
    data, leaf_nodes, inner_nodes = tree_stream(leaves, threshold_log)
    header = (
        f"{HEADER.decode()}\n# (written by voxtool)\n#\nid OcTree\nsize {leaf_nodes + inner_nodes}\n"
        f"res {resolution:.10g}\ndata\n"
    ).encode()
    return header + data, leaf_nodes, inner_nodes


def write_bt(path: str | Path, leaves: Leaves, resolution: float, threshold_log: float) -> tuple[int, int]:
    """Write a .bt file; returns its tree's (leaf nodes, inner nodes)."""
    blob, leaf_nodes, inner_nodes = _bt(leaves, resolution, threshold_log)
    with atomic_writer(path) as handle:
        handle.write(blob)
    return leaf_nodes, inner_nodes


