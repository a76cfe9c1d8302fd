"""voxtool.jit.start: cached kernels load without numba refreshing its compiler (0.2 s of a
command's start), and still give OctoMap's answers; a kernel that is not cached still compiles."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from tests.reference import scan_update_sets

SCRIPT = r"""
import json, sys
import numpy as np
from voxtool import jit
jit.start()
refreshed = "numba.np.arraymath" in sys.modules  # what numba's refresh imports first

from voxtool.config import MapParams
from voxtool.maps.octree import scan_updates
from voxtool.sources.scan import Scan

rng = np.random.default_rng(7)
points = rng.uniform(-6, 6, size=(300, 3)).astype(np.float32)
origin = np.array([0.31, -0.2, 0.45], dtype=np.float32)
packed = scan_updates(Scan(points, origin), MapParams(resolution=0.25))[0]

from numba import njit

@njit  # not cached: compiled here, after start
def ranks(x):
    return np.argsort(np.cumsum(x))

compiled = ranks(np.array([3.0, -5.0, 4.0])).tolist()
print(json.dumps({"refreshed": refreshed, "packed": packed.tolist(), "points": points.tolist(),
                  "origin": origin.tolist(), "compiled": compiled}))
"""


def run_script():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_cached_kernels_load_without_a_refresh_and_match_octomap():
    run_script()  # a cold cache compiles (and so refreshes) once
    out = run_script()
    assert not out["refreshed"]
    from voxtool.keys import morton_decode

    packed = np.array(out["packed"], dtype=np.int64)
    keys = morton_decode(packed >> 1)
    got_free = {tuple(int(v) for v in k) for k in keys[(packed & 1) == 0]}
    got_occ = {tuple(int(v) for v in k) for k in keys[(packed & 1) == 1]}
    free, occ = scan_update_sets(np.array(out["points"], dtype=np.float32),
                                 np.array(out["origin"], dtype=np.float32), 0.25)
    assert got_occ == occ and got_free == free
    assert out["compiled"] == [1, 2, 0]  # argsort of the cumsum [3, -2, 2]
