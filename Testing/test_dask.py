"""Per-case work on a Dask cluster (``build --scheduler``), with real processes throughout: the
test starts a scheduler and two worker processes on 127.0.0.1 with the ``dask`` command of this
interpreter, and runs the real command line against them.

The workers run two threads each, and their environment asks BLAS for two threads: what the
library must make safe (one call at a time per process, one BLAS thread) is then really there to
be made safe. They also carry the test-only crash hook for inputs named ``crashing*``.
"""

import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from distributed import Client

import mdlshapemodel
from mdlshapemodel import BuildConfig, ShapeModel
from mdlshapemodel.build import correspond, fingerprint
from mdlshapemodel.errors import ArgumentError, ConfigError
from mdlshapemodel import parallel
from mdlshapemodel.cluster import dask_executor, on_cluster
from mdlshapemodel.parallel import Task, map_cases
from mdlshapemodel.prepare import preprocess
from mdlshapemodel.prepare.io import read_csv

import crash_on_prepare
import dies_in_a_round
from dying import square_or_die
from on_workers import blas_threads, held
from common import hippocampi, needs_hippocampi, run_cli, run_python
from synthetic import build_objectives, small_state, write_population

# real builds (the command line or build_model): deselected by -m "not slow"
pytestmark = pytest.mark.slow

DASK = Path(sys.executable).with_name("dask")
PACKAGE_ROOT = str(Path(mdlshapemodel.__file__).resolve().parents[1])
TESTING = str(Path(__file__).resolve().parent)
CRASHING = "crashing"
SMALL_BUILD = ["--points", "162", "--max-sweeps", "1", "--evaluation-modes", "2",
               "--specificity-samples", "50", "--surface-samples", "5", "--baselines", "none,cpd",
               "--no-cache"]


def _start(arguments: list, environment: dict, log: Path) -> subprocess.Popen:
    with open(log, "w") as handle:   # the child keeps its own descriptor
        return subprocess.Popen([str(DASK), *arguments], stdout=handle, stderr=subprocess.STDOUT,
                                env=environment, start_new_session=True)


def _stop(process: subprocess.Popen):
    """End ``process`` and every process it started (its own process group)."""
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGTERM)
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()


