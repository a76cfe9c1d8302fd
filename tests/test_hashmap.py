"""The hash-map backend against a slow, obviously-correct recomputation after every scan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference import discrete_points, scan_update_sets
from test_octree import world_scans

from voxtool.config import MapParams, SensorModel, logodds
from voxtool.keys import morton_decode, morton_encode
from voxtool.maps.hashmap import HashVoxelMap, K
from voxtool.sources.scan import Scan

F32 = np.float32
S = SensorModel()


class ReferenceMap:
    """Alg. 1-3 with Python dicts and lists, following docs/backends.md literally."""

    def __init__(self, res, p_init=0.5, n_lim=-1, d_in=-1.0, d_inf=0.2, inf_range=-1.0, p_free=0.4, discretize=1):
        self.res, self.discretize = res, discretize
        self.p = dict(p_init=p_init, n_lim=n_lim, d_in=d_in, d_inf=d_inf, inf_range=inf_range)
        self.p_free = p_free
        self.rec: dict[tuple, dict] = {}
        self.history: list[tuple] = []

    def sphere(self, k, radius):
        out = []
        for dx in range(-radius, radius + 1):
            for dy in range(-radius, radius + 1):
                for dz in range(-radius, radius + 1):
                    if dx * dx + dy * dy + dz * dz <= radius * radius:
                        out.append((k[0] + dx, k[1] + dy, k[2] + dz))
        return out

    def inflate(self, k, sign, radius):
        for n in self.sphere(k, radius):
            r = self.rec.setdefault(n, dict(l=F32(0), in_occ=False, state=2, inf=0, radius=-1))
            r["inf"] += sign
            if r["inf"] == 0 and not r["in_occ"]:
                del self.rec[n]

    def remove_from_map(self, k):
        r = self.rec[k]
        if r["radius"] >= 0:
            self.inflate(k, -1, r["radius"])
            r = self.rec.get(k, r)
            r["radius"] = -1
        if k in self.history:
            self.history.remove(k)
        r["in_occ"] = False
        if r["inf"] == 0:
            del self.rec[k]
        else:
            r["state"] = 2

    def integrate(self, points, origin):
        p = self.p
        if p["d_in"] >= 0:
            d = np.linalg.norm(points.astype(np.float64) - origin.astype(np.float64), axis=1)
            points = points[d <= p["d_in"]]
        if self.discretize:
            points = discrete_points(points, self.res)
        free, occ = scan_update_sets(points, origin, self.res)
        keys = sorted(free | occ, key=lambda k: int(morton_encode(np.array([k]))[0]))
        touched, changed = [], []
        l_init, l_free = F32(logodds(p["p_init"])), F32(logodds(self.p_free))
        for k in keys:
            r = self.rec.get(k)
            new = False
            if k in occ:
                if r is None:
                    r = self.rec[k] = dict(l=F32(0), in_occ=False, state=2, inf=0, radius=-1)
                if not r["in_occ"]:  # entering the map: a new voxel, whatever it was before
                    r.update(in_occ=True, l=l_init, state=2, hits=0, misses=0)
                    new = True
                v = F32(r["l"] + F32(S.hit_log))
                r["hits"] += 1
            else:
                if r is None or not r["in_occ"]:
                    continue
                v = F32(r["l"] + F32(S.miss_log))
                r["misses"] += 1
            v = min(max(v, F32(S.clamp_min_log)), F32(S.clamp_max_log))
            was_occ = r["state"] == 1 and not new
            r["l"] = v
            r["state"] = 1 if v > 0 else (0 if v < l_free else 2)
            touched.append(k)
            if was_occ != (r["state"] == 1):
                changed.append(k)
        radius = int(math.floor(p["d_inf"] / self.res + 1e-9))
        for k in changed:
            r = self.rec[k]
            c = (np.array(k, dtype=np.float64) - 32768 + 0.5) * self.res - origin.astype(np.float64)
            if p["inf_range"] >= 0 and float(c @ c) > p["inf_range"] ** 2:
                continue
            if r["state"] == 1 and r["radius"] < 0:
                r["radius"] = radius
                self.inflate(k, 1, radius)
            elif r["state"] != 1 and r["radius"] >= 0:
                self.inflate(k, -1, r["radius"])
                self.rec[k]["radius"] = -1
        for k in touched:
            r = self.rec.get(k)
            if r is None or not r["in_occ"]:
                continue
            if k in self.history:
                self.history.remove(k)
            if r["state"] == 1:
                self.history.append(k)
            elif r["state"] == 0:
                self.remove_from_map(k)
        n_lim = p["n_lim"] if p["n_lim"] >= 0 else 10**18
        while len(self.history) > n_lim:
            self.remove_from_map(self.history[0])

    def occupied(self):
        return {k for k, r in self.rec.items() if r["in_occ"] and r["state"] == 1}

    def inflation(self):
        return {k: r["inf"] for k, r in self.rec.items() if r["inf"] > 0}

    def counts(self):
        return {k: (r["hits"], r["misses"]) for k, r in self.rec.items() if r["in_occ"]}


def key_list(codes):
    return [tuple(int(v) for v in k) for k in morton_decode(np.asarray(codes, dtype=np.int64))]


def as_keys(codes):
    return set(key_list(codes))


def inflation_by_key(m: HashVoxelMap) -> dict:
    counts = m.inflation_counts()
    return dict(zip(key_list(list(counts)), counts.values()))


def brick_table_voxels(m: HashVoxelMap) -> set:
    """The voxels the ray casting's brick table says the occupancy map holds (and the mask row
    that answers for absent bricks is still all zero)."""
    assert m.bmask.shape[0] == m.bkeys.shape[0] + 1 and not m.bmask[-1].any()
    out = set()
    for slot in np.flatnonzero(m.bkeys >= 0):
        b = int(m.bkeys[slot])
        base = ((b >> 26) << 3, ((b >> 13) & 8191) << 3, (b & 8191) << 3)
        bits = np.unpackbits(m.bmask[slot].view(np.uint8), bitorder="little")
        for v in np.flatnonzero(bits).tolist():
            out.add((base[0] + (v & 7), base[1] + ((v >> 3) & 7), base[2] + (v >> 6)))
    return out


def check(m: HashVoxelMap, ref: ReferenceMap):
    assert as_keys(m.occupied_codes()) == ref.occupied()
    state = m.state_arrays()  # each voxel's hit and miss counts since it last entered the map
    keys = key_list(state["leaf_codes"])
    assert dict(zip(keys, zip(state["hm_hits"].tolist(), state["hm_misses"].tolist()))) == ref.counts()
    assert [keys[i] for i in state["hm_history"]] == ref.history  # the order the oldest leave in
    got = inflation_by_key(m)
    assert got == ref.inflation()
    assert brick_table_voxels(m) == as_keys(m.leaves().codes)  # exact: no stale or missing voxel
    assert int(m.meta[K.M_NINF]) == len(got)
    # the inflation bricks: each row's non-zero count is right, no brick left all zero, the
    # freed rows all zero (they are handed out as they are)
    keys = m.ikeys[m.ikeys >= 0]
    rows = keys & K.ROW_MASK
    assert int(m.meta[K.M_IBRICKS]) == keys.shape[0]
    assert ((m.icounts[rows] != 0).sum(axis=1) == m.inz[rows]).all() and (m.inz[rows] > 0).all()
    assert not m.icounts[m.ifree[: int(m.meta[K.M_IFREE_TOP])]].any()
    assert not m.icounts[int(m.meta[K.M_INEXT]):].any()
    # the hash table finds every live record and holds nothing else
    live = np.flatnonzero(m.rec["state"][: int(m.meta[K.M_NEXT])] >= 0)
    assert [K.find(m.tab, m.rec, int(c)) for c in m.rec["code"][live]] == live.tolist()
    assert sorted(m.tab[m.tab >= 0].tolist()) == live.tolist()


@pytest.mark.parametrize("kw", [
    dict(n_lim=-1, d_inf=0.2),
    dict(n_lim=60, d_inf=0.4),
    dict(n_lim=200, d_inf=0.2, d_in=3.0, p_init=0.6),
    dict(n_lim=200, d_inf=0.2, d_in=3.0, p_init=0.6, discretize=0),
    dict(n_lim=-1, d_inf=0.3, inf_range=2.5),
])
def test_every_scan_equals_brute_force(kw):
    m = HashVoxelMap(MapParams(0.1), S, **kw)
    ref = ReferenceMap(0.1, **kw)
    for scan in world_scans(5, 120, seed=31):
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin)
        check(m, ref)
        if kw["n_lim"] >= 0:
            assert len(m.occupied_codes()) <= kw["n_lim"]


def test_a_box_that_leaves_deflates_as_the_brute_force_does():
    """Occupied voxels that misses turn unknown deflate in the scan's inflation step while the
    wall they hid becomes occupied and inflates (that step applies several voxels at once)."""
    g = np.arange(-0.6, 0.61, 0.05)
    yy, zz = [a.ravel() for a in np.meshgrid(g, g)]
    wall = np.stack([np.full(yy.size, 3.02), yy, zz], axis=1).astype(F32)
    shadow = (np.abs(yy) < 0.3) & (np.abs(zz) < 0.3)
    box = wall[shadow] * F32(0.5)  # at x = 1.51, hiding the wall's middle
    origin = np.array([0.01, 0.02, 0.03], F32)
    scans = [Scan(np.concatenate([box, wall[~shadow]]), origin, i) for i in range(2)]
    # the box has gone: the rays reach the wall, which grows by a strip a scan (new voxels each time)
    for i in range(6):
        strip = wall[np.abs(zz - 0.6) < 0.01] + np.array([0, 0, 0.1 * (i + 1)], F32)
        scans.append(Scan(np.concatenate([wall, strip]), origin, 2 + i))
    m = HashVoxelMap(MapParams(0.1), S, n_lim=-1, d_inf=0.2)
    ref = ReferenceMap(0.1, n_lim=-1, d_inf=0.2)
    box_keys = as_keys(morton_encode(np.floor(box.astype(np.float64) / 0.1).astype(np.int64) + 32768))
    mixed = False
    for scan in scans[:2]:
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin)
    for scan in scans[2:]:
        before = as_keys(m.occupied_codes())
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin)
        check(m, ref)
        after, held = as_keys(m.occupied_codes()), as_keys(m.leaves().codes)
        mixed |= bool(((before & box_keys) - after) & held) and bool(after - before)
    assert mixed  # in one scan a box voxel turned unknown (kept in the map) while others became occupied
    assert not as_keys(m.occupied_codes()) & box_keys


def scheduled_as_brute_force(schedule, scans, **kw):
    """The hash map with `schedule` against the brute force told the same changes at the same
    scans, checked after every scan; yields (scan index, map)."""
    m = HashVoxelMap(MapParams(0.1), S, schedule=schedule, **kw)
    ref = ReferenceMap(0.1, **kw)
    for i, scan in enumerate(scans):
        scan.index = i
        ref.p.update({key: value for at, key, value in schedule if at == i})
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin)
        check(m, ref)
        yield i, m


def test_parameter_schedule_takes_effect_mid_stream():
    schedule = [(3, "n_lim", 40), (4, "d_inf", 0.3), (5, "p_init", 0.7), (6, "d_in", 2.0)]
    for i, m in scheduled_as_brute_force(schedule, world_scans(9, 120, seed=5), n_lim=-1, d_inf=0.1):
        if i >= 3:
            assert len(m.occupied_codes()) <= 40


def test_ttl_forgets_voxels_not_seen_recently():

    ttl = 0.25  # 10 Hz stamps: a voxel survives 2 scans without an update
    m = HashVoxelMap(MapParams(0.1), S, ttl=ttl)
    keep_all = HashVoxelMap(MapParams(0.1), S)
    for i, scan in enumerate(world_scans(8, 150, seed=2)):
        scan.index = i
        m.integrate(scan)
        keep_all.integrate(scan)
        now = i * 100_000_000
        live = m._occupancy_map()
        occ = live[live["state"] == 1]
        assert np.all(occ["last"] >= now - int(ttl * 1e9))
    assert 0 < len(m.occupied_codes()) < len(keep_all.occupied_codes())


def test_relayed_map_from_shared_frames_holds_the_occupied_voxels():
    sender = HashVoxelMap(MapParams(0.1), S)
    receiver = HashVoxelMap(MapParams(0.1), S)
    for i, scan in enumerate(world_scans(6, 200, seed=8)):
        scan.index = i
        sender.integrate(scan)
        receiver.integrate_shared(morton_decode(sender.newly_occupied), i * 100_000_000, i)
    sent, got = as_keys(sender.occupied_codes()), as_keys(receiver.occupied_codes())
    assert sent <= got  # every voxel occupied now was shared when it became occupied


@pytest.mark.parametrize("discretize", [1, 0])
def test_snapshot_round_trip(tmp_path, discretize):
    from voxtool.io.mapfile import load_map, save_map

    m = HashVoxelMap(MapParams(0.1), S, n_lim=500, d_inf=0.2, discretize=discretize)
    for i, scan in enumerate(world_scans(4, 150, seed=12)):
        if i == 3:
            m.set_params(d_inf=0.3)  # voxels of radius 2 and 3: the snapshot's header says 3
        m.integrate(scan)
    save_map(tmp_path / "h.vxm", m, {})
    back, snap = load_map(tmp_path / "h.vxm")
    assert back.sphere_radii == {2, 3}
    assert snap.header["backend_params"]["n_lim"] == 500
    assert back.discretize == discretize  # the rays it casts from here on are the same kind
    a, b = m.leaves(), back.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)
    assert np.array_equal(back.occupied_codes(), m.occupied_codes())
    # the reloaded map keeps updating like the original: the same voxels, the same log-odds,
    # the same inflation (with a smaller radius from here on: the loaded voxels keep theirs)
    for x in (m, back):
        x.set_params(d_inf=0.1)
    for scan in world_scans(2, 150, seed=13):
        back.integrate(scan)
        m.integrate(scan)
    a, b = m.leaves(), back.leaves()
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.values, b.values)
    assert back.inflation_counts() == m.inflation_counts() and back.sphere_radii == {1, 2, 3}


@pytest.mark.parametrize("max_range, set_size, discretize", [(-1.0, None, 1), (2.5, None, 1), (-1.0, 64, 1),
                                                             (-1.0, None, 0), (2.5, None, 0)])
def test_filtered_ray_casting_keeps_exactly_the_updates_that_matter(max_range, set_size, discretize):
    """The hash map casts rays against its own brick table; what it keeps must equal OctoMap's
    full update set (scan_updates; of the scan's voxel centres with discretize, as OctoMap's
    computeDiscreteUpdate) cut down to the hits and the misses on occupancy-map voxels, with
    scans big enough to take the two-thread path and a max range that cuts rays. With
    de-duplicating sets too small at first, the casting grows them and starts over."""
    from voxtool.maps.octree import SMALL_SCAN, scan_updates

    params = MapParams(0.1, max_range=max_range)
    m = HashVoxelMap(params, S, n_lim=3000, d_inf=0.2, discretize=discretize)
    if set_size is not None:
        m._set_size = set_size
    kept_misses = 0
    for i, scan in enumerate(world_scans(6, 2 * SMALL_SCAN, seed=40)):  # > SMALL_SCAN voxels too
        scan.index = i
        rays = Scan(discrete_points(scan.points, 0.1), scan.origin) if discretize else scan
        full, _, _ = scan_updates(rays, params)
        in_map = m.leaves().codes
        keep = (full & 1 == 1) | np.isin(full >> 1, in_map)
        got, _ = m._trace(m.prepare(scan).scan)
        np.testing.assert_array_equal(got, full[keep])
        kept_misses += int((got & 1 == 0).sum())
        m.integrate(scan)
    assert len(m.leaves()) > 1000 and kept_misses > 100  # later scans met a populated map
    if set_size is not None:
        assert m._set_size > set_size


@pytest.mark.parametrize("parts", [3, 5, 16])
def test_rays_cast_in_many_runs_merge_to_the_one_run_updates(parts):
    """A machine with more cores casts a scan in more runs of rays (16 cores: 16 runs); this one
    has two, so the kernel is called with more runs than threads here (prange shares them out).
    Merging a third run once failed an assertion of numba's array analysis, on every machine
    with more than two cores."""
    from voxtool.kernels.raycast import balanced_cuts
    from voxtool.maps.octree import SMALL_SCAN

    m = HashVoxelMap(MapParams(0.1), S, n_lim=3000, d_inf=0.2, threads=1)
    scans = world_scans(4, 2 * SMALL_SCAN, seed=41)
    for scan in scans[:3]:
        m.integrate(scan)
    scan = m.prepare(scans[3]).scan
    want, want_steps = m._trace(scan)  # one run: threads=1
    rays = m._discretized(scan)
    seen, slots, out, counts, merged, spare = m._cast_buffers(parts, m._set_size)
    k = K.trace_parts(rays.points, balanced_cuts(rays.points, rays.origin, parts), rays.origin, 0.1, -1.0, m.bkeys,
                      m.bmask, seen, slots, out, counts, merged, spare)
    assert (counts[:, 0] > 0).all() and (want & 1 == 0).sum() > 100  # every run and the map took part
    np.testing.assert_array_equal(merged[:k], want)
    assert counts[:, 1].sum() == want_steps
    assert (seen == K.EMPTY).all()  # the sets are left empty for the next scan


@pytest.mark.parametrize("cores", [2, 8])
def test_schedule_in_the_build_pipeline_equals_scan_by_scan(tmp_path, monkeypatch, cores):
    """In `build` with a third core free, the next scan is prepared on another thread while this
    one is folded in; a scheduled change must still take effect at exactly its scan. On two
    cores the hash map's scans are read and prepared in turn, on the calling thread."""
    import threading

    from test_packets import scene_dir

    from voxtool import pipeline
    from voxtool.pipeline import build
    from voxtool.sources import SourceOptions, open_source

    monkeypatch.setattr(pipeline, "usable_cores", lambda: cores)
    src = scene_dir(tmp_path, n=8, seed=5)
    schedule = [(2, "n_lim", 150), (3, "d_in", 2.5), (5, "d_inf", 0.3), (6, "n_lim", 400)]
    # two threads as on a two-core machine, whatever this one has (a 16-core one failed the read-ahead check)
    piped = HashVoxelMap(MapParams(0.1), S, n_lim=-1, d_inf=0.2, schedule=schedule, threads=2)
    prepare, threads = piped.prepare, set()

    def spy(scan):
        threads.add(threading.current_thread() is threading.main_thread())
        return prepare(scan)

    piped.prepare = spy
    build(open_source(src, SourceOptions()), piped, progress=False)
    assert threads == ({False} if cores > 2 else {True})
    stepped = HashVoxelMap(MapParams(0.1), S, n_lim=-1, d_inf=0.2, schedule=schedule)
    for scan in open_source(src, SourceOptions()).scans:
        stepped.integrate(scan)
    assert np.array_equal(piped.occupied_codes(), stepped.occupied_codes())
    assert piped.inflation_counts() == stepped.inflation_counts()
    assert np.array_equal(piped.state_arrays()["hm_history"], stepped.state_arrays()["hm_history"])
    assert [m["n_occ"] for m in piped.scan_metrics] == [m["n_occ"] for m in stepped.scan_metrics]
    assert piped.scan_metrics[1]["n_occ"] > 150 >= max(m["n_occ"] for m in piped.scan_metrics[2:6])


