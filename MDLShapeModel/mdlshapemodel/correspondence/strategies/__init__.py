"""Optimisation strategies (section III-D): a registry from name to phase function.

Each strategy is a *phase function* with one signature,
``phase(state, objective, settings, rng, trace, phase, deadline, progress, checkpoint, active,
resume)``, that optimises the state for one objective until convergence or ``deadline`` and returns
the final F, sets ``trace.stopped_by`` to why it ended (:class:`~..trace.Stop`), calls
``checkpoint(point)`` after every step with the :class:`~.base.PhasePoint` reached, and given one
as ``resume`` carries on from it. :func:`optimise` runs the paper's two phases (III-B) with the
chosen one: the fixed-Delta objective (eq. 13) first, then the full objective (eq. 14). ``none``
has no phase: it keeps the initial correspondence (``trace.stopped_by`` stays None).

Whether the optimisation converged is the full objective's phase's to say. The fixed-Delta phase
is a warm start that ends at its share of the time (``fixed_fraction``) by design; being cut
there says nothing about the model, whose objective is the full one.

- ``one-at-a-time`` (III-D3) and ``one-at-a-time-pose`` (III-D4): :mod:`.one_at_a_time`;
- ``multiresolution`` (III-D1) and ``multiscale`` (III-D2): :mod:`.simplex`;
- ``fast`` (ours, the default): :mod:`.fast`.

To add a strategy, write its phase function in a module of this package and register it in
``PHASES`` and its name in ``config.STRATEGIES``.

The trace has a row at the start of each phase and after each example (one-at-a-time) or
level/iteration/round, plus the row after each rebuild. With
``OptimisationSettings.trace_improvements`` it also has a row whenever a trial inside a step beats
the best F so far, i.e. the value that the step would commit if stopped there: convergence curves
at the resolution of single evaluations, which eq. (19) needs when one strategy is hundreds of
times slower than another (:mod:`mdlshapemodel.model.convergence`). Recording does not change the
optimisation.
"""

from __future__ import annotations

import time

import numpy as np

from ...config import STRATEGIES, OptimisationSettings
from ..state import CorrespondenceState, replay_record
from ..trace import RESTORED_INITIAL, Stop, Trace
from .base import PhasePoint, Resumption
from .fast import optimise_fast
# (imported under another name: the package's attribute one_at_a_time stays the module)
from .one_at_a_time import one_at_a_time as _one_at_a_time
from .one_at_a_time import one_at_a_time_pose
from .simplex import multiresolution, multiscale

PHASES = {
    "one-at-a-time": _one_at_a_time,
    "one-at-a-time-pose": one_at_a_time_pose,
    "multiresolution": multiresolution,
    "multiscale": multiscale,
    "fast": optimise_fast,
}
KEEP_INITIAL = "none"


def optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
             rng: np.random.Generator, trace: Trace, progress=None, checkpoint=None,
             active=None, resume: Resumption | None = None) -> float:
    """Run ``settings.strategy``: the fixed-Delta phase, then the full objective.

    ``objectives`` is (fixed, integrated); ``active`` the indices of the examples to optimise
    (default all). Returns the final value of the full objective; ``trace.stopped_by`` says why
    the full objective's phase ended (None for ``none``, which optimises nothing).
    Raises :class:`Cancelled` (from ``progress``) with the state left consistent.

    ``checkpoint(point)`` is called after every sweep, round, level or iteration with the
    :class:`PhasePoint` reached. ``resume``: the initial state is given the checkpoint's state
    and the optimisation carries on from its point (``rng`` must be in the state it had then); a
    run resumed from any checkpoint ends as the uninterrupted run does (bit for bit while the time
    budget is not reached: the phases are deterministic given the state and the generator).

    BLAS runs single-threaded meanwhile: the objective's linear algebra is on n_s x n_s matrices,
    where threaded BLAS costs more than it gains (measured: a 40 x 40 eigh takes 0.2 ms on one
    thread and 7 ms on two when another process is busy on the second core).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _optimise(state, objectives, settings, rng, trace, progress, checkpoint, active,
                         resume)


def _optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
              rng: np.random.Generator, trace: Trace, progress, checkpoint, active,
              resume: Resumption | None) -> float:
    fixed, integrated = objectives
    start = time.perf_counter() - (resume.elapsed if resume is not None else 0.0)
    trace.stopped_by = None
    if settings.strategy == KEEP_INITIAL:
        state.objective = integrated
        value = state.value()
        trace.record(state, value, "integrated", 0)
        return value
    if settings.strategy not in PHASES:
        raise ValueError(f"unknown strategy {settings.strategy!r}; "
                         f"choose one of {', '.join(STRATEGIES)}")
    run = PHASES[settings.strategy]

    phases = [("integrated", integrated, start + settings.max_time)]
    if settings.fixed_fraction > 0:
        phases.insert(0, ("fixed", fixed, start + settings.fixed_fraction * settings.max_time))
    state.objective = integrated
    initial_value = state.value()
    initial = state.snapshot()
    point = None
    if resume is not None:
        replay_record(state, resume.record)
        state.evaluations = resume.evaluations
        point = resume.point
        if point.phase == PhasePoint.DONE:      # checkpointed once it had converged
            trace.stopped_by = Stop.CONVERGED
            return state.value()
        names = [name for name, _, _ in phases]
        if point.phase not in names:
            raise ValueError(f"the checkpoint is of a phase ({point.phase!r}) that these settings "
                             "do not run")
        phases = phases[names.index(point.phase):]
    try:
        for name, objective, deadline in phases:
            trace.stopped_by = None      # the phase sets it as it ends
            value = run(state, objective, settings, rng, trace, name, deadline, progress,
                        checkpoint, active, point if point is not None and name == point.phase
                        else None)
    finally:
        state.objective = integrated
    if value > initial_value:
        # The fixed-Delta phase optimises another function; with a short budget the full
        # objective may end above its start. Never return a worse correspondence than the start.
        state.restore(initial)
        value = state.value()
        trace.record(state, value, RESTORED_INITIAL, trace.last.sweep if trace.rows else 0)
    return value
