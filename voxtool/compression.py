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


# What a compressed record may expand to before voxtool lets a library allocate it: real data
# (point clouds, packet payloads of mostly unchanged cells, NaN-filled organized clouds) stays
# within SMALL + RATIO x its compressed bytes; a decompression bomb (kilobytes declaring
# gigabytes of zeros) does not.
EXPANSION_SMALL = 256 << 20
EXPANSION_RATIO = 64


def expansion_limit(stored: int, small: int = EXPANSION_SMALL, ratio: int = EXPANSION_RATIO) -> int:
    """The most bytes `stored` compressed bytes of real data expand to."""
    return small + ratio * stored


def check_expansion(declared: int, stored: int, what: str, small: int = EXPANSION_SMALL,
                    ratio: int = EXPANSION_RATIO) -> None:
    """Refuse `declared` uncompressed bytes from `stored` compressed ones beyond that bound."""
    if declared > expansion_limit(stored, small, ratio):
        raise FormatError(f"{what} declares {declared:,} bytes from {stored:,} compressed: more than real data "
                          "expands to (a corrupt file, or a decompression bomb)")


def check_mcap_chunks(handle, summary, where: str) -> None:
    """Every chunk of an indexed MCAP file, checked before the mcap library decompresses it
    (it allocates the size a chunk record declares): each chunk record's own uncompressed size
    against its length. Reads 33 bytes a chunk; the file position is kept."""
    import struct

    if summary is None:
        return
    position = handle.tell()
    try:
        for index in summary.chunk_indexes:
            handle.seek(index.chunk_start_offset)
            head = handle.read(33)  # opcode, record length, start and end time, uncompressed size
            if len(head) < 33:
                raise FormatError(f"{where}: a chunk at byte {index.chunk_start_offset} lies beyond the end of the file")
            _, length, _, _, size = struct.unpack("<BQQQQ", head)
            check_expansion(size, length, f"{where}: the chunk at byte {index.chunk_start_offset}")
    finally:
        handle.seek(position)
