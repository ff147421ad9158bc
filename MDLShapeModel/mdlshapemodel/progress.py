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

Examples
--------
>>> from mdlshapemodel.progress import report
>>> seen = []
>>> report(lambda fraction, message: seen.append((fraction, message)), 0.5, "prepared 1/2")
>>> seen
[(0.5, 'prepared 1/2')]
"""

from __future__ import annotations

from typing import Callable, Optional

from .errors import Cancelled

Progress = Callable[[Optional[float], str], Optional[bool]]

__all__ = ["Cancelled", "Progress", "report"]


def report(progress: Progress | None, fraction: float | None, message: str) -> None:
    """Pass one report to ``progress`` (if any); raise :class:`Cancelled` if it returns False."""
    if progress is not None and progress(fraction, message) is False:
        raise Cancelled(message)
