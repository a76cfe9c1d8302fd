"""LAS / LAZ / COPC survey tiles through laspy (with lazrs for LAZ), an optional extra.

A tile is points in a projected coordinate system, often in feet, with no sensor origin. Its
coordinates are read as float64, turned into metres by the units its GeoTIFF keys or WKT name,
and moved to the map's local origin (`--origin auto` for projected coordinates) before they are
rounded to float32. Without a sensor origin no ray can clear free space: the points mark their
voxels occupied (Scan.hits_only) and free space stays unknown, which is said on one line. The
tile is read in chunks of points, each a scan, so a tile larger than memory builds.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import SourceError, VoxtoolWarning
from voxtool.sources.scan import Scan

EXTRA = f"pip install '{DISTRIBUTION}[las]' (laspy with lazrs)"
CHUNK_POINTS = 2_000_000  # points a scan: a chunk's arrays stay ~100 MB whatever the tile
# EPSG linear unit codes of the GeoTIFF keys (ProjLinearUnitsGeoKey 3076, VerticalUnitsGeoKey 4099)
EPSG_UNITS = {9001: ("metre", 1.0), 9002: ("foot", 0.3048), 9003: ("US survey foot", 1200 / 3937)}
WKT_UNIT = re.compile(r'(?:LENGTH)?UNIT\[\s*"([^"]+)"\s*,\s*([-+0-9.eE]+)')
ANGULAR = ("degree", "radian", "grad", "arc")


def _laspy(path: Path):
    try:
        import laspy
    except ImportError:
        raise SourceError(f"{path}: reading LAS/LAZ needs laspy: {EXTRA}") from None
    return laspy


def _wkt_units(wkt: str) -> tuple[tuple[str, float], tuple[str, float]] | None:
    """(horizontal, vertical) linear units of a WKT (1 or 2) coordinate system, None without any:
    the first linear unit, and the one inside a vertical system where there is one."""
    linear = [(m.start(), m.group(1), float(m.group(2))) for m in WKT_UNIT.finditer(wkt)
              if not any(a in m.group(1).lower() for a in ANGULAR)]
    if not linear:
        return None
    horizontal = linear[0][1:]
    vertical = horizontal
    found = re.search(r"VERT_CS\[|VERTCRS\[|VERTICALCRS\[", wkt)
    if found:
        after = [u for u in linear if u[0] > found.start()]
        vertical = after[0][1:] if after else horizontal
    return horizontal, vertical


def tile_units(header) -> dict:
    """The tile's horizontal and vertical units ({name, metres}) and where they were read: the
    WKT record, else the GeoTIFF keys, else metres (assumed: a tile that names no system)."""
    for vlr in header.vlrs:
        if vlr.record_id == 2112 and hasattr(vlr, "string"):
            units = _wkt_units(str(vlr.string))
            if units is not None:
                (hn, hf), (vn, vf) = units
                return {"horizontal": {"name": hn, "metres": hf}, "vertical": {"name": vn, "metres": vf}, "from": "WKT"}
    for vlr in header.vlrs:
        if vlr.record_id == 34735 and hasattr(vlr, "geo_keys"):
            keys = {k.id: k.value_offset for k in vlr.geo_keys}
            code = keys.get(3076, keys.get(2052))
            if code in EPSG_UNITS:
                vcode = keys.get(4099, code)
                (hn, hf), (vn, vf) = EPSG_UNITS[code], EPSG_UNITS.get(vcode, EPSG_UNITS[code])
                return {"horizontal": {"name": hn, "metres": hf}, "vertical": {"name": vn, "metres": vf},
                        "from": "GeoTIFF keys"}
    metre = {"name": "metre", "metres": 1.0}
    return {"horizontal": metre, "vertical": metre, "from": "none: metres assumed"}


def open_tile(path: Path):
    """laspy's reader of a tile (LAZ decompressed on every core); one line naming the file where
    it is no readable LAS/LAZ."""
    laspy = _laspy(path)
    try:
        backend = laspy.LazBackend.LazrsParallel
        return laspy.open(str(path), laz_backend=backend if backend.is_available() else None)
    except Exception as err:  # laspy and lazrs raise their own types
        text = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise SourceError(f"{path}: not a readable LAS/LAZ file ({text})") from None


def las_stream(path: Path, options):
    """A tile as a ScanStream: chunks of its points, in metres, occupied voxels only."""
    from voxtool.errors import ParameterError
    from voxtool.sources import BadScans, ScanStream

    if options.poses is not None:
        raise SourceError(f"{path}: a tile's points are not in a sensor frame: --poses does not apply (a sensor "
                          "trajectory by GPS time is not read yet)")
    if isinstance(options.origin, str):
        raise ParameterError(f"--origin {options.origin} was not resolved (resolve_origin) before reading {path}")
    with open_tile(path) as reader:
        header = reader.header
        count = int(header.point_count)
        units = tile_units(header)
        centre = (np.asarray(header.mins, np.float64) + np.asarray(header.maxs, np.float64)) / 2
    unit = np.array([units["horizontal"]["metres"]] * 2 + [units["vertical"]["metres"]])
    shift = np.zeros(3) if options.origin is None else np.asarray(options.origin, np.float64)
    # no sensor: the tile's centre stands where a sensor origin would (what --origin auto takes)
    origin = (centre * unit - shift).astype(np.float32)
    chunks = max(1, -(-count // CHUNK_POINTS))
    selected = range(chunks)[options.start:options.stop:options.every]

    def scans() -> Iterator[Scan]:
        warnings.warn(f"{path}: a survey tile has no sensor origin: its points mark occupied voxels and free space "
                      "stays unknown", VoxtoolWarning, stacklevel=2)
        with open_tile(path) as reader:
            for i, chunk in enumerate(reader.chunk_iterator(CHUNK_POINTS)):
                if i not in selected:
                    continue
                points = np.empty((len(chunk), 3), np.float32)
                axis_m = np.empty(len(chunk), np.float64)
                for axis, raw in enumerate((chunk.X, chunk.Y, chunk.Z)):
                    # as laspy scales them (integer x scale + offset), then metres about the local
                    # origin in float64, rounded to float32 once
                    np.multiply(raw, header.scales[axis], out=axis_m, casting="unsafe")
                    axis_m += header.offsets[axis]
                    axis_m *= unit[axis]
                    axis_m -= shift[axis]
                    points[:, axis] = axis_m
                # integers scaled: never NaN, and no sensor whose own position would be a "no return"
                yield Scan(points, origin, index=i, source=f"{path}#{i}", points_read=len(chunk),
                           raw_bytes=len(chunk) * header.point_format.size, hits_only=True)

    return ScanStream("las", path, len(selected), scans(), BadScans(options.bad_scans))
