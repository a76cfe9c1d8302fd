"""Starting numba for a command-line run.

numba's import and its set-up at the first kernel take about 0.8 s, a third of it importing
SciPy (to look for BLAS) and cffi, which numba uses only for kernel features voxtool does not
have (linear algebra, cffi calls). A command starts numba with both hidden, exactly as on a
machine without them, so they are not imported; once numba is set up they are visible again.
"""

from __future__ import annotations

import sys

OPTIONAL = ("scipy", "cffi")


def start() -> None:
    """Import numba and set it up (what its first kernel would do), without SciPy and cffi."""
    if "numba.np.arraymath" in sys.modules:  # already set up in this process
        return
    hidden = [name for name in OPTIONAL if name not in sys.modules]
    for name in hidden:
        sys.modules[name] = None  # an import of it raises ImportError, as if not installed
    try:
        from voxtool.kernels.morton import ready

        ready(1)
    finally:
        for name in hidden:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]
