"""The convergence trace of an optimisation: one named row per step."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple


class TraceRow(NamedTuple):
    """One row of a convergence trace (a line of ``convergence.csv``)."""

    wall_seconds: float
    cpu_seconds: float
    evaluations: int
    objective: float
    phase: str      # "fixed" (eq. 13), "integrated" (eq. 14) or "restored-initial"
    sweep: int      # sweep, level, iteration or round within the phase (0: its start)


RESTORED_INITIAL = "restored-initial"


@dataclass
class Trace:
    """Convergence trace: one row per optimisation step."""

    start_wall: float = field(default_factory=time.perf_counter)
    start_cpu: float = field(default_factory=time.process_time)
    rows: list[TraceRow] = field(default_factory=list)

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
