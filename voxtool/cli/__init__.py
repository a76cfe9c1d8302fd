"""voxtool command line: a thin layer over the library, one module per command.

Heavy imports (numpy, numba kernels, open3d) stay inside command bodies, so `voxtool --help`
is instant (tests/test_cli.py checks that it loads neither numba nor open3d).
"""

from __future__ import annotations

import os
import sys

# Before numpy loads: voxtool's matrix products are small (a scan's points times a 3x3
# rotation); threaded BLAS only spins on them and takes the cores the ray casting runs on (seen
# in perf as blas_thread_server). A default for the command line only; a user's setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import click  # noqa: E402

from voxtool import __version__  # noqa: E402
from voxtool.cli.build import build  # noqa: E402
from voxtool.cli.cache_bench import cache_bench_cmd  # noqa: E402
from voxtool.cli.clean import clean  # noqa: E402
from voxtool.cli.common import BACKEND_NAMES, SAMPLE_DIR  # noqa: E402
from voxtool.cli.compile import compile_cmd  # noqa: E402
from voxtool.cli.decode import decode  # noqa: E402
from voxtool.cli.diff import diff  # noqa: E402
from voxtool.cli.encode import encode  # noqa: E402
from voxtool.cli.eval import eval_cmd  # noqa: E402
from voxtool.cli.export import export  # noqa: E402
from voxtool.cli.info import info  # noqa: E402
from voxtool.cli.merge import merge  # noqa: E402
from voxtool.cli.odometry import odometry  # noqa: E402
from voxtool.cli.query import query  # noqa: E402
from voxtool.cli.stats import stats  # noqa: E402
from voxtool.cli.view import view  # noqa: E402

__all__ = ["BACKEND_NAMES", "SAMPLE_DIR", "main", "run"]


class VoxtoolGroup(click.Group):
    """click's group with voxtool's error lines: a usage mistake (a value that is not a number,
    an unknown option) is one line on stderr and exit 2, as every other voxtool error, instead
    of click's usage block."""

    def main(self, args=None, prog_name=None, **extra):
        try:
            code = super().main(args, prog_name or "voxtool", standalone_mode=False, **extra)
        except click.UsageError as err:
            hint = f" (see '{err.ctx.command_path} --help')" if err.ctx is not None else ""
            click.echo(f"voxtool: error: {err.format_message().rstrip('.')}{hint}", err=True)
            sys.exit(err.exit_code)
        except click.ClickException as err:
            click.echo(f"voxtool: error: {err.format_message()}", err=True)
            sys.exit(err.exit_code)
        except click.Abort:
            click.echo("voxtool: interrupted; no output written", err=True)
            sys.exit(130)
        sys.exit(code if isinstance(code, int) else 0)


@click.group(cls=VoxtoolGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="voxtool")
def main() -> None:
    """Turn LiDAR scan streams into 3D occupancy voxel maps, measure and share them.

    Exit codes: 0 ok, 1 error, 2 bad parameter, 3 bad source, 4 point outside the key range,
    5 bad map/packet file, 6 regression found by `stats --compare`, 7 more changes than
    `diff --max-changed`, 8 held-out scans below `eval --min-correct`, 130 interrupted.
    """


for _command in (build, info, odometry, clean, eval_cmd, cache_bench_cmd, encode, decode, merge, query, stats, diff, export,
                 view, compile_cmd):
    main.add_command(_command)


def run() -> None:
    """The `voxtool` console command: main(), then an exit without the interpreter's teardown,
    which after a build spent 0.4-0.6 s releasing numba's compiled code. Every output is written,
    fsynced and renamed into place, and stdout/stderr are flushed, before this point."""
    try:
        main(prog_name="voxtool")
        code = 0
    except SystemExit as stop:
        code = stop.code
    if isinstance(code, str):
        print(code, file=sys.stderr)
        code = 1
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(code or 0)
