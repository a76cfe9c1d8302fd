"""Decompression of untrusted bytes to a size declared beforehand (snapshots, packets)."""

from __future__ import annotations

import zstandard

from voxtool.errors import FormatError


def zstd_exact(data: bytes, size: int, what: str) -> bytes:
    """The zstd frame `data` decompressed, refused unless it is exactly `size` bytes. A frame
    may declare its own size, and the decompressor allocates whatever it declares: that size is
    checked against `size` before anything is allocated."""
    if size == 0:
        return b""
    try:
        declared = zstandard.frame_content_size(data)  # -1: not declared
        if declared not in (-1, size):
            raise FormatError(f"{what}: zstd frame declares {declared} bytes, {size} expected")
        out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    except zstandard.ZstdError as err:
        raise FormatError(f"{what}: does not decompress ({err})") from err
    if len(out) != size:
        raise FormatError(f"{what}: decompressed to {len(out)} bytes, {size} expected")
    return out
