"""A Dask cluster as an executor for per-case work (``--scheduler``, or a caller's
``Client.get_executor()``).

:func:`dask_executor` connects to a scheduler and checks it up front (``distributed`` installed,
the scheduler answering, its workers on this version of mdlshapemodel); :func:`on_cluster` wraps a
Dask client's executor in a :class:`ClusterExecutor`, whose calls run as :class:`InTurn` (one at a
time per worker process, one BLAS thread), so that a cluster gives what a local
:class:`~.parallel.ProcessPool` gives, bit for bit. :func:`killed_on_cluster` tells the scheduler's
giving up of a call whose workers died. ``distributed`` is imported only inside these functions,
so importing this package never imports Dask.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import re
import socket
import sys
import threading
from concurrent.futures import BrokenExecutor, Executor, ThreadPoolExecutor

from .errors import ConfigError
from .version import __version__

log = logging.getLogger("mdlshapemodel")

# How long the build waits for a Dask scheduler to answer before it gives up (seconds).
CONNECT_SECONDS = 10.0
DASK_INSTALL = 'pip install "mdlshapemodel[dask]"'
# The schemes of Dask addresses that are TCP sockets underneath (checked with one before the
# client connects: a refused connection fails at once instead of being retried until the timeout).
_SOCKET_SCHEMES = ("tcp", "tls", "ws", "wss")

# One call of this package at a time in each process, however many threads the Dask worker that
# runs it has: a call changes what belongs to the whole process (the BLAS thread limit that
# threadpoolctl sets, VTK's output window that collects a reader's messages, file descriptor 2).
_ONE_CALL_AT_A_TIME = threading.Lock()


class InTurn:
    """``function`` as a Dask worker runs it: after any other call of this package in the same
    worker process (one at a time: see ``_ONE_CALL_AT_A_TIME``), with one BLAS thread, as in a
    :class:`~.parallel.ProcessPool`'s workers, and only on the mdlshapemodel version that submitted
    it (another raises :class:`~.errors.ConfigError`). Pickles small: ``function`` travels by name,
    and the worker imports it from its own installation."""

    def __init__(self, function, version: str = __version__):
        self.function, self.version = function, version

    def __call__(self, *arguments, **keywords):
        if __version__ != self.version:
            raise ConfigError(f"a Dask worker on {socket.gethostname()} runs mdlshapemodel "
                              f"{__version__}, the build {self.version}: install the build's "
                              "version on every worker")
        from threadpoolctl import threadpool_limits

        with _ONE_CALL_AT_A_TIME, threadpool_limits(limits=1, user_api="blas"):
            return self.function(*arguments, **keywords)


class ClusterExecutor(Executor):
    """A Dask client's executor (``Client.get_executor()``) whose calls run :class:`InTurn`, so
    that they give what they give in a :class:`~.parallel.ProcessPool`, bit for bit, on workers
    with any number of threads. Shutting it down shuts down the client's executor, not the
    client."""

    def __init__(self, executor: Executor):
        self.executor = executor

    def submit(self, fn, /, *args, **kwargs):
        client = getattr(self.executor, "_client", None)
        if client is not None and client.status != "running":   # its scheduler went away
            raise BrokenExecutor(f"the Dask client is {client.status}")
        return self.executor.submit(InTurn(fn), *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False):
        self.executor.shutdown(wait=wait)

    @property
    def client(self):
        """The ``distributed.Client`` whose executor this is."""
        return self.executor._client


def on_cluster(executor: Executor | None) -> Executor | None:
    """``executor`` as a :class:`ClusterExecutor` when it is a Dask client's executor, else
    itself (imports nothing of Dask that the caller has not imported)."""
    if (executor is None or isinstance(executor, ClusterExecutor)
            or "distributed" not in sys.modules):
        return executor
    from distributed.cfexecutor import ClientExecutor

    return ClusterExecutor(executor) if isinstance(executor, ClientExecutor) else executor


def client_of(executor: Executor | None):
    """The ``distributed.Client`` of a Dask client's executor (:func:`on_cluster`), else None."""
    executor = on_cluster(executor)
    return executor.client if isinstance(executor, ClusterExecutor) else None


def killed_on_cluster(error: BaseException) -> bool:
    """Whether ``error`` is Dask's ``KilledWorker``: the scheduler gave a call up because the
    workers running it died each time it tried (``distributed.scheduler.allowed-failures`` + 1)."""
    kind = type(error)
    return kind.__name__ == "KilledWorker" and kind.__module__.split(".")[0] == "distributed"


@contextlib.contextmanager
def dask_executor(address: str, timeout: float = CONNECT_SECONDS):
    """An executor on the Dask cluster whose scheduler listens at ``address`` (e.g.
    ``tcp://10.0.0.5:8786``): a :class:`ClusterExecutor`; the client is closed on exit.

    Checked before it is used, each failure a :class:`~.errors.ConfigError` in one line naming
    the address: ``distributed`` is installed, the scheduler answers within ``timeout``
    seconds and runs this version of mdlshapemodel (it unpickles the tasks, whose classes are
    this package's: another version fails them all as undecodable task graphs), and so do the
    workers connected by then (other versions of its dependencies are a warning: results may
    then differ in the last bits).
    Logs the scheduler and how many workers and threads it has.
    """
    client = _client(address, timeout)
    import dask

    try:
        _check_scheduler(client, address)
        _check_workers(client, address)
        # an evaluation sends the corresponded points and the surface of every case with its
        # call (about 20 MB for 100 hippocampi), by design: Dask's warning about task graphs
        # above 10 MB would be noise
        with dask.config.set({"distributed.admin.large-graph-warning-threshold": "4GB"}):
            yield ClusterExecutor(client.get_executor(pure=False))
    finally:
        client.close()


