"""Ray integration of one scan, bit-exact with OctoMap 1.10 `insertPointCloud`.

OctoMap's float choices are reproduced on purpose: points, ray direction and length are float32
(`point3d`), the DDA's tMax/tDelta are float64, and the voxel border adds a float32-rounded
half-resolution. The result is the scan's set of updated voxels: endpoints (occupied) win over
voxels that rays pass through (free), each voxel once per scan.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numba.cpython.unsafe.numbers import trailing_zeros

from voxtool.kernels.morton import morton3

_HASH_MULT = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)


@njit(cache=True, inline="always")
def _coord_key(c, res_factor):
    # OctoMap coordToKey: floor(resolution_factor * double(coord)) + 32768
    return np.int64(np.floor(res_factor * np.float64(c))) + 32768


BRICK_BITS = 9  # a brick is the 8x8x8 voxels sharing code >> 9; its voxels are Morton-ordered inside


@njit(cache=True, inline="always")
def lowest_bit(x):
    """Index of the lowest set bit of x (64 for 0): LLVM's count of trailing zeros, one
    instruction (the de Bruijn multiply and table load it replaces cost the update of a scan's
    brick masks, kernels.octree.apply_masks, a fifth of its time: docs/design/octree.md)."""
    return trailing_zeros(x)


@njit(cache=True, inline="always")
def _brick_slot(brick, mask):
    return ((brick * _HASH_MULT) >> 24) & mask


class BrickBuffers:
    """Reusable per-thread brick storage for `scan_bricks` (grown by the caller on overflow)."""

    def __init__(self, capacity: int = 1 << 15) -> None:
        self.tab = np.full((capacity * 2, 2), -1, dtype=np.int64)  # (brick code, brick index)
        self.touched = np.zeros((capacity, 8), dtype=np.int64)
        self.occ = np.zeros((capacity, 8), dtype=np.int64)
        self.bricks = np.empty(capacity, dtype=np.int64)

    def reset(self, used: int) -> None:
        if used * 16 < self.tab.shape[0]:
            # few bricks: clear just their slots (probe chains start at their home slot)
            reset_slots(self.tab, self.bricks[:used])
        else:
            self.tab.fill(-1)
        self.touched[:used] = 0
        self.occ[:used] = 0


@njit(cache=True, nogil=True)
def reset_slots(tab, bricks):
    """Clear the table entries of these bricks (and the probe runs they sit in)."""
    tmask = tab.shape[0] - 1
    for i in range(bricks.shape[0]):
        s = _brick_slot(bricks[i], tmask)
        while tab[s, 1] != -1:
            tab[s, 0] = -1
            tab[s, 1] = -1
            s = (s + 1) & tmask


@njit(cache=True, inline="always")
def ray_setup(points, i, origin, okx, oky, okz, resolution, max_range):
    """Ray i of a scan from `origin` (key okx, oky, okz) as OctoMap casts it: computeUpdate's
    max-range cut (the ray ends at max_range and marks no hit) and computeRayKeys'
    initialisation (float32 direction and length, float64 tMax / tDelta). Returns (cut, end key,
    tMax x/y/z, tDelta x/y/z, step signs x/y/z, length); an axis the ray does not move along has
    tMax = tDelta = the largest float64, as has every axis of a ray that ends in its origin's voxel."""
    res_factor = 1.0 / resolution
    ox, oy, oz = origin[0], origin[1], origin[2]
    ex, ey, ez = points[i, 0], points[i, 1], points[i, 2]
    dx, dy, dz = ex - ox, ey - oy, ez - oz
    cut = False
    if max_range >= 0.0:
        norm = np.sqrt(np.float64(dx * dx + dy * dy + dz * dz))
        if norm > max_range:
            cut = True
            ln = np.float32(norm)
            mr32 = np.float32(max_range)
            ex, ey, ez = ox + (dx / ln) * mr32, oy + (dy / ln) * mr32, oz + (dz / ln) * mr32
            dx, dy, dz = ex - ox, ey - oy, ez - oz
    ekx = _coord_key(ex, res_factor)
    eky = _coord_key(ey, res_factor)
    ekz = _coord_key(ez, res_factor)
    big = 1.7976931348623157e308
    if ekx == okx and eky == oky and ekz == okz:  # no voxel to pass through (and no direction)
        return cut, ekx, eky, ekz, big, big, big, big, big, big, 0, 0, 0, 0.0
    length = np.float32(np.sqrt(np.float64(dx * dx + dy * dy + dz * dz)))
    fx, fy, fz = dx / length, dy / length, dz / length
    sx = 1 if fx > 0.0 else (-1 if fx < 0.0 else 0)
    sy = 1 if fy > 0.0 else (-1 if fy < 0.0 else 0)
    sz = 1 if fz > 0.0 else (-1 if fz < 0.0 else 0)
    half = np.float64(np.float32(resolution * 0.5))
    tx = ty = tz = big
    ux = uy = uz = big
    if sx != 0:
        tx = ((np.float64(okx - 32768) + 0.5) * resolution + sx * half - np.float64(ox)) / np.float64(fx)
        ux = resolution / abs(np.float64(fx))
    if sy != 0:
        ty = ((np.float64(oky - 32768) + 0.5) * resolution + sy * half - np.float64(oy)) / np.float64(fy)
        uy = resolution / abs(np.float64(fy))
    if sz != 0:
        tz = ((np.float64(okz - 32768) + 0.5) * resolution + sz * half - np.float64(oz)) / np.float64(fz)
        uz = resolution / abs(np.float64(fz))
    return cut, ekx, eky, ekz, tx, ty, tz, ux, uy, uz, sx, sy, sz, np.float64(length)


