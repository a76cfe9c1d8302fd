"""Map-change packets: Hilbert order, packet round trips, logs, lossless replay, fusion, resend."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scenes import box_scene, write_pcd, yaw_quat

from voxtool.codec.encode import EncodeOptions, encode_stream, split_changes
from voxtool.codec.fusion import Extrinsic, fuse, packets_of
from voxtool.codec.hilbert import box_order, hilbert_index
from voxtool.codec.packet import (
    CODECS,
    KIND_KEYFRAME,
    SCHEMES,
    UNCHANGED,
    address_width,
    decode_packet,
    encode_packet,
    pack_2bit,
    unpack_2bit,
)
from voxtool.codec.resend import ChannelModel, simulate
from voxtool.config import MapParams, SensorModel
from voxtool.errors import FormatError
from voxtool.keys import expand_leaves, morton_decode, morton_encode
from voxtool.maps import make_backend
from voxtool.sources import SourceOptions, open_source


@settings(max_examples=60, deadline=None)
@given(st.tuples(st.integers(1, 12), st.integers(1, 12), st.integers(1, 12)))
def test_box_order_is_skillings_hilbert_order_restricted_to_the_box(dims):
    dx, dy, dz = dims
    bits = max(0, (max(dims) - 1).bit_length())
    cells = [(x, y, z) for z in range(dz) for y in range(dy) for x in range(dx)]
    expected = sorted(range(len(cells)), key=lambda i: hilbert_index(*cells[i], bits))
    assert box_order(dx, dy, dz).tolist() == expected


def test_hilbert_curve_moves_one_cell_at_a_time_in_a_cube():
    order = box_order(8, 8, 8)
    xyz = np.stack([order % 8, (order // 8) % 8, order // 64], axis=1)
    assert np.all(np.abs(np.diff(xyz, axis=0)).sum(axis=1) == 1)


@given(st.lists(st.integers(0, 3), max_size=50))
def test_2bit_packing_round_trip(codes):
    arr = np.array(codes, dtype=np.uint8)
    assert unpack_2bit(pack_2bit(arr), len(codes)).tolist() == codes


voxel_sets = st.integers(0, 2**32 - 1).map(lambda seed: np.random.default_rng(seed))


@settings(max_examples=40, deadline=None)
@given(voxel_sets, st.sampled_from([(s, c) for s in SCHEMES[:3] for c in CODECS if c not in ("cm", "cm1") or s == "nested"]),
       st.integers(1, 300))
def test_packet_round_trip(rng, scheme_codec, n):
    scheme, codec = scheme_codec
    keys = np.unique(rng.integers(40000, 40000 + rng.integers(1, 40), size=(n, 3)), axis=0)
    states = rng.integers(0, 3, keys.shape[0]).astype(np.uint8)
    box = (keys.min(axis=0) - 3, keys.max(axis=0) - keys.min(axis=0) + 7) if scheme == "racer" else None
    blob = encode_packet("robot-7", 42, 123456789, scheme, codec, 0.1, keys, states, box=box)
    p = decode_packet(blob)
    got = dict(zip(map(tuple, p.keys.tolist()), p.states.tolist()))
    assert got == dict(zip(map(tuple, keys.tolist()), states.tolist()))
    assert (p.robot, p.seq, p.stamp_ns, p.scheme, p.codec) == ("robot-7", 42, 123456789, scheme, codec)


def test_keyframe_holds_every_cell_and_no_unchanged():
    grid = np.array([0, 1, 2, 0, 1, 2, 2, 2], np.uint8)
    blob = encode_packet("r", 0, 0, "hilbert", "zstd", 0.2, np.zeros((0, 3)), grid, kind=KIND_KEYFRAME,
                         box=(np.array([10, 10, 10]), np.array([2, 2, 2])))
    p = decode_packet(blob)
    assert p.kind == KIND_KEYFRAME and p.keys.shape[0] == 8 and sorted(p.states.tolist()) == sorted(grid.tolist())
    bad = encode_packet("r", 0, 0, "nested", "none", 0.2, np.zeros((0, 3)), np.array([0, UNCHANGED], np.uint8),
                        kind=KIND_KEYFRAME, box=(np.array([1, 1, 1]), np.array([2, 1, 1])))
    with pytest.raises(FormatError, match="crc|CRC|unchanged"):
        decode_packet(bad)


def test_racer_address_width_follows_the_map_size():
    assert address_width((10, 10, 2)) == 1 and address_width((100, 100, 6)) == 2
    assert address_width((1000, 1000, 16)) == 3 and address_width((2000, 2000, 200)) == 4


@pytest.mark.parametrize("mutate,message", [
    (lambda b: b[:50], "shorter than the 96-byte"),
    (lambda b: b"XXXX" + b[4:], "bad magic"),
    (lambda b: b[:4] + bytes([9]) + b[5:], "version 9"),
    (lambda b: b[:-1] + bytes([b[-1] ^ 0xFF]), "CRC mismatch"),
    (lambda b: b + b"\0", "declares"),
])
def test_bad_packets_are_refused(mutate, message):
    blob = encode_packet("r", 1, 2, "hilbert", "zstd", 0.1, np.array([[5, 5, 5], [6, 7, 8]]), np.array([0, 1], np.uint8))
    with pytest.raises(FormatError, match=message):
        decode_packet(mutate(blob))


def test_huge_declared_box_fails_fast_without_allocating():
    import struct
    import zlib

    from voxtool.codec.packet import HEADER, MAGIC

    head = HEADER.pack(MAGIC, 1, 0, 0, 1, b"r", 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 65535, 65535, 65535, 1, 1 << 29, 10, 0)
    payload = b"\0" * 10
    crc = zlib.crc32(payload, zlib.crc32(head[:-4]))
    with pytest.raises(FormatError, match="exceeds"):
        decode_packet(head[:-4] + struct.pack("<I", crc) + payload)


def test_split_changes_keeps_runs_small_and_covers_everything():
    rng = np.random.default_rng(0)
    codes = np.unique(morton_encode(rng.integers(30000, 36000, size=(20000, 3))))
    runs = split_changes(codes, 1000)
    assert runs[0][0] == 0 and runs[-1][1] == codes.shape[0]
    assert all(a < b and b - a <= 1000 for a, b in runs)
    assert all(runs[i][1] == runs[i + 1][0] for i in range(len(runs) - 1))


def scene_dir(tmp_path, n=5, seed=3):
    d = tmp_path / "scans"
    d.mkdir()
    for i, (pts, o, yaw) in enumerate(box_scene(n, 400, seed=seed)):
        write_pcd(d / f"{i}.pcd", pts, (*o, *yaw_quat(yaw)))
    return d


def map_states(backend):
    lv = backend.leaves()
    codes = expand_leaves(lv.codes, lv.depths)
    vals = np.repeat(lv.values, np.left_shift(1, 3 * (16 - lv.depths.astype(np.int64))))
    return codes, (vals > 0).astype(np.uint8)


@pytest.mark.parametrize("scheme,codec", [(s, c) for s in ("hilbert", "nested", "racer") for c in ("zstd", "zlib", "none")]
                         + [("nested", "cm")])
def test_decoding_a_log_reproduces_the_robots_map(tmp_path, scheme, codec):
    src = scene_dir(tmp_path)
    backend = make_backend("octree", MapParams(0.1), SensorModel())
    out = tmp_path / "r.mcap"
    opts = EncodeOptions(robot="r1", scheme=scheme, codec=codec, max_changes=300, max_interval=0.25,
                         keyframe_every=4 if codec == "cm" else 0)
    report = encode_stream(open_source(src, SourceOptions()), backend, out, opts, {}, progress=False)
    assert report["packets"] > 5
    fused = fuse([out])
    codes, states = map_states(backend)
    assert np.array_equal(fused.codes, codes) and np.array_equal(fused.states, states)


def test_occupied_scheme_carries_the_ever_occupied_voxels(tmp_path):
    src = scene_dir(tmp_path)
    backend = make_backend("octree", MapParams(0.1), SensorModel())
    out = tmp_path / "o.mcap"
    encode_stream(open_source(src, SourceOptions()), backend, out, EncodeOptions(scheme="occupied", ring=2), {}, False)
    fused = fuse([out])
    codes, states = map_states(backend)
    # every voxel occupied now was newly occupied in some frame
    assert set(codes[states == 1].tolist()) <= set(fused.codes.tolist())
    packets = packets_of(out)
    assert all(p.count <= 2 for p in packets)


def test_two_robots_fuse_by_latest_stamp_and_extrinsics_move_keys(tmp_path):
    def mk(robot, keys, states, stamp, seq):
        return decode_packet(encode_packet(robot, seq, stamp, "hilbert", "none", 0.5, np.array(keys),
                                           np.array(states, np.uint8)))

    a = [mk("a", [[10, 10, 10], [11, 10, 10]], [1, 1], 100, 0), mk("a", [[10, 10, 10]], [0], 300, 1)]
    b = [mk("b", [[10, 10, 10], [12, 10, 10]], [1, 0], 200, 0), mk("b", [[12, 10, 10]], [1], 300, 2)]
    order = sorted(a + b, key=lambda p: (p.stamp_ns, p.robot, p.seq))
    fused = fuse([], packets=iter(order))
    got = dict(zip(map(tuple, morton_decode(fused.codes).tolist()), fused.states.tolist()))
    assert got == {(10, 10, 10): 0, (11, 10, 10): 1, (12, 10, 10): 1}
    assert fused.robots["b"]["gaps"] == [1]
    _, ext = Extrinsic.parse("b=1.0,0,0,1,0,0,0")  # two voxels of 0.5 m along x
    shifted = fuse([], {"b": ext}, packets=iter(order))
    keys = set(map(tuple, morton_decode(shifted.codes).tolist()))
    assert (14, 10, 10) in keys and (12, 10, 10) in keys


def test_a_voxel_last_seen_unknown_leaves_the_fused_map():
    """Fusion drops (in place) the voxels whose latest state is unknown, keeping the others in
    Morton order; a voxel unknown and then seen again stays."""
    def mk(keys, states, stamp):
        return decode_packet(encode_packet("a", stamp, stamp, "hilbert", "none", 0.5, np.array(keys),
                                           np.array(states, np.uint8)))

    keys = [[10 + i, 10, 10] for i in range(6)]
    packets = [mk(keys, [1, 0, 1, 0, 1, 0], 0), mk(keys[:3], [2, 2, 2], 1), mk(keys[2:3], [0], 2)]
    fused = fuse([], packets=iter(packets))
    got = dict(zip(map(tuple, morton_decode(fused.codes).tolist()), fused.states.tolist()))
    assert got == {(12, 10, 10): 0, (13, 10, 10): 0, (14, 10, 10): 1, (15, 10, 10): 0}
    assert np.all(np.diff(fused.codes) > 0)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_resend_under_loss_reorder_and_duplicates_equals_lossless(tmp_path, seed):
    blobs = {}
    for robot, start in (("a", 0), ("b", 2)):
        d = tmp_path / robot
        d.mkdir()
        for i, (pts, o, yaw) in enumerate(box_scene(6, 300, seed=10 + start)):
            write_pcd(d / f"{i}.pcd", pts, (*o, *yaw_quat(yaw)))
        out = tmp_path / f"{robot}.mcap"
        encode_stream(open_source(d, SourceOptions()), make_backend("octree", MapParams(0.1), SensorModel()), out,
                      EncodeOptions(robot=robot, max_changes=200, max_interval=0.2), {}, False)
        from voxtool.codec.log import read_log

        blobs[robot] = [b for _, _, b in read_log(out)[1]]
    sim = simulate([], seed=seed, channel=ChannelModel(loss=0.3, duplicate=0.2), blobs=blobs)
    assert sim["lost"] > 0 and sim["resent"] >= sim["lost"] * 0.5 and sim["duplicates"] > 0
    assert sim["complete"] and sim["equal_to_lossless"]


@pytest.mark.parametrize("scheme,codec", [("hilbert", "zstd"), ("nested", "cm")])
def test_resend_falls_back_to_a_keyframe_after_a_long_outage(tmp_path, scheme, codec):
    d = scene_dir(tmp_path, n=6)
    out = tmp_path / "k.mcap"
    encode_stream(open_source(d, SourceOptions()), make_backend("octree", MapParams(0.1), SensorModel()), out,
                  EncodeOptions(robot="k", scheme=scheme, codec=codec, max_changes=100, max_interval=0.1), {}, False)
    from voxtool.codec.log import read_log

    blobs = {"k": [b for _, _, b in read_log(out)[1]]}
    sim = simulate([], seed=5, channel=ChannelModel(loss=0.9, keyframe_gap=3), blobs=blobs)
    assert sim["keyframes"] >= 1 and sim["complete"] and sim["equal_to_lossless"]


def test_periodic_keyframes_keep_the_replay_exact(tmp_path):
    src = scene_dir(tmp_path)
    backend = make_backend("octree", MapParams(0.1), SensorModel())
    out = tmp_path / "kf.mcap"
    report = encode_stream(open_source(src, SourceOptions()), backend, out,
                           EncodeOptions(max_changes=300, max_interval=0.25, keyframe_every=3), {}, progress=False)
    assert report["keyframes"] >= 1
    kinds = [p.kind for p in packets_of(out)]
    assert kinds.count(KIND_KEYFRAME) == report["keyframes"]
    fused = fuse([out])
    codes, states = map_states(backend)
    assert np.array_equal(fused.codes, codes) and np.array_equal(fused.states, states)


def test_bandwidth_windows_and_average():
    from voxtool.codec.logstats import _bandwidth

    s = 1_000_000_000
    # 10 s of 100-byte packets at 2 Hz and a 5 kB burst in second 4: the busiest second holds it
    stamps = np.arange(20) * s // 2
    sizes = np.full(20, 100)
    sizes[9] = 5000
    bw = _bandwidth(stamps, sizes, 10.0)
    assert bw["avg_Bps"] == pytest.approx(sizes.sum() / 10.0)
    assert bw["max_Bps"] == 5100
    # a log shorter than one window: its busiest second is not quieter than its average
    short = _bandwidth(np.array([0, s // 4]), np.array([300, 300]), 0.5)
    assert short["avg_Bps"] == 1200 and short["max_Bps"] == 1200


@pytest.mark.parametrize("n_lim,scheme,codec", [(-1, "hilbert", "zstd"), (400, "hilbert", "zstd"), (400, "nested", "cm")])
def test_hash_map_logs_decode_to_the_hash_map(tmp_path, n_lim, scheme, codec):
    """The hash map casts rays in apply() and drops voxels beyond its limit: a log of it must
    still replay to its map (voxels that left read as unknown, so they are absent; with cm such
    a voxel is the third decision's 'other' code)."""
    src = scene_dir(tmp_path)
    backend = make_backend("hashmap", MapParams(0.1), SensorModel(), n_lim=n_lim, d_inf=0.2)
    out = tmp_path / "h.mcap"
    report = encode_stream(open_source(src, SourceOptions()), backend, out,
                           EncodeOptions(scheme=scheme, codec=codec, max_changes=300, max_interval=0.25), {},
                           progress=False)
    if n_lim >= 0:
        assert any((p.states == 2).any() for p in packets_of(out))  # voxels that left the map
    assert report["packets"] > 5
    fused = fuse([out])
    codes, states = map_states(backend)
    known = fused.states != 2
    assert np.array_equal(fused.codes[known], codes) and np.array_equal(fused.states[known], states)
    if n_lim >= 0:
        assert len(backend.occupied_codes()) <= n_lim < report["changed_voxels"]


@given(st.lists(st.integers(0, (1 << 48) - 1), max_size=300, unique=True))
def test_varint_deltas_round_trip(values):
    from voxtool.codec.varint import decode_deltas, encode_deltas

    codes = np.sort(np.array(values, dtype=np.int64))
    data = b"\x01\x02" + encode_deltas(codes) + b"\xff"  # decoding starts and stops mid-buffer
    back, end = decode_deltas(data, 2, codes.shape[0], "test")
    assert np.array_equal(back, codes) and end == len(data) - 1


def test_varint_deltas_refuse_bad_input():
    from voxtool.codec.varint import decode_deltas, encode_deltas
    from voxtool.errors import FormatError

    good = encode_deltas(np.array([5, 300, 70000], np.int64))
    with pytest.raises(FormatError, match="end early"):
        decode_deltas(good[:-1], 0, 3, "t")  # truncated
    with pytest.raises(FormatError, match="repeat"):
        decode_deltas(bytes([5, 0]), 0, 2, "t")  # a zero step repeats a voxel
    with pytest.raises(FormatError, match="longer than"):
        decode_deltas(bytes([0x80] * 7 + [1, 1]), 0, 2, "t")  # an 8-byte varint
    with pytest.raises(FormatError, match="key range"):
        decode_deltas(bytes([0xFF] * 6 + [0x7F]), 0, 1, "t")  # 2^49 - 1


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200), st.integers(0, 5))
def test_occupied_payload_garbage_is_refused_cleanly(raw, count):
    """Behind the CRC: any payload bytes decode or raise FormatError, nothing else."""
    from voxtool.codec.packet import _read_frames
    from voxtool.errors import FormatError

    for version in (1, 2):
        try:
            frames = _read_frames(raw, count, version, "fuzz")
        except FormatError:
            continue
        for _, keys in frames:
            assert keys.ndim == 2 and keys.shape[1] == 3 and np.all((keys >= 0) & (keys < 65536))


def test_a_box_with_an_empty_side_decodes_to_nothing():
    """Found by the fuzzer: a header box of 0 x 0 x 1 cells (CRC made right) tripped an
    assertion in the Hilbert order instead of decoding to no voxel."""
    import struct
    import zlib

    from voxtool.codec.hilbert import box_order
    from voxtool.codec.packet import HEADER, decode_packet, encode_packet

    assert box_order(0, 0, 1).shape == (0,)
    b = bytearray(encode_packet("r", 1, 2, "hilbert", "none", 0.1, np.zeros((0, 3)), np.zeros(0, np.uint8)))
    struct.pack_into("<3H", b, 74, 0, 0, 1)  # box size
    struct.pack_into("<I", b, 92, zlib.crc32(bytes(b[HEADER.size:]), zlib.crc32(bytes(b[: HEADER.size - 4]))))
    p = decode_packet(bytes(b))
    assert p.keys.shape == (0, 3) and p.count == 0


@pytest.mark.parametrize("make, message", [
    (lambda: EncodeOptions(max_interval=float("nan")), "--max-interval"),
    (lambda: EncodeOptions(rate_hz=float("nan")), "--rate"),
    (lambda: EncodeOptions(keyframe_every=-1), "--keyframe-every -1"),
    (lambda: ChannelModel(loss=1.5), "loss rate 1.5"),
    (lambda: ChannelModel(loss=float("nan")), "loss rate nan"),
    (lambda: ChannelModel(max_delay=-1.0), "delay"),
    (lambda: Extrinsic.parse("r1=nan,0,0,1,0,0,0"), "holds NaN or inf"),
    (lambda: Extrinsic.parse("r1=0,0,0,0,0,0,0"), "quaternion has norm 0.000000"),
    (lambda: Extrinsic.parse("r1=0,0,0,2,0,0,0"), "quaternion has norm 2.000000"),
])
def test_encode_channel_and_extrinsic_values_are_checked(make, message):
    """NaN compares false with every bound, so each check is written to fail on it."""
    from voxtool.errors import ParameterError

    with pytest.raises(ParameterError) as err:
        make()
    assert message in str(err.value)
    assert Extrinsic.parse("r1=0,0,0,0.7071068,0,0,0.7071068")[0] == "r1"  # a unit quaternion passes


