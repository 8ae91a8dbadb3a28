"""Where many independent jobs (replays, benchmark tasks) run: a process pool on this machine or a Dask
cluster given its scheduler address."""

from __future__ import annotations

import concurrent.futures
import contextlib
import os
from collections.abc import Iterator


def local_workers(workers: int | None, n_jobs: int) -> int:
    """Processes for ``n_jobs`` jobs: ``workers`` (default one per core), never more than there are jobs."""
    return max(1, min(workers or os.cpu_count() or 1, n_jobs))


@contextlib.contextmanager
def job_executor(n_jobs: int, workers: int | None = None,
                 dask_address: str | None = None) -> Iterator[concurrent.futures.Executor]:
    """An executor for ``n_jobs`` jobs: a process pool (see :func:`local_workers`), or the executor of the Dask
    cluster at ``dask_address`` (``tcp://host:8786``; needs the ``dask`` extra). Shut down on exit."""
    client = None
    if dask_address:
        try:
            from distributed import Client
        except ImportError:
            raise RuntimeError("a Dask cluster needs the 'distributed' package: pip install 'glassmap[dask]'") from None
        client = Client(dask_address)
        executor: concurrent.futures.Executor = client.get_executor()
    else:
        executor = concurrent.futures.ProcessPoolExecutor(max_workers=local_workers(workers, n_jobs))
    try:
        yield executor
    finally:
        executor.shutdown(wait=True)
        if client is not None:
            client.close()
