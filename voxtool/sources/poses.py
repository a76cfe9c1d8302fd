"""Pose files: TUM (`t x y z qx qy qz qw`), indexed TUM (`i t x y z qx qy qz qw`, as the shared
datasets' poses.txt) and KITTI (12 numbers, a row-major 3x4 [R|t])."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from voxtool.errors import SourceError
from voxtool.geometry import Pose

UNIT_TOLERANCE = 1e-3


def read_poses(path: str | Path) -> list[tuple[float | None, Pose]]:
    """(stamp seconds or None, sensor pose in world) per row, comments (#) skipped."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise SourceError(f"{path}: cannot read pose file: {err}") from err
    rows: list[tuple[float | None, Pose]] = []
    width = None
    for lineno, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip().replace(",", " ")
        if not text:
            continue
        try:
            values = [float(v) for v in text.split()]
        except ValueError:
            raise SourceError(f"{path}:{lineno}: pose row is not numeric") from None
        if width is None:
            width = len(values)
            if width not in (8, 9, 12):
                raise SourceError(
                    f"{path}:{lineno}: pose row has {width} numbers; expected 8 (TUM), 9 (index + TUM) or 12 (KITTI)"
                )
        elif len(values) != width:
            raise SourceError(f"{path}:{lineno}: pose row has {len(values)} numbers, earlier rows have {width}")
        if not np.all(np.isfinite(values)):
            raise SourceError(f"{path}:{lineno}: pose row holds NaN or inf")
        if width == 12:
            m = np.array(values).reshape(3, 4)
            r = m[:, :3]
            if not np.allclose(r @ r.T, np.eye(3), atol=UNIT_TOLERANCE):
                raise SourceError(f"{path}:{lineno}: KITTI rotation is not orthonormal")
            rows.append((None, Pose(r, m[:, 3])))
        else:
            stamp, x, y, z, qx, qy, qz, qw = values[-8:]
            norm = float(np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw))
            if abs(norm - 1.0) > UNIT_TOLERANCE:
                raise SourceError(f"{path}:{lineno}: quaternion has norm {norm:.6f}, expected a unit quaternion")
            rows.append((stamp, Pose.from_quat((x, y, z), qw, qx, qy, qz)))
    if not rows:
        raise SourceError(f"{path}: pose file holds no poses")
    return rows
