"""The real command line, run in a subprocess."""

import dataclasses
import fcntl
import json
import os
import pty
import re
import select
import signal
import struct
import subprocess
import sys
import termios
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.options import BUILD_OPTIONS, NOT_OFFERED
from files import write_label_map
from synthetic import small_mask

# real builds (the command line or build_model): deselected by -m "not slow"
pytestmark = pytest.mark.slow

EXECUTABLE = [sys.executable, "-m", "mdlshapemodel.cli"]


def run(*args, cwd=None):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run(EXECUTABLE + [str(a) for a in args], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=600)


def _sigint_as_in_a_terminal():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_in_terminal(*args, on_output=None, columns: int = 100):
    """The CLI with its stderr a pseudo-terminal (stdout a pipe): (exit code, stdout, what the
    terminal received). ``on_output(process, text so far)`` is called as the output grows."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    # SIGINT as in a terminal even when this test runs where it is ignored (a background job
    # of a non-interactive shell), or the Ctrl-C of the tests below would be lost
    process = subprocess.Popen(EXECUTABLE + [str(a) for a in args], stdin=subprocess.DEVNULL,
                               stdout=subprocess.PIPE, stderr=slave, env=env,
                               preexec_fn=_sigint_as_in_a_terminal)
    os.close(slave)
    received = b""
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 600)
            if not ready:
                raise TimeoutError("the command line wrote nothing for 10 minutes")
            try:
                data = os.read(master, 1 << 16)
            except OSError:  # the terminal is closed: the process has ended
                break
            if not data:
                break
            received += data
            if on_output is not None:
                on_output(process, received.decode(errors="replace"))
        stdout = process.stdout.read().decode()
        process.wait(timeout=60)
    finally:
        os.close(master)
        if process.poll() is None:
            process.kill()
    return process.returncode, stdout, received.decode(errors="replace")


def write_population(folder: Path, n: int = 4):
    folder.mkdir(parents=True, exist_ok=True)
    for k, position in enumerate(np.linspace(-0.6, 0.6, n)):
        # label 1 = the object, label 2 = a bump of another label, to exercise --label
        mask = small_mask(float(position)).astype(np.uint8)
        mask[:, :, :3] = np.where(mask[:, :, :3] > 0, 2, 0)
        write_label_map(folder / f"s{k}.nii.gz", mask)
    return folder


def test_build_end_to_end_with_a_bad_input(tmp_path):
    inputs = write_population(tmp_path / "in")
    (inputs / "broken.vtk").write_text("# vtk DataFile Version 3.0\nnot really\n")
    out = tmp_path / "out"
    result = run("build", inputs, "-o", out, "--points", 162, "--max-time", 3, "--label", "1,2",
                 "--workers", 1, "--specificity-samples", 200, "--evaluation-modes", 3)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    rejection_lines = [line for line in result.stderr.splitlines() if "broken.vtk" in line]
    assert len(rejection_lines) == 1 and "rejected" in rejection_lines[0]
    assert "objective (eq. 14)" in result.stdout
    # stderr is no terminal: the progress as plain log lines (each stage's first and last), no bar
    assert "[100%] prepared 5/5" in result.stderr
    assert "evaluating the baselines" in result.stderr
    assert "\r" not in result.stderr and "\x1b" not in result.stderr
    assert not re.search(r"\d%\|", result.stderr)
    for name in ("model.h5", "mean.vtp", "scores.csv", "metrics.json", "convergence.csv",
                 "report.html", "build.log", "rejected.csv"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "correspondence").iterdir()) == [
        f"s{k}.vtp" for k in range(4)]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_shapes"] == 4 and metrics["n_rejected"] == 1


def test_same_seed_gives_identical_models(tmp_path):
    """The paper's strategies draw random kernels: the seed decides them."""
    inputs = write_population(tmp_path / "in", 3)
    outputs = {}
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        result = run("build", inputs, "-o", tmp_path / name, "--points", 42, "--max-time", 600,
                     "--strategy", "one-at-a-time-pose",
                     "--max-sweeps", 2, "--workers", 2, "--seed", seed,
                     "--specificity-samples", 100, "--evaluation-modes", 2, "-q")
        assert result.returncode == 0, result.stderr
        outputs[name] = [(tmp_path / name / "scores.csv").read_bytes()]
    assert outputs["a"][0] == outputs["b"][0]      # scores, bit for bit
    a = np.load(tmp_path / "a" / "checkpoint.npz")
    b = np.load(tmp_path / "b" / "checkpoint.npz")
    timings = "trace_numbers"   # its first two columns are seconds; the rest must agree
    assert all(np.array_equal(a[k], b[k]) for k in a.files if k != timings)
    assert np.array_equal(a[timings][:, 2:], b[timings][:, 2:])

    def searched(name):  # evaluations and objective values of the trace, not its timings
        lines = (tmp_path / name / "convergence.csv").read_text().splitlines()[1:]
        return [line.split(",")[2:4] for line in lines]

    assert searched("a") == searched("b")
    assert searched("a") != searched("c")


