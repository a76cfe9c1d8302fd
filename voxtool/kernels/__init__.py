"""Compiled (numba) kernels: every per-point / per-voxel loop of voxtool lives here.

Each kernel is `cache=True` so the JIT cost is paid once per machine; importing this package is
what triggers compilation, so the CLI imports it only inside commands that need it.
"""
