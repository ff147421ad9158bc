"""Ctrl-C at any moment of a build, as a terminal sends it: SIGINT to the whole process group
(the command line and its worker processes), at random moments of every phase. Each time the
build ends without a traceback either with the model of the state reached and its whole output
folder (exit code 0), or, interrupted while preparing, with the one line "interrupted" (exit
code 130) and nothing that a new build would have to overwrite. Also the pieces: the workers
ignore SIGINT, the threads leave it to the main thread, and build_model called from Python takes
Ctrl-C at its reports and gives Python's handler back."""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from mdlshapemodel import BuildConfig, Cancelled, ShapeModel
from mdlshapemodel.folders import BuildFolder
from mdlshapemodel.parallel import ProcessPool, Task, Threads
from mdlshapemodel.prepare import io
from mdlshapemodel.progress import ctrl_c

from common import TIMEOUT
from synthetic import write_population

CASES = [f"case_{k}" for k in range(5)]
POINTS = 42
OPTIONS = ["--points", str(POINTS), "--evaluation-modes", "2", "--specificity-samples", "50",
           "--surface-samples", "5", "--workers", "2"]

# The phases of a build and the line (on stderr) that each starts with, in order: the phase a
# SIGINT falls in is that of the last of these lines written before it was sent.
PHASES = {"preparing": "preprocessing 5 cases",
          "optimising": "prepared 5 cases in",
          "writing the model": "final objective",
          "evaluating": "wrote the model, meshes and tables",
          "the report": "evaluated the model in"}
# the early part of each phase (seconds after its first line), where the quick test's signals go
EARLY = {"preparing": 1.5, "optimising": 1.0, "writing the model": 1.0, "evaluating": 0.05,
         "the report": 1.5}
# the command line's progress lines, which may be on their way while the signal is
PREPARING_PROGRESS = re.compile(r"mdlshapemodel: (\[\s*\d+%\] prepared \d+/5|reused .*)$")
# Python's own SIGINT handler in the command line even if this test runs where SIGINT is
# ignored (a background job of a non-interactive shell), as in a terminal
COMMAND_LINE = ("import runpy, signal, sys; "
                "signal.signal(signal.SIGINT, signal.default_int_handler); "
                "sys.argv[0] = 'mdlshapemodel'; "
                "runpy.run_module('mdlshapemodel.cli', run_name='__main__')")
# the files of a whole build of CASES (besides correspondence/ and aligned/, a mesh per case)
OUTPUT_FILES = ("model.h5", "mean.vtp", "scores.csv", "cases.csv", "metrics.json", "report.html",
                "rejected.csv", "convergence.csv", "config.json", "build.log")


@dataclass
class Run:
    """One build of the command line and the SIGINT sent to its process group."""

    output: Path
    aimed_at: str | None                 # the phase the signal was meant for (None: not sent)
    returncode: int = 0
    lines: list = field(default_factory=list)     # (seconds since the start, stderr line)
    sent_after: int | None = None        # how many stderr lines were read when it was sent
    stdout: str = ""

    @property
    def phase(self) -> str | None:
        """The phase the build was in when the signal was sent (by the lines it had written)."""
        if self.sent_after is None:
            return None
        written = [line for _, line in self.lines[:self.sent_after]]
        return next((name for name, start in reversed(PHASES.items())
                     if any(start in line for line in written)), "starting")

    @property
    def before(self) -> list:
        """The stderr lines read before the signal was sent."""
        return [line for _, line in self.lines[:self.sent_after]]

    @property
    def after(self) -> list:
        """The stderr lines read after."""
        return [line for _, line in self.lines[self.sent_after:]]

    @property
    def stderr(self) -> str:
        return "\n".join(line for _, line in self.lines)


