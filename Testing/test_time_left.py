"""How long is left: the estimates in a build's progress reports (progress.TimeLeft), and a real
build's lines that carry them; the same build leaves out a subset of its cases for G(M)
(--generalization-cases) and says so in metrics.json and the report."""

import json
import os
import pickle
import re
import subprocess
import sys

import pytest

import numpy as np

from mdlshapemodel.config import OptimisationSettings
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.strategies.fast import FIELD_LEVELS, ROUNDS_PER_LEVEL, most_rounds
from mdlshapemodel.correspondence.trace import Stop, Trace
from mdlshapemodel.progress import (OBJECTIVE, Message, TimeLeft, kind_of, report, rounds_left_of,
                                    time_left_text)

from files import write_label_map
from synthetic import build_objectives, small_mask, small_state

LEFT = re.compile(r"(?:\(|; )(about|at most about) (\d+(?:\.\d+)?) (s|min|h) left(, the time budget)?\)")
# the optimisation's bound by its schedule: "(at most 9 more rounds, about 4 min)", or the rounds
# beside the budget's bound: "(at most 9 more rounds; at most about 5 min left, the time budget)"
ROUNDS = re.compile(r"\(at most (\d+) more rounds?(?:, about (\d+(?:\.\d+)?) (s|min|h)\)|; )")


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def watched(budget=600.0):
    """The messages seen, the clock and a TimeLeft of ``budget`` that passes them on."""
    seen, clock = [], Clock()
    return seen, clock, TimeLeft(lambda fraction, message: seen.append(message), budget=budget,
                                 clock=clock)


def seconds(text):
    """The time left a report says: the schedule's or the budget's."""
    found = ROUNDS.search(text)
    if found is None or found.group(2) is None:
        found = LEFT.search(text)
    assert found, text
    return float(found.group(2)) * {"s": 1, "min": 60, "h": 3600}[found.group(3)]


def test_the_estimates_of_a_counted_stage_and_of_the_optimisation():
    seen, clock, progress = watched()
    clock.now += 10.0
    progress(0.25, "prepared 1/4")            # 10 s for a quarter: 30 s to go
    clock.now += 10.0
    progress(0.5, "prepared 2/4")
    clock.now += 20.0
    progress(1.0, "prepared 4/4")             # done: no estimate
    assert seconds(seen[0]) == 30 and seconds(seen[1]) == 20
    assert LEFT.search(seen[2]) is None
    clock.now += 5.0
    report(progress, None, "fixed: level 0, round 1, F = 3.000", OBJECTIVE)   # the budget on
    clock.now += 240.0
    report(progress, None, "fixed: level 0, round 2, F = 2.000", OBJECTIVE)
    assert seconds(seen[3]) == 600 and seconds(seen[4]) == 6 * 60
    assert "at most about" in seen[4] and "time budget" in seen[4]
    clock.now += 400.0                        # past the budget: no bound to give
    report(progress, None, "integrated: level 1, round 9, F = 1.000", OBJECTIVE)
    assert LEFT.search(seen[5]) is None
    progress(0.0, "evaluating")               # a new counted stage starts its own clock
    clock.now += 3.0
    progress(0.5, "evaluating the model")
    assert seconds(seen[7]) == 3
    assert time_left_text(3 * 3600) == "3.0 h"


def test_a_landmark_checks_folds_get_no_estimate_and_each_optimisation_its_own_budget():
    seen, clock, progress = watched()
    report(progress, None, "fixed: level 0, round 1, F = 3.000", OBJECTIVE)
    clock.now += 560.0
    report(progress, None, "integrated: level 1, round 9, F = 1.000", OBJECTIVE)
    assert seconds(seen[1]) == 40
    clock.now += 50.0
    progress(None, "landmark check 1 of 4: tip left out of the guides")
    assert seen[2] == "landmark check 1 of 4: tip left out of the guides"
    clock.now += 1.0
    report(progress, None, "fixed: level 0, round 1, F = 3.100", OBJECTIVE)   # its own budget
    clock.now += 60.0
    report(progress, None, "fixed: level 0, round 2, F = 3.000", OBJECTIVE)
    assert seconds(seen[3]) == 600 and seconds(seen[4]) == 9 * 60


def test_the_optimisation_is_known_by_the_reports_kind_not_by_its_text():
    """A report of kind OBJECTIVE is bounded by the budget whatever it says; a report that says
    "F = " without the kind is not; the kind goes on to the next callback with the estimate."""
    seen, clock, progress = watched()
    report(progress, None, "round 1: the objective is 3.0", OBJECTIVE)
    clock.now += 120.0
    report(progress, None, "round 2: the objective is 2.5", OBJECTIVE)
    assert seconds(seen[0]) == 600 and seconds(seen[1]) == 8 * 60
    assert [kind_of(m) for m in seen] == [OBJECTIVE, OBJECTIVE]
    assert seen[1] == "round 2: the objective is 2.5 (at most about 8 min left, the time budget)"
    report(progress, None, "a statistic, F = 4.2")     # no kind: no bound, whatever it says
    assert seen[2] == "a statistic, F = 4.2" and kind_of(seen[2]) is None
    # a message with a kind is its text to any callback, and keeps its kind when pickled
    message = pickle.loads(pickle.dumps(Message("fixed: F = 1.000", OBJECTIVE)))
    assert message == "fixed: F = 1.000" and kind_of(message) == OBJECTIVE


