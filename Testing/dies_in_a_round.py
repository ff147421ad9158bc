"""Test-only: a Dask worker process that dies in the middle of a round of the fast strategy.

Preloaded into Dask workers (``--preload dies_in_a_round``), it wraps
:meth:`mdlshapemodel.correspondence.strategies.spread.Holder.call`, the method a worker runs for
every call of the optimisation on the examples it holds. Once the file named by
``$MDLSHAPEMODEL_TEST_DIE_AFTER`` exists, the first worker process to reach its
:data:`SAMPLINGS`-th sampling of trial parameters from then on kills itself with SIGKILL, as the
out-of-memory killer would, and leaves the file's name with ``.done`` appended (only one dies).
Nothing in the library knows of it.
"""

import os
import signal

VARIABLE = "MDLSHAPEMODEL_TEST_DIE_AFTER"
#: the samplings (calls with new trial parameters) a worker makes before it dies
SAMPLINGS = 5


def arm():
    """In this process: die at the :data:`SAMPLINGS`-th sampling after the file named by
    ``$MDLSHAPEMODEL_TEST_DIE_AFTER`` appears (nothing when it is unset)."""
    trigger = os.environ.get(VARIABLE)
    if not trigger:
        return
    from mdlshapemodel.correspondence.strategies import spread

    original = spread.Holder.call
    counted = []

    def call(holder, method, *arguments):
        if method == "sample" and os.path.exists(trigger):
            counted.append(method)
            if len(counted) == SAMPLINGS:
                try:
                    os.close(os.open(f"{trigger}.done", os.O_CREAT | os.O_EXCL))
                except FileExistsError:       # another worker has died for it
                    return original(holder, method, *arguments)
                os.kill(os.getpid(), signal.SIGKILL)
        return original(holder, method, *arguments)

    spread.Holder.call = call


def dask_setup(worker=None):
    """Dask's preload entry point: arms the worker process."""
    arm()
