"""The module's long work in a process of its own (MDLShapeModelLib.worker), on the shared
hippocampi and a real MRML scene: progress read from the worker, Cancel that ends the process
group (the build then resumes), a worker killed with SIGKILL reported while the module goes on,
and a setting the library refuses named by the panel's field."""

import os
import pathlib
import shutil
import signal
import time

import pytest

import MDLShapeModel as module
from MDLShapeModelLib.jobs import WorkerEnded, WorkerJob
from MDLShapeModelLib.messages import panelLabels, panelMessage
from mdlshapemodel import BuildConfig
from mdlshapemodel.errors import BuildError, ConfigError
from mdlshapemodel.folders import BuildFolder
from mdlshapemodel.progress import OBJECTIVE

pytestmark = pytest.mark.skipif(os.name == "nt", reason="process groups and SIGKILL: POSIX")

# the two hippocampus labels, few points, no baselines: a build of a minute or two
SMALL = dict(labels=[1, 2], points=162, baselines=[], workers=1, evaluation_modes=2,
             specificity_samples=100, surface_samples=0)


def group_alive(pid: int) -> bool:
    """Whether any process of the process group ``pid`` (a worker's) still runs: one that is
    not a zombie (a killed process whose parent, here maybe a container's init, has not yet
    collected it). Read from /proc where there is one."""
    proc = pathlib.Path("/proc")
    if not proc.is_dir():
        try:
            os.killpg(pid, 0)
        except ProcessLookupError:
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue                  # ended while being read
        state, group = fields[0], int(fields[2])
        if group == pid and state not in ("Z", "X"):
            return True
    return False


def group_ends(pid: int, timeout: float = 30.0) -> bool:
    """Whether the process group ``pid`` has no running process left within ``timeout``
    seconds (a process killed takes a moment to be torn down)."""
    stop = time.monotonic() + timeout
    while group_alive(pid):
        if time.monotonic() > stop:
            return False
        time.sleep(0.1)
    return True


def run_until(job, condition, timeout=900):
    """Poll ``job`` (as the panel's timer does) until ``condition(reports)`` or it ends."""
    reports, stop = [], time.monotonic() + timeout
    while not job.done and not condition(reports) and time.monotonic() < stop:
        reports += job.poll()
        time.sleep(0.1)
    return reports


def test_a_build_runs_in_its_own_process_with_progress_and_loads_its_nodes(
        scene, hippocampus_files, tmp_path):
    logic = module.MDLShapeModelLogic()
    job = logic.startBuild(hippocampus_files, tmp_path / "out", BuildConfig(**SMALL))
    assert job.pid != os.getpid() and not job.done        # started, and this thread goes on
    reports = run_until(job, lambda reports: False)
    assert job.wait(60)
    reports += job.poll()
    messages = [report.message for report in reports]
    prepared = [m for m in messages if m.startswith("prepared")]
    # (each but the last with the estimate of the time left)
    assert [m.split(" (about ")[0] for m in prepared] == [f"prepared {k}/4" for k in range(1, 5)]
    assert all(m.endswith(" left)") for m in prepared[:-1])
    # the optimisation's reports say what they are, the first with its rounds at most and the
    # time budget's bound
    objective = [r.message for r in reports if r.kind == OBJECTIVE]
    assert objective and all("F =" in m for m in objective)
    assert "more rounds; at most about" in objective[0]
    assert objective[0].endswith("the time budget)")
    assert not any(r.kind for r in reports if r.message.startswith("prepared"))
    assert all(0 <= r.fraction <= 1 for r in reports if r.fraction is not None)
    result = job.finish()
    assert result.caseNames == [p.name.split(".")[0] for p in hippocampus_files]
    assert len(result.correspondenceModelNodes) == 4     # labels 1 and 2: one object
    assert group_ends(job.pid)


def test_cancel_twice_ends_the_process_group_and_the_build_resumes(
        scene, hippocampus_files, tmp_path):
    logic = module.MDLShapeModelLogic()
    output = tmp_path / "out"
    config = BuildConfig(**{**SMALL, "points": 642, "max_time": 900})
    job = logic.startBuild(hippocampus_files, output, config)
    # once the optimisation has written its first checkpoint
    run_until(job, lambda reports: BuildFolder(output).checkpoint_file.is_file())
    assert not job.done, "the build ended before its optimisation could be stopped"
    job.cancel()
    job.terminate()                                  # the panel's second Cancel
    assert job.done and group_ends(job.pid)
    with pytest.raises(WorkerEnded, match="stopped"):
        job.finish()
    assert BuildFolder(output).unfinished()
    # the folder resumes: the optimisation carries on from its checkpoint and ends
    result = logic.buildModel(hippocampus_files, output,
                              BuildConfig(**{**SMALL, "points": 642, "max_time": 20}),
                              resume=True)
    assert len(result.correspondenceModelNodes) == 4
    assert BuildFolder(output).metrics()["n_shapes"] == 4


