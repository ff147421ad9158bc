"""A dying worker process is one rejected case, not a dead build (real processes throughout).

Workers are killed by Testing/crash_on_prepare.py (armed in a pool's workers through
``parallel.WORKER_STARTUP``: a worker dies as it opens a matching input), by the functions of
Testing/dying.py that end their own process, as a segfault in a native library would, or from
outside, stalled in an evaluation by Testing/stalls_evaluation.py.
"""

import json
import logging
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from concurrent.futures import Executor, ProcessPoolExecutor

import numpy as np
import pytest

from mdlshapemodel import BuildConfig, ShapeModel, build_model
from mdlshapemodel import parallel
from mdlshapemodel.parallel import ProcessPool, Task, map_cases
from mdlshapemodel.prepare import preprocess
from mdlshapemodel.prepare.io import read_csv

import crash_on_prepare
import stalls_evaluation
from dying import die, square_or_die
from common import TIMEOUT, run_python
from synthetic import write_population


def rejected(index: int, how: str) -> str:
    return f"{index}: {how}"


EXPECTED = [0, 1, "2: worker process died (signal 9)", 9, "4: worker process died (exit code 7)",
            25, "6: worker process died (exit code 0)", 49]


def test_a_case_that_kills_its_worker_is_given_up_and_the_others_go_on(caplog):
    """The dying cases become ``died(index, how)`` with their signal or exit code; the cases
    that were running beside them when the pool broke, and those after, get their results."""
    with ProcessPool(2) as pool:
        with caplog.at_level(logging.WARNING, "mdlshapemodel"):
            results = map_cases(square_or_die, [(x,) for x in range(8)], pool, died=rejected)
        assert results == EXPECTED
        # the pool replaced itself: it still works
        assert pool.submit(square_or_die, 5).result() == 25
    assert "each alone in a fresh process" in caplog.text


def test_a_callers_executor_that_breaks_is_replaced_by_a_pool_of_our_own(caplog):
    """A caller's executor is not ours to replace: its unfinished cases run in a pool made for
    them (the log says so), with the same results."""
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as theirs:
        with caplog.at_level(logging.WARNING, "mdlshapemodel"):
            results = map_cases(square_or_die, [(x,) for x in range(8)], theirs, died=rejected,
                                workers=2)
    assert results == EXPECTED
    assert "the executor broke" in caplog.text


class FirstCallDies(Executor):
    """A caller's executor whose first call kills its worker process instead of running."""

    def __init__(self, pool):
        self.pool, self.calls = pool, 0

    def submit(self, fn, /, *args, **kwargs):
        self.calls += 1
        return self.pool.submit(die) if self.calls == 1 else self.pool.submit(fn, *args, **kwargs)


def test_an_evaluation_whose_worker_dies_is_done_here_with_the_same_numbers(rng):
    from mdlshapemodel.model.evaluation import evaluate
    from mdlshapemodel.model.shape_model import ShapeModel as Model
    from synthetic import radial_population

    shapes, triangles, weights, surfaces = radial_population(rng, 5, 3)
    variances = Model.from_shapes(shapes, weights).variances
    here = evaluate(shapes, weights, variances, 2, 100, np.random.default_rng(5),
                    triangles=triangles, surfaces=surfaces, surface_samples=5)
    with ProcessPool(1) as pool:
        # the surface generalization's worker dies: measured here
        dying = FirstCallDies(pool)
        assert evaluate(shapes, weights, variances, 2, 100, np.random.default_rng(5),
                        triangles=triangles, surfaces=surfaces, surface_samples=5,
                        pool=dying) == here
        # a whole evaluation in the background (a baseline's), its worker dies: done here
        dying.calls = 0
        task = Task(dying, evaluate, shapes, weights, variances, 2, 100,
                    np.random.default_rng(5), triangles, surfaces, 5)
        assert task.result() == here
    # an executor already broken when the work is submitted
    broken = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
    broken.submit(die).exception()
    assert Task(broken, square_or_die, 3).result() == 9
    broken.shutdown()


def test_a_settled_task_lets_its_arguments_go():
    """A task whose run ended well gives its value at ``settle`` and drops its arguments; one
    whose run failed keeps them (to be done again); one still running is not settled."""
    with ProcessPool(1) as pool:
        held = Task(pool, time.sleep, 0.5)
        task, failing = Task(pool, square_or_die, 5), Task(pool, int, "five")
        assert not held.settle() and held.arguments == (0.5,)          # still running
        held.result()
        assert pool.submit(abs, -1).result() == 1                       # the others are done
        assert task.settle() and task.arguments == () and task.result() == 25
        assert not failing.settle() and failing.arguments == ("five",)


def test_a_rested_pool_ends_its_workers_and_starts_fresh_ones_at_the_next_call():
    """``rest`` ends the worker processes (their memory with them); the next call starts a new
    one, which gives the right answer; resting an idle or rested pool does nothing."""
    with ProcessPool(1) as pool:
        assert not pool.running()
        pool.rest()
        first = pool.submit(os.getpid).result()
        assert pool.running() and first != os.getpid()
        pool.rest()
        assert not pool.running()
        with pytest.raises(ProcessLookupError):     # ended and reaped
            os.kill(first, 0)
        second = pool.submit(os.getpid).result()
        assert second not in (first, os.getpid())
        assert pool.submit(square_or_die, 7).result() == 49
    assert not pool.running()


