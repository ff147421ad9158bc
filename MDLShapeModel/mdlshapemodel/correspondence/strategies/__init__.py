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

import functools
import logging
import time
from dataclasses import dataclass, field, replace

import numpy as np

from ...config import STRATEGIES, OptimisationSettings
from ...errors import ArgumentError
from ...parallel import Threads
from ...progress import Message, kind_of, rounds_left_of
from ..objective import NoDescription, pooled
from ..coarse import carry_over, coarse_grid_applies, coarse_view
from ..state import CorrespondenceState, replay_record
from ..trace import Stop, Trace
from .base import PhasePoint, Resumption
from .fast import FIELD_LEVELS, most_rounds, optimise_fast
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
#: with landmark guides: the share of ``max_time`` by which the landmark phase ends, and the fast
#: strategy's field levels in it
LANDMARK_PHASE_SHARE = 0.1
LANDMARK_PHASE_LEVELS = (0, 1)

log = logging.getLogger("mdlshapemodel")


def optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
             rng: np.random.Generator, trace: Trace, progress=None, checkpoint=None,
             active=None, resume: Resumption | None = None, cluster=None) -> float:
    """Run ``settings.strategy``: the fixed-Delta phase, then the full objective.

    ``objectives`` is (fixed, integrated); ``active`` the indices of the examples to optimise
    (default all). Returns the final value of the full objective, of :func:`measured_state`
    (on the coarse grid where the optimisation runs there); ``trace.stopped_by`` says why
    the full objective's phase ended (None for ``none``, which optimises nothing).
    Raises :class:`Cancelled` (from ``progress``) with the state left consistent.

    The correspondence returned is where the full objective's phase ends, as in the paper, even
    where its eq. 14 is above the initial correspondence's. The fixed-Delta phase trades the
    description length of the smallest modes for a more compact model; with many examples the
    n_s - 1 modes' terms can make eq. 14 prefer the start although the phases' end is closer to
    a known true correspondence and generalizes better (docs/benchmarks.md, 1000 shapes), so the
    end is not judged against the start.

    ``checkpoint(point, state)`` is called after every sweep, round, level or iteration with the
    state it was reached in (the coarse stage's own, :mod:`..coarse`, during that stage) and the
    :class:`PhasePoint` reached. ``resume``: the initial state is given the checkpoint's state
    and the optimisation carries on from its point (``rng`` must be in the state it had then); a
    run resumed from any checkpoint ends as the uninterrupted run does (bit for bit while the time
    budget is not reached: the phases are deterministic given the state and the generator).
    The resumption's record is emptied once the state has it (:class:`Resumption`).

    BLAS runs single-threaded meanwhile: the objective's linear algebra is on n_s x n_s matrices,
    where threaded BLAS costs more than it gains (measured: a 40 x 40 eigh takes 0.2 ms on one
    thread and 7 ms on two when another process is busy on the second core). Each objective's
    threads past the covariance route are one pool for the whole optimisation
    (:meth:`~..objective.Objective.pooled`), ended with it; or the caller's pool, when it holds
    one (a build keeps eq. 14's for its measures before and after).

    ``cluster``, a ``distributed.Client``: the fast strategy's per-example work runs on its
    workers (:mod:`.spread`), with the same result; the other strategies ignore it.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"), pooled(objectives):
        return _optimise(state, objectives, settings, rng, trace, progress, checkpoint, active,
                         resume, cluster)


def _optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
              rng: np.random.Generator, trace: Trace, progress, checkpoint, active,
              resume: Resumption | None, cluster=None) -> float:
    fixed, integrated = objectives
    start = time.perf_counter() - (resume.elapsed if resume is not None else 0.0)
    trace.stopped_by = None
    if settings.strategy == KEEP_INITIAL:
        state.objective = integrated
        value = state.value()
        trace.record(state, value, "integrated", 0)
        return value
    if settings.strategy not in PHASES:
        raise ArgumentError(f"unknown strategy {settings.strategy!r}; "
                         f"choose one of {', '.join(STRATEGIES)}")
    run = PHASES[settings.strategy]

    phases = _phases(state, objectives, settings, start, active)
    if cluster is not None and settings.strategy == "fast":
        phases = [replace(phase, options={**phase.options, "cluster": cluster})
                  for phase in phases]
    staged = phases[0].coarse
    point, coarse = None, None
    if resume is not None and resume.point.phase == PhasePoint.DONE:   # it had converged
        _replay(state, resume)
        trace.stopped_by = Stop.CONVERGED
        return measured_state(state, settings, active, integrated).value()
    if staged:
        coarse = coarse_view(state, settings.coarse_points, carry=True)
        state.set_aside()         # carried over from the coarse view when the stage ends
    if resume is not None:
        point = resume.point
        names = [phase.name for phase in phases]
        if point.phase not in names:
            raise ArgumentError(f"the checkpoint is of a phase ({point.phase!r}) that these settings "
                             "do not run")
        phases = phases[names.index(point.phase):]
        _replay(coarse if staged else state, resume)
    try:
        for index, phase in enumerate(phases):
            current = coarse if staged else state
            trace.stopped_by = None      # the phase sets it as it ends
            saver = None if checkpoint is None else functools.partial(_checkpoint_of, checkpoint,
                                                                      current)
            value = run(current, phase.objective, phase.settings, rng, trace, phase.name,
                        phase.deadline, _with_later_rounds(progress, phases[index + 1:]),
                        saver, active,
                        point if point is not None and phase.name == point.phase else None,
                        **phase.options)
    finally:
        if staged:      # also when stopped within it: keep what it reached
            _finish_coarse_stage(coarse, state, settings)
        state.objective = integrated
    return value


def _with_later_rounds(progress, later: list):
    """``progress``, to which a phase's reports of the rounds it has left
    (:func:`~...progress.rounds_left_of`, the fast strategy's) go on counting the most rounds
    of the ``later`` phases too: the most rounds the whole optimisation can still make."""
    if progress is None or not later:
        return progress
    after = sum(most_rounds(phase.settings, phase.options.get("levels", FIELD_LEVELS))
                for phase in later)

    def passed_on(fraction, message):
        left = rounds_left_of(message)
        if left is not None:
            message = Message(message, kind_of(message), left + after)
        return progress(fraction, message)
    return passed_on


def _replay(state: CorrespondenceState, resume: Resumption) -> None:
    """Set ``state`` to the resumption's record and evaluation count, then empty the record:
    its arrays (every part's positions, samples and faces: gigabytes for a large population)
    are not needed again, and the build's references to the checkpoint last the whole
    optimisation."""
    replay_record(state, resume.record)
    state.evaluations = resume.evaluations
    resume.record.clear()


def runs_coarse(state: CorrespondenceState, settings: OptimisationSettings,
                active=None) -> bool:
    """Whether :func:`optimise` with ``settings`` runs on the coarse grid of
    :mod:`..coarse` (the fast strategy on all examples of surfaces sampled more finely than
    ``settings.coarse_points``)."""
    return (settings.strategy == "fast" and active is None
            and coarse_grid_applies(state, settings.coarse_points))


def measured_state(state: CorrespondenceState, settings: OptimisationSettings, active=None,
                   objective=None) -> CorrespondenceState:
    """The state whose eq. 14 :func:`optimise` minimises for ``state``: its
    :func:`~..coarse.coarse_view` where the optimisation runs on the coarse grid
    (:func:`runs_coarse`), else ``state`` itself; with ``objective`` set as its objective.

    A build measures the objective of its initial and final correspondence, and of the
    baselines (their grids permitting), on this one."""
    view = (coarse_view(state, settings.coarse_points) if runs_coarse(state, settings, active)
            else state)
    if objective is not None:
        view.objective = objective
    return view


@dataclass(frozen=True)
class Phase:
    """One phase of :func:`optimise`: its name (the trace's and the checkpoints'), objective,
    deadline (``time.perf_counter()`` seconds), whether it runs on the coarse grid, the
    settings it runs with and further keyword options of the phase function."""

    name: str
    objective: object
    deadline: float
    settings: OptimisationSettings
    coarse: bool = False
    options: dict = field(default_factory=dict)


def _phases(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
            start: float, active) -> list:
    """The phases of a run: with landmark guides, the guides' term alone (on the coarse field
    levels :data:`LANDMARK_PHASE_LEVELS` of the fast strategy, within
    :data:`LANDMARK_PHASE_SHARE` of the time); the fixed-Delta objective's (unless
    ``fixed_fraction`` is 0), then the full objective's; for the fast strategy on all examples
    of surfaces sampled more finely than ``coarse_points`` (:func:`runs_coarse`), all on the
    coarse grid (named "coarse landmarks", "coarse fixed" and "coarse integrated";
    ``coarse_passes`` passes over the field levels in the fixed-Delta phase, one in the full
    objective's), whose maps are then carried over to the state's own grid."""
    fixed, integrated = objectives
    total = settings.max_time
    coarse = runs_coarse(state, settings, active)
    names = ("coarse fixed", "coarse integrated") if coarse else ("fixed", "integrated")
    passes = ((settings.coarse_passes, 1) if coarse
              else (settings.field_passes, settings.field_passes))
    phases = [Phase(names[1], integrated, start + total,
                    replace(settings, field_passes=passes[1]), coarse)]
    if settings.fixed_fraction > 0:
        phases.insert(0, Phase(names[0], fixed, start + settings.fixed_fraction * total,
                               replace(settings, field_passes=passes[0]), coarse))
    if state.guides is not None:
        # the landmarks first, alone: the coarsest fields carry each case's landmarks to their
        # shared places, moving whole regions with them, before the description length moves
        # the points between them
        phases.insert(0, Phase("coarse landmarks" if coarse else "landmarks", NoDescription(),
                               start + LANDMARK_PHASE_SHARE * total,
                               replace(settings, field_passes=1), coarse,
                               {"levels": LANDMARK_PHASE_LEVELS}
                               if settings.strategy == "fast" else {}))
    return phases


def _checkpoint_of(checkpoint, state: CorrespondenceState, point: PhasePoint):
    """``checkpoint(point, state)``: the point reached and the state it was reached in (the
    coarse stage's own, during that stage)."""
    checkpoint(point, state)


def _finish_coarse_stage(coarse: CorrespondenceState, state: CorrespondenceState,
                         settings: OptimisationSettings):
    """The coarse stage's correspondence carried over to ``state``'s grid."""
    with Threads(settings.threads) as threads:
        dropped = carry_over(coarse, state, threads)
    if dropped:
        log.warning("%d warp(s) of the coarse stage turned a triangle of the %d-point grid over "
                    "and were left out", dropped, state.n_points)