@pytest.mark.parametrize("dataset,resolution,max_range", [("quick_shack", 0.1, 7.0), ("kaist03", 0.2, 20.0)])
def test_cm_on_real_streams_is_lossless_and_20x_below_racer(shared_data, tmp_path, dataset, resolution, max_range):
    """The paper's Table I settings (its sensing range per resolution, d = 50,000, t = 0.5 s):
    the cm log replays to the robot's map, and RACER's ChunkData messages for the same changes
    (uint32 address + uint8 state per voxel, 52 bytes per message) take 20x its bytes or more."""
    src = shared_data / dataset / "pcd"
    sizes = {}
    for scheme, codec in (("nested", "cm"), ("racer", "none")):
        backend = make_backend("octree", MapParams(resolution, max_range=max_range), SensorModel())
        out = tmp_path / f"{scheme}.mcap"
        encode_stream(open_source(src, SourceOptions()), backend, out, EncodeOptions(scheme=scheme, codec=codec), {},
                      progress=False)
        packets = packets_of(out)
        if codec == "cm":
            sizes[codec] = sum(p.wire_bytes for p in packets)
            fused = fuse([out])
            codes, states = map_states(backend)
            assert np.array_equal(fused.codes, codes) and np.array_equal(fused.states, states)
        else:
            sizes[codec] = sum(52 + 5 * p.count for p in packets)
    assert sizes["none"] >= 20 * sizes["cm"], sizes