@pytest.mark.parametrize("rests_from", [5, 6])
def test_a_large_build_ends_its_helper_once_the_baselines_are_evaluated(tmp_path, monkeypatch,
                                                                         rests_from):
    """With worker processes and at least ``HELPER_RESTS_FROM`` cases (here made 5, then 6:
    the build has 5), the helper that evaluated the baselines during the optimisation ends
    with the first checkpoint after their results came (the log says so) and the model is
    evaluated on a fresh one; a smaller build keeps it. metrics.json has the baselines'
    figures and the model's either way."""
    from mdlshapemodel import build as build_module

    monkeypatch.setattr(build_module, "HELPER_RESTS_FROM", rests_from)
    write_population(tmp_path / "inputs", 5)
    output = tmp_path / "out"
    config = BuildConfig(points=162, coarse_points=42, workers=2, evaluation_modes=2,
                         specificity_samples=50, surface_samples=5)
    rounds = []

    def slow_rounds(fraction, message):
        """The first rounds made to last a second each: the optimisation then outlasts the
        helper's start and evaluation on a busy machine too, so that checkpoints come after
        the results (this build's own rounds may all end first)."""
        if ", round " in message and len(rounds) < 8:
            rounds.append(message)
            time.sleep(1.0)

    build_model([tmp_path / "inputs"], output, config, progress=slow_rounds)
    assert len(rounds) == 8
    log = (output / "build.log").read_text()
    rested = log.find("the baselines are evaluated: the helper process ended")
    if rests_from <= 5:
        assert 0 < log.find("evaluating the none baseline beside the optimisation") < rested
        assert rested < log.find("final objective")
        assert log.count("the helper process ended") == 1
    else:
        assert rested == -1
    metrics = json.loads((output / "metrics.json").read_text())
    assert len(metrics["baselines"]["none"]["generalization"]) == 2
    assert len(metrics["generalization"]) == 2 and len(metrics["specificity"]) == 2


ENDED_AT_ONCE = """
import os, sys
from mdlshapemodel.parallel import ProcessPool, quiet_resource_tracker
if __name__ == "__main__":
    if sys.argv[1] == "quiet":
        quiet_resource_tracker()
    pool = ProcessPool(1)
    assert pool.submit(abs, -3).result() == 3
    os._exit(130)               # as a build's second Ctrl-C ends it, its pool still open
"""


@pytest.mark.parametrize("quiet", [True, False])
def test_a_process_ended_at_once_leaves_no_warning_of_leaked_semaphores(tmp_path, quiet):
    """multiprocessing's resource tracker removes the semaphores of a pool whose process ended at
    once, and warns of them unless told not to (the build tells it)."""
    script = tmp_path / "ended.py"
    script.write_text(ENDED_AT_ONCE)
    environment = {k: v for k, v in os.environ.items() if k != "PYTHONWARNINGS"}
    run = subprocess.run([sys.executable, str(script), "quiet" if quiet else "loud"],
                         capture_output=True, text=True, env=environment, timeout=TIMEOUT)
    assert run.returncode == 130
    assert ("leaked semaphore" in run.stderr) is not quiet, run.stderr


TESTING = Path(__file__).resolve().parent


def build(inputs, output, workers, crash_on):
    """The command line's small build with its pool workers armed to die on inputs whose path
    contains ``crash_on`` (crash_on_prepare.CLI)."""
    environment = dict(os.environ, PYTHONWARNINGS="ignore",
                       PYTHONPATH=os.pathsep.join(filter(None, [str(TESTING),
                                                                os.environ.get("PYTHONPATH")])))
    environment[crash_on_prepare.VARIABLE] = crash_on
    return run_python(crash_on_prepare.CLI, "build", *inputs, "-o", output, "--points", "162",
                      "--baselines", "", "--max-sweeps", "1", "--evaluation-modes", "2",
                      "--specificity-samples", "50", "--surface-samples", "5", "--workers",
                      workers, cwd=TESTING, env=environment, timeout=600)


@pytest.mark.slow
def test_a_build_rejects_the_case_that_kills_its_worker_and_models_the_others(tmp_path):
    """``--workers 2``, one input kills its worker whenever it is prepared: the build succeeds,
    rejected.csv says why, and the model is bit for bit that of the other inputs alone (prepared
    again, in this process, with one worker and no cache)."""
    from mdlshapemodel.build import correspond

    paths = write_population(tmp_path / "inputs")
    culprit = paths[2]
    output = tmp_path / "out"
    result = build([tmp_path / "inputs"], output, 2, crash_on=culprit.name)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    rows = read_csv(output / "rejected.csv")
    assert [(row["case"], row["file"]) for row in rows] == [("case_2", str(culprit))]
    assert rows[0]["reason"] == f"worker process died (signal 9) while preparing {culprit}"
    assert len([line for line in result.stderr.splitlines() if culprit.name in line]) == 1
    assert "each alone in a fresh process" in (output / "build.log").read_text()

    config = BuildConfig.from_dict({**json.loads((output / "config.json").read_text()),
                                    "workers": 1, "cache_dir": ""})
    prepared, _ = preprocess([p for p in paths if p != culprit], config)
    reference = correspond(prepared, config).model
    survived = ShapeModel.load(output / "model.h5")
    assert survived.names == reference.names == ["case_0", "case_1", "case_3", "case_4"]
    for name in ("mean", "modes", "variances", "weights", "scores", "triangles", "parameters"):
        assert np.array_equal(getattr(survived, name), getattr(reference, name)), name