def build(labels, output: Path, cache: Path, phase: str | None = None, delay: float = 0.0,
          no_cache: bool = False, again: float | None = None, extra=()) -> Run:
    """Run the command line's build of ``labels`` (with the ``extra`` arguments) and, with
    ``phase``, send SIGINT to its process group ``delay`` seconds after the phase's first line,
    and once more ``again`` seconds later if given."""
    environment = dict(os.environ, PYTHONWARNINGS="ignore")
    arguments = [sys.executable, "-c", COMMAND_LINE, "build", str(labels), "-o", str(output),
                 *OPTIONS, *(["--no-cache"] if no_cache else ["--cache-dir", str(cache)]),
                 *extra]
    run = Run(output, phase)
    started = time.monotonic()
    process = subprocess.Popen(arguments, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=environment,
                               start_new_session=True)
    reached = threading.Event()

    def read():
        for line in process.stderr:
            run.lines.append((time.monotonic() - started, line.rstrip("\n")))
            if phase is not None and PHASES[phase] in line:
                reached.set()
        reached.set()            # the build ended (before the phase, if it never came)

    printed = []
    readers = [threading.Thread(target=read, daemon=True),
               threading.Thread(target=lambda: printed.append(process.stdout.read()), daemon=True)]
    for reader in readers:
        reader.start()
    try:
        if phase is not None:
            reached.wait(TIMEOUT)
            time.sleep(delay)
            count = len(run.lines)
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGINT)
                run.sent_after = count
            if again is not None:
                time.sleep(again)
                if process.poll() is None:
                    os.killpg(process.pid, signal.SIGINT)
        process.wait(timeout=TIMEOUT)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    for reader in readers:
        reader.join(timeout=60)
    run.returncode, run.stdout = process.returncode, "".join(printed)
    return run


def assert_whole_build(output: Path):
    """The output folder of a whole build of CASES: every file there and readable."""
    for name in OUTPUT_FILES:
        assert (output / name).is_file(), name
    model = ShapeModel.load(output / "model.h5")
    assert model.names == CASES
    json.loads((output / "metrics.json").read_text())
    assert (output / "report.html").read_text().rstrip().endswith("</html>")
    for folder in ("correspondence", "aligned"):
        for case in CASES:
            assert len(io.read_mesh(output / folder / f"{case}.vtp")[0]) == POINTS, (folder,
                                                                                     case)


def assert_ended_well(run: Run):
    """What an interrupted build must end with (see the module's docstring)."""
    said = run.stderr
    assert "Traceback" not in said, said
    # nothing but the command line's own lines (no worker process's)
    assert all(line.startswith("mdlshapemodel: ") for line in run.before + run.after), said
    if run.returncode == 130:     # stopped while preparing: one line, nothing to overwrite
        assert not any(PHASES["optimising"] in line for line in run.before + run.after), said
        assert [line for line in run.after if not PREPARING_PROGRESS.match(line)] == [
            "mdlshapemodel: interrupted"], said
        assert BuildFolder(run.output).earlier_build() == [] and not (run.output / "model.h5").exists()
        return
    assert run.returncode == 0, said
    assert_whole_build(run.output)
    assert "model of 5 cases written" in run.stdout
    # the interrupt was taken, and how to abort at once is said
    assert any("interrupted" in line and "(Ctrl-C again to abort)" in line
               for line in run.after), said
    metrics = json.loads((run.output / "metrics.json").read_text())
    assert metrics["interrupted"] == ("optimisation interrupted" in said)
    if metrics["interrupted"]:
        assert "optimisation: not converged (interrupted)" in run.stdout


def interrupted_builds(labels, folder: Path, count: int, durations: dict, seed: int,
                       parallel: int) -> list:
    """``count`` builds, each sent SIGINT once at a random moment of a phase (the phases in
    turn, the moment uniform over the phase's ``durations``), ``parallel`` at a time."""
    rng = random.Random(seed)
    cache = folder / "cache"
    plans = []
    for k in range(count):
        phase = list(PHASES)[k % len(PHASES)]
        plans.append((folder / f"build_{k}", phase, rng.uniform(0.0, 0.9 * durations[phase])))
    with ThreadPoolExecutor(parallel) as threads:
        return list(threads.map(lambda plan: build(labels, plan[0], cache, plan[1], plan[2],
                                                   no_cache=plan[1] == "preparing"), plans))


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    write_population(folder, len(CASES))
    return folder


