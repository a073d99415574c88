"""One BLAS thread per node process.

OpenBLAS (numpy's and scipy's) starts a worker per core, and between calls its
workers busy-wait for the next one: the fe node, whose estimator makes many tiny
linear-algebra calls, used about one core to estimate three nozzles. The nodes
make small calls and run beside other processes, so one thread is the default.
"""

from __future__ import annotations

import os

#: Environment variables by which a user chooses the BLAS threads themselves.
BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def limit_blas_threads(n_threads: int = 1):
    """Limit the BLAS libraries loaded so far to ``n_threads`` threads each.

    Left alone when the user set one of :data:`BLAS_ENV` (their choice wins). Call it
    after numpy and scipy are imported (threadpoolctl limits the libraries already
    loaded; every node module imports both at the top).

    Parameters
    ----------
    n_threads : int
        Threads per BLAS library, >= 1.

    Returns
    -------
    threadpoolctl.threadpool_limits or None
        The limiter (the limit holds for the process's life), or None when the
        environment decides.
    """
    if any(os.environ.get(name) for name in BLAS_ENV):
        return None
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=n_threads, user_api="blas")
