"""One progress and cancellation protocol for every long operation.

A *progress callback* is any callable ``progress(fraction, message)``: ``fraction`` is the part of
the current stage done, in [0, 1], or None where no fraction is known (an optimisation reports its
objective as it goes); ``message`` says what is being done, in a few words. The callback asks to
stop by returning ``False`` or by raising :class:`~mdlshapemodel.errors.Cancelled`; any other
return value (None included) means go on. The library calls callbacks only through :func:`report`,
so both ways of cancelling act alike: the operation stops at its next report, keeps what it has
reached and raises ``Cancelled``.

The command line shows these reports as a progress bar (or plain log lines when its output is not
a terminal), the VTK filters as ``vtkAlgorithm`` progress events, and the 3D Slicer module in its
panel.

A report may say what it is: its message is then a :class:`Message`, text with a ``kind``
(:data:`OBJECTIVE`: an optimisation's objective), which every callback receives as a ``str``
and which :func:`kind_of` reads, and, on an optimisation's report, the most rounds it can still
make (:func:`rounds_left_of`). A build's reports say how long is left (:class:`TimeLeft`):
"(about 3 min left)" where a stage counts its steps (preparing the cases); on the
optimisation's reports (those of kind :data:`OBJECTIVE`), whose end the convergence rule
decides, "(at most 20 more rounds, about 9 min)" where its schedule bounds the rounds, and
"(at most about 9 min left, the time budget)" where the time budget comes first.

Ctrl-C is a cancellation too: within :func:`ctrl_c` (a build, the command line) it only sets a
flag, :class:`Interrupt`, that the work sees at its next report, where it stops as if the
callback had cancelled; a second Ctrl-C aborts at once.

Examples
--------
>>> from mdlshapemodel.progress import report
>>> seen = []
>>> report(lambda fraction, message: seen.append((fraction, message)), 0.5, "prepared 1/2")
>>> seen
[(0.5, 'prepared 1/2')]
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from typing import Callable, Optional

from .errors import Cancelled

Progress = Callable[[Optional[float], str], Optional[bool]]

__all__ = ["OBJECTIVE", "Cancelled", "Interrupt", "Message", "Progress", "TimeLeft", "ctrl_c",
           "kind_of", "report", "rounds_left_of", "time_left_text"]

log = logging.getLogger("mdlshapemodel")


#: the kind of an optimisation's report of its objective ("fixed: sweep 3, F = 12.345"): the
#: reports that :class:`TimeLeft` bounds by the time budget
OBJECTIVE = "objective"


class Message(str):
    """A report's message that says what it reports: the text itself, ``kind`` (such as
    :data:`OBJECTIVE`; None: a report of no particular kind) and, on an optimisation's report,
    ``rounds_left``: the most rounds the optimisation can still make after it, by its schedule
    (0: it has ended; None: no schedule bounds them).

    It is a ``str`` to every callback (printed, compared and formatted as its text), so that a
    callback that knows nothing of kinds takes it as any message; a callback that passes a
    report on, changing its text, keeps the kind with ``Message(text, kind_of(message))``.

    Examples
    --------
    >>> message = Message("fixed: sweep 3, F = 1.000", OBJECTIVE)
    >>> message == "fixed: sweep 3, F = 1.000", kind_of(message), kind_of("prepared 1/4")
    (True, 'objective', None)
    >>> rounds_left_of(Message("fixed: round 3, F = 1.000", OBJECTIVE, rounds_left=9))
    9
    """

    def __new__(cls, text: str, kind: str | None = None, rounds_left: int | None = None):
        message = super().__new__(cls, text)
        message.kind, message.rounds_left = kind, rounds_left
        return message

    def __reduce__(self):
        return Message, (str(self), self.kind, self.rounds_left)


def kind_of(message: str) -> str | None:
    """The kind of a report's ``message`` (:class:`Message`); None for a plain ``str``."""
    return getattr(message, "kind", None)


def rounds_left_of(message: str) -> int | None:
    """The most rounds an optimisation can still make after the report of ``message``
    (:class:`Message`); None where that is not known (any plain ``str``)."""
    return getattr(message, "rounds_left", None)


def report(progress: Progress | None, fraction: float | None, message: str,
           kind: str | None = None, rounds_left: int | None = None) -> None:
    """Pass one report to ``progress`` (if any), its message a :class:`Message` of ``kind``
    (and ``rounds_left``) when one is given; raise :class:`Cancelled` if it returns False."""
    if kind is not None or rounds_left is not None:
        message = Message(message, kind, rounds_left)
    if progress is not None and progress(fraction, message) is False:
        raise Cancelled(message)


