"""Codecs `cm` (4) and `cm1` (3): a packet box coded by a 3D context model and a binary range coder.

zstd and zlib see a box as a string of bytes, four cells each, along one curve. What a box holds
is 3D: thin lines of newly free voxels and surfaces of new hits. cm codes each cell with a
probability learned from the cells already coded around it in 3D, and so spends 40-60 %
fewer bytes than zstd on the real streams (docs/packets.md). `cm` (codec 4) codes one decision
per 4 x 4 x 4 block first and then the cells of the blocks that hold changes only, so its work
follows the changes, not the box's volume; `cm1` (codec 3, the first cm coder) codes every cell and
is kept so that older logs decode. Bytes: formats/packet.md.
"""

from __future__ import annotations

import numpy as np

from voxtool.errors import FormatError


def compress_box(codes: np.ndarray, dims, background: int) -> bytes:
    """The cm stream of a box's codes (uint8, x-fastest order, 0..3). `background` is the code
    most cells hold: 3 (unchanged) in a delta, 2 (unknown) in a keyframe."""
    from voxtool.kernels.cm import encode_box

    nx, ny, nz = (int(d) for d in dims)
    codes = np.ascontiguousarray(codes, dtype=np.uint8)
    out = np.empty(codes.shape[0] // 4 + 5 * nx + 64, dtype=np.uint8)
    while True:
        n = encode_box(codes, nx, ny, nz, background, out)
        if n >= 0:
            return out[:n].tobytes()
        out = np.empty(2 * out.shape[0], dtype=np.uint8)  # a box that codes to more than 2 bits a cell


def decompress_box(data: bytes, dims, background: int, where: str) -> np.ndarray:
    """The codes of a box from its cm stream; the stream must end exactly where the box does."""
    from voxtool.kernels.cm import decode_box

    nx, ny, nz = (int(d) for d in dims)
    codes = np.empty(nx * ny * nz, dtype=np.uint8)
    used = decode_box(codes, nx, ny, nz, background, np.frombuffer(data, dtype=np.uint8))
    if used < 0:
        raise FormatError(f"{where}: cm stream does not start with its zero byte")
    if used != len(data):
        what = "is truncated" if used > len(data) else f"has {len(data) - used} trailing bytes"
        raise FormatError(f"{where}: cm stream {what} (the box needs {used} bytes, the packet holds {len(data)})")
    return codes


def compress_cells(idx: np.ndarray, vals: np.ndarray, dims, background: int) -> bytes:
    """The codec-4 stream of a box given its non-background cells: `idx` their nested indices
    (x + nx (y + ny z)), ascending, `vals` their codes; every other cell is `background`."""
    from voxtool.kernels.cm import BLOCK, encode_blocks

    nx, ny, nz = (int(d) for d in dims)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    vals = np.ascontiguousarray(vals, dtype=np.uint8)
    # room for what the coder checks before each slab (2 bytes a block of it) and each run of
    # cells (5 bytes a cell) beside about 0.3 bytes a cell coded: a second pass is rare
    blocks = -(-nx // BLOCK) * -(-ny // BLOCK)
    out = np.empty(idx.shape[0] // 2 + 2 * blocks + 5 * nx + 64, dtype=np.uint8)
    while True:
        n, _ = encode_blocks(idx, vals, nx, ny, nz, background, out, idx, vals)
        if n == -3:
            raise ValueError("cm cells must be distinct nested indices inside the box, ascending")
        if n >= 0:
            return out[:n].tobytes()
        out = np.empty(2 * out.shape[0], dtype=np.uint8)


def decompress_cells(data: bytes, dims, background: int, max_cells: int, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(nested indices, codes) of a box's non-background cells from its codec-4 stream, at
    most `max_cells` of them; the stream must end exactly where the box does."""
    from voxtool.kernels.cm import decode_blocks

    nx, ny, nz = (int(d) for d in dims)
    idx = np.empty(max_cells, dtype=np.int64)
    vals = np.empty(max_cells, dtype=np.uint8)
    used, n = decode_blocks(idx[:0], vals[:0], nx, ny, nz, background, np.frombuffer(data, dtype=np.uint8), idx, vals)
    if used == -1:
        raise FormatError(f"{where}: cm stream does not start with its zero byte")
    if used == -2:
        raise FormatError(f"{where}: cm stream holds more than the {max_cells} cells the packet declares")
    if used != len(data):
        what = "is truncated" if used > len(data) else f"has {len(data) - used} trailing bytes"
        raise FormatError(f"{where}: cm stream {what} (the box needs {used} bytes, the packet holds {len(data)})")
    return idx[:n], vals[:n]


def warm_up(codec: str = "cm", decode: bool = True) -> None:
    """Load (or compile) a codec's coder now, so that the first packet's timing is the coder's
    own; the decoder too unless `decode` is False (an encoder never runs it: compiling it cost
    a first `encode --codec cm` 5.5 s of its 16)."""
    idx, vals = np.array([1], dtype=np.int64), np.array([0], dtype=np.uint8)
    if codec == "cm1":
        codes = np.full(8, 3, dtype=np.uint8)
        codes[1] = 0
        blob = compress_box(codes, (2, 2, 2), 3)
        if decode:
            decompress_box(blob, (2, 2, 2), 3, "warm-up")
        return
    blob = compress_cells(idx, vals, (2, 2, 2), 3)
    if decode:
        decompress_cells(blob, (2, 2, 2), 3, 1, "warm-up")
