"""What every strategy shares: starting a phase, the convergence test, why a phase stops,
rebuilding between sweeps, recording the trace, and the point a phase has reached (for
checkpoints and resuming)."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

from ...config import OptimisationSettings
from ...progress import OBJECTIVE, report
from ..objective import Objective
from ..state import CorrespondenceState
from ..trace import Stop, Trace


@dataclass(frozen=True)
class PhasePoint:
    """Where a phase stands after a checkpointed step: what a resumed run needs to carry on
    exactly as the uninterrupted run would (with the state of that moment and the random
    generator's state, which the checkpoint holds beside it).

    ``phase`` is "fixed" or "integrated" (:data:`DONE` once the optimisation has converged: one
    stopped by a limit or interrupted keeps its last step's point, from which ``--resume``
    carries on),
    ``sweep`` the step's number in the phase, ``counters`` the strategy's loop position and
    ``values`` the objective values its decisions still need (e.g. the fast strategy's pass,
    level and round; the start of the phase and of the pass, and F before and after the step).
    """

    phase: str
    sweep: int
    counters: dict = field(default_factory=dict)
    values: dict = field(default_factory=dict)

    DONE = "done"

    def to_json(self) -> str:
        return json.dumps({"phase": self.phase, "sweep": self.sweep, "counters": self.counters,
                           "values": self.values})

    @classmethod
    def from_json(cls, text: str) -> "PhasePoint":
        data = json.loads(text)
        return cls(str(data["phase"]), int(data["sweep"]),
                   {k: int(v) for k, v in data["counters"].items()},
                   {k: float(v) for k, v in data["values"].items()})


@dataclass(frozen=True)
class Resumption:
    """What an optimisation resumes from: the point a checkpoint reached, the state's record of
    that moment (:func:`~mdlshapemodel.correspondence.state.state_record`), its evaluation count
    and the optimisation's seconds so far (the time budget goes on from there).

    :func:`~mdlshapemodel.correspondence.strategies.optimise` empties ``record`` once it has
    set the state to it (its arrays are large and not needed again): pass a copy of a record
    that is needed afterwards."""

    point: PhasePoint
    record: dict
    evaluations: int
    elapsed: float


def stalled(before: float, value: float, start_value: float, settings: OptimisationSettings
            ) -> bool:
    """Whether the last sweep gained less than ``tolerance`` times the phase's total gain."""
    return before - value <= settings.tolerance * max(start_value - value, 1e-12)


def budget_spent(deadline: float, sweep: int, settings: OptimisationSettings) -> Stop | None:
    """Which limit ends a phase after step ``sweep``: :attr:`Stop.TIME_LIMIT` past ``deadline``,
    :attr:`Stop.SWEEP_LIMIT` at ``settings.max_sweeps`` steps, None while neither is reached."""
    if time.perf_counter() > deadline:
        return Stop.TIME_LIMIT
    if sweep >= settings.max_sweeps:
        return Stop.SWEEP_LIMIT
    return None


@dataclass
class Sweeps:
    """Where a phase of sweeps that stops after ``patience`` quiet ones (one-at-a-time,
    multiscale) starts: F now and at the phase's start, the quiet sweeps so far, the first sweep
    to run, and why a resumed phase has nothing left to do (None: it has)."""

    value: float
    start: float
    quiet: int
    first: int
    over: Stop | None = None


def begin_sweeps(state: CorrespondenceState, objective: Objective, trace: Trace, phase: str,
                 deadline: float, settings: OptimisationSettings,
                 resume: PhasePoint | None) -> Sweeps:
    """A new phase (:func:`start_phase`), or the one ``resume`` was checkpointed in."""
    if resume is None:
        value = start_phase(state, objective, trace, phase)
        return Sweeps(value, value, 0, 1)
    state.objective = objective
    quiet = resume.counters["quiet"]
    over = (Stop.CONVERGED if quiet >= settings.patience
            else Stop.TIME_LIMIT if time.perf_counter() > deadline else None)
    return Sweeps(resume.values["value"], resume.values["start"], quiet, resume.sweep + 1, over)


def stop_after_sweep(sweeps: Sweeps, before: float, value: float, deadline: float,
                     settings: OptimisationSettings) -> Stop | None:
    """After a sweep of a patient phase (F from ``before`` to ``value``, the state rebuilt):
    :attr:`Stop.TIME_LIMIT` past ``deadline`` (the sweep may have been cut short), else the quiet
    sweeps counted on and :attr:`Stop.CONVERGED` at ``patience`` of them; None: sweep on."""
    if time.perf_counter() > deadline:
        return Stop.TIME_LIMIT
    sweeps.quiet = sweeps.quiet + 1 if stalled(before, value, sweeps.start, settings) else 0
    return Stop.CONVERGED if sweeps.quiet >= settings.patience else None


def sweep_point(phase: str, sweep: int, before: float, sweeps: Sweeps,
                settings: OptimisationSettings):
    """``point(after)``: the :class:`PhasePoint` of a patient phase after ``sweep``, F having
    gone from ``before`` to ``after`` (for :func:`rebuilt`)."""
    def point(after: float) -> PhasePoint:
        quiet = sweeps.quiet + 1 if stalled(before, after, sweeps.start, settings) else 0
        return PhasePoint(phase, sweep, {"quiet": quiet}, {"start": sweeps.start, "value": after})
    return point


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
                      value: float, label: str, progress, checkpoint, point) -> float:
    """Record the step's F, report it, then :func:`rebuilt` (as between the sweeps of
    one_at_a_time); returns F after the rebuild."""
    trace.record(state, value, phase, sweep)
    report(progress, None, f"{label}: F = {value:.3f}", OBJECTIVE)
    return rebuilt(state, trace, phase, sweep, checkpoint, point)


def rebuilt(state: CorrespondenceState, trace: Trace, phase: str, sweep: int, checkpoint,
            point) -> float:
    """Between sweeps / iterations: area weights on the new mean and fresh sums (no drift), F
    recorded, the state checkpointed with ``point(value)`` (a :class:`PhasePoint` of the F after
    the rebuild); returns that F."""
    state.rebuild()
    value = state.value()
    trace.record(state, value, phase, sweep)
    if checkpoint is not None:
        checkpoint(point(value))
    return value
