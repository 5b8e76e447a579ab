"""Many simulated runs on Dask (``distributed``), the benches' one way to spread work: a local
cluster of single-threaded worker processes (one BLAS thread each), or a scheduler's address for a
lab cluster, with a progress bar."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any


def map_on_dask(
    fn: Callable[..., Any], *iterables: Iterable[Any], workers: int, scheduler: str | None
) -> list[Any]:
    """``[fn(*args) for args in zip(*iterables)]`` on Dask; results in order."""
    from distributed import Client, LocalCluster, progress

    cluster = None if scheduler else LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
        env={"OPENBLAS_NUM_THREADS": "1"})  # fmt: skip
    try:
        with Client(scheduler or cluster) as client:
            futures = client.map(fn, *iterables, pure=False)
            progress(futures, notebook=False)
            return list(client.gather(futures))
    finally:
        if cluster is not None:
            cluster.close()


def add_dask_arguments(parser: Any, workers: int = 2) -> None:
    """``--workers`` (a local cluster's processes) and ``--scheduler`` (a lab cluster's address)."""
    parser.add_argument(
        "--workers", type=int, default=workers, help="local cluster: worker processes"
    )
    parser.add_argument("--scheduler", help="a Dask scheduler's address (default: a local cluster)")
