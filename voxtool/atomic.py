"""The one place voxtool writes output files: temporary file beside the target, fsync, rename.

A failed or interrupted run leaves any existing target untouched and no temporary file behind
(except after SIGKILL, which no process can clean up after; the temporary name starts with
`.voxtool-tmp-` so it is easy to spot).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

from voxtool.errors import VoxtoolError

TMP_PREFIX = ".voxtool-tmp-"
_UMASK = os.umask(0)
os.umask(_UMASK)


def check_writable(target: str | os.PathLike) -> None:
    """Fail before a long run, not after it, when the output cannot be created."""
    directory = Path(target).parent if str(Path(target).parent) else Path(".")
    if not directory.is_dir():
        raise VoxtoolError(f"{target}: output directory {directory} does not exist")
    if not os.access(directory, os.W_OK):
        raise VoxtoolError(f"{target}: output directory {directory} is not writable")


@contextlib.contextmanager
def atomic_writer(target: str | os.PathLike) -> Iterator[BinaryIO]:
    """Yield a binary file; on clean exit it replaces `target` atomically, else it is removed."""
    target = Path(target)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise VoxtoolError(f"{target}: output directory {directory} does not exist")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=target.suffix, dir=directory)
    except OSError as err:
        raise VoxtoolError(f"{target}: cannot create a file in {directory}: {err.strerror}") from err
    tmp = Path(tmp_name)
    try:
        os.chmod(tmp_name, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get ordinary permissions
        with os.fdopen(fd, "wb") as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise

