"""Golden vectors in both directions, and snapshot round trips / corruption detection."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxtool.errors import FormatError
from voxtool.io.snapshot import parse_snapshot, read_snapshot, snapshot_bytes, write_snapshot

VECTORS = sorted((Path(__file__).resolve().parents[1] / "formats" / "vectors").glob("*.vxm"))


@pytest.mark.parametrize("vxm", VECTORS, ids=[p.stem for p in VECTORS])
def test_golden_vector_both_directions(vxm):
    expected = json.loads(vxm.with_suffix(".json").read_text())
    snap = parse_snapshot(vxm.read_bytes(), str(vxm))
    header = {k: v for k, v in snap.header.items() if k != "arrays"}
    assert header == expected["header"]
    assert {k: {"dtype": v.dtype.name, "shape": list(v.shape), "values": v.ravel().tolist()}
            for k, v in snap.arrays.items()} == expected["arrays"]
    arrays = {k: np.array(v["values"], dtype=v["dtype"]).reshape(v["shape"]) for k, v in expected["arrays"].items()}
    planed = tuple(expected.get("planed", ()))  # arrays in the delta8 layout
    assert [a["codec"] for a in snap.header["arrays"] if a["name"] in planed] == ["delta8"] * len(planed)
    assert snapshot_bytes(expected["header"], arrays, codec="raw", planed=planed) == vxm.read_bytes()


def test_vectors_exist():
    assert len(VECTORS) >= 2


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-5, 5, width=32), max_size=40), st.sampled_from(["zstd", "raw"]))
def test_round_trip(values, codec):
    arrays = {"v": np.array(values, np.float32), "i": np.arange(len(values), dtype=np.int64)}
    snap = parse_snapshot(snapshot_bytes({"backend": "x"}, arrays, codec=codec))
    assert snap.header["backend"] == "x"
    assert np.array_equal(snap.arrays["v"], arrays["v"]) and np.array_equal(snap.arrays["i"], arrays["i"])


def test_written_file_is_the_encoded_bytes(tmp_path):
    """write_snapshot writes piece by piece, with a running CRC: the same bytes, and it reads back."""
    arrays = {"codes": np.arange(0, 300_000, 3, dtype=np.int64), "v": np.linspace(-2, 2, 7, dtype=np.float32)}
    write_snapshot(tmp_path / "m.vxm", {"backend": "x"}, arrays)
    assert (tmp_path / "m.vxm").read_bytes() == snapshot_bytes({"backend": "x"}, arrays)
    assert np.array_equal(read_snapshot(tmp_path / "m.vxm").arrays["codes"], arrays["codes"])


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_any_single_byte_change_or_truncation_is_detected(data):
    blob = VECTORS[-1].read_bytes()
    pos = data.draw(st.integers(0, len(blob) - 1))
    flip = data.draw(st.integers(1, 255))
    bad = blob[:pos] + bytes([blob[pos] ^ flip]) + blob[pos + 1 :]
    with pytest.raises(FormatError):
        parse_snapshot(bad)
    with pytest.raises(FormatError):
        parse_snapshot(blob[: data.draw(st.integers(0, len(blob) - 1))])


PACKETS = sorted((Path(__file__).resolve().parents[1] / "formats" / "vectors").glob("packet_*.bin"))


@pytest.mark.parametrize("vector", PACKETS, ids=[p.stem for p in PACKETS])
def test_packet_golden_vector_both_directions(vector):
    from voxtool.codec.packet import decode_packet, encode_packet, occupied_frame
    from voxtool.keys import morton_encode

    spec = json.loads(vector.with_suffix(".json").read_text())
    p = decode_packet(vector.read_bytes())
    got = {"robot": p.robot, "seq": p.seq, "stamp_ns": p.stamp_ns, "scheme": p.scheme, "codec": p.codec, "kind": p.kind,
           "box_min": list(p.box_min), "box_dims": list(p.box_dims), "count": p.count,
           "voxels": sorted([*map(int, k), int(s)] for k, s in zip(p.keys, p.states))}
    assert got == spec["decoded"]
    kw = dict(spec["encode"])
    kw["keys"] = np.array(kw["keys"], dtype=np.int64).reshape(-1, 3)
    kw["states"] = np.array(kw["states"], dtype=np.uint8)
    if "box" in kw:
        kw["box"] = tuple(np.array(v) for v in kw["box"])
    if "frames" in kw:
        kw["frames"] = [occupied_frame(f, morton_encode(np.array(k, dtype=np.int64).reshape(-1, 3))) for f, k in kw["frames"]]
    blob = encode_packet(p.robot, p.seq, p.stamp_ns, resolution=0.1, **{"codec": "none", **kw})
    assert blob == vector.read_bytes()


def test_packet_vectors_exist():
    assert {p.stem for p in PACKETS} == {f"packet_{k}" for k in
                                         ("hilbert", "nested", "racer", "keyframe", "occupied", "cm", "cm_blocks",
                                          "cm_keyframe", "cm1", "cm1_keyframe")}


def test_version_1_packets_still_decode():
    """Logs written before the varint `occupied` payload (version 2) stay readable."""
    from voxtool.codec.packet import decode_packet

    vector = Path(__file__).resolve().parents[1] / "formats" / "vectors" / "v1" / "packet_occupied.bin"
    blob = vector.read_bytes()
    assert blob[4] == 1
    spec = json.loads(vector.with_suffix(".json").read_text())
    p = decode_packet(blob)
    assert sorted([*map(int, k), int(s)] for k, s in zip(p.keys, p.states)) == spec["decoded"]["voxels"]
    frames = p.frames
    assert [f for f, _ in frames] == [f for f, _ in spec["encode"]["frames"]]
    assert [k.tolist() for _, k in frames] == [k for _, k in spec["encode"]["frames"]]


def test_zstd_frames_declaring_another_size_are_refused_before_allocating():
    import struct

    import zstandard

    from voxtool.compression import zstd_exact
    from voxtool.errors import FormatError

    frame = zstandard.ZstdCompressor().compress(b"x" * 10)
    assert zstd_exact(frame, 10, "t") == b"x" * 10
    with pytest.raises(FormatError, match="declares 10 bytes"):
        zstd_exact(frame, 5, "t")
    # a frame header claiming 2^62 bytes (found by benchmarks/fuzz.py behind a valid CRC): the
    # decompressor would try to allocate that much
    hostile = b"\x28\xb5\x2f\xfd" + bytes([0xE0]) + struct.pack("<Q", 1 << 62) + b"\x01\x00\x00"
    with pytest.raises(FormatError):
        zstd_exact(hostile, 7, "t")
    with pytest.raises(FormatError):
        zstd_exact(b"not zstd", 7, "t")


def test_sharded_map_golden_vector():
    """formats/sharded.md: the manifest's parts hold the map's leaves, each in the partition the
    Fibonacci hash of its shard prefix names, and the parts are the snapshots of those leaves."""
    from voxtool.distbuild import partition_of
    from voxtool.io.sharded import iter_parts, load_sharded, read_manifest

    root = Path(__file__).resolve().parents[1] / "formats" / "vectors"
    expected = json.loads((root / "sharded_map.json").read_text())
    manifest = read_manifest(root / "sharded_map")
    leaves = load_sharded(root / "sharded_map").leaves()
    assert leaves.codes.tolist() == expected["leaf_codes"]
    assert leaves.values.tolist() == pytest.approx(expected["leaf_values"])
    codes = np.array(expected["leaf_codes"], np.int64)
    assert partition_of(codes, manifest["shard_depth"], manifest["partitions"]).tolist() == expected["partition"]
    from voxtool.stats import leaf_stats

    for entry, backend in iter_parts(root / "sharded_map"):
        p = int(entry["file"][5:10])
        mine = [c for c, q in zip(expected["leaf_codes"], expected["partition"]) if q == p]
        assert backend.leaves().codes.tolist() == mine
        # every field formats/sharded.md lists for a part, with the part's own figures
        assert set(entry) == {"file", "bytes", "sha256", "leaves", "occupied_voxels", "free_voxels", "occupied_bbox"}
        figures = leaf_stats(backend.leaves(), backend.params.resolution, backend.sensor.threshold_log)
        assert {k: entry[k] for k in figures} == figures


def test_delta8_leaf_codes_round_trip_and_shrink(sample_map):
    """A zstd snapshot stores its leaf codes as delta8 planes (formats/snapshot.md): the same
    codes read back, in blocks across the 2^20 boundary, smaller than zstd of the codes alone;
    a snapshot written before (codes in plain zstd) still reads."""
    from voxtool.io.delta_planes import BLOCK

    snap = read_snapshot(sample_map[0])
    codes = snap.arrays["leaf_codes"]
    assert codes.shape[0] > 2 * BLOCK
    entry = {a["name"]: a for a in snap.header["arrays"]}["leaf_codes"]
    assert entry["codec"] == "zstd-delta8"
    arrays = {k: v for k, v in snap.arrays.items()}
    old = parse_snapshot(snapshot_bytes({"backend": "octree"}, arrays, planed=()))
    new = parse_snapshot(snapshot_bytes({"backend": "octree"}, arrays))
    assert np.array_equal(old.arrays["leaf_codes"], codes) and np.array_equal(new.arrays["leaf_codes"], codes)
    sizes = {a["name"]: a["stored_bytes"] for a in old.header["arrays"]}
    assert entry["stored_bytes"] < sizes["leaf_codes"] / 2