def test_spheres_are_built_for_the_radii_in_use_and_counted_alike():
    """sphere_offsets lists, per radius asked, the offsets |o| <= r of a brute-force cube (in the
    kernels' order: z fastest) and nothing for the radii not asked; sphere_sizes counts them
    without listing."""
    from voxtool.maps.hashmap import sphere_offsets, sphere_sizes

    offsets, start = sphere_offsets({0, 2, 24})
    sizes = sphere_sizes(24)
    g = np.arange(-24, 25)
    cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    d2 = (cube * cube).sum(axis=1)
    for r in range(25):
        got = offsets[start[r]:start[r + 1]]
        want = cube[d2 <= r * r] if r in (0, 2, 24) else np.zeros((0, 3))
        assert np.array_equal(got, want), r
        assert (d2 <= r * r).sum() == sizes[r]
    assert offsets.dtype == np.int8 and start.shape == (26,)


def test_radii_scheduled_down_and_up_each_keep_their_spheres():
    """Spheres are built as radii come (3, then 1, then 2): a voxel inflated with an earlier
    radius still deflates its own sphere, scan after scan as the brute force."""
    schedule = [(2, "d_inf", 0.1), (4, "d_inf", 0.2)]
    radii = []
    for _, m in scheduled_as_brute_force(schedule, world_scans(7, 120, seed=8), n_lim=80, d_inf=0.3):
        radii.append(sorted(m.sphere_radii))
    assert radii == [[3], [3], [1, 3], [1, 3], [1, 2, 3], [1, 2, 3], [1, 2, 3]]
    assert m.offsets.shape[0] == sum(int(np.diff(m.offset_start)[r]) for r in (1, 2, 3))


