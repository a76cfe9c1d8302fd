"""LAS / LAZ / COPC survey tiles through laspy (with lazrs for LAZ), an optional extra.

A tile is points in a projected coordinate system, often in feet, with no sensor origin. Its
coordinates are read as float64, turned into metres by the units its GeoTIFF keys or WKT name,
and moved to the map's local origin (`--origin auto` for projected coordinates) before they are
rounded to float32. Without a sensor origin no ray can clear free space: the points mark their
voxels occupied (Scan.hits_only) and free space stays unknown, which is said on one line; with
the sensor's trajectory by GPS time (--poses), short slices of the points are cast from the
sensor's position at their time. The tile is read in chunks of points, so a tile larger than
memory builds.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import SourceError, VoxtoolWarning, first_line
from voxtool.sources.scan import Scan

EXTRA = f"pip install '{DISTRIBUTION}[las]' (laspy with lazrs)"
CHUNK_POINTS = 2_000_000  # points a scan: a chunk's arrays stay ~100 MB whatever the tile
# with a trajectory, the points of this many seconds share one sensor position: a vehicle at 15 m/s
# moves 15 cm in it, a 2 M points/s scanner gives 20,000 points
SLICE_S = 0.01
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
        raise SourceError(f"{path}: not a readable LAS/LAZ file ({first_line(err)})") from None


def check_complete(path: Path, header) -> None:
    """One line where an uncompressed tile is shorter than the points its header declares (a
    copy cut short); a compressed one is checked as its chunks are read."""
    if header.are_points_compressed:
        return
    count, size = int(header.point_count), header.point_format.size
    held = (path.stat().st_size - header.offset_to_point_data) // size
    if held < count:
        raise SourceError(f"{path}: holds {max(held, 0):,} points, its header declares {count:,}: truncated")


def _chunks(path: Path, reader, count: int) -> Iterator:
    """The tile's points in chunks of CHUNK_POINTS; one line naming the file where its point data
    is cut short or damaged (laspy and lazrs raise their own types, or numpy's)."""
    read = 0
    chunks = reader.chunk_iterator(CHUNK_POINTS)
    while True:
        try:
            chunk = next(chunks)
        except StopIteration:
            break
        except Exception as err:
            raise SourceError(f"{path}: its points cannot be read past point {read:,} of the {count:,} its header "
                              f"declares: truncated or damaged ({first_line(err) or type(err).__name__})") from None
        read += len(chunk)
        yield chunk
    if read < count:
        raise SourceError(f"{path}: holds {read:,} points, its header declares {count:,}: truncated")


def _trajectory(path: Path, options, header, shift: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(times, positions about the local origin) of the sensor trajectory given as --poses (its
    times in the tile's GPS time), None without one."""
    from voxtool.sources import _pose_rows

    if options.poses is None:
        return None
    if "gps_time" not in header.point_format.dimension_names:
        raise SourceError(f"{path}: point format {header.point_format.id} has no GPS time: a trajectory (--poses) "
                          "cannot place its points' sensor")
    rows = _pose_rows(options, None, "poses")
    if not rows or any(t is None for t, _ in rows):
        raise SourceError(f"{options.poses}: a tile's trajectory needs a time on every row (TUM: t x y z qx qy qz qw, "
                          "t in the tile's GPS time)")
    times = np.array([t for t, _ in rows], np.float64)
    if np.any(np.diff(times) <= 0):
        raise SourceError(f"{options.poses}: the trajectory's times must increase")
    return times, np.array([pose.translation for _, pose in rows], np.float64) - shift


def las_stream(path: Path, options):
    """A tile as a ScanStream: chunks of its points in metres, occupied voxels only; or, with a
    sensor trajectory (--poses, by GPS time), slices of SLICE_S seconds of its points, each cast
    from the sensor's position at its mean time."""
    from voxtool.errors import ParameterError
    from voxtool.sources import BadScans, ScanStream

    if isinstance(options.origin, str):
        raise ParameterError(f"--origin {options.origin} was not resolved (resolve_origin) before reading {path}")
    shift = np.zeros(3) if options.origin is None else np.asarray(options.origin, np.float64)
    with open_tile(path) as reader:
        header = reader.header
        count = int(header.point_count)
        check_complete(path, header)
        units = tile_units(header)
        centre = (np.asarray(header.mins, np.float64) + np.asarray(header.maxs, np.float64)) / 2
        trajectory = _trajectory(path, options, header, shift)
    unit = np.array([units["horizontal"]["metres"]] * 2 + [units["vertical"]["metres"]])
    # no sensor: the tile's centre stands where a sensor origin would (what --origin auto takes)
    origin = (centre * unit - shift).astype(np.float32)
    chunks = max(1, -(-count // CHUNK_POINTS))
    selected = range(chunks)[options.start:options.stop:options.every]
    bad = BadScans(options.bad_scans)

    def metres(chunk) -> np.ndarray:
        points = np.empty((len(chunk), 3), np.float32)
        axis_m = np.empty(len(chunk), np.float64)
        for axis, raw in enumerate((chunk.X, chunk.Y, chunk.Z)):
            # as laspy scales them (integer x scale + offset), then metres about the local origin
            # in float64, rounded to float32 once
            np.multiply(raw, header.scales[axis], out=axis_m, casting="unsafe")
            axis_m += header.offsets[axis]
            axis_m *= unit[axis]
            axis_m -= shift[axis]
            points[:, axis] = axis_m
        return points

    def scans() -> Iterator[Scan]:
        if trajectory is None:
            warnings.warn(f"{path}: a survey tile has no sensor origin: its points mark occupied voxels and free "
                          "space stays unknown (a trajectory by GPS time, --poses, gives its rays)", VoxtoolWarning,
                          stacklevel=2)
        index, first, outside = 0, None, 0
        held = (np.empty((0, 3), np.float32), np.empty(0))  # the points of a slice the chunk's end may have cut
        with open_tile(path) as reader:
            for i, chunk in enumerate(_chunks(path, reader, count)):
                if i not in selected:
                    continue
                # integers scaled: never NaN, and no sensor whose own position would be a "no return"
                points = metres(chunk)
                if trajectory is None:
                    yield Scan(points, origin, index=i, source=f"{path}#{i}", points_read=len(chunk),
                               raw_bytes=len(chunk) * header.point_format.size, hits_only=True)
                    continue
                times = np.asarray(chunk.gps_time, np.float64)
                first = times.min() if first is None else first
                points, times = np.concatenate([held[0], points]), np.concatenate([held[1], times])
                slot = np.floor((times - first) / SLICE_S).astype(np.int64)
                if i + 1 < chunks and i + 1 in selected:
                    # a tile stored in time order cuts a slice at a chunk's end: its points wait for the
                    # rest of it in the next chunk, so that the slice is one scan
                    last = slot == slot.max()
                    held = (points[last], times[last])
                    points, times, slot = points[~last], times[~last], slot[~last]
                else:
                    held = held[0][:0], held[1][:0]
                if not slot.size:
                    continue
                order = np.argsort(slot, kind="stable")
                cuts = np.flatnonzero(np.diff(slot[order])) + 1
                for part in np.split(order, cuts):
                    when = float(times[part].mean())
                    if not trajectory[0][0] <= when <= trajectory[0][-1]:
                        outside += part.shape[0]
                        continue
                    sensor = np.array([np.interp(when, trajectory[0], trajectory[1][:, a]) for a in range(3)])
                    yield Scan(points[part], sensor.astype(np.float32), index=index, stamp_ns=int(round(when * 1e9)),
                               source=f"{path}#{i}@{when:.6f}", points_read=part.shape[0],
                               raw_bytes=part.shape[0] * header.point_format.size)
                    index += 1
        if outside:
            warnings.warn(f"{path}: {outside:,} points lie outside the trajectory's times "
                          f"({trajectory[0][0]:.6f} .. {trajectory[0][-1]:.6f} s) and were left out", VoxtoolWarning,
                          stacklevel=2)

    return ScanStream("las", path, len(selected) if trajectory is None else None, scans(), bad)
