"""The convergence trace of an optimisation: one named row per step, and why it stopped."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from enum import Enum
from typing import NamedTuple


class TraceRow(NamedTuple):
    """One row of a convergence trace (a line of ``convergence.csv``)."""

    wall_seconds: float
    cpu_seconds: float
    evaluations: int
    objective: float
    phase: str      # "fixed" (eq. 13) or "integrated" (eq. 14), after "landmarks" (the
                    # guides' term alone) with landmark guides; "coarse " before each on the
                    # coarse grid
    sweep: int      # sweep, level, iteration or round within the phase (0: its start)


class Stop(str, Enum):
    """Why an optimisation phase ended (:attr:`Trace.stopped_by`); the value is what
    metrics.json and the messages say."""

    #: the strategy's own stopping rule: its gains fell within ``tolerance`` (for ``patience``
    #: sweeps), or its schedule of levels and passes is done
    CONVERGED = "converged"
    #: the phase's deadline (``max_time``) came first
    TIME_LIMIT = "time limit"
    #: ``max_sweeps`` sweeps, rounds, iterations or levels came first
    SWEEP_LIMIT = "sweep limit"
    #: Ctrl-C or a cancelling progress callback
    INTERRUPTED = "interrupted"


@dataclass
class Trace:
    """Convergence trace: one row per optimisation step."""

    start_wall: float = field(default_factory=time.perf_counter)
    start_cpu: float = field(default_factory=time.process_time)
    rows: list[TraceRow] = field(default_factory=list)
    #: why the latest phase ended, set by the phase function as it returns (None: no phase
    #: has ended, e.g. the strategy ``none``, which has none)
    stopped_by: Stop | None = None

    HEADER = TraceRow._fields

    def record(self, state, value: float, phase: str, sweep: int):
        """Append a row: the time since the trace started, ``state.evaluations``, F, where."""
        self.rows.append(TraceRow(time.perf_counter() - self.start_wall,
                                  time.process_time() - self.start_cpu, state.evaluations,
                                  float(value), phase, sweep))

    @property
    def last(self) -> TraceRow | None:
        """The latest row (None before the first)."""
        return self.rows[-1] if self.rows else None


def stop_summary(stopped_by: Stop | str | None) -> str:
    """How logs, the command line's summary and the report say why an optimisation ended:
    "converged", "not converged (time limit)" and the like, or "not run" (None: the strategy
    ``none``, the CPD correspondence). ``stopped_by``: a :class:`Stop` or its value."""
    if stopped_by is None:
        return "not run"
    stop = Stop(stopped_by)
    return stop.value if stop is Stop.CONVERGED else f"not converged ({stop.value})"
