"""A build whose optimisation stops before it converges says so, and how to carry it on, in the
four places a user looks (the command line's summary, build.log, metrics.json, report.html); one
that converges says that; carried on with the advised ``--resume --max-time``, the cut build
converges; a build that optimises nothing claims neither."""

import json
import re
import shlex

import pytest

from mdlshapemodel.correspondence.strategies.base import PhasePoint
from mdlshapemodel.folders import read_checkpoint

from common import run_cli
from synthetic import write_population

QUICK = ["--points", "162", "--baselines", "", "--evaluation-modes", "2",
         "--specificity-samples", "100", "--workers", "1", "-q"]


@pytest.fixture(scope="module")
def labels(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    write_population(folder, 5)
    return folder


def built(labels, output, *options) -> dict:
    """Build ``labels`` into ``output`` with ``options`` and read what the four places say: the
    summary (stdout), build.log, metrics.json's ``optimisation``, report.html (as they are
    now: a later resume rewrites them); and the point its checkpoint holds (None without one:
    the CPD correspondence has no optimisation to checkpoint)."""
    done = run_cli("build", labels, "-o", output, *QUICK, *options)
    assert done.returncode == 0, done.stderr
    metrics = json.loads((output / "metrics.json").read_text())
    return {"summary": done.stdout, "log": (output / "build.log").read_text(),
            "optimisation": metrics["optimisation"], "warnings": metrics["warnings"],
            "report": (output / "report.html").read_text(),
            "checkpoint": (read_checkpoint(output / "checkpoint.npz").point
                           if (output / "checkpoint.npz").exists() else None)}


def top_of(report: str) -> str:
    """The report up to its first section: what a reader sees first."""
    return report[:report.index("<h2>")]


@pytest.fixture(scope="module")
def cut(labels, tmp_path_factory):
    """A build given no time at all: its optimisation stops after its first step."""
    output = tmp_path_factory.mktemp("cut")
    return output, built(labels, output, "--max-time", "0")


@pytest.fixture(scope="module")
def resumed(labels, cut):
    """The cut build carried on as its summary advises."""
    output, said = cut
    advice = re.search(r"run the same build \(inputs and options\) with (-o .+ --resume .+)$",
                       said["summary"], re.MULTILINE)
    assert advice, said["summary"]
    arguments = shlex.split(advice.group(1))
    assert arguments[:4] == ["-o", str(output), "--resume", "--max-time"]
    return built(labels, output, *arguments[2:])


@pytest.fixture(scope="module")
def converged(labels, tmp_path_factory):
    """The same build with time enough to converge."""
    output = tmp_path_factory.mktemp("converged")
    return built(labels, output, "--max-time", "600")


@pytest.mark.slow
def test_a_build_out_of_time_says_so_and_how_to_carry_it_on_in_all_four_places(cut):
    output, said = cut
    advice = f"-o {output} --resume --max-time 600"
    assert "optimisation: not converged (time limit)" in said["summary"]
    assert re.search(r"warning: the optimisation stopped at the time limit \(--max-time 0 s\)"
                     r".* before it converged.*" + re.escape(advice), said["summary"])
    assert "optimisation not converged (time limit)" in said["log"]
    assert re.search(r"WARNING the optimisation stopped at the time limit.*" + re.escape(advice),
                     said["log"])
    assert said["optimisation"]["converged"] is False
    assert said["optimisation"]["stopped_by"] == "time limit"
    assert said["optimisation"]["max_time"] == 0
    assert any(advice in warning for warning in said["warnings"])
    top = top_of(said["report"])
    assert "Optimisation: <b>not converged (time limit)</b>" in top
    assert "class=flag>Warning: the optimisation stopped at the time limit" in top
    assert advice in top
    # what --resume carries on from: the last step's checkpoint, not the end of the optimisation
    assert said["checkpoint"].phase == "integrated"


@pytest.mark.slow
def test_a_build_that_converges_says_so(converged):
    assert "optimisation: converged" in converged["summary"]
    assert "--resume" not in converged["summary"] and "warning" not in converged["summary"]
    assert "optimisation converged" in converged["log"] and "WARNING" not in converged["log"]
    assert converged["optimisation"]["converged"] is True
    assert converged["optimisation"]["stopped_by"] == "converged"
    assert converged["warnings"] == []
    assert "Optimisation: <b>converged</b>" in top_of(converged["report"])
    assert "Warning: the optimisation" not in converged["report"]
    assert converged["checkpoint"].phase == PhasePoint.DONE


@pytest.mark.slow
def test_the_cut_build_carried_on_with_a_larger_max_time_ends_converged(cut, resumed):
    assert "optimisation: converged" in resumed["summary"]
    assert "warning" not in resumed["summary"]
    # build.log goes on from the cut run's: after the resume, it converged and warns of nothing
    after = resumed["log"][resumed["log"].index("resuming from"):]
    assert "optimisation converged" in after and "WARNING" not in after
    assert resumed["optimisation"]["converged"] is True
    assert resumed["optimisation"]["max_time"] == 600
    assert resumed["warnings"] == []
    assert "Optimisation: <b>converged</b>" in top_of(resumed["report"])
    assert "Warning: the optimisation" not in resumed["report"]
    assert resumed["checkpoint"].phase == PhasePoint.DONE


@pytest.mark.slow
@pytest.mark.parametrize("option", [["--strategy", "none"], ["--correspondence", "cpd"]])
def test_a_build_that_optimises_nothing_claims_no_convergence(labels, tmp_path, option):
    said = built(labels, tmp_path / "out", *option)
    assert "optimisation: not run" in said["summary"] and "warning" not in said["summary"]
    assert said["optimisation"]["converged"] is None
    assert said["optimisation"]["stopped_by"] is None
    assert "Optimisation: <b>not run</b>" in top_of(said["report"])