def test_a_counted_stage_is_timed_from_the_report_before_its_first():
    """A counted stage's first report comes with its first step done: the stage began at the
    report before it (the last of the stage before), so the first report has an estimate."""
    seen, clock, progress = watched()
    report(progress, None, "integrated: level 1, round 9, F = 1.000", OBJECTIVE)
    clock.now += 10.0
    progress(0.25, "evaluating 1/4")          # 10 s for the first quarter: 30 s to go
    clock.now += 10.0
    progress(0.5, "evaluating 2/4")
    assert seconds(seen[1]) == 30 and seconds(seen[2]) == 20


def test_the_budget_is_counted_from_the_optimisations_first_report():
    """What comes between the last counted report and the optimisation (the registrations, the
    initial correspondence) is not the optimisation's time."""
    seen, clock, progress = watched()
    progress(1.0, "prepared 4/4")
    clock.now += 120.0
    report(progress, None, "fixed: level 0, round 1, F = 3.000", OBJECTIVE)
    clock.now += 60.0
    report(progress, None, "fixed: level 0, round 2, F = 2.000", OBJECTIVE)
    assert seconds(seen[1]) == 600 and seconds(seen[2]) == 9 * 60


def test_the_optimisation_says_the_nearer_of_its_rounds_left_and_the_budget():
    """Where the reports bound the rounds left, those rounds at the mean time between the
    reports so far are said where they end before the budget; the first report (no interval
    yet) and a schedule that outlasts the budget give the budget's bound beside the rounds; no
    rounds left: no estimate."""
    seen, clock, progress = watched(budget=600.0)
    progress(1.0, "prepared 4/4")
    clock.now += 50.0
    report(progress, None, "fixed: level 0, round 1, F = 3.000", OBJECTIVE, rounds_left=20)
    assert seen[1] == ("fixed: level 0, round 1, F = 3.000 (at most 20 more rounds; at most "
                       "about 10 min left, the time budget)")
    clock.now += 20.0
    report(progress, None, "fixed: level 0, round 2, F = 2.000", OBJECTIVE, rounds_left=10)
    assert seen[2].endswith("(at most 10 more rounds, about 3 min)")      # 10 x 20 s
    clock.now += 40.0                                                     # a mean of 30 s
    report(progress, None, "fixed: level 0, round 3, F = 1.900", OBJECTIVE, rounds_left=1)
    assert seen[3].endswith("(at most 1 more round, about 30 s)")
    clock.now += 60.0                                   # 30 rounds of 40 s: past the budget
    report(progress, None, "integrated: level 0, round 1, F = 1.800", OBJECTIVE, rounds_left=30)
    assert seen[4].endswith("(at most 30 more rounds; at most about 8 min left, the time budget)")
    clock.now += 30.0
    report(progress, None, "integrated: level 0, round 2, F = 1.700", OBJECTIVE, rounds_left=0)
    assert seen[5] == "integrated: level 0, round 2, F = 1.700"           # the last round
    assert [rounds_left_of(m) for m in seen[1:]] == [20, 10, 1, 30, 0]    # passed on
    assert all(kind_of(m) == OBJECTIVE for m in seen[1:])
    message = pickle.loads(pickle.dumps(seen[2]))
    assert rounds_left_of(message) == 10 and kind_of(message) == OBJECTIVE
    # a new run of the optimisation's reports (a landmark check's fold) counts its own rounds
    progress(None, "landmark check 1 of 4: tip left out of the guides")
    clock.now += 100.0
    report(progress, None, "fixed: level 0, round 1, F = 3.000", OBJECTIVE, rounds_left=5)
    clock.now += 10.0
    report(progress, None, "fixed: level 0, round 2, F = 2.000", OBJECTIVE, rounds_left=4)
    assert seen[-2].endswith("(at most 5 more rounds; at most about 10 min left, the time budget)")
    assert seen[-1].endswith("(at most 4 more rounds, about 40 s)")


def test_without_a_budget_only_the_rounds_bound_the_optimisation():
    seen, clock, progress = watched(budget=None)
    report(progress, None, "round 1, F = 3.0", OBJECTIVE, rounds_left=6)
    clock.now += 5.0
    report(progress, None, "round 2, F = 2.0", OBJECTIVE, rounds_left=5)
    report(progress, None, "round 3, F = 1.0", OBJECTIVE)      # no rounds known: nothing said
    assert seen == ["round 1, F = 3.0 (at most 6 more rounds)",
                    "round 2, F = 2.0 (at most 5 more rounds, about 25 s)", "round 3, F = 1.0"]


