"""Test-only: a worker process that is about to read an input whose path contains
``$MDLSHAPEMODEL_TEST_CRASH_ON`` kills itself with SIGKILL, as a segfaulting native library
would end it. Nothing in the library knows of it:

- a :class:`mdlshapemodel.parallel.ProcessPool` worker arms it when :func:`arm` is in
  ``mdlshapemodel.parallel.WORKER_STARTUP`` (see :data:`CLI`, the command line so armed);
- a Dask worker arms it when started with ``--preload crash_on_prepare`` (:func:`dask_setup`).

It watches Python's ``open`` audit events (:func:`sys.addaudithook`): preparation reads every
input's bytes (the cache's digest, the integrity checks) before a native reader sees it. The
main process never arms it, so a case prepared there (one worker) is prepared.
"""

import os
import signal
import sys

VARIABLE = "MDLSHAPEMODEL_TEST_CRASH_ON"

#: ``python -c CLI ARGUMENTS``: ``mdlshapemodel ARGUMENTS`` whose pool workers are armed (run
#: with this folder as the working directory, or on ``PYTHONPATH``)
CLI = ("import sys, crash_on_prepare; from mdlshapemodel import cli, parallel; "
       "parallel.WORKER_STARTUP.append(crash_on_prepare.arm); sys.exit(cli.main(sys.argv[1:]))")


def _kill_on(pattern: str):
    def hook(event: str, arguments: tuple):
        if event == "open" and arguments and isinstance(arguments[0], (str, bytes, os.PathLike)) \
                and pattern in os.fsdecode(arguments[0]):
            os.kill(os.getpid(), signal.SIGKILL)
    return hook


def arm():
    """In this process, from now on: die at the opening of a file whose path contains
    ``$MDLSHAPEMODEL_TEST_CRASH_ON`` (nothing when it is unset or empty)."""
    pattern = os.environ.get(VARIABLE)
    if pattern:
        sys.addaudithook(_kill_on(pattern))


def dask_setup(worker=None):
    """Dask's preload entry point: arms the worker process."""
    arm()