def _client(address: str, timeout: float):
    """A ``distributed.Client`` of the scheduler at ``address``, or :class:`ConfigError`."""
    try:
        from distributed import Client
        from distributed.comm import normalize_address
    except ImportError as error:
        raise ConfigError(f"scheduler {address}: the Dask client is not installed ({error}); "
                          f"{DASK_INSTALL}") from None
    try:
        address = normalize_address(address)
        _answers(address, timeout)
    except ValueError as error:
        raise ConfigError(f"scheduler {address}: not a Dask scheduler address ({error}); e.g. "
                          "tcp://127.0.0.1:8786") from None
    except TimeoutError:
        raise ConfigError(f"no Dask scheduler answers at {address} within {timeout:g} s") from None
    except OSError as error:
        raise ConfigError(f"no Dask scheduler reachable at {address} "
                          f"({error.strerror or error or type(error).__name__})") from None
    except Exception as error:   # something else answers there: its bytes are no handshake
        raise ConfigError(f"no Dask scheduler at {address}: what answers there is not one "
                          f"({type(error).__name__}: {error})") from None
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except Exception as error:
        problem = f"no Dask scheduler answers at {address} ({type(error).__name__}: {error})"
    # raised here, not in the except block: the client that failed to connect is then released
    # now (its finaliser waits for its connection, at exit too)
    gc.collect()
    raise ConfigError(problem)


def _answers(address: str, timeout: float):
    """Return when a Dask scheduler at ``address`` (normalized) has answered a connection with
    its handshake; else raise the error met: ``TimeoutError`` after ``timeout`` seconds (the
    client's own connection waits for a handshake without end), an ``OSError`` at once for a
    refused connection (where the client would retry until its timeout)."""
    import asyncio

    from distributed.comm import connect, get_address_host_port, parse_address

    if parse_address(address)[0] in _SOCKET_SCHEMES:
        socket.create_connection(get_address_host_port(address), timeout).close()

    async def handshake():
        comm = await asyncio.wait_for(connect(address, timeout=timeout), timeout)
        await comm.close()

    # in a thread of its own: the caller may be running an event loop (a notebook)
    with ThreadPoolExecutor(1) as thread:
        try:
            thread.submit(asyncio.run, handshake()).result()
        except asyncio.TimeoutError:   # not yet TimeoutError itself in Python 3.10
            raise TimeoutError from None


def _dependency_names() -> tuple:
    """The distributions mdlshapemodel requires (without extras), as installed here."""
    from importlib import metadata

    try:
        requirements = metadata.requires("mdlshapemodel") or []
    except metadata.PackageNotFoundError:   # run from a source tree
        return ()
    return tuple(re.match(r"[A-Za-z0-9._-]+", r).group(0) for r in requirements
                 if "extra ==" not in r)


def installed_versions(names: tuple) -> dict:
    """mdlshapemodel's version and those of the distributions ``names`` (None: not installed)
    in this process; run on the Dask scheduler and each worker before a build uses them."""
    from importlib import metadata

    versions = {"mdlshapemodel": __version__}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _check_scheduler(client, address: str):
    try:
        theirs = client.run_on_scheduler(installed_versions, ())
    except Exception as error:
        raise ConfigError(f"the Dask scheduler {address} cannot run mdlshapemodel "
                          f"({type(error).__name__}: {error}); install mdlshapemodel "
                          f"{__version__} where the scheduler runs") from None
    if theirs["mdlshapemodel"] != __version__:
        raise ConfigError(f"the Dask scheduler {address} runs mdlshapemodel "
                          f"{theirs['mdlshapemodel']}, this build {__version__}; install the "
                          "same version where the scheduler runs")


def _check_workers(client, address: str):
    names = _dependency_names()
    threads = client.nthreads()   # worker address -> its threads
    try:
        theirs = client.run(installed_versions, names)   # worker address -> versions
    except Exception as error:
        raise ConfigError(f"the Dask workers of {address} cannot run mdlshapemodel "
                          f"({type(error).__name__}: {error}); install mdlshapemodel "
                          f"{__version__} and its dependencies on every worker") from None
    ours = installed_versions(names)
    for worker, versions in sorted(theirs.items()):
        if versions["mdlshapemodel"] != ours["mdlshapemodel"]:
            raise ConfigError(f"the Dask worker {worker} runs mdlshapemodel "
                              f"{versions['mdlshapemodel']}, this build {__version__}; install "
                              "the same version on every worker")
    differ = sorted({name for versions in theirs.values() for name, version in versions.items()
                     if version != ours[name]})
    if differ:
        log.warning("the Dask workers have other versions of %s than this process: their "
                    "results may differ from a local build's in the last bits",
                    ", ".join(differ))
    log.info("per-case work on the Dask scheduler %s: %d workers, %d threads", address,
             len(threads), sum(threads.values()))
    if not threads:
        log.warning("the Dask scheduler %s has no workers yet: the per-case work waits for them",
                    address)
    elif max(threads.values()) > 1:
        log.warning("Dask workers with several threads run one case at a time each (what a case "
                    "sets, its BLAS threads and native libraries' messages, is its process's): "
                    "start workers with --nthreads 1, as many processes as cores (--nworkers)")