def schedule(passes):
    """Every position of the fast strategy's full schedule, in order (no level cut short)."""
    return [{"pass": p, "level": level, "round": r} for p in range(passes)
            for level in range(len(FIELD_LEVELS)) for r in range(ROUNDS_PER_LEVEL)]


@pytest.mark.parametrize("passes", [1, 2, 3])
def test_the_most_rounds_of_a_phase_count_its_schedule_from_a_position_on(passes):
    settings = OptimisationSettings(field_passes=passes)
    positions = schedule(passes)
    assert most_rounds(settings) == len(positions)
    for k, at in enumerate(positions):
        assert most_rounds(settings, at=at) == len(positions) - k, at


def rounds_reported(settings):
    """The optimisation's reports of the small state's real optimisation with ``settings``, and
    why it stopped."""
    state, seen, trace = small_state(), [], Trace()
    optimise(state, build_objectives(state), settings, np.random.default_rng(0), trace,
             lambda fraction, message: seen.append(message))
    return [m for m in seen if kind_of(m) == OBJECTIVE], trace.stopped_by


def test_the_fast_strategys_reports_bound_the_rounds_the_optimisation_makes():
    """A real optimisation (both phases, two passes): after every report the rounds that follow
    are at most the number it said, each report's bound is below the one before it, the fixed-
    Delta phase's last report counts the full objective's whole schedule, and the last report
    of a converged optimisation says none."""
    settings = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=0.5,
                                    field_passes=2)
    rounds, stopped_by = rounds_reported(settings)
    assert stopped_by == Stop.CONVERGED
    left = [rounds_left_of(m) for m in rounds]
    phases = [m.split(":")[0] for m in rounds]
    assert "fixed" in phases and "integrated" in phases and len(rounds) > 4
    for k, bound in enumerate(left):
        assert len(rounds) - 1 - k <= bound, (k, left)
    assert all(a > b for a, b in zip(left, left[1:])), left
    assert left[0] <= 2 * most_rounds(settings) - 1
    last_fixed = max(k for k, phase in enumerate(phases) if phase == "fixed")
    assert left[last_fixed] == most_rounds(settings) and left[-1] == 0


def test_the_sweep_limit_bounds_each_phases_rounds_in_the_reports():
    """``max_sweeps`` rounds a phase at most: 5 rounds of the fixed-Delta phase and 5 of the full
    objective's, each report saying exactly the rounds still to come."""
    settings = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=0.5,
                                    max_sweeps=5)
    rounds, stopped_by = rounds_reported(settings)
    assert stopped_by == Stop.SWEEP_LIMIT
    assert [rounds_left_of(m) for m in rounds] == list(range(9, -1, -1))


def test_a_cancelling_callback_still_cancels_through_it():
    progress = TimeLeft(lambda fraction, message: False, budget=10.0)
    assert progress(0.5, "prepared 1/2") is False


@pytest.mark.slow
def test_a_real_build_says_how_long_is_left_and_that_g_is_from_a_sample(tmp_path):
    inputs = tmp_path / "in"
    inputs.mkdir()
    for k, position in enumerate((-0.6, -0.3, 0.0, 0.3, 0.6)):
        write_label_map(inputs / f"s{k}.nii.gz", small_mask(position).astype("uint8"))
    out = tmp_path / "out"
    command = [sys.executable, "-m", "mdlshapemodel.cli", "build", str(inputs), "-o", str(out),
               "--points", "42", "--max-time", "60", "--workers", "1", "--no-cache",
               "--specificity-samples", "100", "--evaluation-modes", "2",
               "--surface-samples", "0", "--generalization-cases", "4"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=900,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    assert result.returncode == 0, result.stderr
    log = (out / "build.log").read_text().splitlines()
    # the first report of the preparation (its stage's first line) estimates the rest
    preparing = [line for line in log if "prepared 1/5" in line]
    assert preparing and LEFT.search(preparing[0]), preparing
    assert seconds(preparing[0]) >= 0
    # the optimisation's first line: its rounds at most, bounded by the 60-s budget; the later
    # lines, by the rounds' mean time or the budget, whichever is nearer, within the budget
    optimising = [line for line in log if "F = " in line and "more round" in line]
    assert optimising, "\n".join(log)
    found = LEFT.search(optimising[0])
    assert ROUNDS.search(optimising[0]).group(2) is None
    assert found.group(1) == "at most about" and 0 < seconds(optimising[0]) <= 60
    assert all(0 <= seconds(line) <= 60 for line in optimising)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_shapes"] == 5 and metrics["generalization_cases"] == 4
    assert len(metrics["generalization_subsample_se"]) == 2
    page = (out / "report.html").read_text()
    assert "random sample of 4 of the 5 cases" in page
