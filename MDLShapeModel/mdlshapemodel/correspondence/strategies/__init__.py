"""Optimisation strategies (section III-D): a registry from name to phase function.

Each strategy is a *phase function* with one signature,
``phase(state, objective, settings, rng, trace, phase, deadline, progress, checkpoint, active)``,
that optimises the state for one objective until convergence or ``deadline`` and returns the
final F. :func:`optimise` runs the paper's two phases (III-B) with the chosen one: the fixed-Delta
objective (eq. 13) first, then the full objective (eq. 14). ``none`` has no phase: it keeps the
initial correspondence.

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
from ..state import CorrespondenceState
from ..trace import RESTORED_INITIAL, Trace
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
             active=None) -> float:
    """Run ``settings.strategy``: the fixed-Delta phase, then the full objective.

    ``objectives`` is (fixed, integrated); ``active`` the indices of the examples to optimise
    (default all). Returns the final value of the full objective.
    Raises :class:`Cancelled` (from ``progress``) with the state left consistent.

    BLAS runs single-threaded meanwhile: the objective's linear algebra is on n_s x n_s matrices,
    where threaded BLAS costs more than it gains (measured: a 40 x 40 eigh takes 0.2 ms on one
    thread and 7 ms on two when another process is busy on the second core).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _optimise(state, objectives, settings, rng, trace, progress, checkpoint, active)


def _optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
              rng: np.random.Generator, trace: Trace, progress, checkpoint, active) -> float:
    fixed, integrated = objectives
    start = time.perf_counter()
    if settings.strategy == KEEP_INITIAL:
        state.objective = integrated
        value = state.value()
        trace.record(state, value, "integrated", 0)
        return value
    if settings.strategy not in PHASES:
        raise ValueError(f"unknown strategy {settings.strategy!r}; "
                         f"choose one of {', '.join(STRATEGIES)}")
    run = PHASES[settings.strategy]

    def phase(objective, name, deadline):
        return run(state, objective, settings, rng, trace, name, deadline, progress, checkpoint,
                   active)

    state.objective = integrated
    initial_value = state.value()
    initial = state.snapshot()
    try:
        if settings.fixed_fraction > 0:
            phase(fixed, "fixed", start + settings.fixed_fraction * settings.max_time)
        value = phase(integrated, "integrated", start + settings.max_time)
    finally:
        state.objective = integrated
    if value > initial_value:
        # The fixed-Delta phase optimises another function; with a short budget the full
        # objective may end above its start. Never return a worse correspondence than the start.
        state.restore(initial)
        value = state.value()
        trace.record(state, value, RESTORED_INITIAL, trace.last.sweep if trace.rows else 0)
    return value
