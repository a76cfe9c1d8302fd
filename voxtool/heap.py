"""Giving freed memory back to the operating system.

glibc's malloc keeps the memory of freed arrays below its (adaptive, up to 32 MiB) mmap threshold
in its heaps for reuse, and each thread that allocated has a heap of its own. After work that
allocated and freed many such arrays on several threads (fusion's batches), that memory still
counts in the process's resident size until malloc_trim returns it: 62 MB of `merge` on kaist03,
held through the save that followed (the command's peak).
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import lru_cache


@lru_cache(maxsize=1)
def _trim():
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):  # not glibc (musl, macOS, Windows): nothing to trim
        return None


def give_back_freed_memory() -> None:
    """Return the free memory of every malloc heap to the system, where the C library can."""
    trim = _trim()
    if trim is not None:
        trim(0)
