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
def _learn(probs, counts, ctx, bit):
    """Move the context's probability of a 1 toward the bit by 1 / (n + 1.5)."""
    n = counts[ctx]
    state = probs[ctx]
    state += (((STATE_ONE if bit else 0) - state) * RATE[n]) >> PROB_BITS  # floor, negative steps too
    probs[ctx] = min(max(state, STATE_MIN), STATE_MAX)
    if n < COUNT_LIMIT:
        counts[ctx] = n + 1


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
        while rng < TOP:
            rng <<= 8
            low, cache, pending, pos = _shift_low(low, cache, pending, data, pos)
    return bit, rng, low, cache, pending, pos


def _make_coder(decode: bool):
    """The encoder or the decoder: one loop written once, so both sides build the same contexts;
    `decode` is a compile-time constant of each, so neither carries the other's branches."""

    @njit(cache=True)
    def code_box(codes, nx, ny, nz, background, data):
        other = 2 if background == 3 else 3  # the non-background code that is neither free nor occupied
        # a box without cells codes nothing: no rows to walk and no planes (a side of 0 beside two
        # large ones would otherwise cost time and memory for a stream that holds no cells)
        planes_z = 0 if nx == 0 or ny == 0 or nz == 0 else nz
        # the classes of the last three planes (z-2, z-1, z), reused in turn: the context reaches
        # two planes back, and the memory stays three planes whatever the box's shape
        planes = np.zeros((3, ny + 2 * PAD if planes_z else 0, nx + 2 * PAD if planes_z else 0), dtype=np.uint8)
        around = np.zeros(nx + 2 * PAD, dtype=np.uint8)
        probs = np.full(N_CONTEXTS, STATE_ONE // 2, dtype=np.int64)
        counts = np.zeros(N_CONTEXTS, dtype=np.int64)
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
                    if window == 0 and r0 == 0:
                        ctx = OFF_FAR  # nothing around: most cells of a sparse box
                    else:
                        left = window >> 16
                        mid = (window >> 8) & 0xFF
                        right = window & 0xFF
                        # the bits in NEAR's and FAR's order (top of this file), from the row bits
                        near = ((r0 & 1) | ((right & 1) << 1) | ((mid & 1) << 2) | ((left & 1) << 3)
                                | ((right & 2) << 3) | ((mid & 2) << 4) | ((left & 2) << 5)
                                | ((mid & 4) << 5) | ((mid & 8) << 5))
                        if near != 0:
                            ctx = near
                        else:
                            ctx = OFF_FAR + (((right >> 2) & 1) | ((left >> 1) & 2) | ((right >> 1) & 4)
                                             | (left & 8) | ((r0 >> 1) << 4) | ((mid & 16) << 1) | ((mid & 32) << 1))
                    code = background if decode else codes[i]
                    # decision 1: is the cell not background?
                    known, rng, low, cache, pending, pos = _code_bit(
                        code != background, probs[ctx] >> STATE_SHIFT, rng, low, cache, pending, data, pos, decode)
                    _learn(probs, counts, ctx, known)
                    cls = BACKGROUND
                    if known:
                        # decision 2: occupied? (context: the classes of the three face neighbours)
                        ctx = OFF_OCC + grid[y, x - 1] + 3 * grid[y - 1, x] + 9 * below[y, x]
                        occ, rng, low, cache, pending, pos = _code_bit(
                            code == 1, probs[ctx] >> STATE_SHIFT, rng, low, cache, pending, data, pos, decode)
                        _learn(probs, counts, ctx, occ)
                        cls = CLASS_OCC
                        if not occ:
                            # decision 3: free, or the fourth code (unknown in a delta)?
                            alt, rng, low, cache, pending, pos = _code_bit(
                                code == other, probs[OFF_ALT] >> STATE_SHIFT, rng, low, cache, pending, data, pos,
                                decode)
                            _learn(probs, counts, OFF_ALT, alt)
                            cls = CLASS_OTHER
                            code = other if alt else 0
                        else:
                            code = 1
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