def test_snapshot_asking_for_absurd_inflation_is_refused(tmp_path):
    from voxtool.errors import FormatError
    from voxtool.io.mapfile import load_map, save_map
    from voxtool.io.snapshot import read_snapshot, write_snapshot

    m = HashVoxelMap(MapParams(0.1), S, d_inf=0.2)
    for scan in world_scans(2, 150, seed=12):
        m.integrate(scan)
    save_map(tmp_path / "h.vxm", m, {})
    snap = read_snapshot(tmp_path / "h.vxm")
    arrays = dict(snap.arrays)
    arrays["hm_radius"] = np.full_like(arrays["hm_radius"], 64)  # 1.1 M cells per voxel
    write_snapshot(tmp_path / "bad.vxm", snap.header, arrays)
    with pytest.raises(FormatError, match="inflation would touch"):
        load_map(tmp_path / "bad.vxm")


def test_snapshot_whose_inflation_would_fill_too_many_bricks_is_refused(tmp_path, monkeypatch):
    """Few sphere cells can still ask for many bricks: voxels one a brick, each with its own
    row of counts. Loading stops when the counts would pass their bound (a small one here)."""
    import voxtool.maps.hashmap as hashmap_module
    from voxtool.errors import FormatError
    from voxtool.io.mapfile import load_map, save_map

    m = HashVoxelMap(MapParams(0.1), S, d_inf=0.1)  # radius 1: 7 cells, in 1-4 bricks
    rng = np.random.default_rng(4)
    points = (rng.integers(-40, 40, (400, 3)) * 1.6 + 0.05).astype(np.float32)  # 16 voxels apart
    m.integrate(Scan(points, np.zeros(3, np.float32)))
    save_map(tmp_path / "h.vxm", m, {})
    bricks = int(m.meta[K.M_IBRICKS])
    assert bricks > 300  # the spheres lie in bricks of their own
    monkeypatch.setattr(hashmap_module, "MAX_LOAD_INFLATION_BYTES", 64 * 512)
    with pytest.raises(FormatError, match="bytes of inflation counts"):
        load_map(tmp_path / "h.vxm")
    monkeypatch.setattr(hashmap_module, "MAX_LOAD_INFLATION_BYTES", 4 * bricks * 512)
    loaded, _ = load_map(tmp_path / "h.vxm")
    assert inflation_by_key(loaded) == inflation_by_key(m)


