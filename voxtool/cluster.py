"""Dask clusters: a LocalCluster for one command (`--workers N`) or an existing scheduler
(`--scheduler ADDRESS`). Imported only when one of the two is given, so commands without them
pay nothing for Dask."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from voxtool.errors import ParameterError, VoxtoolError

MAX_WORKERS = 1024


class ClusterError(VoxtoolError):
    exit_code = 1


def wanted(workers: int | None, scheduler: str | None) -> bool:
    """Whether the user asked for Dask; both at once is a usage error."""
    if workers is not None and scheduler is not None:
        raise ParameterError("give --workers (a local cluster) or --scheduler (an existing one), not both")
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise ParameterError(f"--workers {workers} must lie in 1..{MAX_WORKERS}")
    return workers is not None or scheduler is not None


def check_address(scheduler: str) -> None:
    """Refuse what is not a Dask scheduler address before connecting (Client's own parsing
    failures vary with the process's Dask state: an AssertionError where a ValueError was)."""
    from distributed.comm import get_address_host_port, parse_address
    from distributed.comm.registry import get_backend

    try:
        scheme, _ = parse_address(scheduler)
        get_backend(scheme)
        if scheme in ("tcp", "tls", "ws", "wss"):
            get_address_host_port(scheduler)
    except (ValueError, TypeError) as err:
        raise ParameterError(f"--scheduler {scheduler}: not a Dask scheduler address ({err}; "
                             "for example tcp://10.0.0.5:8786)") from None


def connect_timeout() -> str:
    """How long --scheduler waits for its scheduler to answer: VOXTOOL_CONNECT_TIMEOUT seconds
    (default 10; Dask retries the connection until then)."""
    import os

    try:
        seconds = float(os.environ.get("VOXTOOL_CONNECT_TIMEOUT", "10"))
    except ValueError:
        raise ParameterError(f"VOXTOOL_CONNECT_TIMEOUT={os.environ['VOXTOOL_CONNECT_TIMEOUT']}: give seconds") from None
    return f"{max(seconds, 0.1):g}s"


@contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, quiet: bool = False) -> Iterator:
    """A dask.distributed Client; a LocalCluster of `workers` processes (one thread each: voxtool's
    kernels are the parallel part) is started here and shut down on leaving, Ctrl-C included.
    The dashboard address goes to stderr."""
    import logging

    from dask.distributed import Client, LocalCluster

    # Dask logs worker restarts and closing comms at INFO/WARNING; voxtool reports what matters
    for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.worker"):
        logging.getLogger(name).setLevel(logging.ERROR)
    cluster = None
    try:
        if scheduler is not None:
            check_address(scheduler)
            try:
                client = Client(scheduler, timeout=connect_timeout())
            except ValueError as err:  # Dask's own words: "unknown address scheme", "missing port number"
                raise ParameterError(f"--scheduler {scheduler}: not a Dask scheduler address ({err}; "
                                     "for example tcp://10.0.0.5:8786)") from None
            except (OSError, TimeoutError) as err:
                raise ClusterError(f"{scheduler}: cannot reach the Dask scheduler ({err})") from None
            except Exception as err:  # any other failure to connect (Dask's event loop): one line, not a traceback
                raise ClusterError(f"{scheduler}: cannot reach the Dask scheduler ({type(err).__name__}: {err})") from None
        else:
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=":0", silence_logs=logging.ERROR)
            client = Client(cluster)
        # each worker sets numba up (without SciPy: 0.2 s less) and loads the build kernels now,
        # while this process plans the work; the futures are held until the client closes
        warming = [client.submit(warm_worker, key=f"voxtool-warm-{address}", workers=[address], priority=10)
                   for address in client.scheduler_info(n_workers=-1)["workers"]]
        if not quiet:
            where = scheduler or f"local cluster of {workers} worker processes"
            print(f"voxtool: dask: {where}; dashboard {client.dashboard_link}", file=sys.stderr, flush=True)
        try:
            yield client
        finally:
            del warming
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def warm_worker() -> None:
    """Run on every worker when a client connects: voxtool.jit's start and the build kernels."""
    from voxtool.jit import start
    from voxtool.maps.octree import warm_up_kernels

    start()
    warm_up_kernels()


def gather_all(client, futures: list, desc: str, progress: bool | None) -> list:
    """Results of `futures` in their order, with a tqdm bar over finished tasks; the first
    failed task's error is raised (the rest are cancelled)."""
    from dask.distributed import as_completed
    from distributed.scheduler import KilledWorker

    from voxtool.progress import bar

    try:
        with bar(len(futures), desc, progress, "task") as b:
            for _ in as_completed(futures):
                b.update(1)
        return client.gather(futures)
    except KilledWorker as err:
        # Dask recomputes what a lost worker held; a task that keeps killing its workers ends here
        raise ClusterError(f"Dask workers kept dying while running {desc} task {err.task!r} (last: {err.last_worker.address}); "
                           "nothing was written") from None
