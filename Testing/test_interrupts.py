"""Ctrl-C (SIGINT) reaches every process of a terminal's foreground group: the worker processes
of a ProcessPool ignore it from their start, and the threads of Threads leave it to the main
thread, whose handler decides what it means."""

import signal

from mdlshapemodel.parallel import ProcessPool, Threads


def sigint_disposition():
    """This process's SIGINT handler and whether this thread blocks SIGINT (in a worker)."""
    handler = signal.getsignal(signal.SIGINT)
    return (handler if handler in (signal.SIG_IGN, signal.SIG_DFL) else "python",
            signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))


def test_pool_workers_ignore_sigint_and_pool_threads_leave_it_to_the_main_thread():
    with ProcessPool(1) as pool:
        assert pool.submit(sigint_disposition).result() == (signal.SIG_IGN, False)
    # the pool did not leave SIGINT blocked here
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    blocked = [None, None]

    def note(indices):
        for k in indices:
            blocked[k] = signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])

    with Threads(2) as threads:
        threads.over(2, note)
    assert blocked == [True, True]
