"""Codecs cm (4) and cm1 (3): byte-identical to plain-Python coders written from formats/packet.md,
round trips, and refusal of streams that are truncated, padded, or too short for their box."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxtool.codec.cm import compress_box, compress_cells, decompress_box, decompress_cells
from voxtool.codec.packet import KIND_DELTA, UNCHANGED, UNKNOWN, decode_packet, encode_packet
from voxtool.errors import FormatError

# formats/packet.md, "Codec cm": context neighbours as (dx, dy, dz), bit i = neighbour i
NEAR = [(-1, 0, 0), (1, -1, 0), (0, -1, 0), (-1, -1, 0), (1, 0, -1), (0, 0, -1), (-1, 0, -1), (0, -1, -1), (0, 1, -1)]
FAR = [(1, -1, -1), (-1, -1, -1), (1, 1, -1), (-1, 1, -1), (-2, 0, 0), (0, -2, 0), (0, 0, -2)]


def reference_encode(codes: np.ndarray, dims, background: int, blocks: bool = False) -> bytes:
    """The cm1 stream (codec 3), or with `blocks` the cm stream (codec 4), cell by cell as the
    spec states it. The interval's low end is an exact Python integer, so carries need no
    handling: the stream is that integer's bytes."""
    nx, ny, nz = dims
    grid = codes.reshape(nz, ny, nx)

    def cls(x, y, z):  # class of a coded cell; 0 outside the box
        if not (0 <= x < nx and 0 <= y < ny and 0 <= z < nz):
            return 0
        c = int(grid[z, y, x])
        return 0 if c == background else 1 if c == 1 else 2

    probs = [1 << 31] * (512 + 128 + 27 + 1 + 8)
    counts = [0] * len(probs)
    state = {"low": 0, "range": 0xFFFFFFFF, "shifts": 0}

    def code(bit: bool, ctx: int) -> None:
        p = min(max(probs[ctx] >> 16, 16), 65520)
        bound = (state["range"] >> 16) * p
        if bit:
            state["range"] = bound
        else:
            state["low"] += bound
            state["range"] -= bound
        rate = (2 * 65536) // (2 * counts[ctx] + 3)
        probs[ctx] = min(max(probs[ctx] + ((((1 << 32) if bit else 0) - probs[ctx]) * rate >> 16), 16 << 16), 65520 << 16)
        counts[ctx] = min(counts[ctx] + 1, 254)
        while state["range"] < 1 << 24:
            state["range"] <<= 8
            state["low"] <<= 8
            state["shifts"] += 1

    def flag(bx, by, bz):  # a 4 x 4 x 4 block holds a non-background cell (0 outside the box)
        if bx < 0 or by < 0 or bz < 0:
            return 0
        return int(np.any(grid[4 * bz:4 * bz + 4, 4 * by:4 * by + 4, 4 * bx:4 * bx + 4] != background))

    other = 2 if background == UNCHANGED else 3
    for z in range(nz):
        if blocks and z % 4 == 0 and nx and ny:  # the flags of the slab's blocks, before its planes
            for by in range((ny + 3) // 4):
                for bx in range((nx + 3) // 4):
                    code(bool(flag(bx, by, z // 4)),
                         668 + flag(bx - 1, by, z // 4) + 2 * flag(bx, by - 1, z // 4) + 4 * flag(bx, by, z // 4 - 1))
        for y in range(ny):
            for x in range(nx):
                if blocks and not flag(x // 4, y // 4, z // 4):
                    continue  # a blank block's cells are background and not coded
                c = int(grid[z, y, x])
                near = sum(1 << i for i, (dx, dy, dz) in enumerate(NEAR) if cls(x + dx, y + dy, z + dz))
                if near:
                    ctx = near
                else:
                    ctx = 512 + sum(1 << i for i, (dx, dy, dz) in enumerate(FAR) if cls(x + dx, y + dy, z + dz))
                code(c != background, ctx)
                if c == background:
                    continue
                code(c == 1, 640 + cls(x - 1, y, z) + 3 * cls(x, y - 1, z) + 9 * cls(x, y, z - 1))
                if c != 1:
                    code(c == other, 667)
    # a leading zero byte, then the low end's 32 + 8 * shifts bits
    return state["low"].to_bytes(state["shifts"] + 5, "big")


boxes = st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 7), st.floats(0, 1),
                  st.sampled_from([UNCHANGED, UNKNOWN]), st.integers(0, 2**32 - 1))


def make_box(nx, ny, nz, density, background, seed):
    rng = np.random.default_rng(seed)
    n = nx * ny * nz
    foreground = rng.choice([0, 1, 2, 3], n, p=[0.6, 0.3, 0.05, 0.05]).astype(np.uint8)
    return np.where(rng.random(n) < density, foreground, background).astype(np.uint8)


@settings(max_examples=150, deadline=None)
@given(boxes)
def test_stream_is_byte_identical_to_the_plain_reference_and_round_trips(box):
    nx, ny, nz, density, background, seed = box
    codes = make_box(nx, ny, nz, density, background, seed)
    stream = compress_box(codes, (nx, ny, nz), background)
    assert stream == reference_encode(codes, (nx, ny, nz), background)
    assert decompress_box(stream, (nx, ny, nz), background, "t").tolist() == codes.tolist()


# boxes up to 20 cells a side, changes in a few places: blank 4^3 blocks next to busy ones
sparse_boxes = st.tuples(st.integers(1, 20), st.integers(1, 20), st.integers(1, 20), st.floats(0, 1),
                         st.sampled_from([UNCHANGED, UNKNOWN]), st.integers(0, 2**32 - 1), st.integers(1, 4))


@settings(max_examples=120, deadline=None)
@given(sparse_boxes)
def test_block_stream_is_byte_identical_to_the_plain_reference_and_round_trips(box):
    nx, ny, nz, density, background, seed, clumps = box
    rng = np.random.default_rng(seed)
    codes = np.full(nx * ny * nz, background, np.uint8).reshape(nz, ny, nx)
    for _ in range(clumps):  # a few clumps of changes, so that some blocks stay blank
        x, y, z = rng.integers(0, nx), rng.integers(0, ny), rng.integers(0, nz)
        part = make_box(4, 4, 4, density, background, seed + 1).reshape(4, 4, 4)
        codes[z:z + 4, y:y + 4, x:x + 4] = part[: nz - z, : ny - y, : nx - x]
    codes = codes.reshape(-1)
    idx = np.flatnonzero(codes != background)
    stream = compress_cells(idx, codes[idx], (nx, ny, nz), background)
    assert stream == reference_encode(codes, (nx, ny, nz), background, blocks=True)
    got_idx, got_vals = decompress_cells(stream, (nx, ny, nz), background, idx.shape[0], "t")
    assert got_idx.tolist() == idx.tolist() and got_vals.tolist() == codes[idx].tolist()


def test_a_huge_box_with_one_line_of_changes_codes_to_a_few_hundred_bytes():
    """A box of 4096^2 x 64 cells (1.07e9) with one line of changes: its 16.8 M blank blocks cost
    one decision each, quiet ones almost nothing (the coder never walks their cells: codec 3
    would walk every cell, for ~20 s)."""
    dims = (4096, 4096, 64)
    idx = np.arange(100, 200, dtype=np.int64) + 4096 * 4096 * 30
    vals = np.zeros(100, np.uint8)
    stream = compress_cells(idx, vals, dims, UNCHANGED)
    got = decompress_cells(stream, dims, UNCHANGED, 100, "t")
    assert got[0].tolist() == idx.tolist() and got[1].tolist() == vals.tolist()
    assert len(stream) < 2000


def test_lines_of_free_voxels_code_smaller_than_zstd_and_random_cells_still_round_trip():
    nx, ny, nz = 64, 48, 16
    codes = np.full(nx * ny * nz, UNCHANGED, np.uint8)
    rng = np.random.default_rng(5)
    for _ in range(40):  # rays: runs of free cells ending in a hit, as a LiDAR scan makes them
        y, z, x0 = rng.integers(0, ny), rng.integers(0, nz), rng.integers(0, nx // 2)
        length = rng.integers(5, nx // 2)
        codes[z * nx * ny + y * nx + x0 : z * nx * ny + y * nx + x0 + length] = 0
        codes[z * nx * ny + y * nx + x0 + length] = 1
    keys = np.stack(np.unravel_index(np.flatnonzero(codes != UNCHANGED), (nz, ny, nx))[::-1], axis=1) + 30000
    states = codes[codes != UNCHANGED]
    cm = encode_packet("r", 0, 0, "nested", "cm", 0.1, keys, states)
    zstd = encode_packet("r", 0, 0, "nested", "zstd", 0.1, keys, states)
    assert len(cm) < len(zstd)
    # 49 k cells, mostly far from any ray: contexts settle at their floor, where the coder takes its
    # quick path for quiet cells and blank blocks; the bytes are still the reference's
    idx = np.flatnonzero(codes != UNCHANGED)
    stream = compress_cells(idx, codes[idx], (nx, ny, nz), UNCHANGED)
    assert stream == reference_encode(codes, (nx, ny, nz), UNCHANGED, blocks=True)
    # incompressible input: the stream outgrows the first buffer (2 bits a cell) and still decodes
    noise = rng.integers(0, 4, 4096).astype(np.uint8)
    stream = compress_box(noise, (16, 16, 16), UNCHANGED)
    assert len(stream) > noise.size // 4
    assert np.array_equal(decompress_box(stream, (16, 16, 16), UNCHANGED, "t"), noise)


def test_damaged_streams_are_refused():
    codes = make_box(9, 8, 7, 0.3, UNCHANGED, 1)
    stream = compress_box(codes, (9, 8, 7), UNCHANGED)
    with pytest.raises(FormatError, match="truncated"):
        decompress_box(stream[:-2], (9, 8, 7), UNCHANGED, "t")
    with pytest.raises(FormatError, match="trailing"):
        decompress_box(stream + b"\0", (9, 8, 7), UNCHANGED, "t")
    with pytest.raises(FormatError, match="zero byte"):
        decompress_box(b"\1" + stream[1:], (9, 8, 7), UNCHANGED, "t")


def test_a_box_too_large_for_its_stream_is_refused_before_decoding(monkeypatch):
    import struct
    import zlib

    import voxtool.codec.cm
    from voxtool.codec.packet import HEADER, MAGIC

    # 4000 x 4000 x 100 cells from 20 bytes: at least 1.6e9 / 32768 bytes would be needed
    head = HEADER.pack(MAGIC, 2, KIND_DELTA, 1, 3, b"r", 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 4000, 4000, 100, 1,
                       (4000 * 4000 * 100 + 3) // 4, 20, 0)
    payload = b"\0" * 20
    crc = zlib.crc32(payload, zlib.crc32(head[:-4]))
    monkeypatch.setattr(voxtool.codec.cm, "decompress_box", lambda *a: pytest.fail("decoded a hopeless box"))
    with pytest.raises(FormatError, match="cannot hold a box"):
        decode_packet(head[:-4] + struct.pack("<I", crc) + payload)


def test_cm_needs_the_nested_order():
    keys, states = np.array([[5, 5, 5]]), np.array([0], np.uint8)
    for scheme in ("hilbert", "racer", "occupied"):
        with pytest.raises(ValueError, match="cm"):
            encode_packet("r", 0, 0, scheme, "cm", 0.1, keys, states)


@pytest.mark.parametrize("name", ["packet_cm", "packet_cm_blocks", "packet_cm_keyframe", "packet_cm1",
                                  "packet_cm1_keyframe"])
def test_golden_vectors_payload_is_the_reference_stream(name):
    import json
    from pathlib import Path

    from voxtool.codec.packet import HEADER

    vectors = Path(__file__).resolve().parents[1] / "formats" / "vectors"
    blob = (vectors / f"{name}.bin").read_bytes()
    spec = json.loads((vectors / f"{name}.json").read_text())["decoded"]
    nx, ny, nz = spec["box_dims"]
    background = UNCHANGED if spec["kind"] == KIND_DELTA else UNKNOWN
    codes = np.full(nx * ny * nz, background, np.uint8)
    for x, y, z, s in spec["voxels"]:
        bx, by, bz = spec["box_min"]
        codes[(x - bx) + nx * ((y - by) + ny * (z - bz))] = s
    assert blob[HEADER.size:] == reference_encode(codes, (nx, ny, nz), background, blocks=spec["codec"] == "cm")


def test_a_box_without_cells_is_five_zero_bytes_whatever_its_other_sides():
    # a side of 0 beside two of ~40,000: no rows are walked and no planes allocated (found by
    # benchmarks/fuzz.py, where such a header took 28 s and 2 GB before)
    for dims in ((0, 39322, 39321), (39321, 16313, 0), (0, 0, 0)):
        assert compress_box(np.zeros(0, np.uint8), dims, UNCHANGED) == b"\0" * 5
        assert decompress_box(b"\0" * 5, dims, UNKNOWN, "t").shape == (0,)
        assert compress_cells(np.zeros(0, np.int64), np.zeros(0, np.uint8), dims, UNCHANGED) == b"\0" * 5
        assert decompress_cells(b"\0" * 5, dims, UNKNOWN, 0, "t")[0].shape == (0,)
    with pytest.raises(FormatError, match="trailing"):
        decompress_box(b"\0" * 6, (0, 39322, 39321), UNCHANGED, "t")