def test_more_records_than_the_table_addresses_is_a_clear_error(monkeypatch):
    from voxtool.errors import ParameterError

    m = HashVoxelMap(MapParams(0.1), S, d_inf=0.2)
    monkeypatch.setattr(K, "MAX_RECORDS", 500)
    with pytest.raises(ParameterError, match="exceed the 500 "):
        for scan in world_scans(4, 400, seed=3):
            m.integrate(scan)


@pytest.mark.parametrize("options, message", [
    ({"d_inf": math.nan}, "d_inf=nan must be a finite number"),
    ({"ttl": math.inf}, "ttl=inf must be a finite number (a negative one means unlimited)"),
    ({"d_in": math.nan}, "d_in=nan must be a finite number"),
    ({"p_init": 1.0}, "p_init=1.0 must lie in (0, 1)"),
    ({"d_inf": 6.5}, "d_inf=6.5 must lie in [0, 64 voxels]"),
    ({"p_free": 0.6}, "p_free=0.6 must lie between 0 and the occupancy threshold 0.5"),
    ({"rate_hz": 0.0}, "rate_hz=0.0 must be a positive number"),
    ({"schedule": [(3, "ttl", math.nan)]}, "ttl=nan must be a finite number"),
    ({"schedule": [(3, "radius", 1.0)]}, "no parameter 'radius'"),
])
def test_parameter_values_are_checked_up_front(options, message):
    """Every value, scheduled ones included, is refused before the first scan (NaN compares
    false with every bound, so each check is written to fail on it)."""
    from voxtool.errors import ParameterError

    with pytest.raises(ParameterError) as err:
        HashVoxelMap(MapParams(0.1), S, **options)
    assert message in str(err.value)


