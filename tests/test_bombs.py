"""Decompression bombs: small files whose compressed records declare and expand to gigabytes of
zeros (CRCs matching) are refused before what they declare is allocated, for every compressed
input voxtool reads: snapshots, sharded parts, packet payloads and MCAP chunks. Each runs the
command in a fresh process and checks its peak memory."""

from __future__ import annotations

import hashlib
import json
import struct
import subprocess
import sys
import zlib

import numpy as np
import pytest
import zstandard

from voxtool.io import snapshot as S

PEAK_LIMIT_MIB = 700  # the command itself (Python, numpy, numba, zstd) takes ~250 MiB
# the peak is VmHWM, which exec resets (ru_maxrss keeps the forking parent's: a pytest worker's GBs)
RUN = """import sys
from voxtool.cli import main
try:
    main.main(sys.argv[1:], "voxtool")
    code = 0
except SystemExit as stop:
    code = stop.code
status = open("/proc/self/status").read().split("VmHWM:")[1].split()
print(code, int(status[0]) // 1024)
"""


def run_measured(*args) -> tuple[int, int, str]:
    """(exit code, peak RSS in MiB, stderr) of a voxtool command in a process of its own."""
    proc = subprocess.run([sys.executable, "-c", RUN, *map(str, args)], capture_output=True, text=True, timeout=120)
    code, peak = (int(v) for v in proc.stdout.split()[-2:])
    return code, peak, proc.stderr


def zeros_frame(n: int) -> bytes:
    """A zstd frame of n zero bytes (its size declared), made in 16 MiB steps."""
    stream = zstandard.ZstdCompressor(level=1).compressobj(size=n)
    step = bytes(16 << 20)
    out = [stream.compress(step[: min(len(step), n - k)]) for k in range(0, n, len(step))]
    return b"".join(out) + stream.flush()


def snapshot_with(header: dict, arrays: list[tuple[str, str, int, bytes, int]]) -> bytes:
    """Snapshot bytes with hand-made payloads: (name, dtype, count, stored bytes, raw bytes)."""
    table, payloads, offset = [], [], 0
    for name, dtype, count, stored, raw in arrays:
        table.append({"name": name, "dtype": dtype, "shape": [count], "codec": "zstd", "offset": offset,
                      "stored_bytes": len(stored), "raw_bytes": raw, "crc32": zlib.crc32(stored)})
        payloads.append(stored)
        offset += len(stored)
    head = json.dumps({**header, "arrays": table}).encode()
    body = S._FIXED.pack(S.MAGIC, S.VERSION, 0, len(head)) + head + b"".join(payloads)
    return body + struct.pack("<I", zlib.crc32(body))


@pytest.fixture(scope="module")
def header(sample_map):
    return {k: v for k, v in S.read_snapshot(sample_map[0]).header.items() if k != "arrays"}


LEAVES = 1 << 28  # 2 GiB of codes, 256 MiB of depths, 1 GiB of values: 3.3 GiB declared


@pytest.fixture(scope="module")
def leaf_bomb(header):
    return snapshot_with(header, [("leaf_codes", "int64", LEAVES, zeros_frame(8 * LEAVES), 8 * LEAVES),
                                  ("leaf_depths", "uint8", LEAVES, zeros_frame(LEAVES), LEAVES),
                                  ("leaf_values", "float32", LEAVES, zeros_frame(4 * LEAVES), 4 * LEAVES)])


def test_a_snapshot_bomb_is_refused_in_small_memory(leaf_bomb, tmp_path):
    path = tmp_path / "bomb.vxm"
    path.write_bytes(leaf_bomb)
    assert path.stat().st_size < 200_000
    code, peak, err = run_measured("stats", path)
    assert code == 5 and "not sorted" in err and err.count("\n") == 1, err
    assert peak < PEAK_LIMIT_MIB, peak