def check_all(runs: list) -> dict:
    """Every run ended well; how many signals fell in each phase."""
    failures = []
    for run in runs:
        try:
            assert_ended_well(run)
        except AssertionError as error:
            failures.append(f"{run.output.name} (aimed at {run.aimed_at}, sent in {run.phase}, "
                            f"exit code {run.returncode}): {error}")
    assert not failures, f"{len(failures)} of {len(runs)} interrupted builds ended badly:\n" + \
        "\n\n".join(failures)
    fallen = {}
    for run in runs:
        if run.sent_after is not None:
            fallen[run.phase] = fallen.get(run.phase, 0) + 1
    return fallen


def test_ctrl_c_in_each_phase_of_a_build_ends_with_its_model_or_one_line(labels, tmp_path):
    """The quick variant: one SIGINT early in each phase."""
    runs = interrupted_builds(labels, tmp_path, len(PHASES), EARLY, seed=1, parallel=3)
    fallen = check_all(runs)
    assert sum(fallen.values()) >= len(PHASES) - 1, fallen


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_fifty_ctrl_c_at_random_moments_of_every_phase(labels, tmp_path):
    """55 builds, each sent SIGINT at a random moment of one phase, 11 aimed at each, the
    moment drawn over the phase's length in an uninterrupted build timed first; at least 50
    signals sent (a build may end before its moment comes)."""
    timed = build(labels, tmp_path / "timed", tmp_path / "cache", no_cache=True)
    assert timed.returncode == 0 and "interrupted" not in timed.stderr, timed.stderr
    assert_whole_build(timed.output)
    starts = {name: next(t for t, line in timed.lines if start in line)
              for name, start in PHASES.items()}
    ends = list(starts.values())[1:] + [next(t for t, line in timed.lines
                                             if "wrote the report" in line)]
    durations = {name: end - start for (name, start), end in zip(starts.items(), ends)}
    runs = interrupted_builds(labels, tmp_path, 55, durations, seed=2, parallel=3)
    fallen = check_all(runs)
    assert sum(fallen.values()) >= 50, fallen
    assert set(PHASES) <= set(fallen) and min(fallen[name] for name in PHASES) >= 5, fallen
    ended = [("stopped" if run.returncode == 130 else "optimisation interrupted"
              if "optimisation interrupted" in run.stderr else "outputs finished")
             for run in runs if run.sent_after is not None]
    print("SIGINTs sent, by the phase they fell in:", fallen, "; the builds:",
          {outcome: ended.count(outcome) for outcome in sorted(set(ended))})


@pytest.mark.slow
@pytest.mark.parametrize("phase", ["optimising", "the report"])
def test_a_second_ctrl_c_aborts_at_once_and_resume_carries_the_build_on(labels, tmp_path, phase):
    """Two SIGINTs 0.3 s apart: the build ends at the second (exit code 130) with one line that
    says so, and --resume then ends with the uninterrupted build's model."""
    cache = tmp_path / "cache"
    whole = build(labels, tmp_path / "whole", cache)
    assert whole.returncode == 0, whole.stderr
    run = build(labels, tmp_path / "out", cache, phase, 0.2, again=0.3)
    assert run.returncode == 130 and "Traceback" not in run.stderr, run.stderr
    assert all(line.startswith("mdlshapemodel: ") for _, line in run.lines), run.stderr
    assert run.lines[-1][1] == ("mdlshapemodel: interrupted again: aborted (--resume carries the "
                                "build on)"), run.stderr
    resumed = build(labels, tmp_path / "out", cache, extra=["--resume"])
    # from the checkpoint, or (aborted before the first one) from the start
    assert resumed.returncode == 0, resumed.stderr
    assert_whole_build(tmp_path / "out")
    ours, theirs = (ShapeModel.load(folder / "model.h5") for folder in (tmp_path / "out",
                                                                       tmp_path / "whole"))
    assert ours.metadata["objective"] == theirs.metadata["objective"]
    assert (ours.mean == theirs.mean).all()


# -- the pieces ----------------------------------------------------------------------------------

def sigint_disposition():
    """This process's SIGINT handler and whether this thread blocks SIGINT (in a worker)."""
    handler = signal.getsignal(signal.SIGINT)
    return (handler if handler in (signal.SIG_IGN, signal.SIG_DFL) else "python",
            signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, []))


