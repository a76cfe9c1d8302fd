"""E57 files (ASTM E2807, terrestrial laser scanners) through pye57, an optional extra.

Each scan of a file is one scan here, its points in its own frame and placed by its header's
pose, whose translation is also where its rays start (the scanner's position). Cartesian and
spherical scans are read; points whose invalid state is set (direction only, or no return) are
dropped and counted as not finite. Intensity and colour are read by pye57 but no voxtool output
keeps per-point values, so they are left.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from voxtool import DISTRIBUTION
from voxtool.errors import SourceError, first_line
from voxtool.geometry import Pose
from voxtool.sources.scan import Scan

EXTRA = f"pip install '{DISTRIBUTION}[e57]' (pye57: libE57Format)"
GPS_EPOCH_NS = 315_964_800 * 10**9  # 1980-01-06 in Unix time: E57 dates are GPS seconds


def _pye57(path: Path):
    try:
        import pye57
    except ImportError:
        raise SourceError(f"{path}: reading E57 needs pye57: {EXTRA}") from None
    return pye57


def open_e57(path: Path):
    """The pye57 reader of a file; one line naming the file where it is no readable E57."""
    pye57 = _pye57(path)
    try:
        return pye57.E57(str(path))
    except Exception as err:  # libE57Format raises its own exception types, over several lines
        raise SourceError(f"{path}: not a readable E57 file ({first_line(err)})") from None


def scan_pose(header) -> Pose | None:
    """The scan's pose (its frame in the file's), None where its header has none."""
    if not header.has_pose():
        return None
    return Pose(np.asarray(header.rotation_matrix, dtype=np.float64), np.asarray(header.translation, dtype=np.float64))


def scan_stamp_ns(header) -> int:
    """The scan's acquisition start as Unix nanoseconds (E57 stores GPS seconds), 0 without one."""
    try:
        seconds = float(header.node["acquisitionStart"]["dateTimeValue"].value())
    except Exception:  # absent (optional in the standard): libE57Format raises on a missing child
        return 0
    return int(round(seconds * 1e9)) + GPS_EPOCH_NS if seconds > 0 else 0


def spherical_to_xyz(r, azimuth, elevation) -> np.ndarray:
    """(N, 3) cartesian points of E57 spherical ones: azimuth from +x toward +y, elevation from
    the x-y plane toward +z (radians)."""
    r, az, el = (np.asarray(v, np.float64) for v in (r, azimuth, elevation))
    return np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)


def scan_points(e57, index: int, where: str) -> tuple[np.ndarray, int]:
    """(N, 3) float64 points of scan `index` in its own frame (NaN where the point is invalid),
    and the bytes read."""
    try:
        data = e57.read_scan_raw(index, ignore_unsupported_fields=True)
    except Exception as err:
        raise SourceError(f"{where}: cannot read its points ({first_line(err)})") from None
    if all(f"cartesian{a}" in data for a in "XYZ"):
        xyz = np.stack([np.asarray(data[f"cartesian{a}"], np.float64) for a in "XYZ"], axis=1)
        invalid = data.get("cartesianInvalidState")
    elif all(f"spherical{a}" in data for a in ("Range", "Azimuth", "Elevation")):
        xyz = spherical_to_xyz(*(data[f"spherical{a}"] for a in ("Range", "Azimuth", "Elevation")))
        invalid = data.get("sphericalInvalidState")
    else:
        raise SourceError(f"{where}: has neither cartesian nor spherical coordinates (fields: {', '.join(data)})")
    if invalid is not None:
        xyz[np.asarray(invalid) != 0] = np.nan  # 1: a direction only, 2: no return
    return xyz, int(sum(np.asarray(v).nbytes for v in data.values()))


def e57_stream(path: Path, options):
    """The scans of an E57 file as a ScanStream, each placed by its header's pose (--poses, when
    given, instead)."""
    import warnings

    from voxtool.errors import VoxtoolWarning
    from voxtool.sources import BadScans, ScanStream, _file_scans, _pose_rows, _selected, make_scan

    e57 = open_e57(path)
    count = int(e57.scan_count)
    if count == 0:
        raise SourceError(f"{path}: holds no scans")
    rows = _pose_rows(options, count)
    bad = BadScans(options.bad_scans)
    unposed: list[int] = []

    def read(i: int, _) -> Scan:
        where = f"{path}: scan {i}"
        header = e57.get_header(i)
        points, nbytes = scan_points(e57, i, where)
        pose, stamp = scan_pose(header), scan_stamp_ns(header)
        if rows is not None:
            stamp_s, pose = rows[i]
            stamp = int(round(stamp_s * 1e9)) if stamp_s is not None else stamp
        elif pose is None:
            unposed.append(i)
            pose = Pose.identity()
        return make_scan(points, pose, i, stamp, f"{path}#{i}", nbytes, options)

    def scans() -> Iterator[Scan]:
        read_count = 0
        for scan in _file_scans(list(range(count)), options, read, bad):
            read_count += 1
            yield scan
        if len(unposed) > 1 and len(unposed) == read_count:
            warnings.warn(f"{path}: none of its {read_count} scans has a pose in its header: all were taken as seen "
                          "from the origin; --poses gives one per scan", VoxtoolWarning, stacklevel=2)

    return ScanStream("e57", path, _selected(path, count, options), scans(), bad)
