"""Executors for per-case work: a process pool by default, any ``concurrent.futures.Executor``.

Every room that fans work out over cases (preprocessing, the CPD baseline, evaluation folds) takes
an ``executor`` argument: None runs the work in this process, in order; otherwise the work is
submitted to it and the results are taken in input order, so the results never depend on which
worker ran what. A Dask distributed client's ``get_executor()`` plugs in the same way. Only
:func:`process_pool` creates processes, and only where a caller asks for one.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
from concurrent.futures import Executor, ProcessPoolExecutor

from .progress import Progress, report

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _one_blas_thread_per_worker():
    """Worker processes started inside use one BLAS thread each (unless the user set one): with
    a process per core, threaded BLAS in every worker oversubscribes the cores."""
    added = [name for name in BLAS_THREAD_VARIABLES if name not in os.environ]
    for name in added:
        os.environ[name] = "1"
    try:
        yield
    finally:
        for name in added:
            os.environ.pop(name, None)


@contextlib.contextmanager
def process_pool(workers: int):
    """A pool of ``workers`` processes started with ``spawn`` (one BLAS thread each), shut down on
    exit; None when ``workers`` <= 1 (the work then runs in this process).

    ``spawn`` (not ``fork``): VTK, numba and BLAS threads do not survive a fork safely. A script
    that uses it needs the usual ``if __name__ == "__main__":`` guard.
    """
    if workers <= 1:
        yield None
        return
    with _one_blas_thread_per_worker(), ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield pool


@contextlib.contextmanager
def executor_for(workers: int, executor: Executor | None = None):
    """The caller's ``executor`` if it gave one (left running: it is the caller's), else a
    :func:`process_pool` of ``workers``."""
    if executor is not None:
        yield executor
        return
    with process_pool(workers) as pool:
        yield pool


@contextlib.contextmanager
def helper_for(workers: int, executor: Executor | None = None):
    """The executor for work that overlaps the main process's (evaluating baselines while the
    single-threaded optimisation runs): the caller's ``executor`` if it gave one, else one worker
    process when ``workers`` > 1, else None. One process, not ``workers``: the main process keeps
    a core, and an idle pool would hold its workers' memory for the whole build."""
    if executor is not None or workers <= 1:
        yield executor
        return
    with _one_blas_thread_per_worker(), ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        yield pool


def map_cases(function, arguments: list, executor: Executor | None = None,
              progress: Progress | None = None, message: str = "cases") -> list:
    """``[function(*a) for a in arguments]``, on ``executor`` when given; results in input order,
    progress reported after each."""
    total = len(arguments)
    if executor is None or total <= 1:
        results = []
        for k, a in enumerate(arguments):
            results.append(function(*a))
            report(progress, (k + 1) / total, f"{message} {k + 1}/{total}")
        return results
    futures = [executor.submit(function, *a) for a in arguments]
    try:
        results = []
        for k, future in enumerate(futures):
            results.append(future.result())
            report(progress, (k + 1) / total, f"{message} {k + 1}/{total}")
        return results
    finally:
        for future in futures:
            future.cancel()
