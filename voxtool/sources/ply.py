"""PLY reader (ascii, binary little/big endian): the x, y, z of the `vertex` element."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.errors import SourceError
from voxtool.sources.pcd import MAX_POINTS

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_ply(path: str | Path) -> np.ndarray:
    """(N, 3) vertex positions: float32, or float64 where the file stores them as doubles."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise SourceError(f"{path}: cannot read: {err.strerror}") from err
    return parse_ply(blob, path)


def parse_ply(blob: bytes, path: str | Path = "ply") -> np.ndarray:
    """Decode PLY bytes; `path` only names the input in error messages."""
    if not blob.startswith(b"ply"):
        raise SourceError(f"{path}: not a PLY file (no 'ply' magic)")
    end = blob.find(b"end_header")
    if end < 0:
        raise SourceError(f"{path}: PLY header has no end_header")
    body_start = blob.find(b"\n", end) + 1
    header = blob[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[list] = []  # [name, count, [(prop, dtype)], has_list]
    for line in header[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            try:
                elements.append([parts[1], int(parts[2]), [], False])
            except ValueError:
                raise SourceError(f"{path}: PLY element count '{parts[2]}' is not an integer") from None
        elif parts[0] == "property" and elements and len(parts) >= 3:
            if parts[1] == "list":
                elements[-1][3] = True
                elements[-1][2].append((parts[-1], None))
            elif len(parts) == 3 and parts[1] in _PLY_TYPES:
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
            else:
                raise SourceError(f"{path}: PLY property line not understood: '{line.strip()}'")
        else:
            raise SourceError(f"{path}: PLY header line not understood: '{line.strip()}'")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SourceError(f"{path}: PLY format '{fmt}' is not ascii or binary")
    offset = 0
    for name, count, props, has_list in elements:
        if name == "vertex":
            break
        if has_list or fmt == "ascii":
            raise SourceError(f"{path}: PLY element '{name}' before 'vertex' is not fixed-size binary")
        offset += count * sum(np.dtype(dt).itemsize for _, dt in props)
    else:
        raise SourceError(f"{path}: PLY has no 'vertex' element")
    _, count, props, has_list = elements[[e[0] for e in elements].index("vertex")]
    names = [p for p, _ in props]
    if len(set(names)) != len(names):
        raise SourceError(f"{path}: PLY vertex element repeats a property name ({' '.join(names)})")
    for axis in "xyz":
        if axis not in names:
            raise SourceError(f"{path}: PLY vertex element has no '{axis}' property")
    if has_list:
        raise SourceError(f"{path}: PLY vertex element with list properties is not supported")
    if count < 0 or count > MAX_POINTS:
        raise SourceError(f"{path}: PLY declares {count} vertices (limit {MAX_POINTS})")
    body = blob[body_start:]
    if fmt == "ascii":
        lines = body.split(b"\n", count)[:count]
        try:
            table = np.array(b" ".join(lines[:count]).decode("ascii", errors="replace").split(), dtype=np.float64)
        except ValueError:
            raise SourceError(f"{path}: PLY ascii body holds a non-numeric value") from None
        if len(lines) < count or table.shape[0] != count * len(props):
            raise SourceError(f"{path}: PLY ascii body is short: expected {count} vertices of {len(props)} values")
        table = table.reshape(count, len(props))
        wide = any(dict(props)[a] == "f8" for a in "xyz")
        return np.stack([table[:, names.index(a)] for a in "xyz"], axis=1).astype(np.float64 if wide else np.float32)
    order = "<" if fmt == "binary_little_endian" else ">"
    record = np.dtype([(p, order + dt) for p, dt in props])
    need = offset + count * record.itemsize
    if len(body) < need:
        raise SourceError(f"{path}: PLY body has {len(body)} bytes, header declares {need}")
    rec = np.frombuffer(body, dtype=record, count=count, offset=offset)
    wide = any(dict(props)[a] == "f8" for a in "xyz")  # doubles stay doubles (see pcd.py)
    return np.stack([rec[a] for a in "xyz"], axis=1).astype(np.float64 if wide else np.float32)
