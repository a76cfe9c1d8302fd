"""The `cm` packet codec: a box of 2-bit cell codes, coded cell by cell by an adaptive binary
range coder whose probabilities are conditioned on already-coded 3D neighbours.

Specified byte for byte in formats/packet.md ("Codec cm"); the reasons for each choice are in
docs/packets.md. Cells go in x-fastest order, so the causal neighbours of a cell are the same
offsets everywhere: that is what lets a 3D context see the structure (thin lines of newly free
voxels, surfaces of new hits) that a byte-oriented coder such as zstd only sees along one axis.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# Context bits; the coder below reads these neighbours written out, in this bit order.
# "near" (9 bits, bit i set when that causal neighbour (dx, dy, dz) is not background):
NEAR = ((-1, 0, 0), (1, -1, 0), (0, -1, 0), (-1, -1, 0), (1, 0, -1), (0, 0, -1), (-1, 0, -1), (0, -1, -1), (0, 1, -1))
# "far" (7 bits), used instead when no near neighbour is set: corners below, cells two steps back
FAR = ((1, -1, -1), (-1, -1, -1), (1, 1, -1), (-1, 1, -1), (-2, 0, 0), (0, -2, 0), (0, 0, -2))
# probability tables, one after the other: near (512), far (128), occupied (27), other (1)
OFF_FAR = 1 << len(NEAR)
OFF_OCC = OFF_FAR + (1 << len(FAR))
OFF_ALT = OFF_OCC + 27
N_CONTEXTS = OFF_ALT + 1
PROB_BITS = 16
PROB_ONE = 1 << PROB_BITS
P_MIN, P_MAX = 16, PROB_ONE - 16  # no decision ever costs more than 12 bits
# each context keeps its probability with 32 fractional bits and codes with the top 16: updates
# in 16 bits would round every small step away from zero and drive rare events to P_MIN
STATE_BITS = 32
STATE_ONE = 1 << STATE_BITS
STATE_SHIFT = STATE_BITS - PROB_BITS
STATE_MIN, STATE_MAX = P_MIN << STATE_SHIFT, P_MAX << STATE_SHIFT
COUNT_LIMIT = 254
# adaptation rate 1 / (n + 1.5) after n observations of a context, floored at 1/256
RATE = (2 * PROB_ONE) // (2 * np.arange(COUNT_LIMIT + 1, dtype=np.int64) + 3)
TOP = 1 << 24
PAD = 2  # rows and planes of cell classes are padded by 2 on each side: no bounds tests per neighbour

# cell classes in the context grid
BACKGROUND, CLASS_OCC, CLASS_OTHER = 0, 1, 2


@njit(cache=True, inline="always")
def _shift_low(low, cache, pending, data, pos):
    """Encoder: move the top byte of `low` out, resolving a pending carry (runs of 0xFF bytes)."""
    if (low & 0xFFFFFFFF) < 0xFF000000 or (low >> 32) != 0:
        carry = low >> 32
        data[pos] = (cache + carry) & 0xFF
        pos += 1
        for _ in range(pending - 1):
            data[pos] = (0xFF + carry) & 0xFF
            pos += 1
        pending = 0
        cache = (low >> 24) & 0xFF
    return (low & 0x00FFFFFF) << 8, cache, pending + 1, pos


@njit(cache=True, inline="always")
def _code_bit(bit, p, rng, low, cache, pending, data, pos, decode):
    """One binary decision with probability p / 2^16 of a 1: encode `bit`, or decode it."""
    bound = (rng >> PROB_BITS) * p
    if decode:
        bit = low < bound
        if bit:
            rng = bound
        else:
            low -= bound
            rng -= bound
        while rng < TOP:
            rng <<= 8
            low = ((low << 8) | (np.int64(data[pos]) if pos < data.shape[0] else 0)) & 0xFFFFFFFF
            pos += 1
    else:
        if bit:
            rng = bound
        else:
            low += bound
            rng -= bound
        while rng < TOP:  # _shift_low written out: numba compiles it nested in here 5x slower
            rng <<= 8
            if (low & 0xFFFFFFFF) < 0xFF000000 or (low >> 32) != 0:
                carry = low >> 32
                data[pos] = (cache + carry) & 0xFF
                pos += 1
                for _ in range(pending - 1):
                    data[pos] = (0xFF + carry) & 0xFF
                    pos += 1
                pending = 0
                cache = (low >> 24) & 0xFF
            low = (low & 0x00FFFFFF) << 8
            pending += 1
    return bit, rng, low, cache, pending, pos


@njit(cache=True, inline="always")
def _code_entry(bit, entry, rng, low, cache, pending, data, pos, decode):
    """_code_bit, then the entry (a context's state << 8 | its count n of observations) learns the
    bit: its probability of a 1 moves toward it by 1 / (n + 1.5), floored (negative steps too).
    Returns the entry updated."""
    state = entry >> 8
    n = entry & 0xFF
    bit, rng, low, cache, pending, pos = _code_bit(bit, state >> STATE_SHIFT, rng, low, cache, pending, data, pos,
                                                   decode)
    if bit:
        state = min(state + (((STATE_ONE - state) * RATE[n]) >> PROB_BITS), STATE_MAX)
    else:
        state = max(state + ((-state * RATE[n]) >> PROB_BITS), STATE_MIN)
    return bit, (state << 8) | (n + (n < COUNT_LIMIT)), rng, low, cache, pending, pos


@njit(cache=True, inline="always")
def _code_packed(bit, table, ctx, rng, low, cache, pending, data, pos, decode):
    """_code_entry on the table's entry of context ctx."""
    at = np.uintp(ctx)  # unsigned: no wraparound test for negative indices
    bit, table[at], rng, low, cache, pending, pos = _code_entry(bit, table[at], rng, low, cache, pending, data, pos,
                                                                decode)
    return bit, rng, low, cache, pending, pos


@njit(cache=True, inline="always")
def _cell_context(window, r0):
    """Decision 1's context from the sliding window of row bits (see code_box) and r0."""
    if window == 0 and r0 == 0:
        return OFF_FAR  # nothing around: most cells of a sparse box
    left = window >> 16
    mid = (window >> 8) & 0xFF
    right = window & 0xFF
    near = ((r0 & 1) | ((right & 1) << 1) | ((mid & 1) << 2) | ((left & 1) << 3)
            | ((right & 2) << 3) | ((mid & 2) << 4) | ((left & 2) << 5)
            | ((mid & 4) << 5) | ((mid & 8) << 5))
    if near != 0:
        return near
    return OFF_FAR + (((right >> 2) & 1) | ((left >> 1) & 2) | ((right >> 1) & 4)
                      | (left & 8) | ((r0 >> 1) << 4) | ((mid & 16) << 1) | ((mid & 32) << 1))


@njit(cache=True, inline="always")
def _code_cell(code, background, other, ctx, grid, below, yy, x, table, rng, low, cache, pending, data, pos, decode):
    """A cell's decisions (formats/packet.md): known? then occupied? then other or free?
    Returns (its code, its class, the coder's state); the decoder learns the code here.
    The decisions go round one loop so that the coder is compiled once: three copies of it in
    one function made numba's code 7x slower per cell. Decisions 2 and 3 are codec 4's
    code_known written out again on purpose: calling it made this coder 1.6x slower, and
    inlining it (two copies of the coder) 2x (a 120 x 120 x 60 box, 8.6 ms to 13.5 and 17.5)."""
    step = 0
    bit = code != background
    while True:
        bit, rng, low, cache, pending, pos = _code_packed(bit, table, ctx, rng, low, cache, pending, data, pos, decode)
        if step == 0:  # known?
            if not bit:
                return background, BACKGROUND, rng, low, cache, pending, pos
            # decision 2: occupied? (context: the classes of the three face neighbours)
            ctx = OFF_OCC + grid[yy, x - 1] + 3 * grid[yy - 1, x] + 9 * below[yy, x]
            bit = code == 1
        elif step == 1:
            if bit:
                return 1, CLASS_OCC, rng, low, cache, pending, pos
            # decision 3: free, or the fourth code (unknown in a delta)?
            ctx = OFF_ALT
            bit = code == other
        else:
            return (other if bit else 0), CLASS_OTHER, rng, low, cache, pending, pos
        step += 1


def _make_coder(decode: bool):
    """The encoder or the decoder: one loop written once, so both sides build the same contexts;
    `decode` is a compile-time constant of each, so neither carries the other's branches."""

    @njit(cache=True, nogil=True)
    def code_box(codes, nx, ny, nz, background, data):
        other = 2 if background == 3 else 3  # the non-background code that is neither free nor occupied
        # a box without cells codes nothing: no rows to walk and no planes (a side of 0 beside two
        # large ones would otherwise cost time and memory for a stream that holds no cells)
        planes_z = 0 if nx == 0 or ny == 0 or nz == 0 else nz
        # the classes of the last three planes (z-2, z-1, z), reused in turn: the context reaches
        # two planes back, and the memory stays three planes whatever the box's shape
        planes = np.zeros((3, ny + 2 * PAD if planes_z else 0, nx + 2 * PAD if planes_z else 0), dtype=np.uint8)
        around = np.zeros(nx + 2 * PAD, dtype=np.uint8)
        table = np.full(N_CONTEXTS, (STATE_ONE // 2) << 8, dtype=np.int64)  # packed entries (see _code_entry)
        cap = data.shape[0]
        rng = np.int64(0xFFFFFFFF)
        low = np.int64(0)  # encoder: low end of the interval (33 bits); decoder: offset into it
        cache = np.int64(0)
        pending = np.int64(1)
        pos = 0
        if decode:
            if cap < 1 or data[0] != 0:
                return -1
            pos = 1
            for _ in range(4):
                low = (low << 8) | (np.int64(data[pos]) if pos < cap else 0)
                pos += 1
        row_bytes = 5 * nx + 8  # a cell's three decisions emit at most 36 bits
        i = 0
        for z in range(planes_z):
            grid = planes[z % 3]  # plane z (it held z-3)
            grid[:, :] = 0
            below = planes[(z + 2) % 3]  # plane z-1 (zeros for the first plane)
            below2 = planes[(z + 1) % 3]  # plane z-2
            for y in range(PAD, ny + PAD):
                if not decode and pos + pending + row_bytes > cap:
                    return -1
                # per cell, six bits of the rows already coded (one vectorizable pass): bit 0 row
                # y-1, bit 1 row y below, bit 2 row y-1 below, bit 3 row y+1 below, bit 4 row y-2,
                # bit 5 row y two planes below; then a sliding window of three cells (x-1, x, x+1)
                for xx in range(nx + 2 * PAD):
                    around[xx] = ((grid[y - 1, xx] != 0) | ((below[y, xx] != 0) << 1)
                                  | ((below[y - 1, xx] != 0) << 2) | ((below[y + 1, xx] != 0) << 3)
                                  | ((grid[y - 2, xx] != 0) << 4) | ((below2[y, xx] != 0) << 5))
                window = (np.int64(around[PAD]) << 8) | around[PAD + 1]  # byte 2: x-1, 1: x, 0: x+1
                r0 = 0  # bit 0: cell x-1 of this row, bit 1: cell x-2
                for x in range(PAD, nx + PAD):
                    ctx = _cell_context(window, r0)
                    code, cls, rng, low, cache, pending, pos = _code_cell(
                        background if decode else codes[i], background, other, ctx, grid, below, y, x, table,
                        rng, low, cache, pending, data, pos, decode)
                    if decode:
                        codes[i] = code
                    i += 1
                    grid[y, x] = cls
                    r0 = ((r0 << 1) & 3) | (cls != 0)
                    window = ((window << 8) & 0xFFFFFF) | around[x + 2]
        if not decode:
            for _ in range(5):  # flush: the decoder reads the 4 bytes of `low` after the leading 0
                if pos + pending + 1 > cap:
                    return -1
                low, cache, pending, pos = _shift_low(low, cache, pending, data, pos)
        return pos

    return code_box


# encode_box(codes, nx, ny, nz, background, out): codes = uint8 cells in x-fastest order (0..3);
# returns the bytes written to `out`, or -1 when `out` is too small (call again, larger)
encode_box = _make_coder(False)
# decode_box(codes, nx, ny, nz, background, data): fills `codes`; returns the bytes consumed
# (more than len(data) when the stream is truncated), or -1 without the leading zero byte
decode_box = _make_coder(True)


# Codec cm (4): the box in 4 x 4 x 4 blocks. Before each slab of 4 planes, one decision per block
# of the slab says whether it holds any non-background cell (context: the flags of the blocks
# before it in x, in y and in the slab below); then the cells of the flagged blocks alone are
# coded, in nested order, exactly as codec 3 codes them. Cells of unflagged blocks are
# background and cost nothing, so the work follows the changed cells, not the box's volume.
BLOCK = 4
OFF_BLOCK = N_CONTEXTS  # 8 contexts for the block flags
N_CONTEXTS_BLOCKS = N_CONTEXTS + 8

# Codec 4's coder makes codec 3's decisions in the same order with the same probabilities, in
# fewer instructions a cell (about half its time went on the work around the range coder, not on
# the coder: docs/design/packets.md):
# - a context's probability state and its count share one int64 (_code_entry, as in codec 3):
#   one load and one store a decision;
# - a cell's row bits (code_box's) are written by the known cells that set them (six stores a
#   change) rather than read from six rows at every cell coded (about 11 a change);
# - decision 1's context comes from two tables indexed by a 12-bit window of bits 0-3 of the row
#   bits of cells x-1, x, x+1: what _cell_context computes bit by bit.


def _context_tables():
    """_cell_context of every window of bits 0-3 of three cells' row bits, with r0 and the middle
    cell's bits 4-5 zero: near[w] where a near neighbour is set (else 0), far[w] where none is
    (the rest is or'ed in by the coder). Made by _cell_context's Python function at import."""
    near = np.zeros(1 << 12, dtype=np.int64)
    far = np.full(1 << 12, OFF_FAR, dtype=np.int64)
    for w in range(1 << 12):
        ctx = _cell_context.py_func(((w >> 8) << 16) | (((w >> 4) & 15) << 8) | (w & 15), 0)
        if ctx < OFF_FAR:
            near[w] = ctx
        else:
            far[w] = ctx
    return near, far


NEAR_OF_WINDOW, FAR_OF_WINDOW = _context_tables()


def _make_known_coder(decode: bool):
    """Decisions 2 and 3 of a cell decision 1 found known (formats/packet.md): occupied? then
    other or free? A function of its own whose decisions go round one loop, so that the coder is
    compiled once here and once for decision 1 (more copies in one function made numba's code
    several times slower); `decode` a compile-time constant, as in the coders below."""

    @njit(cache=True, nogil=True)
    def code_known(code, other, ctx, table, rng, low, cache, pending, data, pos):
        """Returns (the cell's code, its class, the coder's state)."""
        bit = code == 1
        step = 0
        while True:
            bit, rng, low, cache, pending, pos = _code_packed(bit, table, ctx, rng, low, cache, pending, data, pos,
                                                              decode)
            if step == 1:
                return (other if bit else 0), CLASS_OTHER, rng, low, cache, pending, pos
            if bit:
                return 1, CLASS_OCC, rng, low, cache, pending, pos
            ctx = OFF_ALT
            bit = code == other
            step = 1

    return code_known


_encode_known = _make_known_coder(False)
_decode_known = _make_known_coder(True)


@njit(cache=True, inline="always")
def _code_background(table, row_bits, at, end, stop, window, hi, r0, held, entry, rng, low, cache, pending, data,
                     pos, decode):
    """Decision 1 of the cells of a run from place `at` up to `end` (not included), the loop most
    of the time goes round: written apart from a known cell's work, to which it returns, it keeps
    to a load of the cell's row bits, two table lookups and the coder. The encoder codes the cell
    at place `stop` as known and every other as background; the decoder decodes. Either returns
    at the first known cell: (where it stopped, window, hi, r0, known?, held, entry, the coder's
    state). `held`, `entry`: the context of the decision before and its table entry, kept out of
    the table while the next cells use the same context (most do), so that a decision does not
    wait for the store of the one before."""
    near_of, far_of = NEAR_OF_WINDOW, FAR_OF_WINDOW
    while at < end:
        bits = row_bits[np.uintp(at + 1)]
        window = ((window << 4) & 0xFF0) | (bits & 15)
        ctx = near_of[window] | (r0 & 1)
        if ctx == 0:
            ctx = far_of[window] | ((r0 >> 1) << 4) | (hi << 1)
        hi = np.int64(bits & 48)
        if ctx != held:  # the context of the decision before is held in `entry`, not in the table
            table[np.uintp(held)] = entry
            entry = table[np.uintp(ctx)]
            held = ctx
        known, entry, rng, low, cache, pending, pos = _code_entry(
            at == stop, entry, rng, low, cache, pending, data, pos, decode)
        r0 = ((r0 << 1) & 3) | known
        if known:
            return at, window, hi, r0, True, held, entry, rng, low, cache, pending, pos
        at += 1
    return at, window, hi, r0, False, held, entry, rng, low, cache, pending, pos


def _make_block_coder(decode: bool):
    """Codec 4's encoder or decoder (one loop, `decode` a compile-time constant of each)."""

    @njit(cache=True, nogil=True)
    def code_blocks(idx, vals, nx, ny, nz, background, data, out_idx, out_vals):
        other = 2 if background == 3 else 3
        bxn = (nx + BLOCK - 1) // BLOCK
        byn = (ny + BLOCK - 1) // BLOCK
        bzn = (nz + BLOCK - 1) // BLOCK
        if nx == 0 or ny == 0 or nz == 0:
            bzn = 0
        # Three planes in turn (z, z+1, z+2 in slots z % 3), each padded by 2 cells on every side
        # and flattened: a cell's place in its plane is `at` = (y + PAD) * width + x + PAD.
        # classes: the classes of planes z-2..z (decision 2's context). row_bits: each cell's six
        # row bits (code_box's), set when a known cell is coded, by that cell, in the six cells
        # that read it; so a cell's context costs one load, and the work is per change, not per
        # cell. Both are cleared cell by cell from the known cells' places (`known_at`).
        width = nx + 2 * PAD if bzn else 0
        plane = (ny + 2 * PAD) * width
        classes = np.zeros(3 * plane, dtype=np.uint8)
        row_bits = np.zeros(3 * plane, dtype=np.uint8)
        known_at = np.empty(out_idx.shape[0] if decode else idx.shape[0], dtype=np.int64)
        plane_first = np.zeros(nz + 1, dtype=np.int64)  # the first known cell of each plane
        # block flags of this slab and the one below, padded by one block before x and y
        flags = np.zeros((2, byn + 1, bxn + 1), dtype=np.uint8)
        # per slab parity, each block row's runs of flagged blocks (x0, x1 in cells): row by's
        # runs are runs[p, run_at[p, by]:run_at[p, by + 1]]
        runs = np.empty((2, byn * (bxn + 1) + 1, 2), dtype=np.int64)
        run_at = np.zeros((2, byn + 1), dtype=np.int64)
        table = np.full(N_CONTEXTS_BLOCKS, (STATE_ONE // 2) << 8, dtype=np.int64)
        # decision 1's context last used, and its entry, held out of the table while cells use it
        held = 0
        entry = table[0]
        cap = data.shape[0]
        rng = np.int64(0xFFFFFFFF)
        low = np.int64(0)
        cache = np.int64(0)
        pending = np.int64(1)
        pos = 0
        if decode:
            if cap < 1 or data[0] != 0:
                return -1, 0
            pos = 1
            for _ in range(4):
                low = (low << 8) | (np.int64(data[pos]) if pos < cap else 0)
                pos += 1
        plane_cells = np.int64(nx) * ny
        j = 0  # encoder: next cell of idx; decoder: cells written to out_*
        n_in = idx.shape[0]
        next_cell = idx[0] if not decode and n_in > 0 else -1
        for bz in range(bzn):
            par = bz & 1
            cur = flags[par]
            below_flags = flags[1 - par]
            cur[:, :] = 0
            if not decode:
                # the blocks this slab's cells lie in
                k = j
                while k < n_in and idx[k] < (bz + 1) * BLOCK * plane_cells:
                    cell = idx[k]
                    cur[(cell // nx) % ny // BLOCK + 1, cell % nx // BLOCK + 1] = 1
                    k += 1
                if pos + pending + 2 * bxn * byn + 8 > cap:
                    return -1, j
            n_runs = 0
            for by in range(byn):
                run_at[par, by] = n_runs
                row, before, under = cur[by + 1], cur[by], below_flags[by + 1]
                for bx in range(bxn):
                    ctx = OFF_BLOCK + row[bx] + 2 * before[bx + 1] + 4 * under[bx + 1]
                    flag, rng, low, cache, pending, pos = _code_packed(
                        row[bx + 1] != 0, table, ctx, rng, low, cache, pending, data, pos, decode)
                    row[bx + 1] = flag
                    if flag:
                        if bx > 0 and row[bx] and n_runs > run_at[par, by]:
                            runs[par, n_runs - 1, 1] = min((bx + 1) * BLOCK, nx)  # extends the run before
                        else:
                            runs[par, n_runs, 0] = bx * BLOCK
                            runs[par, n_runs, 1] = min((bx + 1) * BLOCK, nx)
                            n_runs += 1
            run_at[par, byn] = n_runs
            for z in range(bz * BLOCK, min((bz + 1) * BLOCK, nz)):
                plane_first[z] = j
                here = (z % 3) * plane
                below = ((z + 2) % 3) * plane
                above = ((z + 1) % 3) * plane
                # slot z+2 held plane z-1: clear what planes z-3..z-1 set there (rows -1..+2 of
                # each known cell), and the classes plane z-3 set in slot z
                for k in range(plane_first[max(z - 3, 0)], j):
                    at = below + known_at[k]
                    row_bits[at - width] = 0
                    row_bits[at] = 0
                    row_bits[at + width] = 0
                    row_bits[at + 2 * width] = 0
                if z >= 3:
                    for k in range(plane_first[z - 3], plane_first[z - 2]):
                        classes[here + known_at[k]] = 0
                for y in range(ny):
                    by = y // BLOCK
                    row_at = (y + PAD) * width + PAD  # the place of cell (0, y)
                    for r in range(run_at[par, by], run_at[par, by + 1]):
                        x0 = runs[par, r, 0]
                        x1 = runs[par, r, 1]
                        if not decode and pos + pending + 5 * (x1 - x0) + 8 > cap:
                            return -1, j
                        # window: bits 0-3 of the row bits of cells x-1 (bits 8-11), x, x+1;
                        # hi: bits 4-5 of cell x's
                        at = here + row_at + x0
                        end = at + (x1 - x0)
                        window = ((np.int64(row_bits[at - 1]) & 15) << 4) | (row_bits[at] & 15)
                        hi = np.int64(row_bits[at] & 48)
                        r0 = 0  # bit 0: cell x-1 of this row, bit 1: cell x-2 (blank blocks or outside before a run)
                        cell_at = (np.int64(z) * ny + y) * nx + x0 - at  # a cell's index is cell_at + its place
                        while at < end:
                            stop = -1
                            if not decode and next_cell >= 0 and next_cell - cell_at < end:
                                stop = next_cell - cell_at
                            at, window, hi, r0, known, held, entry, rng, low, cache, pending, pos = _code_background(
                                table, row_bits, at, end, stop, window, hi, r0, held, entry, rng, low, cache, pending,
                                data, pos, decode)
                            if not known:
                                break
                            code = background if decode else vals[j]
                            ctx = OFF_OCC + classes[at - 1] + 3 * classes[at - width] + 9 * classes[at - here + below]
                            if decode:  # a global each (a closure's dispatcher would keep numba from caching)
                                code, cls, rng, low, cache, pending, pos = _decode_known(
                                    code, other, ctx, table, rng, low, cache, pending, data, pos)
                            else:
                                code, cls, rng, low, cache, pending, pos = _encode_known(
                                    code, other, ctx, table, rng, low, cache, pending, data, pos)
                            classes[at] = cls
                            placed = at - here
                            row_bits[at + width] |= 1  # row y+1 of this plane: its row y-1
                            row_bits[at + 2 * width] |= 16  # row y+2: its row y-2
                            row_bits[above + placed] |= 2  # plane z+1, row y: below, row y
                            row_bits[above + placed + width] |= 4  # row y+1: below, row y-1
                            row_bits[above + placed - width] |= 8  # row y-1: below, row y+1
                            row_bits[below + placed] |= 32  # plane z+2 (in slot z-1), row y: two below
                            if decode:
                                if j >= out_idx.shape[0]:
                                    return -2, j  # more cells than the packet declares
                                out_idx[j] = cell_at + at
                                out_vals[j] = code
                            known_at[j] = placed
                            j += 1
                            if not decode:
                                next_cell = idx[j] if j < n_in else -1
                            at += 1
        if not decode:
            if j != n_in:
                return -3, j  # a cell outside the box, or idx not in nested order
            for _ in range(5):
                if pos + pending + 1 > cap:
                    return -1, j
                low, cache, pending, pos = _shift_low(low, cache, pending, data, pos)
        return pos, j

    return code_blocks


# encode_blocks(idx, vals, nx, ny, nz, background, out, _, _): idx = nested indices of the
# non-background cells, ascending, vals their codes; returns (bytes written, cells): bytes -1 when
# `out` is too small (call again, larger), -3 when idx is not ascending inside the box
encode_blocks = _make_block_coder(False)
# decode_blocks(_, _, nx, ny, nz, background, data, out_idx, out_vals): writes the non-background
# cells; returns (bytes consumed, cells): bytes -1 without the leading zero byte, -2 when the
# cells outnumber out_idx
decode_blocks = _make_block_coder(True)
