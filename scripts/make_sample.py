"""Regenerate voxtool/data/sample from ../shared/data/norlab (BSD-3): every 2nd scan of the
first 10, every 5th point, plus an OctoMap 1.10 reference map of it built with pyoctomap."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from voxtool.geometry import Pose
from voxtool.sources.pcd import read_pcd

SRC = Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/norlab/pcd")
DST = Path(__file__).resolve().parents[1] / "voxtool" / "data" / "sample"


def main() -> None:
    import pyoctomap

    DST.mkdir(parents=True, exist_ok=True)
    files = sorted(SRC.glob("*.pcd"))[0:10:2]
    tree = pyoctomap.OcTree(0.2)
    lines = ["# index timestamp tx ty tz qx qy qz qw (sensor pose in world; points in sensor frame)"]
    src_poses = {int(r.split()[0]): r.split()[1] for r in (SRC / "poses.txt").read_text().splitlines() if r and r[0] != "#"}
    total = 0
    for i, f in enumerate(files):
        cloud = read_pcd(f)
        pts = cloud.xyz[::5]
        vp = cloud.viewpoint
        header = (
            f"# .PCD v0.7 - Point Cloud Data file format\n# voxtool sample: {f.name} of norlab_icp_mapper (BSD-3), every 5th point\n"
            f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\n"
            f"VIEWPOINT {' '.join(repr(float(v)) for v in vp)}\nPOINTS {len(pts)}\nDATA binary\n"
        )
        (DST / f"{i:06d}.pcd").write_bytes(header.encode() + pts.astype("<f4").tobytes())
        q = vp[3:]
        lines.append(f"{i} {src_poses[int(f.stem)]} {vp[0]!r} {vp[1]!r} {vp[2]!r} {q[1]!r} {q[2]!r} {q[3]!r} {q[0]!r}")
        world = Pose.from_quat(vp[:3], *vp[3:]).apply(pts)
        tree.insertPointCloud(world.astype(np.float64), np.asarray(vp[:3], dtype=np.float32).astype(np.float64))
        total += len(pts)
    (DST / "poses.txt").write_text("\n".join(lines) + "\n")
    tree.writeBinary(str(DST / "reference_octomap_res0.2.bt"))
    (DST / "reference_octomap_res0.2.json").write_text(json.dumps(
        {"octomap": f"OctoMap C++ via pyoctomap {pyoctomap.__version__ if hasattr(pyoctomap, '__version__') else '1.2.2'}",
         "resolution": 0.2, "scans": len(files), "points": total, "maxrange": -1.0}, indent=2) + "\n")


if __name__ == "__main__":
    main()