def test_a_snapshot_whose_other_array_is_a_bomb_is_refused(header, tmp_path):
    """Three real leaves, and a values array declaring 2^28 entries of zeros."""
    codes = np.array([0, 8, 16], dtype="<i8")
    path = tmp_path / "values.vxm"
    path.write_bytes(snapshot_with(header, [
        ("leaf_codes", "int64", 3, zstandard.compress(codes.tobytes()), 24),
        ("leaf_depths", "uint8", 3, zstandard.compress(bytes([16, 16, 16])), 3),
        ("leaf_values", "float32", LEAVES, zeros_frame(4 * LEAVES), 4 * LEAVES)]))
    code, peak, err = run_measured("stats", path)
    assert code == 5 and "decompression bomb" in err and "leaf_values" in err, err
    assert peak < PEAK_LIMIT_MIB


def test_a_sharded_part_bomb_is_refused(leaf_bomb, sample_map, tmp_path):
    from voxtool.io.sharded import FORMAT, MANIFEST, VERSION

    d = tmp_path / "parts"
    d.mkdir()
    (d / "part-0.vxm").write_bytes(leaf_bomb)
    manifest = {"format": FORMAT, "version": VERSION, "partitions": 1, "shard_depth": 6,
                "partition_rule": "fibonacci-hash", "backend": "octree",
                "map_params": {"resolution": 0.2}, "sensor_model": {}, "info": {},
                "parts": [{"file": "part-0.vxm", "bytes": len(leaf_bomb),
                           "sha256": hashlib.sha256(leaf_bomb).hexdigest()}]}
    (d / MANIFEST).write_text(json.dumps(manifest))
    code, peak, err = run_measured("export", d, "-o", tmp_path / "p.bt")
    assert code == 5 and "not sorted" in err, err
    assert peak < PEAK_LIMIT_MIB


def test_a_packet_payload_bomb_is_refused(tmp_path):
    """A keyframe packet whose box of 2^31 cells declares 512 MiB of 2-bit states, all zeros in
    a 16 KiB zstd frame, inside a real packet log."""
    from voxtool.codec.log import PacketLogWriter
    from voxtool.codec.packet import KIND_KEYFRAME, _assemble

    cells = 1 << 31
    raw = (cells + 3) // 4
    payload = zeros_frame(raw)
    blob = _assemble("r1", 0, 1_000_000_000, "hilbert", "zstd", KIND_KEYFRAME, 0.2, (0.0, 0.0, 0.0),
                     (0, 0, 0), (2048, 1024, 1024), 0, raw, payload)
    log = tmp_path / "bomb.mcap"
    with PacketLogWriter(log) as writer:
        writer.write("r1", 0, 1_000_000_000, blob)
    code, peak, err = run_measured("merge", log, "-o", tmp_path / "f.vxm", "--no-progress")
    assert code == 5 and "decompression bomb" in err, err
    assert peak < PEAK_LIMIT_MIB and not (tmp_path / "f.vxm").exists()