def time_left_text(seconds: float) -> str:
    """A duration, rounded as an estimate is: "40 s", "12 min", "2.5 h".

    Examples
    --------
    >>> time_left_text(42.4), time_left_text(754), time_left_text(9000)
    ('42 s', '13 min', '2.5 h')
    """
    if seconds < 90:
        return f"{max(seconds, 0.0):.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


class TimeLeft:
    """A progress callback that adds to each report an estimate of the time its stage has
    left, and passes it on to ``progress``.

    A stage begins where the reports switch between a fraction and none, or the fraction falls
    back or starts again after 1 (as the command line's display counts them). Where the reports
    carry a fraction (the cases prepared), the stage's rate so far gives the rest: "(about 40 s
    left)". The optimisation's reports (no fraction; of kind :data:`OBJECTIVE`, whatever their
    text says) have no rate that foretells their end, which is for the convergence rule to
    decide. Two things bound it: the time budget ``budget``, counted from the first of a run of
    them, and, where a report says the most rounds left (:func:`rounds_left_of`), those rounds
    at the mean time between the run's reports so far. The nearer bound is said: "(at most 20
    more rounds, about 9 min)", or "(at most 20 more rounds; at most about 5 min left, the
    time budget)" ("(at most about 5 min left, the time budget)" where no rounds are bounded),
    while some of the budget is left; nothing once no rounds are left. Any other report ends
    such a run (a landmark check's fold starts an optimisation of its own, with its own budget)
    and gets no estimate. Each report goes on with its kind (and its rounds left).

    Parameters
    ----------
    progress : callable(fraction or None, message)
        Where the reports go on.
    budget : float, optional
        The optimisation's time limit, s (``BuildConfig.max_time``).
    clock : callable, optional
        Seconds (default :func:`time.monotonic`).
    """

    def __init__(self, progress: Progress, budget: float | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.progress, self.budget, self.clock = progress, budget, clock
        self.fraction = None
        self.started = self.optimising = False
        self.stage_start = self.last = clock()    # the first stage: from the start of the work
        self.rounds = 0                           # the optimisation's reports in this run

    def __call__(self, fraction, message):
        now = self.clock()
        previous = self.fraction
        kind, rounds_left = kind_of(message), rounds_left_of(message)
        optimising = fraction is None and kind == OBJECTIVE
        if self.started and ((fraction is None) != (previous is None)
                             or (fraction is not None and (fraction < previous
                                                           or previous >= 1.0))
                             or (optimising and not self.optimising)):
            self.stage_start = now if fraction is None else self.last
        self.rounds = self.rounds + 1 if optimising and self.optimising else int(optimising)
        self.started, self.fraction, self.last = True, fraction, now
        self.optimising = optimising
        elapsed = now - self.stage_start
        if fraction is not None and 0.0 < fraction < 1.0 and elapsed > 0.0:
            message = (f"{message} (about {time_left_text(elapsed * (1.0 - fraction) / fraction)}"
                       f" left)")
        elif optimising and rounds_left != 0 and not (self.budget and self.budget <= elapsed):
            bound = self._optimisation_left(elapsed, rounds_left)
            message = f"{message} ({bound})" if bound else message
        if kind is None and rounds_left is None:
            return self.progress(fraction, message)
        return self.progress(fraction, Message(message, kind, rounds_left))

    def _optimisation_left(self, elapsed: float, rounds_left: int | None) -> str:
        """The nearer bound of the optimisation's time left, ``elapsed`` s into its run of
        reports: its rounds left at the mean time between the reports so far, or the budget
        ("" where neither is known)."""
        rounds = (None if rounds_left is None else
                  f"at most {rounds_left} more round{'s' if rounds_left > 1 else ''}")
        budget = (None if not self.budget else
                  f"at most about {time_left_text(self.budget - elapsed)} left, the time budget")
        if rounds is not None and self.rounds > 1:
            schedule = elapsed / (self.rounds - 1) * rounds_left
            if budget is None or schedule < self.budget - elapsed:
                return f"{rounds}, about {time_left_text(schedule)}"
        return "; ".join(text for text in (rounds, budget) if text is not None)


class Interrupt:
    """Ctrl-C (SIGINT) as a request to stop at the next report, not an exception raised anywhere.

    Python's own handler raises ``KeyboardInterrupt`` wherever the main thread happens to be:
    inside a numba kernel (which then returns with the exception set, a ``SystemError``), while
    a thread pool is half-way through a loop, between two writes of a file. Installed by
    :func:`ctrl_c` instead, the first Ctrl-C only sets :attr:`requested`; the work sees it at its
    next :func:`report` through :meth:`watch` (or at :meth:`check`) and raises
    :class:`Cancelled` there, at a point where what it has reached is consistent: a build
    interrupted while preparing stops, one interrupted while optimising writes the model of the
    state reached. Once the work is :meth:`finishing` (a build writing its outputs), a Ctrl-C
    no longer stops it: it is said (``announcement``) and the work finishes. A second Ctrl-C
    aborts at once: ``abort()`` if given (a program ends there), else ``KeyboardInterrupt``
    raised wherever the main thread is.
    """

    def __init__(self, abort: Callable[[], None] | None = None):
        self.requested = threading.Event()   # set by the first Ctrl-C
        self.installed = False               # Ctrl-C reaches this one (see :func:`ctrl_c`)
        self.abort = abort
        self.presses = 0
        self._stops = True                   # a request raises Cancelled (not yet finishing)
        self._lock = threading.Lock()
        self._seen = False                   # the request has raised Cancelled, or been said
        self._announcement = None
        self._saying = None                  # the thread that says it (see _press)

    def check(self) -> None:
        """Raise :class:`Cancelled` if Ctrl-C was pressed and the work is not finishing."""
        if self._stops and self.requested.is_set():
            with self._lock:
                self._seen = True
            raise Cancelled("interrupted (Ctrl-C)")

    def watch(self, progress: Progress | None) -> Progress:
        """``progress`` (None: no callback) preceded by :meth:`check` at every report."""
        def watched(fraction, message):
            self.check()
            return None if progress is None else progress(fraction, message)
        return watched

    def finishing(self, announcement: str | None = None) -> None:
        """From now on a Ctrl-C lets the work finish, with ``announcement`` logged as a warning
        (at once if Ctrl-C was pressed since the last report and nothing has stopped for it)."""
        self._stops, self._announcement = False, announcement
        if self.requested.is_set():
            self._announce()

    @property
    def again(self) -> str:
        """What a message about a Ctrl-C adds: how to abort hard ("" without one)."""
        return (" (Ctrl-C again to abort)" if self.installed and self.requested.is_set()
                else "")

    def _announce(self):
        with self._lock:                     # once, whichever thread comes first
            if self._seen:
                return
            self._seen = True
        if self._announcement:
            log.warning("%s%s", self._announcement, self.again)

    def _press(self, number, frame):
        """The SIGINT handler (it runs in the main thread, between two bytecodes)."""
        self.presses += 1
        if self.presses > 1:
            if self.abort is not None:
                self.abort()
            raise KeyboardInterrupt
        self.requested.set()
        if not self._stops:
            # said by a thread of its own: this handler may run within a write to the stream
            # that the message goes to (a write that a signal cut short), where writing again
            # from this thread would fail
            self._saying = threading.Thread(target=self._announce, name="mdlshapemodel-ctrl-c",
                                            daemon=True)
            self._saying.start()


# the Interrupt that Ctrl-C reaches, while a :func:`ctrl_c` block of the main thread runs
_active: Interrupt | None = None


@contextlib.contextmanager
def ctrl_c(abort: Callable[[], None] | None = None):
    """An :class:`Interrupt` (with ``abort``) that Ctrl-C reaches while the block runs.

    Its handler is installed only in the main thread (the only one Python runs signal handlers
    in) and only where Ctrl-C would raise ``KeyboardInterrupt`` (Python's default handler: a
    script, a notebook); elsewhere (a thread, an application with a handler of its own, Ctrl-C
    ignored) the Interrupt is never pressed. The previous handler is back when the block ends.
    Nested in the main thread (the command line's around a build's), the inner block gets the
    outer block's Interrupt.
    """
    global _active
    main = threading.current_thread() is threading.main_thread()
    if main and _active is not None:
        yield _active
        return
    interrupt = Interrupt(abort)
    if not main or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield interrupt
        return
    previous = signal.signal(signal.SIGINT, interrupt._press)
    interrupt.installed, _active = True, interrupt
    try:
        yield interrupt
    finally:
        _active = None
        signal.signal(signal.SIGINT, previous)
        if interrupt._saying is not None:    # said before the program goes on (or ends)
            interrupt._saying.join(timeout=10.0)
