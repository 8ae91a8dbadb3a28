"""One BLAS thread in this process: the glass path's matrix products are small (1081 rows x a few dozen
columns), and a team of one BLAS thread per core spends most of its time waiting for its own threads on a
busy machine (~20x slower for the classifier's network on 2 cores). Parallel work runs in processes."""

from __future__ import annotations

import sys


def one_thread() -> None:
    """Limit the BLAS libraries loaded so far (numpy's OpenBLAS; scipy's once scipy.ndimage or scipy.linalg
    is imported) to one thread, and torch too if it is loaded (training)."""
    import numpy  # noqa: F401  (loads numpy's BLAS, so that the limit reaches it)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
