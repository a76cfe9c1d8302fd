"""Box payloads built and read by their changed cells only (hilbert.ranks_of / cells_at,
kernels.cells2bit, the fusion's running latest-state set) against the whole-box references they
replace: the Hilbert order of every cell (box_order, itself checked against Skilling's index),
a dense grid packed cell by cell, and a lexicographic sort of every change."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxtool.codec.hilbert import box_order, cells_at, ranks_of
from voxtool.codec.packet import UNCHANGED, decode_packet, encode_packet, pack_2bit

dims_st = st.tuples(st.integers(1, 33), st.integers(1, 33), st.integers(1, 20))


def _cells(dims, seed, share):
    rng = np.random.default_rng(seed)
    n = int(np.prod(dims))
    idx = rng.choice(n, max(1, int(n * share)), replace=False)
    rel = np.stack([idx % dims[0], (idx // dims[0]) % dims[1], idx // (dims[0] * dims[1])], axis=1)
    return idx, rel, rng


@settings(max_examples=150)
@given(dims_st, st.integers(0, 2**32 - 1), st.floats(0.0, 1.0))
def test_ranks_and_cells_are_the_curve_of_every_cell(dims, seed, share):
    order = box_order(*dims)  # nested index of every cell, in curve order
    rank_of = np.empty(order.shape[0], np.int64)
    rank_of[order] = np.arange(order.shape[0])
    idx, rel, _ = _cells(dims, seed, share)
    ranks = ranks_of(rel, dims)
    assert np.array_equal(ranks, rank_of[idx])
    back = cells_at(np.sort(ranks), dims)
    assert np.array_equal(back[:, 0] + dims[0] * (back[:, 1] + dims[1] * back[:, 2]), order[np.sort(ranks)])


@pytest.mark.parametrize("dims", [(300, 200, 3), (1000, 2, 2), (2, 3, 1500), (64, 64, 64), (90, 70, 33)])
def test_ranks_of_cells_in_morton_order_on_large_and_flat_boxes(dims):
    """A packet's cells come in Morton order, which the rank walk reuses (each cell's descent
    starts where it leaves the one before); duplicates get the same rank. Against the curve of
    every cell, on boxes far from cubes (levels across the box's faces) and up to 2^11 a side."""
    from voxtool.keys import morton_encode

    order = box_order(*dims)
    rank_of = np.empty(order.shape[0], np.int64)
    rank_of[order] = np.arange(order.shape[0])
    idx, rel, rng = _cells(dims, 7, 0.05)
    idx = np.concatenate([idx, idx[:50]])  # some cells twice
    rel = np.stack([idx % dims[0], (idx // dims[0]) % dims[1], idx // (dims[0] * dims[1])], axis=1)
    by_morton = np.argsort(morton_encode(rel + 1000), kind="stable")
    assert np.array_equal(ranks_of(rel[by_morton], dims), rank_of[idx[by_morton]])


def test_code_keys_is_morton_decode():
    from voxtool.kernels.morton import code_keys
    from voxtool.keys import morton_decode, morton_encode

    keys = np.random.default_rng(3).integers(0, 65536, (5000, 3)).astype(np.uint16)
    keys[0] = 65535
    keys[1] = 0
    codes = morton_encode(keys)
    out = np.empty((codes.shape[0], 3), np.uint16)
    code_keys(codes, out)
    assert np.array_equal(out, keys) and np.array_equal(out, morton_decode(codes))


@settings(max_examples=120)
@given(dims_st, st.integers(0, 2**32 - 1), st.floats(0.0, 0.5), st.sampled_from(["hilbert", "nested"]),
       st.sampled_from(["none", "zstd"]))
def test_a_delta_payload_is_the_dense_grid_packed_cell_by_cell(dims, seed, share, scheme, codec):
    """The payload of placed changed cells equals the whole grid of 'unchanged' with the changes
    set, put in curve (or nested) order and packed; decoding gives the changes back."""
    idx, rel, rng = _cells(dims, seed, share)
    lo = np.array([30000, 31000, 32000])
    states = rng.integers(0, 3, idx.shape[0]).astype(np.uint8)
    blob = encode_packet("r", 0, 0, scheme, codec, 0.1, rel + lo, states, box=(lo, np.array(dims)))
    grid = np.full(int(np.prod(dims)), UNCHANGED, np.uint8)
    grid[idx] = states
    reference = pack_2bit(grid[box_order(*dims)] if scheme == "hilbert" else grid)
    packet = decode_packet(blob)
    assert packet.raw_size == len(reference) and packet.count == idx.shape[0]
    if codec == "none":
        assert blob[96:] == reference
    order = np.argsort(idx)
    assert np.array_equal(packet.keys.astype(np.int64), (rel + lo)[order]) and np.array_equal(packet.states, states[order])
    unordered = decode_packet(blob, ordered=False)
    assert sorted(map(tuple, unordered.keys.tolist())) == sorted(map(tuple, packet.keys.tolist()))


@settings(max_examples=80)
@given(st.lists(st.lists(st.tuples(st.integers(0, 300), st.integers(0, 2)), max_size=60), max_size=40),
       st.booleans())
def test_the_running_latest_state_equals_a_sort_of_every_change(packets, background):
    """Packets fused in order: each voxel's state is its last change (the lexsort of all changes
    by code, then by packet, that fusion used before), whatever the batch sizes, merged on the
    caller's thread or on a thread of their own while packets are still added."""
    from voxtool.codec.fusion import LatestStates

    latest = LatestStates(background=background)
    latest.MIN_BATCH = 7  # small batches: merges of the running set happen many times
    all_codes, all_states, ranks = [], [], []
    for k, changes in enumerate(packets):
        codes = np.array([c for c, _ in changes], np.int64)
        states = np.array([s for _, s in changes], np.uint8)
        latest.add(codes, states)
        all_codes.append(codes)
        all_states.append(states)
        ranks.append(np.full(codes.shape[0], k))
    got_codes, got_states = latest.result()
    if not all_codes or not sum(c.shape[0] for c in all_codes):
        assert got_codes.shape[0] == 0
        return
    codes, states, rank = map(np.concatenate, (all_codes, all_states, ranks))
    order = np.lexsort((np.arange(codes.shape[0]), codes))  # by code, then in the order given
    codes, states = codes[order], states[order]
    last = np.append(codes[1:] != codes[:-1], True)
    assert np.array_equal(got_codes, codes[last]) and np.array_equal(got_states, states[last])


@settings(max_examples=60)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4000), st.integers(0, 3))
def test_pruning_the_sorted_voxels_equals_the_octrees_pruned_leaves(seed, n, levels):
    """prune_into, in place as fusion's snapshot uses it (no tree built), gives the leaves OctreeMap
    gives for the same finest voxels: whole blocks of 2^levels voxels of one value merge up, mixed
    ones do not; and so does fusion.prune_in_parts, which prunes parts of them on threads at once."""
    from voxtool.codec.fusion import prune_in_parts
    from voxtool.config import MapParams, SensorModel
    from voxtool.kernels.sort import prune_into
    from voxtool.keys import morton_encode
    from voxtool.maps.octree import OctreeMap

    rng = np.random.default_rng(seed)
    side = 1 << levels
    corners = rng.integers(0, 40, (max(1, n // side ** 3), 3)) * side + 32000
    offsets = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = (corners[:, None, :] + offsets[None]).reshape(-1, 3)
    keys = np.concatenate([keys, rng.integers(32000, 32000 + 40 * side, (n // 4, 3))])
    codes = np.unique(morton_encode(keys.astype(np.uint16)))
    # one value per aligned block of side^3 voxels (whole blocks can merge), two values between blocks
    values = np.where((codes >> (3 * levels)) % 5 != 0, np.float32(3.5), np.float32(-2.0)).astype(np.float32)
    m = OctreeMap(MapParams(resolution=0.1), SensorModel())
    m.load_state({"leaf_codes": codes, "leaf_depths": np.full(codes.shape[0], 16, np.uint8), "leaf_values": values})
    reference = m.leaves()
    got_codes, got_values = codes.copy(), values.copy()
    got_depths = np.empty(codes.shape[0], np.uint8)
    top = prune_into(got_codes, got_values, got_codes, got_depths, got_values)
    got_codes, got_depths, got_values = got_codes[:top], got_depths[:top], got_values[:top]
    assert np.array_equal(got_codes, reference.codes) and np.array_equal(got_depths, reference.depths)
    assert np.array_equal(got_values, reference.values)
    assert levels == 0 or (reference.depths < 16).any()  # the blocks did merge: pruning was exercised
    for threads in (2, 3, 5):  # in parts at once, as the save prunes them: the same leaves
        got_codes, got_values, got_depths = codes.copy(), values.copy(), np.empty(codes.shape[0], np.uint8)
        top = prune_in_parts(got_codes, got_values, got_depths, threads)
        assert np.array_equal(got_codes[:top], reference.codes) and np.array_equal(got_depths[:top], reference.depths)
        assert np.array_equal(got_values[:top], reference.values)


@settings(max_examples=150)
@given(st.integers(0, 2**32 - 1), st.integers(0, 70), st.floats(0.0, 1.0), st.integers(0, 3), st.integers(-2, 2))
def test_the_scan_finds_the_cells_a_cell_by_cell_read_finds(seed, cells, share, background, room):
    """scan (four cells of a changed byte written at once) against unpack_2bit and a compare, with
    output room around the true count: exactly enough finds them all, one short is refused (-1),
    whatever padding the last byte holds."""
    from voxtool.codec.packet import unpack_2bit
    from voxtool.kernels.cells2bit import scan

    rng = np.random.default_rng(seed)
    codes = np.where(rng.random(cells) < share, rng.integers(0, 4, cells), background).astype(np.uint8)
    data = np.frombuffer(pack_2bit(codes), np.uint8)
    data = data.copy()
    if cells % 4:  # padding cells of another code than the background must not count either
        data[-1] |= np.uint8(0xFF << (2 * (cells % 4)) & 0xFF)
    want = np.flatnonzero(unpack_2bit(data.tobytes(), cells) != background)
    capacity = max(0, want.shape[0] + room)
    ranks, found = np.empty(capacity + 3, np.int64), np.empty(capacity + 3, np.uint8)
    n = scan(data, cells, background, ranks, found)
    if capacity < want.shape[0]:
        assert n == -1
    else:
        assert n == want.shape[0]
        assert np.array_equal(ranks[:n], want) and np.array_equal(found[:n], codes[want])


def test_a_header_count_that_differs_from_the_payload_is_refused():
    """A delta whose header declares one change more or fewer than its payload holds (CRC made
    anew, so only the count is wrong) is refused with the count named."""
    import zlib

    import pytest

    from voxtool.codec.packet import HEADER
    from voxtool.errors import FormatError

    rel = np.array([[0, 0, 0], [3, 1, 2], [4, 4, 4], [1, 2, 3]])
    lo = np.array([100, 100, 100])
    for scheme in ("hilbert", "nested"):
        blob = encode_packet("r", 0, 0, scheme, "none", 0.1, rel + lo, np.array([0, 1, 2, 1], np.uint8),
                             box=(lo, np.array([5, 5, 5])))
        for count, message in ((3, "more changed cells than the header's 3"), (5, "4 changed cells, header declares 5")):
            fields = list(HEADER.unpack_from(blob, 0))
            fields[18], fields[21] = count, 0
            head = HEADER.pack(*fields)[:-4]
            forged = head + zlib.crc32(blob[HEADER.size:], zlib.crc32(head)).to_bytes(4, "little") + blob[HEADER.size:]
            with pytest.raises(FormatError, match=message):
                decode_packet(forged)


def test_a_fusion_that_fails_midway_leaves_no_merging_thread():
    """Packets of two resolutions: fusion refuses the second after merging has started on its own
    thread (batches of 7 changes), and that thread is gone when the error reaches the caller."""
    import threading

    import pytest

    from voxtool.codec.fusion import LatestStates, fuse
    from voxtool.errors import FormatError

    lo = np.array([100, 100, 100])
    rel = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    states = np.zeros(rel.shape[0], np.uint8)
    blobs = [encode_packet("r", k, k, "hilbert", "zstd", 0.1 if k < 3 else 0.2, rel + lo, states) for k in range(4)]
    LatestStates.MIN_BATCH, before = 7, LatestStates.MIN_BATCH
    try:
        with pytest.raises(FormatError, match="resolution 0.2 m"):
            fuse([], packets=[decode_packet(b) for b in blobs])
    finally:
        LatestStates.MIN_BATCH = before
    assert not [t for t in threading.enumerate() if t.name.startswith("voxtool-fusion")]