# Run at the start of every Python process of the worker's environment (the worker and its
# pools): the first one (the worker) starts a child that outlives its parent's death, as a
# helper process of a native library may; only the kill of the whole process group ends it.
SLEEPER = """
import os, subprocess
_pid_file = os.environ.pop("MDLSHAPEMODEL_TEST_SLEEPER", None)
if _pid_file:
    _child = subprocess.Popen(["sleep", "600"], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with open(_pid_file, "w") as _stream:
        _stream.write(str(_child.pid))
"""


def test_a_worker_killed_is_reported_and_the_module_goes_on(
        scene, hippocampus_files, tmp_path, monkeypatch):
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(SLEEPER, encoding="utf-8")
    sleeper = tmp_path / "sleeper.pid"
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(hook)] + [
        p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    monkeypatch.setenv("MDLSHAPEMODEL_TEST_SLEEPER", str(sleeper))
    logic = module.MDLShapeModelLogic()
    # two worker processes of its own, preparing the cases again (no cache): a process group
    config = BuildConfig(**{**SMALL, "workers": 2, "cache_dir": ""})
    job = logic.startBuild(hippocampus_files, tmp_path / "killed", config)
    monkeypatch.undo()                             # later workers start without the hook
    run_until(job, lambda reports: any(r.message.startswith("prepared") for r in reports))
    assert not job.done
    child = int(sleeper.read_text())
    try:
        assert os.getpgid(child) == job.pid           # the child is of the worker's group
        os.kill(job.pid, signal.SIGKILL)          # a crash of native code, as Slicer sees it
        assert job.wait(60)
        with pytest.raises(WorkerEnded, match="ended unexpectedly .killed by signal SIGKILL"):
            job.finish()
        # no process of its group is left: the pools, and the child that outlives its parent
        assert group_ends(job.pid)
    finally:
        try:
            os.kill(child, signal.SIGKILL)        # the test's own child, if the check failed
        except ProcessLookupError:
            pass
    # the module is still usable: the next build in the same scene, with the same Logic
    result = logic.buildModel(hippocampus_files, tmp_path / "again",
                              BuildConfig(**{**SMALL, "strategy": "none"}))
    assert len(result.correspondenceModelNodes) == 4


def test_a_setting_the_library_refuses_is_named_by_the_panels_field(scene, tmp_path):
    labels = panelLabels(module.resourcePath("UI/MDLShapeModel.ui"))
    assert labels["points"] == "Points" and labels["max_time"] == "Time budget"
    # refused in the worker process: the error comes back with the setting's name
    config = BuildConfig().to_dict() | {"points": 5}
    job = WorkerJob({"command": "build", "inputs": [], "output": str(tmp_path / "out"),
                     "config": config, "overwrite": False, "resume": False}, "build",
                    lambda end: end, tmp_path / "job")
    assert job.wait(300)
    with pytest.raises(ConfigError) as raised:
        job.finish()
    assert raised.value.setting == "points"
    assert panelMessage(raised.value, labels) == "Points: must be at least 12 (got 5)"
    assert "points:" in str(raised.value)               # the command line's own wording
    # refused as the panel fills the parameter node
    parameters = module.MDLShapeModelLogic().getParameterNode()
    parameters.labels = "1, a"
    with pytest.raises(ConfigError) as raised:
        module.buildConfigOf(parameters)
    assert panelMessage(raised.value, labels) == "Labels: labels must be integers, got '1, a'"


def test_a_refused_build_advises_the_panels_field_not_the_command_lines_flag(
        scene, hippocampus_files, tmp_path):
    labels = panelLabels(module.resourcePath("UI/MDLShapeModel.ui"))
    twice = tmp_path / "again.nii.gz"
    shutil.copyfile(hippocampus_files[0], twice)
    job = module.MDLShapeModelLogic().startBuild(hippocampus_files + [twice], tmp_path / "out",
                                                 BuildConfig(**SMALL))
    assert job.wait(300)
    with pytest.raises(BuildError, match="--allow-duplicates") as raised:
        job.finish()
    said = panelMessage(raised.value, labels)
    assert "'Allow duplicates'" in said and "--" not in said
    assert "are identical files" in said