def test_clear_errors_and_exit_codes(tmp_path):
    missing = run("build", tmp_path / "nothing-here", "-o", tmp_path / "out")
    assert missing.returncode == 2
    assert "no such file" in missing.stderr and "Traceback" not in missing.stderr
    inputs = write_population(tmp_path / "in", 2)
    too_few = run("build", inputs, "-o", tmp_path / "out2", "--points", 42, "--workers", 1)
    assert too_few.returncode == 2 and "at least 3" in too_few.stderr
    bad_option = run("build", inputs, "-o", tmp_path / "out3", "--points", 5)
    assert bad_option.returncode == 2 and "points" in bad_option.stderr
    three = write_population(tmp_path / "in3", 3)
    missing_label = run("build", three, "-o", tmp_path / "out4", "--label", "7", "--workers", 1)
    assert missing_label.returncode == 2
    assert "label 7 not present" in missing_label.stderr


def test_demo_runs_and_reports(tmp_path):
    out = tmp_path / "demo"
    result = run("demo", "-o", out, "--subjects", 4, "--max-time", 2)
    assert result.returncode == 0, result.stderr
    assert "objective (eq. 14)" in result.stdout and str(out) in result.stdout
    assert len(list((out / "inputs").glob("*.nii.gz"))) == 4
    assert (out / "model.h5").is_file() and (out / "report.html").is_file()


def test_rebuild_reuses_preprocessing_and_no_cache_does_not(tmp_path):
    inputs = write_population(tmp_path / "in", 3)
    cache = tmp_path / "cache"
    common = ["--points", 42, "--max-sweeps", 1, "--workers", 1, "--specificity-samples", 50,
              "--evaluation-modes", 1, "--cache-dir", cache]
    first = run("build", inputs, "-o", tmp_path / "a", *common)
    second = run("build", inputs, "-o", tmp_path / "b", *common)
    assert first.returncode == 0 and second.returncode == 0, second.stderr
    assert "reused" not in first.stderr
    assert "reused 3 of 3 preprocessed cases" in second.stderr
    assert len(list(cache.glob("*.npz"))) == 3
    third = run("build", inputs, "-o", tmp_path / "c", *common[:-2], "--no-cache")
    assert third.returncode == 0 and "reused" not in third.stderr


