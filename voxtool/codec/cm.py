"""Codec `cm`: a packet box coded by a 3D context model and a binary range coder.

zstd and zlib see a box as a string of bytes, four cells each, along one curve. What a box holds
is 3D: thin lines of newly free voxels and surfaces of new hits. `cm` codes each cell with a
probability learned from the cells already coded around it in 3D, and so spends 40-60 %
fewer bytes than zstd on the real streams (docs/packets.md). Bytes: formats/packet.md.
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


def warm_up() -> None:
    """Load (or compile) the coder now, so that the first packet's timing is the coder's own."""
    codes = np.full(8, 3, dtype=np.uint8)
    decompress_box(compress_box(codes, (2, 2, 2), 3), (2, 2, 2), 3, "warm-up")