def test_pool_workers_ignore_sigint_and_pool_threads_leave_it_to_the_main_thread():
    with ProcessPool(1) as pool:
        assert pool.submit(sigint_disposition).result() == (signal.SIG_IGN, False)
    # the pool did not leave SIGINT blocked here
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    blocked = [None, None]

    def note(indices):
        for k in indices:
            blocked[k] = signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])

    with Threads(2) as threads:
        threads.over(2, note)
    assert blocked == [True, True]


def interrupted_in_a_worker(seconds: float) -> str:
    """In a worker process: KeyboardInterrupt after ``seconds``; here: "done here"."""
    import multiprocessing

    time.sleep(seconds)
    if multiprocessing.parent_process() is not None:
        raise KeyboardInterrupt
    return "done here"


def test_a_task_redoes_work_interrupted_in_its_worker_but_not_a_ctrl_c_here():
    with ProcessPool(1) as pool:
        # the worker's own KeyboardInterrupt (a caller's executor whose workers Ctrl-C reaches)
        task = Task(pool, interrupted_in_a_worker, 0.0)
        assert task.result(redo=(KeyboardInterrupt,)) == "done here"
        # Ctrl-C here while the task runs there: raised on, not taken for lost work
        task = Task(pool, interrupted_in_a_worker, 2.0)
        timer = threading.Timer(0.5, signal.pthread_kill, (threading.main_thread().ident,
                                                           signal.SIGINT))
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            task.result(redo=(KeyboardInterrupt,))
        timer.join()


def test_ctrl_c_sets_a_flag_taken_at_the_next_report_and_a_second_one_raises():
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    reports = []
    with ctrl_c() as interrupt:
        assert interrupt.installed
        progress = interrupt.watch(lambda fraction, message: reports.append(message))
        progress(0.5, "before")
        signal.raise_signal(signal.SIGINT)      # no KeyboardInterrupt: a flag
        assert interrupt.requested.is_set()
        with pytest.raises(Cancelled):
            progress(1.0, "after")
        interrupt.finishing("finishing")        # from now on the reports go on
        progress(1.0, "finishing")
        with ctrl_c() as inner:                 # nested: the same one
            assert inner is interrupt
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert reports == ["before", "finishing"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_is_left_alone_outside_the_main_thread():
    found = []

    def in_a_thread():
        with ctrl_c() as interrupt:
            found.append((interrupt.installed, signal.getsignal(signal.SIGINT)))

    thread = threading.Thread(target=in_a_thread)
    thread.start()
    thread.join()
    assert found == [(False, signal.default_int_handler)]


@pytest.mark.slow
def test_build_model_finishes_its_outputs_after_a_ctrl_c_and_gives_the_handler_back(labels,
                                                                                    tmp_path):
    """From Python (a notebook): a Ctrl-C once the optimisation has ended lets the build write
    every output, then Python's handler is back; one while preparing raises Cancelled."""
    from mdlshapemodel import build_model

    config = BuildConfig(points=POINTS, evaluation_modes=2, specificity_samples=50,
                         surface_samples=5, workers=1, cache_dir=str(tmp_path / "cache"))
    pressed = []

    def press_once_evaluating(fraction, message):
        if message.startswith("evaluating") and not pressed:
            pressed.append(message)
            signal.raise_signal(signal.SIGINT)

    try:
        result = build_model([labels], tmp_path / "out", config, progress=press_once_evaluating)
    except KeyboardInterrupt:        # (not let through: it would end the test run)
        pytest.fail("a Ctrl-C after the optimisation raised KeyboardInterrupt out of the build")
    assert pressed and not result.interrupted and result.converged
    assert_whole_build(tmp_path / "out")
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler

    def press_preparing(fraction, message):
        if message.startswith("prepared 1/"):
            signal.raise_signal(signal.SIGINT)

    with pytest.raises(Cancelled):
        build_model([labels], tmp_path / "stopped", config, progress=press_preparing)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert BuildFolder(tmp_path / "stopped").earlier_build() == []
