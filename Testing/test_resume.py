"""Resuming: an optimisation carried on from any of its checkpoints ends exactly as the
uninterrupted one, for every strategy; and a real build killed with SIGKILL at any stage and run
again with --resume gives the uninterrupted build's model, with no half-written file left."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel import ShapeModel
from mdlshapemodel.config import OptimisationSettings
from mdlshapemodel.correspondence.state import state_record
from mdlshapemodel.correspondence.strategies.base import PhasePoint
from mdlshapemodel.errors import BuildError
from mdlshapemodel.folders import BuildFolder, read_checkpoint
from mdlshapemodel.prepare import io

from common import TIMEOUT, run_cli
from resuming import assert_same_record, optimised_with_checkpoints, resumed_from
from synthetic import small_state, write_population


@pytest.mark.parametrize("strategy, sweeps", [("fast", 10_000), ("one-at-a-time-pose", 3),
                                              ("multiscale", 4), ("multiresolution", 2)])
def test_an_optimisation_resumed_from_any_checkpoint_ends_as_the_uninterrupted_one(strategy,
                                                                                    sweeps):
    settings = OptimisationSettings(strategy=strategy, max_time=1e6, max_sweeps=sweeps,
                                    fixed_fraction=0.5, simplex_evaluations=60)
    state = small_state()
    final, trace, saved = optimised_with_checkpoints(state, settings)
    expected = state_record(state)
    phases = {point.phase for point, *_ in saved}
    assert phases == {"fixed", "integrated"} and len(saved) >= 3
    chosen = [saved[0], saved[len(saved) // 2], saved[-1]]
    if strategy == "fast":   # a checkpoint where the next pass over the levels starts
        chosen += [s for s in saved if s[0].counters["level"] == 3][:1]
    for entry in chosen:
        resumed = small_state()
        value, resumed_trace = resumed_from(resumed, settings, entry)
        point = entry[0]
        assert value == final, (point.phase, point.sweep)
        assert_same_record(state_record(resumed), expected)
        assert [r[2:] for r in resumed_trace.rows] == [r[2:] for r in trace.rows]


def test_a_phase_point_survives_json():
    point = PhasePoint("integrated", 7, {"pass": 1, "level": 2, "round": 0},
                       {"start": 12.5, "value": 3.25, "before": 3.5, "pass_start": 4.0})
    assert PhasePoint.from_json(point.to_json()) == point


# -- a real build killed and resumed ------------------------------------------------------------

QUICK = ["--points", "162", "--baselines", "", "--max-time", "600", "--evaluation-modes", "2",
         "--specificity-samples", "100", "-q"]


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    write_population(folder, 5)
    return folder


def command(labels, output, *extra) -> list:
    """The arguments of the small build of ``labels`` into ``output``."""
    return ["build", labels, "-o", output, *QUICK, *extra]


@pytest.fixture(scope="module")
def uninterrupted(labels, tmp_path_factory):
    output = tmp_path_factory.mktemp("uninterrupted")
    done = run_cli(*command(labels, output, "--workers", "1"))
    assert done.returncode == 0, done.stderr
    return output


def killed_at(labels, output, reached, workers: str, cache, extra=()) -> list:
    """Run a build (options ``extra`` added) and SIGKILL it as soon as ``reached(output)``
    (polled) is true; check that its worker processes end with it, and return their pids."""
    environment = {**os.environ, "MDLSHAPEMODEL_CACHE": str(cache)}
    process = subprocess.Popen([sys.executable, "-m", "mdlshapemodel.cli",
                                *map(str, command(labels, output, *extra, "--workers", workers))],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env=environment)
    try:
        deadline = time.monotonic() + TIMEOUT
        while process.poll() is None and not reached(output):
            assert time.monotonic() < deadline, f"the build reached no point in {TIMEOUT} s"
            time.sleep(0.005)
        # held where it is while its workers are listed: none is started or reaped meanwhile
        if process.poll() is None:
            process.send_signal(signal.SIGSTOP)
        workers = descendants(process.pid)
        process.send_signal(signal.SIGKILL)
    finally:
        if process.poll() is None:
            process.kill()
        process.wait(timeout=60)
    assert process.returncode == -signal.SIGKILL, "the build ended before the point"
    # its worker processes end with it (they would otherwise wait for work for ever)
    deadline = time.monotonic() + 10.0
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(alive(pid) for pid in workers), "a worker outlived the killed build"
    return workers


def descendants(pid: int) -> list:
    """The pids of a process's children and theirs (Linux /proc)."""
    found, queue = [], [pid]
    while queue:
        for task in Path(f"/proc/{queue.pop()}/task").glob("*"):
            try:
                children = [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
            found += children
            queue += children
    return found


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def checkpoint_at(phase: str, sweep: int = 1):
    """The build's checkpoint says it has reached step ``sweep`` of ``phase``."""
    def reached(output) -> bool:
        try:
            point = read_checkpoint(output / "checkpoint.npz").point
        except BuildError:       # none yet
            return False
        return point.phase == phase and point.sweep >= sweep
    return reached


def prepared_one(cache):
    """A first case is prepared (its cache entry is written)."""
    return lambda output: any(Path(cache).glob("*.npz"))


def writing_outputs(output) -> bool:
    """The build has begun writing its outputs (model.h5 comes first)."""
    return (output / "model.h5").exists()


def assert_whole_outputs(output):
    """Every file under its final name is whole: it reads back."""
    for path in output.rglob("*"):
        if not path.is_file() or ".partial" in path.name or path.suffix == ".gz":
            continue
        if path.suffix == ".h5":
            ShapeModel.load(path)
        elif path.suffix == ".vtp":
            assert len(io.read_mesh(path)[0]) == 162, path
        elif path.suffix == ".json":
            json.loads(path.read_text())
        elif path.suffix == ".csv":   # a header, and every row has its fields, no more
            assert path.read_text().endswith("\n"), path
            for row in io.read_csv(path):
                assert None not in row and None not in row.values(), (path, row)
        elif path.suffix == ".npz":
            np.load(path, allow_pickle=False).files


@pytest.mark.slow
@pytest.mark.parametrize("stage, workers", [("preparing", "2"), ("fixed", "1"),
                                            ("integrated", "2"), ("writing outputs", "1")])
def test_a_build_killed_at_any_stage_resumes_to_the_uninterrupted_model(
        labels, uninterrupted, tmp_path, stage, workers):
    output, cache = tmp_path / "out", tmp_path / "cache"
    reached = {"preparing": prepared_one(cache), "fixed": checkpoint_at("fixed", 2),
               "integrated": checkpoint_at("integrated", 1),
               "writing outputs": writing_outputs}[stage]
    pids = killed_at(labels, output, reached, workers, cache)
    if stage == "preparing":
        assert len(pids) >= 2             # the pool's workers were there, and ended
    assert_whole_outputs(output)
    if stage == "preparing":    # killed before any checkpoint: nothing blocks a plain rerun
        assert BuildFolder(output).earlier_build() == []
    else:
        refused = run_cli(*command(labels, output))
        assert refused.returncode == 2 and "--overwrite" in refused.stderr   # not without --resume
    environment = {**os.environ, "MDLSHAPEMODEL_CACHE": str(cache)}
    resumed = run_cli(*[c for c in command(labels, output, "--resume", "--workers", "1")
                        if c != "-q"], env=environment)
    assert resumed.returncode == 0, resumed.stderr
    if stage == "preparing":   # no checkpoint yet: started over, the prepared case from the cache
        assert "starting over" in resumed.stderr and "reused" in resumed.stderr
    else:
        assert "resuming from" in resumed.stderr
    ours, theirs = (ShapeModel.load(folder / "model.h5") for folder in (output, uninterrupted))
    for name in ("mean", "modes", "variances", "scores", "weights"):
        assert np.array_equal(getattr(ours, name), getattr(theirs, name)), name
    assert ours.metadata["objective"] == theirs.metadata["objective"]
    assert not list(output.rglob(".*.partial*"))


@pytest.mark.slow
def test_resuming_with_other_settings_is_refused(labels, uninterrupted, tmp_path):
    output = tmp_path / "out"
    killed_at(labels, output, checkpoint_at("integrated"), "1", tmp_path / "cache")
    other = run_cli(*command(labels, output, "--resume", "--seed", "3"))
    assert other.returncode == 2
    assert "other inputs or settings (seed)" in other.stderr and "Traceback" not in other.stderr


@pytest.mark.slow
@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_resumed_build_takes_the_baselines_evaluation_its_first_run_kept(labels, tmp_path,
                                                                           workers):
    """A build killed after its baseline was evaluated (here or on the helper) and resumed does
    not evaluate it again: it takes the evaluation kept in baselines.json, and metrics.json
    says of the baseline what the uninterrupted build's says, number for number. Evaluated
    here, before the optimisation, it is kept at the first checkpoint (on the helper it may
    come after this small build's last one)."""
    extra = ("--baselines", "none")
    whole = tmp_path / "whole"
    done = run_cli(*command(labels, whole, *extra, "--workers", workers))
    assert done.returncode == 0, done.stderr
    output, cache = tmp_path / "out", tmp_path / "cache"
    kept = checkpoint_at("integrated")
    killed_at(labels, output,
              lambda out: (out / "baselines.json").exists() and (workers == "2" or kept(out)),
              workers, cache, extra)
    if workers == "1":      # killed while it optimised: kept as it came, not at the build's end
        assert "final objective" not in (output / "build.log").read_text()
    resumed = run_cli(*[c for c in command(labels, output, *extra, "--resume", "--workers",
                                           workers) if c != "-q"],
                      env={**os.environ, "MDLSHAPEMODEL_CACHE": str(cache)})
    assert resumed.returncode == 0, resumed.stderr
    assert "the none baseline's evaluation comes from" in resumed.stderr
    assert "evaluating the none baseline" in (whole / "build.log").read_text()
    assert "evaluating the none baseline" not in resumed.stderr
    ours, theirs = (json.loads((folder / "metrics.json").read_text())
                    for folder in (output, whole))
    assert ours["baselines"] == theirs["baselines"] and "none" in ours["baselines"]
    assert ours["generalization"] == theirs["generalization"]