_X9, _Y9, _Z9 = 0x49, 0x92, 0x124  # the x, y and z bits of a 9-bit in-brick Morton index


@njit(cache=True, inline="always")
def _morton_step(v, m, up):
    """Morton index v with the axis whose bits are `m` moved one voxel (+1 when up, else -1),
    wrapping inside the brick: dilated-integer arithmetic, no de-interleaving."""
    if up:
        return (v & ~m) | (((v | ~m) + 1) & m)
    return (v & ~m) | (((v & m) - 1) & m)


@njit(cache=True, inline="always")
def _in_brick(kx, ky, kz):
    """Morton index (9 bits) of key (kx, ky, kz) inside its 8x8x8 brick."""
    return morton3(kx & 7, ky & 7, kz & 7)


@njit(cache=True, inline="always")
def _brick_of(kx, ky, kz, tab, bricks, n_bricks, tmask):
    """Index of the brick holding key (kx, ky, kz), added when new: (index, brick count), index
    -1 when the buffers are full."""
    return _brick_index(morton3(kx >> 3, ky >> 3, kz >> 3), tab, bricks, n_bricks, tmask)


# the x, y and z bits of a brick code (13 bits an axis): a ray steps its brick code with
# dilated arithmetic too, instead of interleaving three keys at every brick it enters
_BRICK_X = 0x249249249249 & ((1 << 39) - 1)
_BRICK_Y = _BRICK_X << 1
_BRICK_Z = _BRICK_X << 2


@njit(cache=True, inline="always")
def _brick_index(brick, tab, bricks, n_bricks, tmask):
    """Index of brick code `brick` in the scan's brick table, added when new: (index, brick
    count), index -1 when the buffers are full."""
    s = _brick_slot(brick, tmask)
    while True:
        b = tab[s, 1]
        if b == -1:
            if n_bricks == bricks.shape[0]:
                return -1, n_bricks
            bricks[n_bricks] = brick
            tab[s, 0] = brick
            tab[s, 1] = n_bricks
            return n_bricks, n_bricks + 1
        if tab[s, 0] == brick:
            return b, n_bricks
        s = (s + 1) & tmask


@njit(cache=True, inline="always")
def _near_row(near_keys, brick, mask):
    """Row of `brick` in a near-hit table (kernels.clean.near_hits_table), -1 when absent."""
    s = ((brick * _HASH_MULT) >> 20) & mask
    while True:
        k = near_keys[s]
        if k == brick:
            return s
        if k == -1:
            return -1
        s = (s + 1) & mask


