"""Test-only: a worker process that starts a baseline's evaluation (a whole evaluation with the
jackknife, on a build's helper process) stalls in it until it is killed, as a worker the
out-of-memory killer picks would never finish it. Nothing in the library knows of it:

a :class:`mdlshapemodel.parallel.ProcessPool` worker arms it when :func:`arm` is in
``mdlshapemodel.parallel.WORKER_STARTUP`` (see :data:`CLI`, the command line so armed). The
stalled worker writes its process id to the file named by ``$MDLSHAPEMODEL_TEST_STALL_PID``,
for the test to kill it. The main process never arms it: an evaluation done there runs.
"""

import inspect
import os
import time

VARIABLE = "MDLSHAPEMODEL_TEST_STALL_PID"

#: ``python -c CLI ARGUMENTS``: ``mdlshapemodel ARGUMENTS`` whose pool workers are armed (run
#: with this folder as the working directory, or on ``PYTHONPATH``)
CLI = ("import sys, stalls_evaluation; from mdlshapemodel import cli, parallel; "
       "parallel.WORKER_STARTUP.append(stalls_evaluation.arm); sys.exit(cli.main(sys.argv[1:]))")


def arm():
    """In this process, from now on: a call of ``mdlshapemodel.model.evaluation.evaluate`` with
    the jackknife (a baseline's) writes the process id to the file named by
    ``$MDLSHAPEMODEL_TEST_STALL_PID`` and waits to be killed; other calls (the compilation of
    the kernels ahead of a first build) run (nothing when it is unset)."""
    path = os.environ.get(VARIABLE)
    if not path:
        return
    from mdlshapemodel.model import evaluation

    original = evaluation.evaluate
    signature = inspect.signature(original)

    def stalled(*arguments, **options):
        if not signature.bind(*arguments, **options).arguments.get("jackknife"):
            return original(*arguments, **options)
        written = f"{path}.partial"
        with open(written, "w") as file:
            file.write(str(os.getpid()))
        os.replace(written, path)       # the test reads a whole id
        while True:
            time.sleep(0.1)

    evaluation.evaluate = stalled
