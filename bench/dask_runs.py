"""Many simulated runs on Dask (``distributed``), the benches' one way to spread work: a local
cluster of single-threaded worker processes (one BLAS thread each), or a scheduler's address for a
lab cluster, with a progress line.

Each result comes back to the client as soon as its run ends (``as_completed``), and the future is
released: a worker lost later (a run's guardian kills a process whose heartbeat stalls for 3 s, as
it must on a real rig; seen on two cores at a load of 30) loses only the run it was doing, not every
result it held. ``on_result(i, result)`` may keep them (a file) as they come."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable
from typing import Any

INSTALL = (
    "the benches' Monte Carlo runs on Dask, not installed here: .venv/bin/pip install -e"
    " '.[bench]' (the README's main command installs the rig alone; the dev extra has Dask)"
)


def require_dask() -> None:
    """Exit with the one line that says how to install Dask, when it is not installed."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        sys.exit(f"bench: {INSTALL}")


def local_cluster(workers: int) -> Any:
    """A local cluster: ``workers`` processes of one thread each, one BLAS thread each, without
    the workers' statistical profiler.

    The profiler calls ``sys._current_frames()`` every 10 ms, and on Python 3.11 a garbage
    collection inside that call can deadlock the interpreter (CPython gh-106883): a worker hung
    so twice here, its task thread mid-run, its event loop in the profiler. It is switched off in
    the configuration each nanny hands its worker (an environment variable set through ``env``
    comes too late). A lab cluster's workers: start them with
    ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False``."""
    import dask
    from distributed import LocalCluster

    # the scheduler's HTTP server on a free port (its default, 8787, is taken by a second cluster)
    with dask.config.set({"distributed.worker.profile.enabled": False}):
        return LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                            dashboard_address=":0", env={"OPENBLAS_NUM_THREADS": "1"})  # fmt: skip


def map_on_dask(fn: Callable[..., Any], *iterables: Iterable[Any], workers: int,
                scheduler: str | None,
                on_result: Callable[[int, Any], None] | None = None) -> list[Any]:  # fmt: skip
    """``[fn(*args) for args in zip(*iterables)]`` on Dask; results in order."""
    require_dask()
    from distributed import Client, as_completed

    cluster = None if scheduler else local_cluster(workers)
    try:
        with Client(scheduler or cluster) as client:
            futures = client.map(fn, *iterables, pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            results: list[Any] = [None] * len(futures)
            start = time.monotonic()
            for done, future in enumerate(as_completed(futures), start=1):
                i = index[future.key]
                results[i] = future.result()
                future.release()
                if on_result is not None:
                    on_result(i, results[i])
                _progress(done, len(futures), time.monotonic() - start)
            print(file=sys.stderr)
            return results
    finally:
        if cluster is not None:
            cluster.close()


def _progress(done: int, total: int, elapsed_s: float) -> None:
    """One line, rewritten: runs done, elapsed, the time left at this rate."""
    left = elapsed_s / done * (total - done)
    print(
        f"\r{done}/{total} runs ({100 * done / total:.0f} %), {elapsed_s / 60:.1f} min,"
        f" about {left / 60:.1f} min left  ",
        end="",
        file=sys.stderr,
        flush=True,
    )


def add_dask_arguments(parser: Any, workers: int = 2) -> None:
    """``--workers`` (a local cluster's processes) and ``--scheduler`` (a lab cluster's address)."""
    parser.add_argument(
        "--workers", type=int, default=workers, help="local cluster: worker processes"
    )
    parser.add_argument("--scheduler", help="a Dask scheduler's address (default: a local cluster)")
