from __future__ import annotations

import os

# voxtool's matrix products are small (a scan's points times a 3x3 rotation); threaded BLAS only
# spins on them and takes the cores the ray casting runs on (seen in perf as blas_thread_server).
# Only a default: a user's own setting wins, and it has no effect once numpy is loaded.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
