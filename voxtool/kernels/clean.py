"""Kernels of `voxtool clean` (voxtool.clean): void evidence kept away from a scan's hits, and
the neighbours a point's voxel is judged with."""

from __future__ import annotations

import numpy as np
from numba import njit

from voxtool.kernels.morton import compact16, morton3
from voxtool.kernels.raycast import lowest_bit

_HASH_MULT = np.int64(-7046029254386353131)  # 0x9E3779B97F4A7C15 as int64 (Fibonacci hashing)


@njit(cache=True, inline="always")
def _slot(code, mask):
    return ((code * _HASH_MULT) >> 20) & mask


@njit(cache=True, inline="always")
def _moved(code, dx, dy, dz):
    """The Morton code of the voxel `code` moved by (dx, dy, dz) voxels; -1 outside the key range."""
    x = compact16(code) + dx
    y = compact16(code >> 1) + dy
    z = compact16(code >> 2) + dz
    if x < 0 or y < 0 or z < 0 or x > 0xFFFF or y > 0xFFFF or z > 0xFFFF:
        return np.int64(-1)
    return morton3(x, y, z)


@njit(cache=True, inline="always")
def _brick_row(keys, brick, mask, insert):
    """(row of `brick` in the open-addressing table, whether this call inserted it); row -1:
    absent and not inserted, -2: the table is full."""
    s = _slot(brick, mask)
    for _ in range(keys.shape[0]):
        k = keys[s]
        if k == brick:
            return s, False
        if k == -1:
            if not insert:
                return -1, False
            keys[s] = brick
            return s, True
        s = (s + 1) & mask
    return -2, False


SEGMENT_SAMPLES_PER_VOXEL = 4  # samples along a hit's segment per voxel edge
_XYZ = np.arange(512, dtype=np.int64)
# the 9-bit Morton index inside a brick of x + 8 y + 64 z (x in bits 0, 3, 6: kernels.morton)
IN_BRICK = sum(((_XYZ >> (3 * a + b)) & 1) << (3 * b + a) for a in range(3) for b in range(3))


BALL_TABLE_RADIUS = 8  # a ball this wide reaches at most the 26 bricks around a voxel's own


@njit(cache=True, nogil=True)
def ball_brick_masks(offsets):
    """What a ball (`offsets`, within BALL_TABLE_RADIUS voxels) marks around each voxel of a
    brick, so that near_hits_table ORs whole words instead of setting bits one offset at a time:
    masks[p, nb, w], the word w of brick nb's skip mask for the ball around in-brick voxel p
    (Morton index), nb = (dx + 1) + 3 (dy + 1) + 9 (dz + 1) for the brick dx, dy, dz away;
    lists[p, :counts[p]], the bricks nb that it marks at all."""
    masks = np.zeros((512, 27, 8), dtype=np.int64)
    for p in range(512):
        x, y, z = compact16(p), compact16(p >> 1), compact16(p >> 2)
        for j in range(offsets.shape[0]):
            nx, ny, nz = x + offsets[j, 0], y + offsets[j, 1], z + offsets[j, 2]
            nb = ((nx >> 3) + 1) + 3 * ((ny >> 3) + 1) + 9 * ((nz >> 3) + 1)
            inner = IN_BRICK[(nx & 7) | ((ny & 7) << 3) | ((nz & 7) << 6)]
            masks[p, nb, inner >> 6] |= np.int64(1) << (inner & 63)
    lists = np.zeros((512, 27), dtype=np.int64)
    counts = np.zeros(512, dtype=np.int64)
    for p in range(512):
        for nb in range(27):
            for w in range(8):
                if masks[p, nb, w] != 0:
                    lists[p, counts[p]] = nb
                    counts[p] += 1
                    break
    return masks, lists, counts


NO_BALL_TABLE = (np.zeros((0, 27, 8), dtype=np.int64), np.zeros((0, 27), dtype=np.int64), np.zeros(0, dtype=np.int64))


