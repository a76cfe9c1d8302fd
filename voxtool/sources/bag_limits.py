"""What reading a ROS bag may meet that is not a bag's fault of format alone: the errors rosbags
and its decompressors raise on corrupt or truncated bags, and decompressors bounded so that a
bag bomb is refused before it fills memory. Both bag readers use it: rosbags' indexed one
(voxtool.sources.rosbag) and the record-by-record one (voxtool.sources.bag1_linear)."""

from __future__ import annotations


def bag_errors() -> tuple:
    """What rosbags and its decompressors raise on a corrupt or truncated bag (-> SourceError)."""
    import struct
    import zlib

    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error
    from rosbags.serde import SerdeError

    errors = [AnyReaderError, Reader1Error, Reader2Error, SerdeError, ValueError, EOFError, KeyError, IndexError,
              struct.error, zlib.error, AssertionError, OSError, BagBomb]
    try:
        import sqlite3

        errors.append(sqlite3.Error)
    except ImportError:  # a Python built without sqlite reads no .db3 bag anyway
        pass
    return tuple(errors)


class BagBomb(Exception):
    """A bag chunk that expands beyond what real data does (_bounded)."""


def _bounded(name: str, decompress) -> callable:
    """A chunk decompressor that stops at what real data expands to (compression.check_expansion's
    bound on the chunk's compressed bytes) instead of expanding a bomb to its end."""
    from voxtool.compression import expansion_limit

    def bounded(data, *_):
        limit = expansion_limit(len(data))
        out = decompress(bytes(data), limit + 1)
        if len(out) > limit:
            raise BagBomb(f"a {name} chunk of {len(data):,} bytes expands beyond {limit:,} bytes: more than real "
                          "data expands to (a corrupt bag, or a decompression bomb)")
        return out

    return bounded


def _bz2(data: bytes, most: int) -> bytes:
    import bz2

    return bz2.BZ2Decompressor().decompress(data, max_length=most)


def _lz4(data: bytes, most: int) -> bytes:
    import lz4.frame

    return lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=most)


def _zstd(data: bytes, most: int) -> bytes:
    import zstandard

    with zstandard.ZstdDecompressor().stream_reader(data) as reader:
        return reader.read(most)


def bounded_chunk_decompressor(kind: str):
    """The bounded decompressor of a ROS 1 chunk's compression (bz2, lz4)."""
    if kind == "bz2":
        return _bounded("bz2", _bz2)
    if kind == "lz4":
        return _bounded("lz4", _lz4)
    raise ValueError(f"unknown chunk compression '{kind}'")


_BOUNDED = False


def bound_bag_chunks() -> None:
    """rosbags decompresses a chunk whole, to whatever it expands to (a ROS 1 chunk by bz2 or lz4,
    a ROS 2 MCAP chunk by zstd or lz4, a ROS 2 bag's messages by zstd). Its decompressors are
    swapped, once per process, for bounded ones, so that a bag bomb is refused before it fills
    memory (rosbags offers no limit of its own)."""
    global _BOUNDED
    if _BOUNDED:
        return
    from rosbags.rosbag1 import reader as ros1
    from rosbags.rosbag2 import reader as ros2_reader
    from rosbags.rosbag2 import storage_mcap as ros2

    ros1.decompressors.update(bz2=_bounded("bz2", _bz2), lz4=_bounded("lz4", _lz4))
    ros2.DECOMPRESSORS.update(zstd=_bounded("zstd", _zstd), lz4=_bounded("lz4", _lz4))
    ros2_reader.zstd = _MessageZstd(ros2_reader.zstd)  # a ROS 2 bag compressed message by message
    _BOUNDED = True


class _MessageZstd:
    """rosbags' zstd module with decompress() bounded (its file-mode reading streams to disk)."""

    def __init__(self, real) -> None:
        self._real = real
        self.decompress = _bounded("zstd message", _zstd)

    def __getattr__(self, name: str):
        return getattr(self._real, name)
