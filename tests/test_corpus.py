"""Every case of the bad-input corpus: exact exit code, one clean error line naming the file and
the problem, no output file, no temporary file, and a pre-existing output left untouched."""

from __future__ import annotations

import pytest
from click.testing import CliRunner
from corpus.cases import CASES

from voxtool.cli import main

NAMES = [c[0] for c in CASES]


def test_corpus_is_large_and_names_are_unique():
    assert len(CASES) >= 60
    assert len(set(NAMES)) == len(NAMES)


@pytest.mark.parametrize("case", CASES, ids=NAMES)
def test_bad_input(tmp_path, case):
    name, make, exit_code, message = case
    args = [str(a) for a in make(tmp_path)]
    outputs = [tmp_path / n for n in ("out.vxm", "out.bt")]
    for out in outputs:
        out.write_bytes(b"previous result")
    result = CliRunner().invoke(main, args)
    lines = result.stderr.strip().splitlines()
    assert result.exit_code == exit_code, (name, result.stderr, result.exception)
    assert len(lines) == 1 and lines[0].startswith("voxtool: error: "), result.stderr
    assert message in lines[0], lines[0]
    assert str(tmp_path) in lines[0], "the message must name the file"
    for out in outputs:
        assert out.read_bytes() == b"previous result"
    assert not list(tmp_path.rglob(".voxtool-tmp-*"))


def test_empty_and_all_nan_scans_are_valid_input(tmp_path):
    """Not errors: an empty scan changes nothing, a scan of NaNs is dropped point by point."""
    import json

    import numpy as np
    from scenes import write_pcd

    d = tmp_path / "scans"
    d.mkdir()
    write_pcd(d / "0.pcd", np.zeros((0, 3), np.float32))
    write_pcd(d / "1.pcd", np.full((5, 3), np.nan, np.float32))
    write_pcd(d / "2.pcd", np.array([[1.0, 0.5, 0.2]], np.float32))
    result = CliRunner().invoke(main, ["build", str(d), "--json", "-o", str(tmp_path / "m.vxm")])
    assert result.exit_code == 0, result.stderr
    stats = json.loads(result.stdout)
    assert stats["scans"] == 3 and stats["points"] == 6 and stats["points_dropped"] == 5
    assert stats["occupied_voxels"] == 1
