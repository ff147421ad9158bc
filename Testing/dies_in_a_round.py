"""Test-only: a Dask worker process that dies in the middle of a round of the fast strategy.

Preloaded into Dask workers (``--preload dies_in_a_round``), it wraps
:meth:`mdlshapemodel.correspondence.strategies.spread.Holder.call`, the method a worker runs for
every call of the optimisation on the examples it holds. Once the file named by
``$MDLSHAPEMODEL_TEST_DIE_AFTER`` exists, the first worker process to reach its
:data:`SAMPLINGS`-th sampling of trial parameters since the file appeared kills itself with
SIGKILL, as the out-of-memory killer would, and leaves the file's name with ``.done`` appended
(only one dies).
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
    counted = {}        # samplings since each appearance of the file (its inode and time)

    def call(holder, method, *arguments):
        try:
            made = os.stat(trigger)
        except FileNotFoundError:
            made = None
        if method == "sample" and made is not None:
            # a file made anew (by a later test) counts from zero in every worker, whatever
            # the worker counted while an earlier one existed
            appearance = (made.st_ino, made.st_mtime_ns)
            counted[appearance] = counted.get(appearance, 0) + 1
            if counted[appearance] == SAMPLINGS:
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
