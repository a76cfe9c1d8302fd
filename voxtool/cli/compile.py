"""`voxtool compile`: fill numba's cache once, at install, so no command compiles on first use."""

from __future__ import annotations

import click

from voxtool.cli.common import emit, handle_errors


@click.command("compile")
@click.option("--json", "as_json", is_flag=True, help="Print the seconds each command took as JSON.")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr (default: when stderr is a terminal).")
@handle_errors
def compile_cmd(as_json, progress):
    """Compile every kernel ahead into numba's cache (beside the installed sources, or
    NUMBA_CACHE_DIR), by running each command once on a sliver of the shipped sample.

    Without it, each command's first run after an install compiles the kernels it needs
    (about 3 s for `build`, 2 s for `encode --codec cm`). This takes about 15 s once;
    run it again only after changing voxtool's sources (the cache then recompiles by itself).

    \b
    Example:
      pip install -e . && voxtool compile
    """
    from voxtool.warmup import compile_ahead

    times = compile_ahead(progress)
    total = round(sum(times.values()), 2)
    emit({"seconds": times, "total_s": total}, as_json,
         [("commands", str(len(times))), ("time", f"{total:.1f} s (compiling, or loading the cached kernels)")])
