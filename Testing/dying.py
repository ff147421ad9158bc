"""Functions that end their own worker process, as a segfault in a native library would; in a
module of their own that imports nothing heavy, so that the spawned workers of
test_workers.py start quickly."""

import multiprocessing
import os
import signal


def square_or_die(x: int) -> int:
    """x squared; 2 kills its process with SIGKILL, 4 ends it with exit code 7 and 6 with exit
    code 0 (in a worker: in the main process nothing dies)."""
    if multiprocessing.parent_process() is not None:
        if x == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        if x in (4, 6):
            os._exit(7 if x == 4 else 0)
    return x * x


def die():
    os.kill(os.getpid(), signal.SIGKILL)