def test_a_refused_parameter_change_leaves_the_parameters_as_they_were():
    from voxtool.errors import ParameterError

    m = HashVoxelMap(MapParams(0.1), S, n_lim=100, d_inf=0.2)
    with pytest.raises(ParameterError):
        m.set_params(n_lim=50, d_inf=math.nan)
    assert m.values["n_lim"] == 100 and m.values["d_inf"] == 0.2


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_a_child_forked_after_a_parallel_cast_casts_the_same_map():
    """GNU OpenMP is not fork-safe: numba ends a forked child that launches a parallel region
    after its parent did. Such a child must cast on its own thread and build the same map."""
    from test_octree import forked_child_builds_the_same_map

    from voxtool.maps.octree import SMALL_SCAN

    scans = world_scans(3, 2 * SMALL_SCAN, seed=7)
    assert forked_child_builds_the_same_map(lambda: HashVoxelMap(MapParams(0.1), S, n_lim=2000, d_inf=0.2), scans) == 0


def test_discretized_rays_match_octomap_discretize():
    """discretize=1 casts OctoMap's computeDiscreteUpdate rays (insertPointCloud with
    discretize=true): an octree fed the kernel's voxel centres equals the real OctoMap's tree
    built with discretize, leaf for leaf, and the centres equal the literal reference's."""
    pyoctomap = pytest.importorskip("pyoctomap")
    from test_octree import finest_values

    from voxtool.maps.octree import OctreeMap

    tree = pyoctomap.OcTree(0.1)
    ours = OctreeMap(MapParams(0.1), S)
    m = HashVoxelMap(MapParams(0.1), S)
    for scan in world_scans(4, 1500, seed=9):
        centres = m._discretized(scan)
        np.testing.assert_array_equal(centres.points, discrete_points(scan.points, 0.1))
        assert centres.points.shape[0] < scan.points.shape[0]  # points shared end voxels
        ours.integrate(centres)
        tree.insertPointCloud(scan.points.astype(np.float64), scan.origin.astype(np.float64), discretize=True)
    values = finest_values(ours)
    count = 0
    for leaf in tree.begin_leafs():
        c = np.array(leaf.getCoordinate())
        for key in _finest_keys(c, leaf.getSize(), 0.1):
            assert values.pop(key) == pytest.approx(tree.search(c).getLogOdds(), abs=0)
            count += 1
    assert count > 1000 and not values


