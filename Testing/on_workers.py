"""Functions that test_dask.py runs on the workers of its Dask cluster (imported there by name,
so in a module of their own that imports nothing heavy)."""

import os
import time


def held(seconds: float) -> tuple:
    """(process id, start, end) of a call that holds its thread for ``seconds``."""
    start = time.monotonic()
    time.sleep(seconds)
    return os.getpid(), start, time.monotonic()


def blas_threads() -> int:
    """The number of threads BLAS would use now in this process."""
    import numpy  # noqa: F401  (loads the BLAS library that threadpoolctl inspects)
    from threadpoolctl import threadpool_info

    return max(info["num_threads"] for info in threadpool_info() if info["user_api"] == "blas")