def _make_scan_bricks(stop_near_hits: bool):
    """scan_bricks, or (stop_near_hits, a compile-time constant) its variant for `clean`'s void
    evidence: no endpoints, and each ray stops at the first voxel of the near-hit table."""

    @njit(cache=True, nogil=True)
    def scan_bricks(points, origin, resolution, max_range, tab, touched, occ, bricks, near_keys, near_bits):
        """Voxels updated by one scan, as bricks of 8x8x8 voxels, into caller-owned buffers.

        Returns (n_bricks, steps); n_bricks = -1 when the buffers are too small (the caller grows
        them and calls again). Per brick: its code (Morton code >> 9) and two 512-bit masks
        (8 x int64) of the voxels touched by the scan and of those holding an endpoint (occupied
        wins over free, whatever the order rays come in). points: (N, 3) float32 world
        coordinates; origin: (3,) float32; max_range < 0 means unlimited. Coordinates must already
        be checked to lie in key range. near_keys / near_bits: the near-hit table (only read by
        the stopping variant).
        The DDA state lives in scalars (registers), the in-brick Morton index and the brick code
        are stepped with dilated arithmetic, and the brick table is consulted only when a step
        crosses into another brick, so a step is a few compares and one OR into a mask that stays
        in cache.
        """
        tmask = tab.shape[0] - 1
        nmask = near_keys.shape[0] - 1
        res_factor = 1.0 / resolution
        okx = _coord_key(origin[0], res_factor)
        oky = _coord_key(origin[1], res_factor)
        okz = _coord_key(origin[2], res_factor)
        origin_brick = morton3(okx >> 3, oky >> 3, okz >> 3)
        n_bricks = 0
        steps = 0
        for i in range(points.shape[0]):
            cut, ekx, eky, ekz, tx, ty, tz, ux, uy, uz, sx, sy, sz, length64 = ray_setup(
                points, i, origin, okx, oky, okz, resolution, max_range)
            if not cut and not stop_near_hits:  # a ray cut at max range marks no endpoint (OctoMap computeUpdate)
                b, n_bricks = _brick_of(ekx, eky, ekz, tab, bricks, n_bricks, tmask)
                if b < 0:
                    return -1, steps
                v = _in_brick(ekx, eky, ekz)
                bit = np.int64(1) << (v & 63)
                touched[b, v >> 6] |= bit
                occ[b, v >> 6] |= bit
            if ekx == okx and eky == oky and ekz == okz:
                continue
            # free voxels from the origin's up to (not including) the end voxel (computeRayKeys)
            kx, ky, kz = okx, oky, okz
            bc = origin_brick
            b, n_bricks = _brick_index(bc, tab, bricks, n_bricks, tmask)
            if b < 0:
                return -1, steps
            near = -1
            if stop_near_hits:
                near = _near_row(near_keys, bc, nmask)
            v = _in_brick(kx, ky, kz)
            bx = 0 if sx > 0 else 7  # the key & 7 that starts a new brick when stepping along x
            by = 0 if sy > 0 else 7
            bz = 0 if sz > 0 else 7
            # every step moves one axis one voxel towards the end key, so the ray can reach it only
            # after exactly this many steps (an axis that overshoots never comes back)
            to_end = abs(ekx - okx) + abs(eky - oky) + abs(ekz - okz)
            while True:
                if stop_near_hits and near >= 0 and (near_bits[near, v >> 6] >> (v & 63)) & 1:
                    break
                if not stop_near_hits or near < 0 or not (near_bits[near, 8 + (v >> 6)] >> (v & 63)) & 1:
                    touched[b, v >> 6] |= np.int64(1) << (v & 63)
                steps += 1
                # advance (Amanatides-Woo with OctoMap's tie-breaking and stop rules)
                crossed = False
                if tx < ty:
                    if tx < tz:
                        kx += sx
                        tx += ux
                        v = _morton_step(v, _X9, sx > 0)
                        if (kx & 7) == bx:
                            bc = _morton_step(bc, _BRICK_X, sx > 0)
                            crossed = True
                    else:
                        kz += sz
                        tz += uz
                        v = _morton_step(v, _Z9, sz > 0)
                        if (kz & 7) == bz:
                            bc = _morton_step(bc, _BRICK_Z, sz > 0)
                            crossed = True
                else:
                    if ty < tz:
                        ky += sy
                        ty += uy
                        v = _morton_step(v, _Y9, sy > 0)
                        if (ky & 7) == by:
                            bc = _morton_step(bc, _BRICK_Y, sy > 0)
                            crossed = True
                    else:
                        kz += sz
                        tz += uz
                        v = _morton_step(v, _Z9, sz > 0)
                        if (kz & 7) == bz:
                            bc = _morton_step(bc, _BRICK_Z, sz > 0)
                            crossed = True
                to_end -= 1
                if to_end == 0 and kx == ekx and ky == eky and kz == ekz:
                    break
                if min(tx, min(ty, tz)) > length64:
                    break
                if crossed:
                    b, n_bricks = _brick_index(bc, tab, bricks, n_bricks, tmask)
                    if b < 0:
                        return -1, steps
                    if stop_near_hits:
                        near = _near_row(near_keys, bc, nmask)
        return n_bricks, steps

    return scan_bricks


scan_bricks = _make_scan_bricks(False)
# clean's void evidence (voxtool.clean): the free voxels of each ray up to the first voxel within
# d_s of one of the scan's hits, as DUFOMap casts them (its ray_passthrough_hits = false)
scan_bricks_to_near_hits = _make_scan_bricks(True)
NO_NEAR_HITS = (np.full(1, -1, dtype=np.int64), np.zeros((1, 16), dtype=np.int64))