def _finest_keys(centre, size, res):
    """The finest voxels of an OctoMap leaf (a pruned leaf covers several)."""
    n = int(round(size / res))
    lo = np.floor((centre - size / 2) / res + 0.5).astype(np.int64) + 32768
    g = np.arange(n)
    return [(int(lo[0] + i), int(lo[1] + j), int(lo[2] + k)) for i in g for j in g for k in g]


def test_the_golden_snapshot_loads_its_voxels_history_and_inflation():
    """formats/vectors/snapshot_hashmap.vxm (formats/snapshot.md, `hashmap` arrays): loading
    rebuilds the inflation map from the stored radii (each voxel's sphere, brute force), and
    the map writes back the arrays it was loaded from."""
    from pathlib import Path

    from voxtool.io.mapfile import load_map

    m, snap = load_map(Path(__file__).resolve().parents[1] / "formats" / "vectors" / "snapshot_hashmap.vxm")
    keys = key_list(snap.arrays["leaf_codes"])
    want: dict = {}
    for k, radius in zip(keys, snap.arrays["hm_radius"].tolist()):
        for cell in (ReferenceMap(0.1).sphere(k, radius) if radius >= 0 else []):
            want[cell] = want.get(cell, 0) + 1
    got = inflation_by_key(m)
    # spheres of radius 2 (33 voxels) and 1 (7) two voxels apart along x share two voxels, counted twice
    assert got == want and len(want) == 33 + 7 - 2 and sorted(want.values())[-3:] == [1, 2, 2]
    state = m.state_arrays()
    for name, stored in snap.arrays.items():
        np.testing.assert_array_equal(state[name], stored)
    assert as_keys(m.occupied_codes()) == {keys[0], keys[2]}  # the undecided voxel is kept, not occupied


