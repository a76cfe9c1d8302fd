"""PCD reader (PCL's format v0.5-0.7): DATA ascii, binary and binary_compressed (LZF).

Only x, y, z are decoded; other fields are skipped by their declared size. Every declared
length is checked against the file before anything is allocated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from voxtool.errors import SourceError

MAX_POINTS = 50_000_000  # a scan larger than this is refused before allocation
_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
          ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


@dataclass
class PcdCloud:
    xyz: np.ndarray  # (N, 3) float32 (float64 where the file stores x, y, z as doubles), may hold NaN
    viewpoint: tuple[float, ...]  # tx ty tz qw qx qy qz
    has_viewpoint: bool
    data_kind: str


def _header(path: Path, blob: bytes) -> tuple[dict[str, list[str]], int]:
    fields: dict[str, list[str]] = {}
    pos = 0
    if not blob:
        raise SourceError(f"{path}: the file is empty (0 bytes): no PCD header, no points (an interrupted write or copy?)")
    for _ in range(64):
        end = blob.find(b"\n", pos)
        if end < 0:
            raise SourceError(f"{path}: the file ends after {len(blob):,} bytes inside its PCD header, before the "
                              "DATA line (cut short, or not a PCD file)")
        line = blob[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        name, _, rest = line.partition(" ")
        fields[name.upper()] = rest.split()
        if name.upper() == "DATA":
            return fields, pos
    raise SourceError(f"{path}: PCD header has no DATA line within 64 lines")


def _ints(path: Path, fields: dict[str, list[str]], key: str) -> list[int]:
    try:
        return [int(v) for v in fields[key]]
    except KeyError:
        raise SourceError(f"{path}: PCD header lacks {key}") from None
    except ValueError:
        raise SourceError(f"{path}: PCD header {key} is not a list of integers: {' '.join(fields[key])}") from None


def read_pcd(path: str | Path) -> PcdCloud:
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as err:
        raise SourceError(f"{path}: cannot read: {err.strerror}") from err
    return parse_pcd(blob, path)


def parse_pcd(blob: bytes, path: str | Path = "pcd") -> PcdCloud:
    """Decode PCD bytes; `path` only names the input in error messages."""
    fields, data_start = _header(path, blob)
    names = fields.get("FIELDS")
    if not names:
        raise SourceError(f"{path}: PCD header lacks FIELDS")
    sizes = _ints(path, fields, "SIZE")
    types = fields.get("TYPE")
    if types is None:
        raise SourceError(f"{path}: PCD header lacks TYPE")
    counts = _ints(path, fields, "COUNT") if "COUNT" in fields else [1] * len(names)
    if not (len(names) == len(sizes) == len(types) == len(counts)):
        raise SourceError(
            f"{path}: PCD header FIELDS/SIZE/TYPE/COUNT disagree in length "
            f"({len(names)}/{len(sizes)}/{len(types)}/{len(counts)})"
        )
    for axis in "xyz":
        if axis not in names:
            raise SourceError(f"{path}: PCD has no '{axis}' field (FIELDS {' '.join(names)})")
    dtypes = []
    for name, size, kind, count in zip(names, sizes, types, counts):
        code = _TYPES.get((kind.upper(), size))
        if code is None:
            raise SourceError(f"{path}: PCD field '{name}' has unsupported TYPE {kind} SIZE {size}")
        if count < 1 or count > 4096:
            raise SourceError(f"{path}: PCD field '{name}' has COUNT {count}")
        dtypes.append(("<" + code, count))
    width = _ints(path, fields, "WIDTH")[0] if fields.get("WIDTH") else None
    height = _ints(path, fields, "HEIGHT")[0] if fields.get("HEIGHT") else 1
    if width is None:
        raise SourceError(f"{path}: PCD header lacks WIDTH")
    npts = _ints(path, fields, "POINTS")[0] if fields.get("POINTS") else width * height
    if width < 0 or height < 0 or npts != width * height:
        raise SourceError(f"{path}: PCD POINTS {npts} != WIDTH {width} x HEIGHT {height}")
    if npts > MAX_POINTS:
        raise SourceError(f"{path}: PCD declares {npts} points, more than the limit of {MAX_POINTS}")
    viewpoint: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    has_vp = "VIEWPOINT" in fields
    if has_vp:
        try:
            viewpoint = tuple(float(v) for v in fields["VIEWPOINT"])
        except ValueError:
            raise SourceError(f"{path}: PCD VIEWPOINT is not numeric") from None
        if len(viewpoint) != 7 or not np.all(np.isfinite(viewpoint)):
            raise SourceError(f"{path}: PCD VIEWPOINT needs 7 finite numbers (tx ty tz qw qx qy qz)")
        if np.linalg.norm(viewpoint[3:]) < 1e-6:
            raise SourceError(f"{path}: PCD VIEWPOINT quaternion is zero")
    kind = fields["DATA"][0].lower() if fields["DATA"] else ""
    body = memoryview(blob)[data_start:]
    record = np.dtype([(f"f{i}", dt[0], (dt[1],)) for i, dt in enumerate(dtypes)])
    axis_idx = [names.index(a) for a in "xyz"]
    # doubles stay doubles: world-frame clouds (UTM) lose centimetres in float32 before an
    # --origin is subtracted; the points become float32 only after (sources.make_scan)
    out = np.float64 if any(np.dtype(dtypes[i][0]).itemsize == 8 for i in axis_idx) else np.float32
    if kind not in ("binary", "binary_compressed", "ascii"):
        raise SourceError(f"{path}: PCD DATA '{kind}' is not ascii, binary or binary_compressed")
    # a signalling NaN in the bytes raises the FPU's invalid flag when widened (a RuntimeWarning
    # from numpy); it is a NaN either way, and non-finite points are dropped and counted later
    with np.errstate(invalid="ignore"):
        if kind == "binary":
            need = npts * record.itemsize
            if len(body) < need:
                raise SourceError(f"{path}: PCD binary body has {len(body)} bytes, header declares {need}")
            rec = np.frombuffer(body, dtype=record, count=npts)
            xyz = np.stack([rec[f"f{i}"][:, 0] for i in axis_idx], axis=1).astype(out)
        elif kind == "binary_compressed":
            xyz = _binary_compressed(path, body, npts, dtypes, axis_idx).astype(out, copy=False)
        else:
            xyz = _ascii(path, bytes(body), npts, dtypes, axis_idx).astype(out, copy=False)
    return PcdCloud(xyz, viewpoint, has_vp, kind)


def _binary_compressed(path: Path, body: memoryview, npts: int, dtypes: list, axis_idx: list[int]) -> np.ndarray:
    from voxtool.kernels.lzf import lzf_decompress

    if len(body) < 8:
        raise SourceError(f"{path}: PCD binary_compressed body is shorter than its 8-byte size header")
    csize, usize = (int(v) for v in np.frombuffer(body[:8], dtype="<u4"))
    point_size = sum(np.dtype(dt).itemsize * count for dt, count in dtypes)
    if usize != npts * point_size:
        raise SourceError(f"{path}: PCD binary_compressed declares {usize} uncompressed bytes, expected {npts * point_size}")
    if csize > len(body) - 8:
        raise SourceError(f"{path}: PCD binary_compressed declares {csize} compressed bytes, file holds {len(body) - 8}")
    raw = np.empty(usize, dtype=np.uint8)
    got = lzf_decompress(np.frombuffer(body[8 : 8 + csize], dtype=np.uint8), raw) if csize else 0
    if got != usize:
        reason = {-1: "output larger than declared", -2: "truncated", -3: "bad back reference"}.get(got, f"{got} bytes")
        raise SourceError(f"{path}: PCD binary_compressed LZF data is corrupt ({reason})")
    # column-major: each field's values for all points are contiguous
    offset = 0
    columns = []
    for i, (dt, count) in enumerate(dtypes):
        nbytes = np.dtype(dt).itemsize * count * npts
        if i in axis_idx:
            columns.append((i, np.frombuffer(raw[offset : offset + nbytes].tobytes(), dtype=dt).reshape(npts, count)[:, 0]))
        offset += nbytes
    by_field = dict(columns)
    return np.stack([by_field[i] for i in axis_idx], axis=1).astype(np.float64)


def _ascii(path: Path, text: bytes, npts: int, dtypes: list, axis_idx: list[int]) -> np.ndarray:
    ncols = sum(count for _, count in dtypes)
    try:
        values = np.array(text.decode("ascii", errors="replace").split(), dtype=np.float64)
    except ValueError:
        raise SourceError(f"{path}: PCD ascii body holds a non-numeric value") from None
    if values.shape[0] != npts * ncols:
        raise SourceError(f"{path}: PCD ascii body has {values.shape[0]} values, header declares {npts} x {ncols}")
    table = values.reshape(npts, ncols)
    starts = np.cumsum([0] + [count for _, count in dtypes])
    return np.stack([table[:, starts[i]] for i in axis_idx], axis=1)