@pytest.mark.slow
@pytest.mark.timeout(3 * TIMEOUT)
def test_a_build_whose_helper_is_killed_with_a_baseline_queued_evaluates_them_here(tmp_path):
    """``--workers 2`` with two baselines: the helper process holds the first one's evaluation
    (stalled in it: Testing/stalls_evaluation.py) while the second one's waits behind it, and is
    killed (SIGKILL, as by the out-of-memory killer) once the optimisation has begun. The build
    does not hang: it evaluates both baselines here, the model on a fresh helper, and succeeds."""
    paths = write_population(tmp_path / "inputs")
    output, stalled = tmp_path / "out", tmp_path / "helper.pid"
    environment = dict(os.environ, PYTHONWARNINGS="ignore",
                       PYTHONPATH=os.pathsep.join(filter(None, [str(TESTING),
                                                                os.environ.get("PYTHONPATH")])))
    environment[stalls_evaluation.VARIABLE] = str(stalled)
    command = [sys.executable, "-c", stalls_evaluation.CLI, "build", str(tmp_path / "inputs"),
               "-o", str(output), "--points", "162", "--baselines", "none,cpd", "--max-sweeps",
               "1", "--evaluation-modes", "2", "--specificity-samples", "50",
               "--surface-samples", "5", "--workers", "2"]
    build = subprocess.Popen(command, cwd=TESTING, env=environment, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    try:
        # the first baseline is on the helper; the CPD baseline's evaluation was submitted
        # before the optimisation's first checkpoint (a hang fails at TIMEOUT)
        waited = time.monotonic()
        while build.poll() is None and not (stalled.exists()
                                            and (output / "checkpoint.npz").exists()):
            assert time.monotonic() - waited < TIMEOUT, "the build never reached its optimisation"
            time.sleep(0.1)
        assert build.poll() is None, build.communicate()[1]
        os.kill(int(stalled.read_text()), signal.SIGKILL)
        _, stderr = build.communicate(timeout=TIMEOUT)
    finally:
        if build.poll() is None:
            build.kill()
            build.communicate()
    assert build.returncode == 0, stderr
    assert "Traceback" not in stderr
    log = (output / "build.log").read_text()
    assert log.count("an evaluation on the executor did not finish (BrokenProcessPool); "
                     "doing it here") == 2
    metrics = json.loads((output / "metrics.json").read_text())
    assert sorted(metrics["baselines"]) == ["cpd", "none"]
    for values in metrics["baselines"].values():
        assert len(values["generalization"]) == 2
    assert len(metrics["generalization"]) == 2


def test_worker_startup_functions_run_in_every_pool_worker_and_never_here(tmp_path, monkeypatch):
    """``parallel.WORKER_STARTUP`` is run by each worker a pool starts (also the fresh one that
    runs a suspect case alone), never by the main process: with one worker the case is prepared
    here; on a pool of two its worker dies, and again alone, and it is rejected."""
    paths = write_population(tmp_path / "inputs", 2)
    monkeypatch.setenv(crash_on_prepare.VARIABLE, paths[1].name)
    monkeypatch.setattr(parallel, "WORKER_STARTUP", [crash_on_prepare.arm])
    prepared, rejected_cases = preprocess(paths, BuildConfig(workers=1, cache_dir=""))
    assert [case.name for case in prepared] == ["case_0", "case_1"] and rejected_cases == []
    with ProcessPool(2) as pool:
        prepared, rejected_cases = preprocess(paths, BuildConfig(cache_dir=""), pool)
    assert [case.name for case in prepared] == ["case_0"]
    assert [(r.name, r.reason) for r in rejected_cases] == [
        ("case_1", f"worker process died (signal 9) while preparing {paths[1]}")]


@pytest.mark.parametrize("threads", [None, 1])
def test_a_finished_task_lets_go_of_its_inputs(threads):
    # a task keeps its inputs to redo lost work; once it has its value they may be freed
    import gc
    import weakref
    from concurrent.futures import ThreadPoolExecutor

    data = np.arange(1000.0)
    ref = weakref.ref(data)
    executor = None if threads is None else ThreadPoolExecutor(threads)
    task = Task(executor, np.sum, data, what="a sum")
    del data
    assert task.result() == 499500.0
    gc.collect()
    assert ref() is None
    assert task.result() == 499500.0          # asked again: the same value
    if executor is not None:
        executor.shutdown()
