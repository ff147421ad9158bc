"""Executors for per-case work: a process pool by default, any ``concurrent.futures.Executor``.

Every room that fans work out over cases (preprocessing, the CPD baseline, evaluation folds) takes
an ``executor`` argument: None runs the work in this process, in order; otherwise the work is
submitted to it and the results are taken in input order, so the results never depend on which
worker ran what. Only :class:`ProcessPool` creates processes, and only where a caller asks for
one. A Dask cluster plugs in through :func:`.cluster.dask_executor` (a scheduler's address:
``--scheduler``) or a caller's ``Client.get_executor()``, wrapped by :func:`.cluster.on_cluster`.

A worker process that dies (a segfault in a native library, ``os._exit``, the kernel's
out-of-memory killer) loses the work it held, not the build: :func:`map_cases` finds the case that
kills its worker and hands it to the caller's ``died`` (preprocessing rejects it), and runs the
other cases again; :class:`Task` does lost work again here.

Ctrl-C (SIGINT), which a terminal sends to every process of its foreground group, is the main
process's to decide on (:func:`.progress.ctrl_c`): the worker processes of a :class:`ProcessPool`
ignore it from their start, and the threads of :class:`Threads` leave it to the main thread.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from concurrent.futures import (FIRST_COMPLETED, BrokenExecutor, CancelledError, Executor,
                                ProcessPoolExecutor, ThreadPoolExecutor, wait)

from .cluster import killed_on_cluster, on_cluster
from .errors import InternalError
from .memory import release_freed_memory
from .progress import Progress, report

log = logging.getLogger("mdlshapemodel")

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


def _end_with_parent(parent: int, interval: float = 0.5) -> None:
    """Worker initializer: end this worker process soon after the process that started it is
    gone (killed with SIGKILL, it cannot shut its pool down). A worker waiting for work would
    otherwise live on, holding its memory, once its parent had died."""
    def watch():
        while os.getppid() == parent:
            time.sleep(interval)
        os._exit(1)

    threading.Thread(target=watch, name="mdlshapemodel-parent-watch", daemon=True).start()


#: Functions that every worker process of a :class:`ProcessPool` calls when it starts, in order,
#: without arguments (a spawned worker imports them by module and name, so module-level
#: functions or ``functools.partial`` objects of them). Empty in the library; a program (a test,
#: say, that makes a worker die) may add to it before a pool starts its workers.
WORKER_STARTUP: list = []


#: the warnings option that keeps multiprocessing's resource tracker from reporting the worker
#: pools' semaphores as leaked (:func:`quiet_resource_tracker`)
RESOURCE_TRACKER_QUIET = "ignore::UserWarning:multiprocessing.resource_tracker"


def quiet_resource_tracker() -> None:
    """A process ended at once (a build's second Ctrl-C, ``os._exit``) leaves its worker pools'
    semaphores to multiprocessing's resource tracker, which removes them and warns of "leaked
    semaphore objects": a message about a clean-up that worked, which a user would take for a
    fault. The tracker, started later with this process's warnings options, is given one that
    ignores its own warnings (this process's filters are unchanged)."""
    if RESOURCE_TRACKER_QUIET not in sys.warnoptions:
        sys.warnoptions.append(RESOURCE_TRACKER_QUIET)


@contextlib.contextmanager
def _ctrl_c_held():
    """SIGINT blocked in this thread while the block starts worker processes, which inherit the
    block (until :func:`_ignore_ctrl_c`): a Ctrl-C while one imports its modules is no
    ``KeyboardInterrupt`` there. One that arrives here meanwhile is delivered when the block
    ends."""
    if not hasattr(signal, "pthread_sigmask"):   # (Windows: no signal masks)
        yield
        return
    # multiprocessing starts its resource tracker along with the first process, and unblocks
    # SIGINT in the calling thread when it has: started first, it leaves the block alone
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _ignore_ctrl_c() -> None:
    """Worker initializer: SIGINT ignored (and no longer blocked: :func:`_ctrl_c_held`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _leave_ctrl_c_to_the_main_thread() -> None:
    """Thread-pool initializer: SIGINT blocked in the pool's threads, so that the kernel delivers
    it to the main thread, the one Python runs signal handlers in (its waits are cut short)."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


def _start_worker(parent: int, startup: tuple = ()) -> None:
    """Worker initializer of :class:`ProcessPool`: :func:`_ignore_ctrl_c`,
    :func:`_end_with_parent`, then ``startup`` (:data:`WORKER_STARTUP` when the pool started
    this worker)."""
    _ignore_ctrl_c()
    _end_with_parent(parent)
    for function in startup:
        function()


class ProcessPool(Executor):
    """A pool of ``workers`` processes started with ``spawn`` (one BLAS thread each) that replaces
    itself when a worker process dies.

    A ``ProcessPoolExecutor`` whose worker dies is broken for good: the futures of every call it
    was running or holding fail with ``BrokenProcessPool``, and it takes no new ones. This pool
    starts a fresh ``ProcessPoolExecutor`` at the next :meth:`submit` instead, so the lost calls
    can be submitted again. :meth:`death` says how a worker died. Workers start on demand, at a
    submission, and are shut down with the pool (``with ProcessPool(n) as pool:``). They ignore
    Ctrl-C (SIGINT) from their start: the main process decides what it means.

    ``spawn`` (not ``fork``): VTK, numba and BLAS threads do not survive a fork safely. A script
    that uses it needs the usual ``if __name__ == "__main__":`` guard.
    """

    def __init__(self, workers: int):
        self.workers = workers
        self._pool = None
        self._processes = {}   # the worker processes of the current pool, by pid
        self._closed = False

    def _fresh(self) -> ProcessPoolExecutor:
        if self._pool is not None:
            if getattr(self._pool, "_broken", False):
                # a broken executor's manager thread joins every worker process, also one that a
                # submission started while the pool was breaking; nothing sends that one its
                # stop, so the join (and this shutdown) would wait for ever: end them first
                for process in list((getattr(self._pool, "_processes", None) or {}).values()):
                    if process.exitcode is None:
                        process.kill()
            self._pool.shutdown(wait=True)
        self._pool = ProcessPoolExecutor(max_workers=self.workers,
                                         mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_start_worker,
                                         initargs=(os.getpid(), tuple(WORKER_STARTUP)))
        self._processes = {}
        return self._pool

    def submit(self, fn, /, *args, **kwargs):
        if self._closed:
            raise RuntimeError("cannot schedule new futures after shutdown")
        with _one_blas_thread_per_worker(), _ctrl_c_held():   # workers start within submit
            try:
                future = (self._pool or self._fresh()).submit(fn, *args, **kwargs)
            except BrokenExecutor:
                future = self._fresh().submit(fn, *args, **kwargs)
        # kept to read their exit codes after a death (the executor forgets them at shutdown)
        self._processes.update(getattr(self._pool, "_processes", None) or {})
        return future

    def death(self, wait_seconds: float = 5.0) -> str:
        """How a worker of the current pool died: 'signal N', 'exit code N' (0 too: a worker
        must not end while it holds work) or 'cause unknown'. Exact for a pool of one worker; with
        more, the others are stopped (signal 15) when one dies, and a dead one is named."""
        deadline = time.monotonic() + wait_seconds
        while True:
            # the executor's thread may be reaping the process at this moment: ask again
            codes = [process.exitcode for process in self._processes.values()]
            dead = [code for code in codes if code is not None]
            if dead or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        if not dead:
            return "cause unknown"
        code = next((code for code in dead if code), 0)
        return f"signal {-code}" if code < 0 else f"exit code {code}"

    def running(self) -> bool:
        """Whether worker processes have been started since the pool's start or its last
        :meth:`rest`."""
        return self._pool is not None

    def rest(self) -> None:
        """End the worker processes now, and their memory with them (a pool idle for a long
        while); the next :meth:`submit` starts fresh ones. Waits for running calls to end."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool, self._processes = None, {}

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False):
        self._closed = True
        if self._pool is not None:
            self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)
            self._pool = None


class Threads:
    """Runs ``function(indices)`` over contiguous chunks of ``range(n)``, one chunk per thread,
    for loops whose work is in compiled code that releases the GIL (numba ``nogil``).

    Each index is handled by exactly one call, with the same arithmetic as in one thread, so the
    results do not depend on the number of threads. ``threads`` <= 1 runs in the calling thread.
    The threads leave Ctrl-C (SIGINT) to the main thread.
    Use as a context manager (the threads end with it).

    Examples
    --------
    >>> import numpy as np
    >>> out = np.zeros(10)
    >>> def square(indices):
    ...     for k in indices:
    ...         out[k] = k * k
    >>> with Threads(2) as threads:
    ...     threads.over(10, square)
    >>> int(out.sum())
    285
    """

    def __init__(self, threads: int):
        self.threads = max(int(threads), 1)
        self._pool = (ThreadPoolExecutor(self.threads,
                                         initializer=_leave_ctrl_c_to_the_main_thread)
                      if self.threads > 1 else None)

    def over(self, n: int, function) -> None:
        """``function(range(a, b))`` for the chunks of ``range(n)``; the first exception of a
        chunk is raised once every chunk has ended."""
        parts = min(self.threads, n)
        if self._pool is None or parts <= 1:
            function(range(n))
            return
        edges = [n * k // parts for k in range(parts + 1)]
        futures = [self._pool.submit(function, range(a, b)) for a, b in zip(edges, edges[1:])]
        wait(futures)
        for future in futures:
            future.result()

    def close(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@contextlib.contextmanager
def process_pool(workers: int):
    """A :class:`ProcessPool` of ``workers`` processes, shut down on exit; None when ``workers``
    <= 1 (the work then runs in this process)."""
    if workers <= 1:
        yield None
        return
    with ProcessPool(workers) as pool:
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
    with ProcessPool(1) as pool:
        yield pool


def map_cases(function, arguments: list, executor: Executor | None = None,
              progress: Progress | None = None, message: str = "cases", died=None,
              workers: int = 1) -> list:
    """``[function(*a) for a in arguments]``, on ``executor`` when given; results in input order,
    progress reported after each.

    A worker process that dies takes down the calls it was running (on a :class:`ProcessPool`,
    at most one per worker: no more are submitted than it has workers, so the calls that were
    running are known), and the pool with them. Each of those cases runs again alone, one after
    another, in a fresh process of its own: the result of one that finishes there is kept; one
    whose process dies again becomes ``died(index, how)``, ``how`` e.g. ``"worker process died
    (signal 9)"`` (``died`` None: an :class:`InternalError`). The pool replaces itself and the
    remaining cases go on.

    Why alone and not by which worker's pid held which case: the pid tells which case was in the
    process that died, not whether that case killed it. A worker killed from outside (the out-of-memory killer
    picks the largest process, someone's ``kill``) would have its case given up though it did
    nothing wrong, and which cases met in a pool depends on timing. Run alone, a case is given up
    only when it kills a process that runs nothing else: the same cases whatever the timing or
    the number of workers.

    A caller's ``executor`` that breaks (or cancels calls: a Dask client whose scheduler went
    away) is not ours to replace: its unfinished cases run in a :class:`ProcessPool` of
    ``workers`` processes made for them (and through it alone, should they kill a worker
    there), and the log says so. On a Dask cluster a dying worker breaks nothing: the
    scheduler runs the call again on another worker, and gives it up (``KilledWorker``) only
    when its workers died every time; such a case then runs alone in a fresh process here, as
    above, while the cluster goes on with the others.

    Any other exception of ``function`` is re-raised, that of the first such case in input
    order, once the cases running beside it have finished.
    """
    total = len(arguments)
    executor = on_cluster(executor)
    if executor is None or total <= 1:
        results = []
        for k, a in enumerate(arguments):
            results.append(function(*a))
            report(progress, (k + 1) / total, f"{message} {k + 1}/{total}")
        return results
    with contextlib.ExitStack() as owned:
        mapping = _CaseMap(function, arguments, executor, progress, message, died, workers, owned)
        try:
            return mapping.run()
        finally:
            for future in mapping.running:
                future.cancel()


class _CaseMap:
    """The state of one :func:`map_cases` on an executor: the cases to submit, those running,
    the results so far."""

    def __init__(self, function, arguments, executor, progress, message, died, workers, owned):
        self.function, self.arguments, self.executor = function, arguments, executor
        self.progress, self.message, self.died, self.workers = progress, message, died, workers
        self.owned = owned          # the pools made here, shut down when the map ends
        self.alone = None           # the one-worker pool that runs a suspect case alone
        self.results = [None] * len(arguments)
        self.todo = deque(range(len(arguments)))
        self.running = {}           # future -> case index
        self.errors = {}            # case index -> exception of the function
        self.killed = []            # cases given up by a Dask cluster whose workers they killed
        self.finished = 0

    def run(self) -> list:
        while self.running or (self.todo and not self.errors):
            if not self.errors:
                self._submit()
            lost = self._collect(wait(self.running, return_when=FIRST_COMPLETED).done)
            if lost and not self.errors:
                self._recover(lost)
            while self.killed and not self.errors:
                index = self.killed.pop(0)
                log.warning("case %d of %d (%s) was given up by the Dask cluster, whose "
                            "workers died while they held it: it runs again alone in a fresh "
                            "process here", index + 1, len(self.arguments), self.message)
                self._keep(index, self._run_alone(index))
        if self.errors:
            raise self.errors[min(self.errors)]
        return self.results

    def _submit(self):
        ours = isinstance(self.executor, ProcessPool)
        width = self.executor.workers if ours else len(self.arguments)
        while self.todo and len(self.running) < width:
            index = self.todo.popleft()
            try:
                future = self.executor.submit(self.function, *self.arguments[index])
            except BrokenExecutor:            # a caller's executor, broken earlier
                self.todo.appendleft(index)
                self._recover([])
                return
            self.running[future] = index

    def _collect(self, futures) -> list:
        """Results of finished ``futures`` kept, exceptions noted; returns the lost cases."""
        lost = []
        for future in futures:
            index = self.running.pop(future)
            try:
                value = future.result()
            except (BrokenExecutor, CancelledError):   # cancelled: not by us (a Dask
                lost.append(index)                       # client that lost its scheduler)
                continue
            except BaseException as error:     # a bug, or an interrupt in the worker
                if killed_on_cluster(error):
                    self.killed.append(index)
                else:
                    self.errors[index] = error
                continue
            self._keep(index, value)
        return lost

    def _keep(self, index: int, value):
        self.results[index] = value
        self.finished += 1
        total = len(self.arguments)
        report(self.progress, self.finished / total, f"{self.message} {self.finished}/{total}")

    def _recover(self, lost: list):
        # the broken executor fails every call it held: wait for them all
        lost = sorted(lost + self._collect(wait(self.running).done))
        if self.errors:
            return
        if not isinstance(self.executor, ProcessPool):
            log.warning("the executor broke with %d of %d cases unfinished: they run in a "
                        "process pool of %d made for them", len(lost) + len(self.todo),
                        len(self.arguments), max(1, self.workers))
            self.executor = self.owned.enter_context(ProcessPool(max(1, self.workers)))
            self.todo = deque(sorted(lost + list(self.todo)))
            return
        log.warning("a worker process died: the cases it may have taken down (%s of %d) run "
                    "again, each alone in a fresh process", ", ".join(str(i + 1) for i in lost),
                    len(self.arguments))
        for index in lost:
            self._keep(index, self._run_alone(index))

    def _run_alone(self, index: int):
        if self.alone is None:
            self.alone = self.owned.enter_context(ProcessPool(1))
        try:
            return self.alone.submit(self.function, *self.arguments[index]).result()
        except BrokenExecutor:
            how = f"worker process died ({self.alone.death()})"
        if self.died is None:
            raise InternalError(f"case {index + 1} of {len(self.arguments)} ({self.message}): "
                                f"{how}, also when it ran alone; please report it")
        return self.died(index, how)


def _then_release(function, *arguments):
    """``function(*arguments)`` where a :class:`Task` runs it (a worker process), then the memory
    it freed handed back to the operating system (:func:`.memory.release_freed_memory`): an
    evaluation's arrays, freed in the worker, would otherwise stay resident there."""
    try:
        return function(*arguments)
    finally:
        release_freed_memory()


class Task:
    """``function(*arguments)`` on ``executor`` (None: run here, now); :meth:`result` gives its
    value. Work the executor lost (its worker process died, the executor was broken when the
    work was submitted or cancelled it, or a Dask cluster gave it up after its workers died) is
    done again here, in this process, with a warning in the log; a :class:`ProcessPool`
    replaces itself for the next submission.

    Meant for work on data already in memory (an evaluation's linear algebra): if its worker dies,
    the cause is outside it (a kill, lack of memory), and doing it again here is sound."""

    def __init__(self, executor: Executor | None, function, *arguments, what: str = "work"):
        self.function, self.arguments, self.what = function, arguments, what
        self.future = self.error = None
        executor = on_cluster(executor)
        if executor is None:
            self.value, self.arguments = function(*arguments), ()
            return
        try:
            self.future = executor.submit(_then_release, function, *arguments)
        except BrokenExecutor as error:
            self.error = error

    def settle(self) -> bool:
        """Whether the value is here. A run that has ended well on the executor gives it now,
        and the arguments go (they may be large); a run still going, or one that failed (done
        again at :meth:`result`), keeps them."""
        if self.future is None:
            return self.error is None
        if (not self.future.done() or self.future.cancelled()
                or self.future.exception() is not None):
            return False
        self.value, self.future, self.arguments = self.future.result(), None, ()
        return True

    def result(self, redo: tuple = ()):
        """The value; also done again here when the executor's run raised one of ``redo`` (not
        when this thread's wait did: a second Ctrl-C is raised on)."""
        if self.future is None and self.error is None:
            return self.value
        try:
            if self.error is not None:
                raise self.error
            value = self.future.result()
        except BaseException as error:
            if not (isinstance(error, (BrokenExecutor, CancelledError, *redo))
                    or killed_on_cluster(error)) or not self._raised_there(error):
                raise
            log.warning("%s on the executor did not finish (%s); doing it here", self.what,
                        type(error).__name__)
            return self.function(*self.arguments)
        self.arguments = ()      # done: its inputs are not needed again (they may be large)
        return value

    def _raised_there(self, error: BaseException) -> bool:
        """Whether ``error`` is the executor's (its run's, or a lost run's), not one raised in
        this thread while it waited (a KeyboardInterrupt)."""
        if self.future is None or not isinstance(error, KeyboardInterrupt):
            return True
        return (self.future.done() and not self.future.cancelled()
                and self.future.exception() is error)