def mcap_with_chunk(chunk_data: bytes, uncompressed_size: int) -> bytes:
    """A ROS 2 MCAP by hand: a PointCloud2 channel and one zstd chunk of the given data and
    declared size, with its summary (schema, channel, statistics, chunk index)."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Schema, Statistics
    from ros2_writer import POINTCLOUD2

    magic = b"\x89MCAP0\r\n"
    schema = Schema(id=1, name="sensor_msgs/msg/PointCloud2", encoding="ros2msg", data=POINTCLOUD2.encode())
    channel = Channel(id=1, topic="/points", message_encoding="cdr", schema_id=1, metadata={})
    b = RecordBuilder()
    Header(profile="ros2", library="voxtool test").write(b)
    schema.write(b)
    channel.write(b)
    start = len(magic) + b.count
    Chunk(message_start_time=0, message_end_time=0, uncompressed_size=uncompressed_size, uncompressed_crc=0,
          compression="zstd", data=chunk_data).write(b)
    length = len(magic) + b.count - start
    DataEnd(data_section_crc=0).write(b)
    summary_start = len(magic) + b.count
    schema.write(b)
    channel.write(b)
    Statistics(message_count=1, schema_count=1, channel_count=1, attachment_count=0, metadata_count=0,
               chunk_count=1, message_start_time=0, message_end_time=0, channel_message_counts={1: 1}).write(b)
    ChunkIndex(message_start_time=0, message_end_time=0, chunk_start_offset=start, chunk_length=length,
               message_index_offsets={}, message_index_length=0, compression="zstd",
               compressed_size=len(chunk_data), uncompressed_size=uncompressed_size).write(b)
    Footer(summary_start=summary_start, summary_offset_start=0, summary_crc=0).write(b)
    return magic + b.end() + magic


def test_an_mcap_chunk_bomb_is_refused(tmp_path):
    n = 3 << 30
    path = tmp_path / "bomb.mcap"
    path.write_bytes(mcap_with_chunk(zeros_frame(n), n))
    code, peak, err = run_measured("build", path, "-o", tmp_path / "m.vxm", "--no-progress")
    assert code == 3 and "decompression bomb" in err and err.count("\n") == 1, err
    assert peak < PEAK_LIMIT_MIB and not (tmp_path / "m.vxm").exists()


def test_bag_chunks_are_decompressed_within_bounds(tmp_path):
    """rosbags expands a bag's chunk whole; voxtool bounds its decompressors: a 1 GiB lz4 frame
    of zeros (4 MB) stops at the bound, while a real lz4-compressed ROS 1 bag
    still reads (the PCD map, voxel for voxel)."""
    import lz4.frame
    from bag_writer import write_bag
    from scenes import box_scene, write_pcd, yaw_quat

    from voxtool.sources import open_source
    from voxtool.sources.bag_limits import BagBomb, bound_bag_chunks

    bound_bag_chunks()
    from rosbags.rosbag1 import reader as ros1

    frame = lz4.frame.compress(bytes(64 << 20))  # 64 MiB of zeros: within the bound's slack
    assert len(ros1.decompressors["lz4"](frame)) == 64 << 20
    stream = lz4.frame.LZ4FrameCompressor()  # 1 GiB of zeros in a 4 MB frame: beyond 256 MiB + 64x
    bomb = stream.begin() + b"".join(stream.compress(bytes(64 << 20)) for _ in range(16)) + stream.flush()
    with pytest.raises(BagBomb, match="decompression bomb"):
        ros1.decompressors["lz4"](bomb)
    scans = [(pts, o, yaw_quat(y)) for pts, o, y in box_scene(3, 300, seed=2)]
    from rosbags.rosbag1 import Writer

    real = tmp_path / "lz4.bag"
    original = Writer.__init__

    def lz4_writer(self, path):
        original(self, path)
        self.set_compression(Writer.CompressionFormat.LZ4)

    Writer.__init__ = lz4_writer
    try:
        write_bag(real, scans, "ros1")
    finally:
        Writer.__init__ = original
    assert b"compression=lz4" in real.read_bytes()
    d = tmp_path / "pcd"
    d.mkdir()
    for i, (pts, o, q) in enumerate(scans):
        write_pcd(d / f"{i}.pcd", pts, (*o, *q))
    got = [s.points for s in open_source(real).scans]
    want = [s.points for s in open_source(d).scans]
    assert all(np.array_equal(a, b) for a, b in zip(got, want)) and len(got) == 3


def test_a_ros2_bag_compressed_per_message_is_bounded_too(tmp_path):
    """A ROS 2 bag written by rosbags with zstd message compression still reads (the PCD map),
    and its message decompressor is the bounded one."""
    from bag_writer import write_bag
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Writer
    from scenes import box_scene, yaw_quat

    from voxtool.sources import open_source
    from voxtool.sources.bag_limits import BagBomb, bound_bag_chunks

    scans = [(pts, o, yaw_quat(y)) for pts, o, y in box_scene(3, 300, seed=3)]
    original = Writer.__init__

    def compressed(self, path, **kw):
        original(self, path, **kw)
        self.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)

    Writer.__init__ = compressed
    try:
        bag = write_bag(tmp_path / "zbag", scans, "ros2-db3")
    finally:
        Writer.__init__ = original
    assert "compression_mode: message" in (bag / "metadata.yaml").read_text()
    assert len(list(open_source(bag).scans)) == 3
    bound_bag_chunks()
    from rosbags.rosbag2 import reader

    with pytest.raises(BagBomb):
        reader.zstd.decompress(zeros_frame(1 << 30))