def test_cpd_build_compare_and_fit(tmp_path):
    """A CPD-baseline build, a comparison of it with an MDL build, and a fit of a new case."""
    inputs = write_population(tmp_path / "in", 5)
    held_back = tmp_path / "new"
    held_back.mkdir()
    (inputs / "s2.nii.gz").rename(held_back / "s2.nii.gz")
    common = ["--points", 162, "--workers", 2, "--specificity-samples", 200,
              "--evaluation-modes", 2, "--surface-samples", 20, "-q"]
    mdl = run("build", inputs, "-o", tmp_path / "mdl", "--max-sweeps", 1, "--baselines",
              "none,cpd", *common)
    assert mdl.returncode == 0, mdl.stderr
    metrics = json.loads((tmp_path / "mdl" / "metrics.json").read_text())
    assert set(metrics["baselines"]) == {"none", "cpd"}
    assert "(cpd: " in mdl.stdout
    assert len(metrics["generalization_surface_mm"]) == 2
    cpd = run("build", inputs, "-o", tmp_path / "cpd", "--correspondence", "cpd", *common)
    assert cpd.returncode == 0, cpd.stderr
    assert json.loads((tmp_path / "cpd" / "metrics.json").read_text())["strategy"] == "cpd"
    # the CPD build's measures equal the MDL build's CPD baseline (same cases, same seed)
    cpd_metrics = json.loads((tmp_path / "cpd" / "metrics.json").read_text())
    np.testing.assert_allclose(cpd_metrics["generalization"],
                               metrics["baselines"]["cpd"]["generalization"], rtol=1e-6)

    compared = run("compare", tmp_path / "mdl", tmp_path / "cpd", "-o", tmp_path / "cmp",
                   "--modes", 2, "--samples", 300)
    assert compared.returncode == 0, compared.stderr
    assert "generalization" in compared.stdout and "4 shared cases" in compared.stdout
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert set(result["models"]) == {"mdl (fast)", "cpd (cpd)"}
    assert (tmp_path / "cmp" / "compare.html").is_file()

    fitted = run("fit", tmp_path / "mdl", held_back, "-o", tmp_path / "fit", "--max-sweeps", 2,
                 "--strategy", "one-at-a-time-pose")
    assert fitted.returncode == 0, fitted.stderr
    assert "s2: reconstruction error" in fitted.stdout
    fit = json.loads((tmp_path / "fit" / "fit.json").read_text())["s2"]
    errors = fit["reconstruction_squared_mm2"]
    # M = 0..3: each mode lowers the reconstruction error, or keeps it
    assert len(errors) == 4 and errors[-1] < errors[0]
    assert np.all(np.diff(errors) <= 1e-12 * errors[0]), errors
    assert fit["objective"]["strategy"] == "one-at-a-time-pose"
    bad = run("fit", tmp_path / "nowhere", held_back, "-o", tmp_path / "fit2")
    assert bad.returncode == 2 and "no such model file" in bad.stderr
    assert "Traceback" not in bad.stderr


# Each user-facing field of BuildConfig: its options on the command line and the value they give.
NON_DEFAULT_OPTIONS = {
    "labels": (["--label", "1,2", "--label", "3"], [1, 2, 3]),
    "voxel_size": (["--voxel-size", "0.5"], 0.5),
    "mirror": (["--mirror", "*_r*", "--mirror", "a,b"], ["*_r*", "a,b"]),
    "allow_duplicates": (["--allow-duplicates"], True),
    "parts": (["--part", "head=1", "--part", "tail=2,3"], ["head=1", "tail=2,3"]),
    "surface_method": (["--surface", "slicer"], "slicer"),
    "smoothing_factor": (["--smoothing-factor", "0.25"], 0.25),
    "decimation": (["--decimation", "0.2"], 0.2),
    "smoothing_sigma": (["--smoothing", "1.5"], 1.5),
    "max_smoothing_sigma": (["--max-smoothing", "3"], 3.0),
    "edge_length": (["--edge-length", "1.5"], 1.5),
    "target_vertices": (["--target-vertices", "5000"], 5000),
    "correspondence": (["--correspondence", "cpd"], "cpd"),
    "baselines": (["--baselines", "none,cpd"], ["none", "cpd"]),
    "points": (["--points", "162"], 162),
    "strategy": (["--strategy", "one-at-a-time-pose"], "one-at-a-time-pose"),
    "warps": (["--warps", "symmetric,shear"], ["symmetric", "shear"]),
    "scaling": (["--no-scaling"], False),
    "delta_range": (["--delta-range", "0.001", "0.25"], [0.001, 0.25]),
    "fixed_delta": (["--fixed-delta", "0.2"], 0.2),
    "sigma_g": (["--sigma-g", "0.05"], 0.05),
    "max_time": (["--max-time", "30"], 30.0),
    "fixed_fraction": (["--fixed-fraction", "0.5"], 0.5),
    "tolerance": (["--tolerance", "0.01"], 0.01),
    "max_sweeps": (["--max-sweeps", "7"], 7),
    "coarse_points": (["--coarse-points", "162"], 162),
    "curvature_pairs": (["--curvature-pairs", "single"], "single"),
    "landmarks": (["--landmarks", "marks"], "marks"),      # made by config_of_command_line
    "landmark_weight": (["--landmark-weight", "3"], 3.0),
    "check_landmarks": (["--check-landmarks", "--landmarks", "marks"], True),
    "smoothness": (["--smoothness", "0.1"], 0.1),
    "placement": (["--placement", "sphere"], "sphere"),
    "seed": (["--seed", "5"], 5),
    "evaluation_modes": (["--evaluation-modes", "3"], 3),
    "specificity_samples": (["--specificity-samples", "300"], 300),
    "surface_samples": (["--surface-samples", "0"], 0),
    "generalization_cases": (["--generalization-cases", "50"], 50),
    "workers": (["--workers", str((os.cpu_count() or 1) + 1)], (os.cpu_count() or 1) + 1),
    "scheduler": (["--scheduler", "tcp://127.0.0.1:1"], "tcp://127.0.0.1:1"),
    "cache_dir": (["--cache-dir", "somewhere"], "somewhere"),
    "strict": (["--strict"], True),
}