@pytest.mark.parametrize("d_inf, dtype, peak", [(0.3, np.uint8, 123), (0.4, np.int32, 257)])
def test_a_solid_block_reaches_the_largest_count_its_counts_hold(d_inf, dtype, peak):
    """Inflation counts are one byte up to radius 3 (K.count_dtype): a voxel's count is at most
    one sphere's cells, reached inside a solid block of occupied voxels (123 at radius 3, 257
    at radius 4, which takes int32)."""
    g = (np.arange(9) + 0.5) * 0.1 + 1.0  # the centres of 9 x 9 x 9 voxels
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3).astype(F32)
    m = HashVoxelMap(MapParams(0.1), S, d_inf=d_inf)
    ref = ReferenceMap(0.1, d_inf=d_inf)
    for _ in range(2):
        m.integrate(Scan(block, np.zeros(3, F32)))
        ref.integrate(block, np.zeros(3, F32))
        check(m, ref)
    assert m.icounts.dtype == dtype and max(m.inflation_counts().values()) == peak


def test_a_larger_radius_mid_stream_widens_the_counts():
    """A schedule raising d_inf past 3 voxels turns one-byte counts into int32 ones, counts kept."""
    m = HashVoxelMap(MapParams(0.1), S, n_lim=-1, d_inf=0.2, schedule=[(2, "d_inf", 0.4)])
    ref = ReferenceMap(0.1, n_lim=-1, d_inf=0.2)
    for i, scan in enumerate(world_scans(3, 60, seed=7)):
        scan.index = i
        if i == 2:
            ref.p["d_inf"] = 0.4
        m.integrate(scan)
        ref.integrate(scan.points, scan.origin)
        check(m, ref)
        assert m.icounts.dtype == (np.uint8 if i < 2 else np.int32) and m.n_inflated() > 0  # counts carried over
