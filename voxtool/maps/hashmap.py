"""The `hashmap` backend: task-agnostic hash-table voxel map with dynamic voxel management and
map sharing (seed: voxel-mapping-hash-map-sharing.md, Alg. 1-3, Sec. V). See docs/backends.md."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from voxtool.config import MapParams, SensorModel, logodds
from voxtool.errors import ParameterError
from voxtool.kernels import hashmap as K
from voxtool.maps.base import IntegrateTiming, Leaves, PreparedScan
from voxtool.maps.octree import OctreeMap, prepare_scan
from voxtool.sources.scan import Scan

SCHEDULABLE = ("p_init", "n_lim", "d_in", "d_inf", "inf_range", "ttl")
_DTYPES = (np.int64, np.float32, np.int8, np.uint8, np.int32, np.int32, np.int32, np.int32, np.int32, np.int32, np.int64)


def sphere_offsets(max_radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer offsets with |o| <= r, grouped by r = 0..max_radius: rows start[r]:start[r+1]."""
    rows, start = [], [0]
    for r in range(max_radius + 1):
        g = np.arange(-r, r + 1)
        o = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        o = o[(o * o).sum(axis=1) <= r * r]
        rows.append(o)
        start.append(start[-1] + o.shape[0])
    return np.concatenate(rows).astype(np.int64), np.array(start, dtype=np.int64)


