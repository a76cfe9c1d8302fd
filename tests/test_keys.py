from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from voxtool.errors import KeyRangeError
from voxtool.keys import coords_to_keys, expand_leaves, key_bounds, keys_to_coords, morton_decode, morton_encode


def brute_morton(x: int, y: int, z: int) -> int:
    code = 0
    for b in range(16):
        code |= ((x >> b) & 1) << (3 * b) | ((y >> b) & 1) << (3 * b + 1) | ((z >> b) & 1) << (3 * b + 2)
    return code


@given(st.lists(st.tuples(*[st.integers(0, 65535)] * 3), min_size=1, max_size=50))
def test_morton_matches_bit_interleaving_and_round_trips(keys):
    arr = np.array(keys, dtype=np.int64)
    codes = morton_encode(arr)
    assert [int(c) for c in codes] == [brute_morton(*k) for k in keys]
    assert (morton_decode(codes) == arr).all()


def test_coords_to_keys_matches_octomap_floor_rule():
    pts = np.array([[0.0, -0.0, 0.19999], [-0.0001, 0.2, -0.2]], dtype=np.float32)
    keys = coords_to_keys(pts, 0.2)
    # float32(-0.2) = -0.2000000030 lies just below -0.2: floor(-1.00000001) = -2, as in OctoMap
    assert keys.tolist() == [[32768, 32768, 32768], [32767, 32769, 32766]]
    assert np.allclose(keys_to_coords(keys[:1], 0.2), [[0.1, 0.1, 0.1]])


def test_out_of_range_point_is_an_error_naming_point_and_limit():
    pts = np.array([[0, 0, 0], [7000.0, 0, 0]], dtype=np.float32)
    with pytest.raises(KeyRangeError, match=r"point 1 at \(7000.0, 0.0, 0.0\).*6553.6 m"):
        coords_to_keys(pts, 0.2)


def test_expand_leaves_covers_contiguous_morton_ranges():
    codes = expand_leaves(np.array([0, 64]), np.array([15, 16], dtype=np.uint8))
    assert codes.tolist() == list(range(8)) + [64]


@given(st.lists(st.tuples(*[st.integers(0, 65535)] * 3), min_size=1, max_size=50))
def test_key_bounds_are_the_per_axis_extremes(keys):
    arr = np.array(keys, dtype=np.uint16)
    lo, hi = key_bounds(arr)
    assert lo.tolist() == [min(k[a] for k in keys) for a in range(3)]
    assert hi.tolist() == [max(k[a] for k in keys) for a in range(3)]
    assert lo.dtype == np.int64 and (hi - lo + 1).min() >= 1  # no uint16 wrap-around in box sizes


@settings(deadline=None)  # the first example loads the kernel
@given(st.integers(0, (1 << 63) - 1), st.lists(st.integers(0, (1 << 63) - 1), max_size=300),
       st.integers(0, 62), st.integers(0, 62))
def test_sort_codes_sorts_like_python(base, values, low, high):
    """The radix sort over only the differing bits: values clustered around `base` (bits between
    low and high varying, so passes skip shared bits), duplicates, the top bit, empty lists."""
    from voxtool.kernels.sort import sort_codes

    keep = ((1 << 63) - 1) & ~(((1 << (max(low, high) + 1)) - 1) ^ ((1 << min(low, high)) - 1))
    a = np.array([(base & keep) | (v & ~keep) for v in values] + values[:3], dtype=np.int64)
    want = sorted(a.tolist())
    scratch = np.full(a.shape[0] + 1, -1, np.int64)
    sort_codes(a, scratch)
    assert a.tolist() == want


def test_sort_codes_sorts_a_scans_worth_in_place():
    from voxtool.kernels.sort import sort_codes

    rng = np.random.default_rng(5)
    codes = (np.int64(1) << 47) | rng.integers(0, 1 << 30, 20_000) << 1 | rng.integers(0, 2, 20_000)
    a = codes.copy()
    sort_codes(a, np.empty(a.shape[0], np.int64))
    assert np.array_equal(a, np.sort(codes))
    a = codes[:5].copy()
    sort_codes(a[1:4], np.empty(3, np.int64))  # a view: the values beyond it stay
    assert a[0] == codes[0] and a[4] == codes[4] and a[1:4].tolist() == sorted(codes[1:4].tolist())


def test_no_property_test_has_a_wall_clock_deadline():
    """Hypothesis' default 200 ms deadline failed a compiled-kernel property on a busy machine:
    the suite's profile (conftest) turns deadlines off for every property test."""
    from hypothesis import settings

    assert settings.default.deadline is None
