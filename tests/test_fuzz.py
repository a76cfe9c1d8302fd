"""Property-based fuzzing of every decoder (small budget here; benchmarks/fuzz.py runs 10^6+):
any bytes either decode or raise VoxtoolError — never another exception."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from voxtool.errors import VoxtoolError

SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.fixture(scope="module")
def seeds():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import fuzz

    return fuzz.seeds(), fuzz.targets()


@st.composite
def mutated(draw, blobs):
    blob = bytearray(draw(st.sampled_from(blobs)))
    for _ in range(draw(st.integers(1, 4))):
        if not blob:
            break
        i = draw(st.integers(0, len(blob) - 1))
        op = draw(st.integers(0, 3))
        if op == 0:
            blob[i] ^= 1 << draw(st.integers(0, 7))
        elif op == 1:
            del blob[i:]
        elif op == 2:
            blob[i:i] = draw(st.binary(min_size=1, max_size=8))
        else:
            blob[i : i + 4] = b"\xff\xff\xff\x7f"
    return bytes(blob)


@pytest.mark.parametrize("target", ["pcd", "ply", "snapshot", "packet", "packet_log", "bt"])
def test_decoder_never_crashes(seeds, target):
    pool, funcs = seeds

    @SETTINGS
    @given(mutated(pool[target]))
    def run(blob):
        try:
            funcs[target](blob)
        except VoxtoolError:
            pass

    run()


@SETTINGS
@given(st.binary(max_size=300))
def test_random_bytes_are_refused_as_snapshot_and_packet(blob):
    from voxtool.codec.packet import decode_packet
    from voxtool.io.snapshot import parse_snapshot

    for f in (parse_snapshot, decode_packet):
        with pytest.raises(VoxtoolError):
            f(blob)


def test_valid_seeds_decode(seeds):
    pool, funcs = seeds
    for name, blobs in pool.items():
        for blob in blobs:
            funcs[name](blob)