@njit(cache=True, nogil=True)
def near_hits_table(points, hits, origin, resolution, length, offsets, ball_masks, ball_lists, ball_counts,
                    keys, bits):
    """The two voxel sets near a scan's hits that clean's rays respect, as bits of 8x8x8-brick
    masks in one hash table (`keys`: brick codes, -1 empty, a power-of-two length; `bits`:
    (len(keys), 16) int64, zero):
    - words 0-7, *stop*: the voxels of the last `length` metres of every ray (from the sensor
      origin to each of `points`, sampled 4 times a voxel edge, the point's voxel included).
      A ray stops at the first (DUFOMap's hits, inflated backwards along the ray).
    - words 8-15, *skip*: the voxels within the `offsets` ball of every hit voxel (`hits`: their
      Morton codes, sorted). A ray passes them without void evidence: a porous surface such as
      foliage, seen through between the hits of one scan, stays unvoided.
    ball_masks / ball_lists / ball_counts: ball_brick_masks(offsets) (the balls as whole words,
    3-5x faster), or NO_BALL_TABLE for a ball wider than BALL_TABLE_RADIUS (one bit an offset).
    Points must lie in key range. Returns False when the table is too small (the caller
    doubles it)."""
    mask = keys.shape[0] - 1
    used = 0
    last_brick = np.int64(-1)
    row = -1
    res_factor = 1.0 / resolution
    ox, oy, oz = np.float64(origin[0]), np.float64(origin[1]), np.float64(origin[2])
    for i in range(points.shape[0]):
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        dx, dy, dz = px - ox, py - oy, pz - oz
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        seg = min(length, dist)
        n = int(np.ceil(seg * res_factor * SEGMENT_SAMPLES_PER_VOXEL))
        lx = ly = lz = np.int64(-1)
        per = 0.0 if n == 0 or dist == 0.0 else 1.0 / (n * dist)  # one division a ray, not a sample
        for k in range(n + 1):
            f = seg * k * per  # seg * k / n metres back
            kx = np.int64(np.floor(res_factor * (px - dx * f))) + 32768
            ky = np.int64(np.floor(res_factor * (py - dy * f))) + 32768
            kz = np.int64(np.floor(res_factor * (pz - dz * f))) + 32768
            if kx == lx and ky == ly and kz == lz:  # most samples fall in the voxel of the one before
                continue
            lx, ly, lz = kx, ky, kz
            if kx < 0 or ky < 0 or kz < 0 or kx > 0xFFFF or ky > 0xFFFF or kz > 0xFFFF:
                continue
            code = morton3(kx, ky, kz)
            if code >> 9 != last_brick:
                last_brick = code >> 9
                row, new = _brick_row(keys, last_brick, mask, True)
                used += new
                if row < 0 or used * 2 > keys.shape[0]:
                    return False
            bits[row, (code & 511) >> 6] |= np.int64(1) << (code & 63)
    # the balls: hits come Morton-sorted, so runs of them share a brick; the rows of the 27 bricks
    # around the current one are remembered (most of a ball's marks then cost no look-up)
    rows = np.empty(27, dtype=np.int64)
    hit_brick = np.int64(-1)
    if ball_masks.shape[0] == 512:
        bx = by = bz = np.int64(0)
        for i in range(hits.shape[0]):
            code = hits[i]
            if code >> 9 != hit_brick:
                hit_brick = code >> 9
                rows[:] = -2
                bx, by, bz = compact16(hit_brick), compact16(hit_brick >> 1), compact16(hit_brick >> 2)
            p = code & 511
            for j in range(ball_counts[p]):
                nb = ball_lists[p, j]
                row = rows[nb]
                if row == -2:
                    nx, ny, nz = bx + nb % 3 - 1, by + (nb // 3) % 3 - 1, bz + nb // 9 - 1
                    if nx < 0 or ny < 0 or nz < 0 or nx > 0x1FFF or ny > 0x1FFF or nz > 0x1FFF:
                        rows[nb] = -3  # a brick outside the key range: nothing to mark
                        continue
                    row, new = _brick_row(keys, morton3(nx, ny, nz), mask, True)
                    used += new
                    if row < 0 or used * 2 > keys.shape[0]:
                        return False
                    rows[nb] = row
                elif row == -3:
                    continue
                for w in range(8):
                    bits[row, 8 + w] |= ball_masks[p, nb, w]
        return True
    for i in range(hits.shape[0]):
        code = hits[i]
        if code >> 9 != hit_brick:
            hit_brick = code >> 9
            rows[:] = -2
        kx, ky, kz = compact16(code), compact16(code >> 1), compact16(code >> 2)
        bx, by, bz = kx >> 3, ky >> 3, kz >> 3
        for j in range(offsets.shape[0]):
            nx, ny, nz = kx + offsets[j, 0], ky + offsets[j, 1], kz + offsets[j, 2]
            if nx < 0 or ny < 0 or nz < 0 or nx > 0xFFFF or ny > 0xFFFF or nz > 0xFFFF:
                continue
            d = ((nx >> 3) - bx + 1) + 3 * ((ny >> 3) - by + 1) + 9 * ((nz >> 3) - bz + 1)
            row = rows[d]
            if row == -2:
                row, new = _brick_row(keys, morton3(nx >> 3, ny >> 3, nz >> 3), mask, True)
                used += new
                if row < 0 or used * 2 > keys.shape[0]:
                    return False
                rows[d] = row
            inner = IN_BRICK[(nx & 7) | ((ny & 7) << 3) | ((nz & 7) << 6)]
            bits[row, 8 + (inner >> 6)] |= np.int64(1) << (inner & 63)
    return True


@njit(cache=True, nogil=True)
def or_bricks(keys, bits, bricks, masks):
    """OR 512-bit brick masks (Morton order within the brick) into a table of bricks (`keys`:
    brick codes, -1 empty; `bits`: (len(keys), 8) int64). Returns (bricks added, bits in the
    masks), or (-1, 0) when the table filled up (the caller grows it and calls again)."""
    mask = keys.shape[0] - 1
    added = 0
    voxels = 0
    for i in range(bricks.shape[0]):
        row, new = _brick_row(keys, bricks[i], mask, True)
        if row < 0:
            return -1, 0
        added += new
        for w in range(8):
            x = masks[i, w]
            bits[row, w] |= x
            while x != 0:  # Kernighan's count of the set bits
                x &= x - 1
                voxels += 1
    return added, voxels


@njit(cache=True, nogil=True)
def or_codes(keys, bits, bricks, codes):
    """Set the bits of finest-level voxels (Morton codes) in a table of bricks (`keys`: brick
    codes, -1 empty; `bits`: (len(keys), 8) int64) holding `bricks` bricks. Returns the bricks
    it holds after, or -1 when it would pass half full (the caller grows it and calls again:
    the bits set so far stay)."""
    mask = keys.shape[0] - 1
    last = np.int64(-1)
    row = np.int64(-1)
    for i in range(codes.shape[0]):
        code = codes[i]
        if code >> 9 != last:
            last = code >> 9
            row, new = _brick_row(keys, last, mask, True)
            bricks += new
            if row < 0 or bricks * 2 > keys.shape[0]:
                return -1
        bits[row, (code & 511) >> 6] |= np.int64(1) << (code & 63)
    return bricks


@njit(cache=True, nogil=True)
def rehash_bricks(keys, bits, new_keys, new_bits):
    """The table's bricks moved into a larger (empty) one."""
    mask = new_keys.shape[0] - 1
    for i in range(keys.shape[0]):
        if keys[i] != -1:
            row, _ = _brick_row(new_keys, keys[i], mask, True)
            new_bits[row] = bits[i]


@njit(cache=True, nogil=True)
def bricks_hold(keys, bits, codes, out):
    """out[i]: whether the table's bit of finest-level voxel codes[i] is set (codes >= 0;
    sorted codes find each brick once)."""
    mask = keys.shape[0] - 1
    last = np.int64(-1)
    row = np.int64(-1)
    for i in range(codes.shape[0]):
        code = codes[i]
        if code >> 9 != last:
            last = code >> 9
            row, _ = _brick_row(keys, last, mask, False)
        out[i] = row >= 0 and ((bits[row, (code & 511) >> 6] >> (code & 63)) & 1) == 1


@njit(cache=True, nogil=True)
def cube_brick_table(radius, flat=False):
    """For each in-brick voxel p (Morton index) and each voxel of the (2r+1)^3 cube around it
    (itself excluded; the 6 face neighbours first, the likeliest to fail), where that voxel
    lies: nb * 512 + its in-brick index, nb = (dx + 1) + 3 (dy + 1) + 9 (dz + 1) for the brick
    dx, dy, dz away (radius <= BALL_TABLE_RADIUS). flat: the (2r+1)^2 square in p's own layer
    (dz = 0), for level 2D scans, whose rays never cross the layers above and below."""
    r = int(radius)
    rz = 0 if flat else r
    n = (2 * r + 1) ** 2 * (2 * rz + 1) - 1
    offsets = np.empty((n, 3), dtype=np.int64)
    k = 0
    for dist in range(1, 3 * r * r + 1):  # by squared distance: faces, edges, corners, ...
        for dx in range(-r, r + 1):
            for dy in range(-r, r + 1):
                for dz in range(-rz, rz + 1):
                    if dx * dx + dy * dy + dz * dz == dist:
                        offsets[k, 0], offsets[k, 1], offsets[k, 2] = dx, dy, dz
                        k += 1
    table = np.empty((512, n), dtype=np.int32)
    for p in range(512):
        x, y, z = compact16(p), compact16(p >> 1), compact16(p >> 2)
        for j in range(n):
            nx, ny, nz = x + offsets[j, 0], y + offsets[j, 1], z + offsets[j, 2]
            nb = ((nx >> 3) + 1) + 3 * ((ny >> 3) + 1) + 9 * ((nz >> 3) + 1)
            table[p, j] = nb * 512 + IN_BRICK[(nx & 7) | ((ny & 7) << 3) | ((nz & 7) << 6)]
    return table


@njit(cache=True, nogil=True)
def _rows_around(keys, brick, rows):
    """rows[nb]: the row of each of the 27 bricks around `brick` (nb as in cube_brick_table)
    in a table, -1 where absent or outside the key range."""
    mask = keys.shape[0] - 1
    bx, by, bz = compact16(brick), compact16(brick >> 1), compact16(brick >> 2)
    for nb in range(27):
        nx, ny, nz = bx + nb % 3 - 1, by + (nb // 3) % 3 - 1, bz + nb // 9 - 1
        if nx < 0 or ny < 0 or nz < 0 or nx > 0x1FFF or ny > 0x1FFF or nz > 0x1FFF:
            rows[nb] = -1
        else:
            rows[nb] = _brick_row(keys, morton3(nx, ny, nz), mask, False)[0]


@njit(cache=True, nogil=True)
def seen_whole(keys, bits, point_keys, point_bits, stop_keys, stop_bits, cube, start, stop, out):
    """One scan's void voxels where points lie, rows start..stop of the table of the voxels its
    rays crossed (`keys`, `bits` words 0-7): out[row], those crossed voxels that hold a point of
    some scan (`point_keys`/`point_bits`, an 8-word brick table) and whose whole `cube`
    (cube_brick_table) the scan knows: each voxel of it crossed or stopped at (`stop_keys`,
    `stop_bits` words 0-7: near_hits_table). A voxel near space the scan did not see (between
    sparse rays, behind a surface, within d_s of a hit) is not void: DUFOMap's unknown
    inflated by d_p. Only voxels holding points are decided: no other is ever asked."""
    point_mask = point_keys.shape[0] - 1
    crossed_rows = np.empty(27, dtype=np.int64)
    stop_rows = np.empty(27, dtype=np.int64)
    for r in range(start, stop):
        brick = keys[r]
        if brick == -1:
            continue
        prow = _brick_row(point_keys, brick, point_mask, False)[0]
        if prow < 0:
            continue
        looked = False
        for w in range(8):
            x = bits[r, w] & point_bits[prow, w]
            if x == 0:
                continue
            if not looked:
                _rows_around(keys, brick, crossed_rows)
                _rows_around(stop_keys, brick, stop_rows)
                looked = True
            while x != 0:
                k = lowest_bit(x)
                x &= x - 1
                p = w * 64 + k
                whole = True
                for j in range(cube.shape[1]):
                    e = cube[p, j]
                    nb = e >> 9
                    inner = e & 511
                    word = inner >> 6
                    known = np.int64(0)
                    if crossed_rows[nb] >= 0:
                        known |= bits[crossed_rows[nb], word]
                    if stop_rows[nb] >= 0:
                        known |= stop_bits[stop_rows[nb], word]
                    if (known >> (inner & 63)) & 1 == 0:
                        whole = False
                        break
                if whole:
                    out[r, w] |= np.int64(1) << k


# the 26 neighbours of a voxel, z slowest; the last 13 come after it (the others see it): a
# group's links, once each
_AROUND = np.array([(dx, dy, dz) for dz in (-1, 0, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                    if (dx, dy, dz) != (0, 0, 0)], dtype=np.int64)
_FORWARD = _AROUND[13:]


@njit(cache=True, nogil=True)
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]  # path halving
        i = parent[i]
    return i


@njit(cache=True, nogil=True)
def voxel_groups(codes):
    """The groups of 26-connected voxels among `codes` (Morton codes, sorted, distinct): each
    voxel's group as the index of one of its voxels."""
    n = codes.shape[0]
    parent = np.arange(n)
    for i in range(n):
        for j in range(_FORWARD.shape[0]):
            c = _moved(codes[i], _FORWARD[j, 0], _FORWARD[j, 1], _FORWARD[j, 2])
            if c < 0:
                continue
            k = np.searchsorted(codes, c)
            if k < n and codes[k] == c:
                a, b = _root(parent, i), _root(parent, k)
                if a != b:
                    parent[a] = b
    for i in range(n):
        parent[i] = _root(parent, i)
    return parent


@njit(cache=True, nogil=True)
def within_steps(codes, seeds, steps):
    """Which of `codes` (Morton codes, sorted, distinct) lie at most `steps` 26-neighbour steps
    from a seed (`seeds`: bool per code), stepping through `codes` only (breadth first)."""
    n = codes.shape[0]
    reached = seeds.copy()
    frontier = np.flatnonzero(seeds)
    for _ in range(steps):
        found = np.empty(n, dtype=np.int64)
        m = 0
        for i in frontier:
            for j in range(_AROUND.shape[0]):
                c = _moved(codes[i], _AROUND[j, 0], _AROUND[j, 1], _AROUND[j, 2])
                if c < 0:
                    continue
                k = np.searchsorted(codes, c)
                if k < n and codes[k] == c and not reached[k]:
                    reached[k] = True
                    found[m] = k
                    m += 1
        if m == 0:
            break
        frontier = found[:m].copy()
    return reached