@njit(cache=True, nogil=True)
def balanced_cuts(points, origin, parts):
    """Indices cutting a scan's rays into `parts` runs of about equal DDA work: a ray's step
    count is the L1 length of its key difference, so the L1 length of the ray is its weight
    (LiDAR point order is not uniform: half a Livox scan's points can take 20 % more steps
    than the other half). cuts[0] = 0, cuts[parts] = len(points), never decreasing."""
    n = points.shape[0]
    running = np.empty(n)  # summed ray lengths up to and including ray i
    acc = 0.0
    for i in range(n):
        acc += abs(points[i, 0] - origin[0]) + abs(points[i, 1] - origin[1]) + abs(points[i, 2] - origin[2])
        running[i] = acc
    cuts = np.empty(parts + 1, dtype=np.int64)
    cuts[0] = 0
    j = 0
    for k in range(1, parts):
        while j < n and running[j] < acc * k / parts:
            j += 1
        cuts[k] = min(j + 1, n)
    cuts[parts] = n
    return cuts


_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@njit(cache=True, inline="always")
def _popcount(x):
    u = np.uint64(x)
    u = u - ((u >> np.uint64(1)) & _M1)
    u = (u & _M2) + ((u >> np.uint64(2)) & _M2)
    u = (u + (u >> np.uint64(4))) & _M4
    return np.int64((u * _H01) >> np.uint64(56))


@njit(cache=True, nogil=True)
def brick_voxels(touched, order, firsts, k0, k1, counts):
    """counts[k] = how many voxels distinct brick k holds, for k in k0..k1: its entries are
    order[firsts[k]:firsts[k + 1]] (one brick filled by several threads), masks OR-ed."""
    for k in range(k0, k1):
        total = 0
        for w in range(8):
            x = np.int64(0)
            for j in range(firsts[k], firsts[k + 1]):
                x |= touched[order[j], w]
            total += _popcount(x)
        counts[k] = total


@njit(cache=True, inline="always")
def brick_word(touched, occ, order, first, end, w):
    """Word w of a distinct brick's touched and endpoint masks: the OR of its rows
    order[first:end] (a brick several ray runs filled has several)."""
    x = np.int64(0)
    o = np.int64(0)
    for j in range(first, end):
        x |= touched[order[j], w]
        o |= occ[order[j], w]
    return x, o


@njit(cache=True, nogil=True)
def expand_bricks(codes, touched, occ, order, firsts, k0, k1, starts, out):
    """The voxels of distinct bricks k0..k1 (brick k: code codes[k], entries
    order[firsts[k]:firsts[k + 1]]) as Morton-sorted updates code << 1 | occupied, brick k's at
    out[starts[k]:]: a voxel is occupied when any endpoint of the scan fell in it."""
    for k in range(k0, k1):
        n = starts[k]
        base = codes[k] << BRICK_BITS
        for w in range(8):
            x, o = brick_word(touched, occ, order, firsts[k], firsts[k + 1], w)
            word = (base | (w << 6)) << 1
            while x != 0:
                tz = lowest_bit(x)
                out[n] = word | (tz << 1) | ((o >> tz) & 1)
                n += 1
                x &= x - 1


@njit(cache=True, nogil=True)
def ray_signatures(points, origin, resolution, max_range, out_end, out_sig):
    """Per ray: Morton code of its end voxel (<< 1 | cut) and a 64-bit signature of its voxel
    path (the DDA of scan_bricks, keys hashed in order), for merging rays with identical paths
    (TinyOctoMap Sec. IV-B). Rays whose end voxel is the origin voxel get signature 0."""
    res_factor = 1.0 / resolution
    okx = _coord_key(origin[0], res_factor)
    oky = _coord_key(origin[1], res_factor)
    okz = _coord_key(origin[2], res_factor)
    for i in range(points.shape[0]):
        cut, ekx, eky, ekz, tx, ty, tz, ux, uy, uz, sx, sy, sz, length64 = ray_setup(
            points, i, origin, okx, oky, okz, resolution, max_range)
        # a cut ray marks no endpoint: never merge it with a hit
        out_end[i] = (morton3(ekx, eky, ekz) << 1) | np.int64(cut)
        sig = np.int64(0)
        if not (ekx == okx and eky == oky and ekz == okz):
            kx, ky, kz = okx, oky, okz
            to_end = abs(ekx - okx) + abs(eky - oky) + abs(ekz - okz)
            while True:
                sig = (sig ^ morton3(kx, ky, kz)) * _HASH_MULT + 0x632BE59BD9B4E019
                if tx < ty:
                    if tx < tz:
                        kx += sx
                        tx += ux
                    else:
                        kz += sz
                        tz += uz
                else:
                    if ty < tz:
                        ky += sy
                        ty += uy
                    else:
                        kz += sz
                        tz += uz
                to_end -= 1
                if to_end == 0 and kx == ekx and ky == eky and kz == ekz:
                    break
                if min(tx, min(ty, tz)) > length64:
                    break
        out_sig[i] = sig
