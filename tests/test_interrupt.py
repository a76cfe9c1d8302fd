"""Interrupting `voxtool build`: SIGINT exits 130 cleanly, SIGKILL loses nothing the user had."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from scenes import write_pcd


@pytest.fixture(scope="module")
def slow_source(tmp_path_factory):
    """Scans that take seconds at 4 cm: long rays through a 36 m room."""
    d = tmp_path_factory.mktemp("slow")
    rng = np.random.default_rng(0)
    for i in range(40):
        dirs = rng.normal(size=(20000, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        write_pcd(d / f"{i}.pcd", (dirs * 18.0).astype(np.float32), (0.1 * i, 0, 0, 1, 0, 0, 0))
    return d


def start_build(source, out):
    proc = subprocess.Popen([sys.executable, "-m", "voxtool.cli", "build", str(source), "-o", str(out),
                             "--resolution", "0.04", "--progress"], stderr=subprocess.PIPE)
    proc.captured = []

    def pump():
        while chunk := os.read(proc.stderr.fileno(), 4096):
            proc.captured.append(chunk.decode(errors="replace"))

    threading.Thread(target=pump, daemon=True).start()
    return proc


def wait_for_progress(proc, scans=1, timeout=60.0):
    """Watch the progress bar until `scans` scans are done (the build is then mid-run)."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if f"{scans}/40" in "".join(proc.captured):
            return
        time.sleep(0.05)
    raise AssertionError(f"build did not progress: {''.join(proc.captured)[-500:]}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL])
def test_interrupted_build_keeps_the_previous_output(tmp_path, slow_source, sig):
    out = tmp_path / "map.vxm"
    out.write_bytes(b"previous map")
    proc = start_build(slow_source, out)
    wait_for_progress(proc)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    time.sleep(0.2)
    rest = "".join(proc.captured)
    if sig == signal.SIGINT:
        assert proc.returncode == 130
        assert "voxtool: interrupted; no output written" in rest
    else:
        assert proc.returncode == -signal.SIGKILL
    assert out.read_bytes() == b"previous map"
    assert not list(tmp_path.glob(".voxtool-tmp-*"))