class HashVoxelMap:
    name = "hashmap"

    def __init__(self, params: MapParams, sensor: SensorModel, p_init: float = 0.5, n_lim: int = -1,
                 d_in: float = -1.0, d_inf: float = 0.2, inf_range: float = -1.0, ttl: float = -1.0,
                 p_free: float = 0.4, schedule: list | None = None, rate_hz: float = 10.0) -> None:
        self.params, self.sensor = params, sensor
        self.p_free = p_free
        self.values: dict[str, float] = {}
        self.offsets, self.offset_start = sphere_offsets(0)
        self.set_params(p_init=p_init, n_lim=n_lim, d_in=d_in, d_inf=d_inf, inf_range=inf_range, ttl=ttl)
        self.schedule = sorted((int(i), str(k), float(v)) for i, k, v in (schedule or []))
        for _, k, _ in self.schedule:
            if k not in SCHEDULABLE:
                raise ParameterError(f"schedule: '{k}' is not one of {', '.join(SCHEDULABLE)}")
        self.period_ns = int(1e9 / rate_hz)
        self.records = tuple(np.zeros(1024, dtype=d) for d in _DTYPES)
        self.records[2][:] = -1
        self.free = np.zeros(1024, dtype=np.int64)
        self.tab_key = np.full(4096, K.EMPTY, dtype=np.int64)
        self.tab_val = np.zeros(4096, dtype=np.int64)
        self.meta = np.array([-1, -1, 0, 0, 0, 0, 0], dtype=np.int64)
        self.presence = np.zeros(K.PRESENCE_BITS // 64, dtype=np.int64)
        self.scan_metrics: list[dict] = []
        self.newly_occupied: np.ndarray = np.zeros(0, np.int64)

    # -- parameters ----------------------------------------------------------------------------
    def set_params(self, **kw) -> None:
        """Change p_init, n_lim, d_in, d_inf, inf_range, ttl; they take effect from the next scan."""
        for k, v in kw.items():
            if k not in SCHEDULABLE:
                raise ParameterError(f"hashmap has no parameter '{k}'")
            self.values[k] = float(v)
        v = self.values
        if not 0 < v["p_init"] < 1:
            raise ParameterError(f"p_init={v['p_init']} must lie in (0, 1)")
        if v["d_inf"] < 0 or v["d_inf"] / self.params.resolution > 64:
            raise ParameterError(f"d_inf={v['d_inf']} must lie in [0, 64 voxels]")
        self.radius_vox = int(math.floor(v["d_inf"] / self.params.resolution + 1e-9))
        if self.radius_vox + 1 >= self.offset_start.shape[0]:
            self.offsets, self.offset_start = sphere_offsets(self.radius_vox)

    def _schedule_for(self, index: int) -> None:
        for i, k, value in self.schedule:
            if i == index:
                self.set_params(**{k: value})

    # -- storage -------------------------------------------------------------------------------
    def _reserve(self, new_records: int) -> None:
        need = int(self.meta[K.M_NEXT]) + new_records
        cap = self.records[0].shape[0]
        if need > cap:
            new_cap = max(need, 2 * cap)
            grown = []
            for arr in self.records:
                g = np.zeros(new_cap, dtype=arr.dtype)
                g[:cap] = arr
                grown.append(g)
            grown[2][cap:] = -1
            self.records = tuple(grown)
            f = np.zeros(new_cap, dtype=np.int64)
            f[: self.free.shape[0]] = self.free
            self.free = f
        live = int(self.meta[K.M_LIVE]) + new_records
        tab = self.tab_key.shape[0]
        if 2 * (live + int(self.meta[K.M_TOMBS])) > tab:
            size = tab
            while 2 * live > size // 2:
                size *= 2
            self.tab_key = np.full(size, K.EMPTY, dtype=np.int64)
            self.tab_val = np.zeros(size, dtype=np.int64)
            K.rehash(self.tab_key, self.tab_val, self.records[0], self.records[2], int(self.meta[K.M_NEXT]))
            self.meta[K.M_TOMBS] = 0

    # -- MapBackend ------------------------------------------------------------------------------
    def warm_up(self) -> None:
        OctreeMap(self.params, self.sensor).warm_up()
        probe = HashVoxelMap(MapParams(resolution=0.5), self.sensor, n_lim=1, d_inf=0.5)
        for x in (1.0, 3.0):
            probe.integrate(Scan(np.array([[x, 0.5, 0.25]], dtype=np.float32), np.zeros(3, dtype=np.float32)))

    def prepare(self, scan: Scan) -> PreparedScan:
        self._schedule_for(scan.index)
        d_in = self.values["d_in"]
        if d_in >= 0 and scan.points.shape[0]:
            d = np.linalg.norm(scan.points.astype(np.float64) - scan.origin.astype(np.float64), axis=1)
            scan = Scan(scan.points[d <= d_in], scan.origin, scan.index, scan.stamp_ns, scan.source)
        prepared = prepare_scan(scan, self.params)
        prepared.stamp_ns = scan.stamp_ns if scan.stamp_ns else scan.index * self.period_ns
        prepared.origin = scan.origin
        return prepared

    def apply(self, prepared: PreparedScan) -> IntegrateTiming:
        v, s = self.values, self.sensor
        packed = prepared.packed
        stamp = prepared.stamp_ns
        origin = (prepared.origin if prepared.origin is not None else np.zeros(3, np.float32)).astype(np.float64)
        t0 = time.perf_counter()
        n_hits = int((packed & 1).sum())
        self._reserve(n_hits)
        touched = np.empty(packed.shape[0], dtype=np.int64)
        new = np.empty(packed.shape[0], dtype=np.bool_)
        changed = np.empty(packed.shape[0], dtype=np.int64)
        nt, nc = K.input_update(packed, stamp, np.float32(logodds(v["p_init"])), np.float32(s.hit_log),
                                np.float32(s.miss_log), np.float32(s.clamp_min_log), np.float32(s.clamp_max_log),
                                np.float32(s.threshold_log), np.float32(logodds(self.p_free)), self.records, self.free,
                                self.meta, self.tab_key, self.tab_val, self.presence, touched, new, changed)
        state = self.records[2]
        ch = changed[:nc]
        self.newly_occupied = self.records[0][ch[state[ch] == 1]].copy()
        t1 = time.perf_counter()
        sphere = int(self.offset_start[self.radius_vox + 1] - self.offset_start[self.radius_vox])
        self._reserve(nc * sphere)
        K.inflate(changed, nc, origin[0], origin[1], origin[2], v["inf_range"], self.params.resolution,
                  self.radius_vox, self.offsets, self.offset_start, self.records, self.free, self.meta,
                  self.tab_key, self.tab_val)
        t2 = time.perf_counter()
        n_lim = int(v["n_lim"]) if v["n_lim"] >= 0 else np.iinfo(np.int64).max
        oldest = stamp - int(v["ttl"] * 1e9) if v["ttl"] >= 0 else np.iinfo(np.int64).min
        K.manage(touched, nt, n_lim, oldest, self.offsets, self.offset_start, self.records, self.free, self.meta,
                 self.tab_key, self.tab_val)
        t3 = time.perf_counter()
        self.scan_metrics.append({"n_occ": int(self.meta[K.M_HSIZE]), "n_inf": self.n_inflated(),
                                  "t_tot_ms": 1e3 * (prepared.seconds + t3 - t0), "t_occ_ms": 1e3 * (prepared.seconds + t1 - t0),
                                  "t_inf_ms": 1e3 * (t2 - t1), "t_m_ms": 1e3 * (t3 - t2), "memory_bytes": self.memory_bytes()})
        return IntegrateTiming(raycast=prepared.seconds, update=t3 - t0, voxel_updates=int(packed.shape[0]),
                               ray_steps=prepared.steps, rays=prepared.rays, merged_rays=prepared.merged_rays)

    def integrate(self, scan: Scan) -> IntegrateTiming:
        return self.apply(self.prepare(scan))

    def integrate_shared(self, keys: np.ndarray, stamp_ns: int, index: int) -> None:
        """Integrate shared newly-occupied voxels like sensor hits, without ray casting."""
        from voxtool.keys import morton_encode

        self._schedule_for(index)
        codes = np.unique(morton_encode(np.asarray(keys, dtype=np.int64).reshape(-1, 3)))
        self.apply(PreparedScan((codes << 1) | 1, 0, 0.0, stamp_ns=stamp_ns, origin=np.zeros(3, np.float32)))

    # -- views ---------------------------------------------------------------------------------
    def _live(self) -> np.ndarray:
        n = int(self.meta[K.M_NEXT])
        return np.flatnonzero(self.records[2][:n] >= 0)

    def occupied_codes(self) -> np.ndarray:
        r = self._live()
        r = r[(self.records[3][r] == 1) & (self.records[2][r] == 1)]
        return np.sort(self.records[0][r])

    def inflation_counts(self) -> dict[int, int]:
        r = self._live()
        r = r[self.records[4][r] > 0]
        return dict(zip(self.records[0][r].tolist(), self.records[4][r].tolist()))

    def n_inflated(self) -> int:
        n = int(self.meta[K.M_NEXT])
        return int(((self.records[2][:n] >= 0) & (self.records[4][:n] > 0)).sum())

    def leaves(self) -> Leaves:
        """The occupancy map (occupied and undecided voxels) as one-voxel leaves."""
        r = self._live()
        r = r[self.records[3][r] == 1]
        order = np.argsort(self.records[0][r])
        r = r[order]
        return Leaves(self.records[0][r].copy(), np.full(r.shape[0], 16, np.uint8), self.records[1][r].copy())

    def query(self, codes: np.ndarray) -> np.ndarray:
        lv = self.leaves()
        idx = np.searchsorted(lv.codes, codes)
        idx = np.clip(idx, 0, max(lv.codes.shape[0] - 1, 0))
        out = np.full(codes.shape[0], np.nan, dtype=np.float32)
        if lv.codes.shape[0]:
            hit = lv.codes[idx] == codes
            out[hit] = lv.values[idx[hit]]
        return out

    def node_counts(self) -> tuple[int, int]:
        return int(self.leaves().codes.shape[0]), 0

    def memory_bytes(self) -> int:
        return int(sum(a.nbytes for a in self.records) + self.free.nbytes + self.tab_key.nbytes + self.tab_val.nbytes
                   + self.presence.nbytes)

    def _history(self) -> np.ndarray:
        """Record indices of the history list, oldest first."""
        out = np.empty(int(self.meta[K.M_HSIZE]), dtype=np.int64)
        r, k = int(self.meta[K.M_HEAD]), 0
        nxt = self.records[7]
        while r >= 0 and k < out.shape[0]:  # a snapshot write, not a hot path
            out[k] = r
            r = int(nxt[r])
            k += 1
        return out

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Occupancy-map voxels (Morton order) plus what makes the map resume exactly: each
        voxel's inflation radius, last-update stamp, hit/miss counts, and the history order."""
        r = self._live()
        r = r[self.records[3][r] == 1]
        r = r[np.argsort(self.records[0][r])]
        position = np.full(int(self.meta[K.M_NEXT]), -1, dtype=np.int64)
        position[r] = np.arange(r.shape[0])
        return {"leaf_codes": self.records[0][r].copy(), "leaf_depths": np.full(r.shape[0], 16, np.uint8),
                "leaf_values": self.records[1][r].copy(), "hm_radius": self.records[5][r].astype(np.int32),
                "hm_last": self.records[10][r].copy(), "hm_hits": self.records[8][r].copy(),
                "hm_misses": self.records[9][r].copy(), "hm_history": position[self._history()]}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        from voxtool.errors import FormatError

        codes, values = arrays["leaf_codes"], arrays["leaf_values"]
        n = codes.shape[0]
        extra = [arrays.get(k) for k in ("hm_radius", "hm_last", "hm_hits", "hm_misses", "hm_history")]
        if any(a is None for a in extra) or any(a.shape[0] != n for a in extra[:4]):
            raise FormatError("hashmap snapshot: per-voxel arrays missing or of the wrong length")
        radius, last, hits, misses, history = extra
        if np.any(radius > 64) or np.any(history < 0) or np.any(history >= n) or np.unique(history).size != history.size:
            raise FormatError("hashmap snapshot: inflation radius or history out of range")
        max_r = int(max(radius.max(initial=0), self.radius_vox))
        if max_r + 1 >= self.offset_start.shape[0]:
            self.offsets, self.offset_start = sphere_offsets(max_r)
        sphere = int(self.offset_start[max_r + 1] - self.offset_start[max_r])
        self._reserve(n + int((radius >= 0).sum()) * sphere)
        K.load_records(codes, values, np.float32(self.sensor.threshold_log), np.float32(logodds(self.p_free)),
                       self.records, self.free, self.meta, self.tab_key, self.tab_val, self.presence)
        K.restore(radius.astype(np.int32), last.astype(np.int64), hits.astype(np.int32), misses.astype(np.int32),
                  history.astype(np.int64), self.offsets, self.offset_start, self.records, self.free, self.meta,
                  self.tab_key, self.tab_val)

    def extra_meta(self) -> dict[str, Any]:
        return {k: self.values[k] for k in ("p_init", "n_lim", "d_in", "d_inf", "inf_range", "ttl")} | {"p_free": self.p_free}

    def extra_stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {"n_occ": int(self.meta[K.M_HSIZE]), "n_inf": self.n_inflated()}
        if self.scan_metrics:
            for key in ("n_occ", "n_inf", "t_tot_ms", "t_occ_ms", "t_inf_ms", "t_m_ms", "memory_bytes"):
                a = np.array([m[key] for m in self.scan_metrics], dtype=np.float64)
                out[f"per_scan_{key}"] = {"mean": round(float(a.mean()), 4), "median": round(float(np.median(a)), 4),
                                          "p95": round(float(np.percentile(a, 95)), 4), "max": round(float(a.max()), 4)}
        return out

    def close(self) -> None:
        pass