@pytest.fixture(scope="module")
def dying(tmp_path_factory) -> Path:
    """The file whose creation arms the workers to lose one of them in a round of the
    optimisation (Testing/dies_in_a_round.py)."""
    return tmp_path_factory.mktemp("dying") / "die-after"


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory, dying) -> str:
    """The address of a scheduler on 127.0.0.1 with two worker processes of two threads each;
    the scheduler gives a call up at its first dead worker (allowed-failures 0)."""
    folder = tmp_path_factory.mktemp("dask")
    inherited = [os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []
    environment = dict(os.environ, PYTHONWARNINGS="ignore",
                       PYTHONPATH=os.pathsep.join([PACKAGE_ROOT, TESTING, *inherited]))
    file = folder / "scheduler.json"
    started = []
    try:
        started.append(_start(["scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(file)],
                              {**environment, "DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES": "0"},
                              folder / "scheduler.log"))
        deadline = time.monotonic() + 60
        while not file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(file.read_text())["address"]
        # the workers are armed to die on inputs named crashing* (Testing/crash_on_prepare.py)
        # and, once ``dying`` exists, one of them in a round (Testing/dies_in_a_round.py)
        started.append(_start(["worker", address, "--nworkers", "2", "--nthreads", "2",
                               "--no-dashboard", "--local-directory", str(folder),
                               "--preload", "crash_on_prepare", "--preload", "dies_in_a_round"],
                              {**environment, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2",
                               crash_on_prepare.VARIABLE: CRASHING,
                               dies_in_a_round.VARIABLE: str(dying)}, folder / "workers.log"))
        with Client(address, set_as_default=False) as client:
            client.wait_for_workers(2, timeout=90)
        yield address
    finally:
        for process in reversed(started):
            _stop(process)


def build(inputs: list, output: Path, *options):
    """The real command line's ``build`` of ``inputs`` with the small settings and ``options``."""
    environment = dict(os.environ, PYTHONWARNINGS="ignore")
    return run_cli("build", *inputs, "-o", output, *SMALL_BUILD, *options, env=environment,
                   timeout=300)


def free_port() -> int:
    """A TCP port of 127.0.0.1 on which nothing listens (just now)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_importing_the_library_and_its_build_imports_no_dask():
    code = ("import sys, mdlshapemodel, mdlshapemodel.build, mdlshapemodel.parallel; "
            "print(','.join(m for m in ('dask', 'distributed') if m in sys.modules))")
    result = run_python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""


def test_the_scheduler_is_not_part_of_what_a_checkpoint_is_of():
    """A build interrupted on one cluster (or locally) resumes on another: the address is not
    in the fingerprint that ``--resume`` checks."""
    assert (fingerprint([], BuildConfig(scheduler="tcp://10.0.0.5:8786"))
            == fingerprint([], BuildConfig()))
    with pytest.raises(ConfigError, match="scheduler"):
        BuildConfig(scheduler=" ").validate()


def test_an_unreachable_scheduler_is_one_line_and_exit_code_2_before_any_work(tmp_path):
    paths = write_population(tmp_path / "inputs", 3)
    address = f"tcp://127.0.0.1:{free_port()}"
    result = build(paths, tmp_path / "out", "--scheduler", address)
    assert result.returncode == 2, result.stderr
    # the refusal itself, not a retry until the connect timeout ("... answers ... within N s")
    assert result.stderr.splitlines() == [
        f"mdlshapemodel: error: no Dask scheduler reachable at {address} (Connection refused)"]
    assert not (tmp_path / "out" / "rejected.csv").exists()   # nothing was prepared


def test_a_scheduler_of_another_mdlshapemodel_is_refused_naming_it_and_both_versions(tmp_path):
    """A real scheduler whose Python imports another install of the package: a copy of this
    one whose version says 0.0.0+other, first on its path."""
    other = tmp_path / "other"
    shutil.copytree(Path(mdlshapemodel.__file__).parent, other / "mdlshapemodel",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (other / "mdlshapemodel" / "version.py").write_text('__version__ = "0.0.0+other"\n')
    file = tmp_path / "scheduler.json"
    scheduler = _start(["scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                        "--scheduler-file", str(file)],
                       dict(os.environ, PYTHONWARNINGS="ignore", PYTHONPATH=str(other)),
                       tmp_path / "scheduler.log")
    try:
        deadline = time.monotonic() + 60
        while not file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(file.read_text())["address"]
        expected = (f"the Dask scheduler {address} runs mdlshapemodel 0.0.0+other, this build "
                    f"{mdlshapemodel.__version__}; install the same version where the scheduler "
                    "runs")
        with pytest.raises(ConfigError) as raised:
            with dask_executor(address):
                pass
        assert str(raised.value) == expected
        paths = write_population(tmp_path / "inputs", 3)
        result = build(paths, tmp_path / "out", "--scheduler", address)
        assert result.returncode == 2, result.stderr
        # one line (after the first run's note on compiling, where it comes)
        assert result.stderr.splitlines()[-1] == f"mdlshapemodel: error: {expected}"
        assert "Traceback" not in result.stderr
        assert not (tmp_path / "out" / "rejected.csv").exists()   # nothing was prepared
    finally:
        _stop(scheduler)


def test_without_distributed_the_error_says_what_to_install(tmp_path):
    """The package made unimportable as if it were not installed (None in sys.modules)."""
    paths = write_population(tmp_path / "inputs", 3)
    code = ("import sys; sys.modules['distributed'] = None; from mdlshapemodel.cli import main; "
            "sys.exit(main(sys.argv[1:]))")
    result = run_python(code, "build", *paths, "-o", tmp_path / "out", "--scheduler",
                        "tcp://127.0.0.1:8786")
    assert result.returncode == 2, result.stderr
    (line,) = result.stderr.splitlines()
    assert line.startswith("mdlshapemodel: error: scheduler tcp://127.0.0.1:8786: the Dask "
                           "client is not installed")
    assert line.endswith('pip install "mdlshapemodel[dask]"')


def test_calls_run_one_at_a_time_per_worker_process_with_one_blas_thread(scheduler):
    """The workers run two threads and ask BLAS for two: a Dask client's executor as the
    library uses it runs one call at a time in each process, with one BLAS thread; the same
    calls straight on the client overlap and have two."""
    with Client(scheduler, set_as_default=False) as client:
        raw = client.get_executor(pure=False)
        ours = on_cluster(raw)

        def overlapping(executor) -> bool:
            calls = defaultdict(list)
            for pid, start, end in (f.result() for f in
                                    [executor.submit(held, 0.5) for _ in range(4)]):
                calls[pid].append((start, end))
            return any(later[0] < earlier[1] for spans in calls.values()
                       for earlier, later in zip(sorted(spans), sorted(spans)[1:]))

        assert overlapping(raw)
        assert not overlapping(ours)
        assert client.submit(blas_threads, pure=False).result() == 2
        assert ours.submit(blas_threads).result() == 1


def test_work_a_closed_dask_client_cannot_take_is_done_locally(scheduler, caplog):
    """A client whose scheduler went away closes itself: the cases then run in a local pool,
    an evaluation here (as when a caller's executor breaks)."""
    with Client(scheduler, set_as_default=False) as client:
        executor = client.get_executor(pure=False)
    with caplog.at_level(logging.WARNING, "mdlshapemodel"):
        assert map_cases(square_or_die, [(1,), (3,)], executor, workers=1) == [1, 9]
        assert Task(executor, square_or_die, 5).result() == 25
    assert "the executor broke with 2 of 2 cases unfinished" in caplog.text
    assert "did not finish (BrokenExecutor); doing it here" in caplog.text


@needs_hippocampi
def test_an_optimisation_given_a_closed_dask_client_runs_here(scheduler, caplog):
    """A client whose scheduler went away: the optimisation's per-example work runs in this
    process, with a warning, and gives the correspondence of a run without a cluster."""
    config = BuildConfig(labels=[1], points=162, max_sweeps=2, workers=1, cache_dir="")
    prepared, _ = preprocess(hippocampi(4), config)
    with Client(scheduler, set_as_default=False) as client:
        executor = client.get_executor(pure=False)
    with caplog.at_level(logging.WARNING, "mdlshapemodel"):
        there = correspond(prepared, config, executor=executor)
    assert caplog.text.count("the Dask cluster has no workers (or no scheduler) now") == 2
    here = correspond(prepared, config)
    assert np.array_equal(there.state.shapes, here.state.shapes)
    assert there.final_objective == here.final_objective


def model_arrays(output: Path) -> dict:
    model = ShapeModel.load(output / "model.h5")
    arrays = {name: getattr(model, name) for name in ("mean", "modes", "variances", "weights",
                                                      "scores", "triangles", "parameters")}
    arrays["names"] = model.names
    return arrays


def test_a_build_on_the_cluster_equals_the_local_builds_bit_for_bit(scheduler, tmp_path):
    """Four cases and a truncated file, built on the cluster, with two local worker processes
    and in one process: the same rejection, model, meshes and measures (baselines too)."""
    paths = write_population(tmp_path / "inputs", 4)
    truncated = tmp_path / "inputs" / "truncated.nii.gz"
    data = paths[0].read_bytes()
    truncated.write_bytes(data[:len(data) // 2])
    outputs = {how: tmp_path / how for how in ("cluster", "two", "one")}
    options = {"cluster": ["--scheduler", scheduler], "two": ["--workers", "2"],
               "one": ["--workers", "1"]}
    for how, output in outputs.items():
        result = build([tmp_path / "inputs"], output, *options[how])
        assert result.returncode == 0, result.stderr
        assert "Traceback" not in result.stderr
    log = (outputs["cluster"] / "build.log").read_text()
    assert f"per-case work on the Dask scheduler {scheduler}: 2 workers, 4 threads" in log
    assert "start workers with --nthreads 1" in log   # they have two threads each

    rejected = read_csv(outputs["cluster"] / "rejected.csv")
    assert [(row["case"], row["file"]) for row in rejected] == [("truncated", str(truncated))]
    assert rejected[0]["reason"].startswith("compressed data is truncated or corrupt")
    reference = model_arrays(outputs["cluster"])
    assert reference["names"] == ["case_0", "case_1", "case_2", "case_3"]
    metrics = json.loads((outputs["cluster"] / "metrics.json").read_text())
    assert set(metrics["baselines"]) == {"none", "cpd"}
    meshes = sorted(p.relative_to(outputs["cluster"]) for p in outputs["cluster"].rglob("*.vtp"))
    assert len(meshes) == 9   # the mean, and each case corresponded and aligned
    for how in ("two", "one"):
        assert read_csv(outputs[how] / "rejected.csv") == rejected, how
        arrays = model_arrays(outputs[how])
        for name, value in reference.items():
            assert np.array_equal(arrays[name], value), (how, name)
        other = json.loads((outputs[how] / "metrics.json").read_text())
        # the warnings name the build's own folder and the optimisation's seconds
        assert [w.split(" after ")[0] for w in other.pop("warnings")] == [
            w.split(" after ")[0] for w in metrics["warnings"]], how
        assert other == {k: v for k, v in metrics.items() if k != "warnings"}, how
        for mesh in meshes:
            assert (outputs[how] / mesh).read_bytes() == (outputs["cluster"] / mesh).read_bytes(), (
                how, mesh)


def test_an_input_that_kills_its_dask_workers_is_rejected_and_the_others_are_prepared(
        scheduler, tmp_path, monkeypatch, caplog):
    """crash_on_prepare, preloaded, kills the worker that prepares ``crashing.nii.gz``: the
    scheduler gives it
    up, it dies again alone in a fresh process here, and is rejected; the other cases (also any
    that the dead worker held) are prepared. Through a caller's client, as from Python."""
    paths = write_population(tmp_path / "inputs", 4)
    culprit = paths[1].rename(paths[1].with_name(f"{CRASHING}.nii.gz"))
    # the fresh process here is armed too
    monkeypatch.setenv(crash_on_prepare.VARIABLE, CRASHING)
    monkeypatch.setattr(parallel, "WORKER_STARTUP", [crash_on_prepare.arm])
    with Client(scheduler, set_as_default=False) as client:
        with caplog.at_level(logging.WARNING, "mdlshapemodel"):
            prepared, rejected = preprocess([paths[0], culprit, *paths[2:]],
                                            BuildConfig(cache_dir=""),
                                            client.get_executor(pure=False))
    assert [case.name for case in prepared] == ["case_0", "case_2", "case_3"]
    assert [(r.name, r.path, r.reason) for r in rejected] == [
        (CRASHING, str(culprit), f"worker process died (signal 9) while preparing {culprit}")]
    assert "was given up by the Dask cluster" in caplog.text


# six real hippocampi, optimised for three rounds per phase (the fast strategy on their own
# 162 points: no coarse stage)
OPTIMISED = ["--label", "1", "--points", "162", "--max-sweeps", "3", "--baselines", "none"]
ON_THE_WORKERS = "the optimisation's per-example work on 2 Dask workers (3 examples each)"


@pytest.fixture(scope="module")
def optimised_here(tmp_path_factory) -> Path:
    """The outputs of the six hippocampi built in one process."""
    output = tmp_path_factory.mktemp("here") / "out"
    result = build(hippocampi(6), output, *OPTIMISED, "--workers", "1")
    assert result.returncode == 0, result.stderr
    return output


@needs_hippocampi
def test_the_optimisation_on_the_workers_gives_the_local_correspondence(
        scheduler, optimised_here, tmp_path):
    """With --scheduler each of the two workers holds three of the six hippocampi for a phase
    and samples them and chains their gradients at every evaluation: the same model, meshes and
    measures as the build in one process, bit for bit."""
    output = tmp_path / "cluster"
    result = build(hippocampi(6), output, *OPTIMISED, "--scheduler", scheduler)
    assert result.returncode == 0, result.stderr
    log = (output / "build.log").read_text()
    assert log.count(ON_THE_WORKERS) == 2      # the fixed-Delta phase and the full one
    reference = model_arrays(optimised_here)
    for name, value in model_arrays(output).items():
        assert np.array_equal(value, reference[name]), name
    metrics = json.loads((output / "metrics.json").read_text())
    here = json.loads((optimised_here / "metrics.json").read_text())
    assert metrics["objective"] == here["objective"]
    for mesh in sorted(p.relative_to(output) for p in output.rglob("*.vtp")):
        assert (output / mesh).read_bytes() == (optimised_here / mesh).read_bytes(), mesh


@needs_hippocampi
def test_a_worker_lost_in_a_round_leaves_its_examples_to_the_build(
        scheduler, dying, optimised_here, tmp_path):
    """One worker is killed at its fifth sampling of trial parameters, in the first round: the
    build takes its three hippocampi over, samples the round's kept trials of them again, and
    ends with the correspondence of the build in one process (to rounding: a point on a
    triangle's edge may be located in the other triangle, walking from elsewhere)."""
    output = tmp_path / "cluster"
    dying.touch()
    try:
        result = build(hippocampi(6), output, *OPTIMISED, "--scheduler", scheduler)
    finally:
        dying.unlink()
    assert result.returncode == 0, result.stderr
    assert Path(f"{dying}.done").exists()      # a worker died
    log = (output / "build.log").read_text()
    # the second phase spreads over the workers connected then: the one killed may be back
    assert log.index(ON_THE_WORKERS) < log.index("while it held examples")
    assert len(re.findall(r"the optimisation's per-example work on (2 Dask workers \(3|1 Dask "
                          r"worker \(6) examples each\)", log)) == 2
    assert re.search(r"WARNING the Dask worker tcp://127\.0\.0\.1:\d+ (died|left the cluster) "
                     r"while it held examples [14]-[36] of 6 of the optimisation: they are "
                     r"optimised in this process from now on", log)
    reference = model_arrays(optimised_here)
    for name, value in model_arrays(output).items():
        if name == "names":
            assert value == reference[name]
        else:
            np.testing.assert_allclose(value, reference[name], rtol=1e-9, atol=1e-9,
                                       err_msg=name)


def test_a_stretch_taken_from_a_lost_worker_keeps_the_trials_the_round_kept(scheduler, dying,
                                                                            caplog):
    """A round of five examples on the two workers; its first trial is kept through five later
    ones, at the last of which a worker dies (Testing/dies_in_a_round.py): the build takes the
    worker's stretch over and samples the kept trials again, so the first trial still has its
    fold check and commits the state that committing it at once in one process gives (to
    rounding: a point may be located in a neighbouring triangle, walking from elsewhere). Its
    gradient, asked for right after its sampling only, is not kept, here or there."""
    from mdlshapemodel.correspondence.strategies.fast import FieldRound, gradient_at
    from mdlshapemodel.correspondence.strategies.spread import ExamplesOnCluster

    done = Path(f"{dying}.done")
    done.unlink(missing_ok=True)          # (left by a test before: no worker would die)

    def a_round(client=None):
        state = small_state()
        state.objective = build_objectives(state)[1]
        examples = (None if client is None
                    else ExamplesOnCluster(client, state, range(state.n_shapes)))
        round_ = FieldRound(state, range(state.n_shapes), 1, 2.0, examples=examples)
        upper = np.where(np.isfinite(round_.limit), round_.limit, 0.05)
        steps = np.random.default_rng(5).uniform(-0.2, 0.2, (6, round_.size)) * upper
        return state, round_, steps, examples

    here, round_, steps, _ = a_round()
    round_.commit(round_.trial(steps[0]))
    with Client(scheduler, set_as_default=False) as client:
        client.wait_for_workers(2, timeout=90)
        state, round_, steps, examples = a_round(client)
        try:
            first = round_.trial(steps[0])
            gradient = round_.gradient(first, gradient_at(state, first.shapes)[1])
            dying.touch()
            for x in steps[1:]:
                round_.trial(x, keep=(first.number,))
            assert done.exists()                                    # a worker died
            assert "they are optimised in this process from now on" in caplog.text
            assert np.all(np.isfinite(gradient))
            assert not round_.folds(first)
            with pytest.raises(ArgumentError, match="sampled last"):
                round_.gradient(first, gradient_at(state, first.shapes)[1])
            round_.commit(first)
        finally:
            dying.unlink(missing_ok=True)
            done.unlink(missing_ok=True)
            examples.close()
    np.testing.assert_allclose(state.shapes, here.shapes, rtol=1e-9, atol=1e-9)


# Python's own SIGINT handler in the command line even where this test runs with SIGINT
# ignored (a background job of a non-interactive shell), as in a terminal
COMMAND_LINE = ("import runpy, signal, sys; "
                "signal.signal(signal.SIGINT, signal.default_int_handler); "
                "sys.argv[0] = 'mdlshapemodel'; "
                "runpy.run_module('mdlshapemodel.cli', run_name='__main__')")


@needs_hippocampi
def test_ctrl_c_stops_the_optimisation_on_the_workers_and_resume_ends_it_here(
        scheduler, optimised_here, tmp_path):
    """SIGINT to the command line's process group (as a terminal sends it; the workers are in a
    session of their own) once the workers hold the examples: the build stops after the round,
    writes the model of the state reached (exit code 0) and keeps the round's checkpoint, from
    which --resume without the cluster ends with the uninterrupted build's model, bit for bit."""
    output = tmp_path / "cluster"
    arguments = [sys.executable, "-c", COMMAND_LINE, "build", *map(str, hippocampi(6)), "-o",
                 str(output), *SMALL_BUILD, *OPTIMISED, "--scheduler", scheduler]
    process = subprocess.Popen(arguments, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL, start_new_session=True,
                               env=dict(os.environ, PYTHONWARNINGS="ignore"))
    log = output / "build.log"
    try:
        deadline = time.monotonic() + 300
        while (process.poll() is None and time.monotonic() < deadline
               and ON_THE_WORKERS not in (log.read_text() if log.exists() else "")):
            time.sleep(0.05)
        assert process.poll() is None, "the build ended before its examples were on the workers"
        os.killpg(process.pid, signal.SIGINT)
        assert process.wait(timeout=300) == 0
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    text = log.read_text()
    assert text.count(ON_THE_WORKERS) == 1          # the first phase, not the second
    metrics = json.loads((output / "metrics.json").read_text())
    assert metrics["optimisation"]["stopped_by"] == "interrupted"
    result = build(hippocampi(6), output, *OPTIMISED, "--workers", "1", "--resume")
    assert result.returncode == 0, result.stderr
    reference = model_arrays(optimised_here)
    for name, value in model_arrays(output).items():
        assert np.array_equal(value, reference[name]), name
