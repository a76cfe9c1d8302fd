"""Another revision of voxtool beside this checkout, for the before/after benchmarks
(bench_ab.py, bench_hashmap_ab.py): a detached git worktree in a temporary folder, removed
after, and a check that a python given PYTHONPATH=tree imports voxtool from that tree."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@contextlib.contextmanager
def revision(rev: str, tmp: Path) -> Iterator[Path]:
    """The tree of `rev` (a commit, tag or branch) as tmp/base while the block runs."""
    base = tmp / "base"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(base), rev], check=True)
    try:
        yield base
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base)], check=False)


def check_imports(tree: Path, cwd: Path) -> None:
    """Exit unless `python` with PYTHONPATH=tree, run in cwd, imports voxtool from tree (an
    editable install elsewhere must not win)."""
    check = subprocess.run([sys.executable, "-c", "import voxtool; print(voxtool.__file__)"], text=True,
                           capture_output=True, env={**os.environ, "PYTHONPATH": str(tree)}, cwd=cwd)
    if not check.stdout.startswith(str(tree)):
        sys.exit(f"{tree}: python imports voxtool from {check.stdout.strip() or check.stderr.strip()} instead")
