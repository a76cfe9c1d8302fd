"""Starting numba for a command-line run.

A command's kernels are all in numba's cache (`voxtool compile`), so numba's work at start is
only loading machine code. Two things numba does around that are left out:

- Before loading a cached kernel, numba "refreshes" its compiler: it imports every module that
  implements Python and NumPy features for compilation (NumPy's linear algebra, random numbers,
  typed containers, ...) and registers them, 0.2 s on the 2-core VM, a third of a small build's
  start-up. Loading machine code needs none of it, only numba's runtime (NRT), which the kernels
  use to allocate arrays. `start` makes a cached kernel's load initialise just the runtime; a
  kernel that is not cached still compiles, and compiling refreshes the compiler itself.
- That refresh would import SciPy (to look for BLAS) and cffi, for kernel features voxtool does
  not have. While numba is set up they are hidden, as on a machine without them; afterwards they
  are importable again.
"""

from __future__ import annotations

import sys

OPTIONAL = ("scipy", "cffi")
_started = False


def start() -> None:
    """Import numba and set it up to load cached kernels (what its first kernel would do),
    without SciPy and cffi."""
    global _started
    if _started:
        return
    hidden = [name for name in OPTIONAL if name not in sys.modules]
    for name in hidden:
        sys.modules[name] = None  # an import of it raises ImportError, as if not installed
    try:
        load_cached_kernels_without_refresh()
        from voxtool.kernels.morton import ready

        ready(1)
    finally:
        for name in hidden:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]
    _started = True


def load_cached_kernels_without_refresh() -> bool:
    """Make numba load a cached kernel without first refreshing its compiler (module doc).
    False, leaving numba as it is, where its cache does not have the parts this relies on."""
    from numba.core import caching
    from numba.core.runtime import rtsys

    cache = caching.Cache
    if getattr(cache.load_overload, "voxtool", False):
        return True
    if not all(hasattr(cache, name) for name in ("load_overload", "_load_overload",
                                                 "_guard_against_spurious_io_errors")):
        return False

    def load_overload(self, sig, target_context):
        rtsys.initialize(target_context)  # the runtime the kernels allocate with (idempotent)
        with self._guard_against_spurious_io_errors():
            return self._load_overload(sig, target_context)
        return None  # the `with` block swallowed a spurious I/O error: numba compiles instead

    load_overload.voxtool = True
    cache.load_overload = load_overload
    return True
