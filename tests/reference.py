"""Slow, obviously-correct references the compiled code is checked against.

`ray_keys` transcribes OctoMap 1.10's computeRayKeys line by line with numpy float32/float64
scalars; `scan_update_sets` is insertPointCloud's set logic; `DictOctoMap` is OctoMap's per-voxel
update rule on a plain dict (the finest-level meaning of the tree).
"""

from __future__ import annotations

import math

import numpy as np

F32 = np.float32


def coord_key(c: float, res: float) -> int:
    return int(math.floor((1.0 / res) * float(c))) + 32768


def discrete_points(points: np.ndarray, res: float) -> np.ndarray:
    """OctoMap's computeDiscreteUpdate: the centre of each distinct end voxel (keyToCoord), in
    the order the voxels first occur."""
    seen, out = set(), []
    for p in points:
        k = tuple(coord_key(p[i], res) for i in range(3))
        if k not in seen:
            seen.add(k)
            out.append([F32((k[i] - 32768 + 0.5) * res) for i in range(3)])
    return np.array(out, dtype=np.float32).reshape(-1, 3)


def ray_keys(origin: np.ndarray, end: np.ndarray, res: float) -> list[tuple[int, int, int]]:
    ko = tuple(coord_key(origin[i], res) for i in range(3))
    ke = tuple(coord_key(end[i], res) for i in range(3))
    if ko == ke:
        return []
    ray = [ko]
    d = [F32(end[i] - origin[i]) for i in range(3)]
    length = F32(math.sqrt(float(F32(F32(d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]))))
    d = [F32(v / length) for v in d]
    step, t_max, t_delta = [0, 0, 0], [0.0] * 3, [0.0] * 3
    key = list(ko)
    for i in range(3):
        step[i] = 1 if d[i] > 0 else (-1 if d[i] < 0 else 0)
        if step[i]:
            border = (float(key[i] - 32768) + 0.5) * res
            border += float(F32(step[i] * res * 0.5))
            t_max[i] = (border - float(origin[i])) / float(d[i])
            t_delta[i] = res / abs(float(d[i]))
        else:
            t_max[i] = t_delta[i] = 1.7976931348623157e308
    while True:
        if t_max[0] < t_max[1]:
            dim = 0 if t_max[0] < t_max[2] else 2
        else:
            dim = 1 if t_max[1] < t_max[2] else 2
        key[dim] += step[dim]
        t_max[dim] += t_delta[dim]
        if tuple(key) == ke:
            break
        if min(t_max) > float(length):
            break
        ray.append(tuple(key))
    return ray


def scan_update_sets(points: np.ndarray, origin: np.ndarray, res: float, max_range: float = -1.0):
    """(free keys, occupied keys) of one scan, as OctoMap's computeUpdate."""
    free, occ = set(), set()
    for p in points:
        p = p.astype(np.float32)
        diff = [F32(p[i] - origin[i]) for i in range(3)]
        norm = math.sqrt(float(F32(F32(diff[0] * diff[0] + diff[1] * diff[1]) + diff[2] * diff[2])))
        if max_range < 0 or norm <= max_range:
            free.update(ray_keys(origin, p, res))
            occ.add(tuple(coord_key(p[i], res) for i in range(3)))
        else:
            ln = F32(norm)
            end = np.array([F32(origin[i] + F32(F32(diff[i] / ln) * F32(max_range))) for i in range(3)], dtype=np.float32)
            free.update(ray_keys(origin, end, res))
    return free - occ, occ


class DictOctoMap:
    """OctoMap's occupancy update per finest voxel, with float32 arithmetic and clamping."""

    def __init__(self, hit=0.85, miss=-0.4, cmin=-2.0, cmax=3.5):
        self.hit, self.miss, self.cmin, self.cmax = F32(hit), F32(miss), F32(cmin), F32(cmax)
        self.values: dict[tuple[int, int, int], np.float32] = {}

    def integrate(self, points, origin, res, max_range=-1.0):
        free, occ = scan_update_sets(points, origin, res, max_range)
        for keys, upd in ((free, self.miss), (occ, self.hit)):
            for k in keys:
                v = F32(self.values.get(k, F32(0.0)) + upd)
                self.values[k] = F32(min(max(v, self.cmin), self.cmax))