def config_of_command_line(tmp_path: Path, name: str, *options) -> dict:
    """The configuration that ``build`` makes of ``options``: the build writes config.json into
    its output folder before it prepares its inputs, which here are three damaged label maps
    (so it stops there, or at an unreachable --scheduler). It runs in ``tmp_path``, which holds
    a landmark folder ``marks`` for one of them."""
    inputs = tmp_path / "damaged"
    if not inputs.exists():
        inputs.mkdir()
        for k in range(3):
            (inputs / f"case_{k}.nii.gz").write_bytes(b"not image %d" % k)   # not one file 3 times
        (tmp_path / "marks").mkdir()
        (tmp_path / "marks" / "case_0.csv").write_text("label,x,y,z\ntip,1,2,3\n")
    result = run("build", inputs, "-o", tmp_path / name, *options, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    return json.loads((tmp_path / name / "config.json").read_text())


def test_build_options_are_the_fields_of_build_config(tmp_path):
    """Every build option sets a BuildConfig field and shows its help; every field is offered
    or named as not offered, with why; the defaults are the fields' defaults."""
    defaults = BuildConfig()
    offered = [f for f in dataclasses.fields(BuildConfig) if f.name in BUILD_OPTIONS]
    assert {f.name for f in offered} == set(NON_DEFAULT_OPTIONS)
    names = [f.name for f in dataclasses.fields(BuildConfig)]
    assert set(BUILD_OPTIONS) <= set(names)
    for name in names:  # each field is offered or says why not
        assert (name in BUILD_OPTIONS) != (name in NOT_OFFERED), name

    def squeezed(text):  # argparse rewraps help texts
        return re.sub(r"\s+", "", text)

    help_text = run("build", "--help").stdout
    entries = {}  # flag -> its entry in the help (whitespace removed)
    for entry in re.split(r"\n(?= {2}-)", help_text):
        flag = re.match(r" {2}(?:-\w, )?(--[\w-]+)", entry)
        if flag:
            entries[flag.group(1)] = squeezed(entry)
    # besides the settings: what goes in (a manifest), where the build goes and how (again into
    # an earlier build's folder)
    run_options = {"--help", "--manifest", "--output", "--quiet", "--overwrite", "--resume"}
    assert set(entries) - run_options == (
        {arguments[0] for arguments, _ in NON_DEFAULT_OPTIONS.values()} | {"--no-cache"})
    for f in offered:
        default = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        flag = NON_DEFAULT_OPTIONS[f.name][0][0]
        assert squeezed(BUILD_OPTIONS[f.name].help % {"default": default}) in entries[flag], f.name
    cache_dir = next(f for f in offered if f.name == "cache_dir")
    assert squeezed(BUILD_OPTIONS[cache_dir.name].off_help) in entries["--no-cache"]

    # no options: the defaults, with the blur rule (max_smoothing_sigma = max(2, smoothing))
    assert config_of_command_line(tmp_path, "defaults") == json.loads(
        json.dumps(defaults.to_dict()))
    # every option: its field
    options = [a for arguments, _ in NON_DEFAULT_OPTIONS.values() for a in arguments]
    made = config_of_command_line(tmp_path, "options", *options)
    for name, (_, value) in NON_DEFAULT_OPTIONS.items():
        assert value != json.loads(json.dumps(defaults.to_dict()))[name], name
        assert made[name] == value, name
    assert made["max_amplitude"] == defaults.max_amplitude
    # --no-cache wins over --cache-dir; unless set, the largest blur follows --smoothing
    made = config_of_command_line(tmp_path, "rules", "--no-cache", "--cache-dir", "x",
                                  "--smoothing", "3")
    assert made["cache_dir"] == "" and made["smoothing_sigma"] == 3.0
    assert made["max_smoothing_sigma"] == 3.0
    assert BuildConfig(smoothing_sigma=3.0).validate().max_smoothing_sigma == 3.0
    assert defaults.max_smoothing_sigma == 2.0


def test_progress_bars_on_a_terminal_and_ctrl_c_keeps_the_state_reached(tmp_path):
    """With stderr a terminal: bars for the preparation and the evaluation, the objective live
    during the optimisation; Ctrl-C there still writes the model of the state reached."""
    inputs = write_population(tmp_path / "in")
    out = tmp_path / "out"
    interrupted = []

    def interrupt_the_optimisation(process, text):
        if not interrupted and text.count("F = ") >= 2:  # the objective has been shown twice
            process.send_signal(signal.SIGINT)
            interrupted.append(True)

    code, stdout, terminal = run_in_terminal(
        "build", inputs, "-o", out, "--points", 162, "--strategy", "one-at-a-time-pose",
        "--max-time", 300, "--tolerance", 1e-9, "--label", "1,2", "--workers", 1,
        "--specificity-samples", 200, "--evaluation-modes", 2, "--surface-samples", 0,
        on_output=interrupt_the_optimisation)
    assert interrupted and code == 0, terminal
    assert "Traceback" not in terminal
    # preparation: a bar redrawn in place up to 100%
    assert re.search(r"\r\s*25%\|[^\r\n]*\| prepared 1/4", terminal), terminal
    assert re.search(r"\r100%\|[^\r\n]*\| prepared 4/4", terminal), terminal
    # the optimisation: its phase, sweep and F, redrawn in place
    assert len(re.findall(r"\roptimisation \[[\d:]+\] fixed: sweep \d+, F = -?\d+\.\d{3}",
                          terminal)) >= 2, terminal
    assert "optimisation interrupted: writing the model of the state reached" in terminal
    # the evaluation: a bar to the end
    assert re.search(r"\r100%\|[^\r\n]*\| evaluated, outputs written", terminal), terminal
    # the bars stand in for the plain progress lines, which go to build.log only
    assert "[100%] prepared 4/4" not in terminal
    assert "[100%] prepared 4/4" in (out / "build.log").read_text()
    assert "objective (eq. 14)" in stdout
    assert json.loads((out / "metrics.json").read_text())["interrupted"] is True
    assert (out / "model.h5").is_file()


def test_ctrl_c_while_preparing_closes_the_bar(tmp_path):
    inputs = write_population(tmp_path / "in")
    interrupted = []

    def interrupt_the_preparation(process, text):
        if not interrupted and "prepared 1/4" in text:
            process.send_signal(signal.SIGINT)
            interrupted.append(True)

    code, _, terminal = run_in_terminal("build", inputs, "-o", tmp_path / "out", "--points", 42,
                                        "--workers", 1, "--no-cache",
                                        on_output=interrupt_the_preparation)
    assert interrupted and code == 130, terminal
    assert "prepared 4/4" not in terminal and "Traceback" not in terminal
    # the bar was closed (its line ended) before the message
    before, after = terminal.split("mdlshapemodel: interrupted")
    assert re.search(r"\| prepared 1/4( \(about [^)\r\n]* left\))? \[[^\r\n]*\]\r?\n$", before), \
        terminal
