"""What every strategy shares: starting a phase, the convergence test, rebuilding between sweeps
and recording the trace."""

from __future__ import annotations

from ...config import OptimisationSettings
from ...progress import report
from ..objective import Objective
from ..state import CorrespondenceState
from ..trace import Trace


def stalled(before: float, value: float, start_value: float, settings: OptimisationSettings
            ) -> bool:
    """Whether the last sweep gained less than ``tolerance`` times the phase's total gain."""
    return before - value <= settings.tolerance * max(start_value - value, 1e-12)


def improvements(current: float, report):
    """Wrap ``report(value)`` (or None) to be called only when a trial beats the best so far."""
    if report is None:
        return lambda value: None
    best = [current]

    def seen(value: float):
        if value < best[0]:
            best[0] = value
            report(value)
    return seen


def recorder(state: CorrespondenceState, trace: Trace, phase: str, sweep: int,
              settings: OptimisationSettings):
    """``improved(value)`` recording a trace row, if ``settings.trace_improvements``; else None."""
    if not settings.trace_improvements:
        return None
    return lambda value: trace.record(state, value, phase, sweep)


def active_parts(state: CorrespondenceState, active) -> list:
    active = range(state.n_shapes) if active is None else sorted(int(i) for i in active)
    return [(i, j) for i in active for j in range(len(state.examples[i].parts))]


def start_phase(state: CorrespondenceState, objective: Objective, trace: Trace, phase: str
                ) -> float:
    """Set the phase's objective, rebuild the state, record and return the starting F."""
    state.objective = objective
    state.rebuild()
    value = state.value()
    trace.record(state, value, phase, 0)
    return value


def end_of_iteration(state: CorrespondenceState, trace: Trace, phase: str, sweep: int,
                      value: float, label: str, progress, checkpoint) -> float:
    """Record the step's F, report it, then :func:`rebuilt` (as between the sweeps of
    one_at_a_time); returns F after the rebuild."""
    trace.record(state, value, phase, sweep)
    report(progress, None, f"{label}: F = {value:.3f}")
    return rebuilt(state, trace, phase, sweep, checkpoint)


def rebuilt(state: CorrespondenceState, trace: Trace, phase: str, sweep: int, checkpoint
             ) -> float:
    """Between sweeps / iterations: area weights on the new mean and fresh sums (no drift), F
    recorded, the state checkpointed; returns F after the rebuild."""
    state.rebuild()
    value = state.value()
    trace.record(state, value, phase, sweep)
    if checkpoint is not None:
        checkpoint()
    return value
