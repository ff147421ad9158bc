"""Why an optimisation stopped (``Trace.stopped_by``), for every strategy: its own stopping rule
(converged), the time limit or the sweep limit; only the full objective's phase decides; and an
optimisation stopped by ``max_sweeps`` and resumed with a larger one ends as if never stopped."""

import numpy as np
import pytest

from mdlshapemodel.config import OptimisationSettings
from mdlshapemodel.correspondence.state import state_record
from mdlshapemodel.correspondence.strategies import PHASES, optimise
from mdlshapemodel.correspondence.trace import Stop, Trace, stop_summary

from resuming import assert_same_record, optimised_with_checkpoints, resumed_from
from synthetic import build_objectives, small_state

# short steps, one phase (the full objective), one pass of the fast strategy's levels and two
# levels of multiresolution: every strategy runs to its end in seconds
QUICK = dict(fixed_fraction=0.0, pose_evaluations=20, simplex_evaluations=60, field_passes=1,
             max_levels=2)
# a tolerance every sweep after the first meets (a gain below 99 % of the phase's gain), and one
# quiet sweep is enough: each strategy's stopping rule ends it after a few steps
EASY = dict(tolerance=0.99, patience=1)


def stopped_by(strategy: str, **settings) -> Stop | None:
    """Why ``optimise`` of the small state with ``strategy`` and ``settings`` stopped."""
    state = small_state()
    trace = Trace()
    optimise(state, build_objectives(state), OptimisationSettings(strategy=strategy, **settings),
             np.random.default_rng(0), trace)
    return trace.stopped_by


@pytest.mark.parametrize("strategy", sorted(PHASES))
def test_a_strategy_left_to_its_stopping_rule_says_converged(strategy):
    assert stopped_by(strategy, max_time=1e6, **QUICK, **EASY) is Stop.CONVERGED


@pytest.mark.parametrize("strategy", sorted(PHASES))
def test_a_strategy_out_of_time_says_time_limit(strategy):
    # no time at all: the first step runs, then the deadline has passed
    assert stopped_by(strategy, max_time=0.0, **QUICK, **EASY) is Stop.TIME_LIMIT


@pytest.mark.parametrize("strategy", sorted(PHASES))
def test_a_strategy_out_of_sweeps_says_sweep_limit(strategy):
    # one step, with a tolerance no step meets: the stopping rule cannot end it first
    assert stopped_by(strategy, max_time=1e6, max_sweeps=1, tolerance=1e-12,
                      **QUICK) is Stop.SWEEP_LIMIT


def test_the_fixed_delta_phase_cut_by_its_share_of_the_time_does_not_make_it_unconverged():
    """The fixed-Delta phase ends at ``fixed_fraction`` of ``max_time`` by design (here after
    its first round: a millisecond); the full objective's phase, converged, decides."""
    state = small_state()
    trace = Trace()
    settings = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=1e-9,
                                    field_passes=1, **EASY)
    optimise(state, build_objectives(state), settings, np.random.default_rng(0), trace)
    assert max(row.sweep for row in trace.rows if row.phase == "fixed") == 1
    assert trace.stopped_by is Stop.CONVERGED


def test_keeping_the_initial_correspondence_optimises_nothing():
    assert stopped_by("none", max_time=1e6) is None
    assert stop_summary(None) == "not run"
    assert stop_summary(Stop.TIME_LIMIT) == stop_summary("time limit") == \
        "not converged (time limit)"


@pytest.mark.parametrize("strategy", sorted(PHASES))
def test_a_sweep_limited_optimisation_resumed_with_more_sweeps_ends_as_if_never_stopped(strategy):
    """The remedy for the sweep limit: the last checkpoint of a run stopped by ``max_sweeps``
    one step before it would have converged, resumed with a larger ``max_sweeps``, converges to
    the uninterrupted run's state bit for bit."""
    # two quiet sweeps to converge (the fast strategy: a round per level; multiresolution: two
    # levels): a run of at least two steps, which one step fewer stops short
    easy = {**EASY, "patience": 2}
    unlimited = OptimisationSettings(strategy=strategy, max_time=1e6, **QUICK, **easy)
    whole = small_state()
    final, whole_trace, _ = optimised_with_checkpoints(whole, unlimited)
    assert whole_trace.stopped_by is Stop.CONVERGED
    steps = max(row.sweep for row in whole_trace.rows)
    assert steps >= 2
    limited = OptimisationSettings(strategy=strategy, max_time=1e6, max_sweeps=steps - 1,
                                   **QUICK, **easy)
    _, trace, saved = optimised_with_checkpoints(small_state(), limited)
    assert trace.stopped_by is Stop.SWEEP_LIMIT
    resumed = small_state()
    value, resumed_trace = resumed_from(resumed, unlimited, saved[-1])
    assert resumed_trace.stopped_by is Stop.CONVERGED
    assert value == final
    assert_same_record(state_record(resumed), state_record(whole))
