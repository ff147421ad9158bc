"""Every example in every ``--help`` runs: the examples are read from each command's help and run
in its order (the builds first, then what uses them), in one folder holding small real inputs of
the names the examples use, through the real command line in subprocesses. Options that only
make a run quicker are put before the example's own words, so that the example's own options win
where both are given."""

import shlex

import numpy as np
import pytest

from mdlshapemodel.demo import write_demo_population

from common import run_cli

COMMANDS = ("build", "demo", "compare", "fit", "analyze")

QUICKER = {"build": ["--points", "42", "--workers", "1", "--max-time", "5",
                     "--evaluation-modes", "1", "--specificity-samples", "50",
                     "--surface-samples", "0", "--baselines", "", "--no-cache"],
           "demo": ["--subjects", "4", "--max-time", "3"],
           "compare": ["--modes", "2", "--samples", "50"],
           "fit": ["--max-time", "3"],
           "analyze": ["--permutations", "99"]}


def help_examples(command: str) -> list:
    """The example command lines of ``mdlshapemodel COMMAND --help`` (their comments dropped),
    as word lists after ``mdlshapemodel``."""
    text = run_cli(command, "--help").stdout
    assert "examples:" in text, f"{command} --help has no examples"
    lines = text[text.index("examples:"):].splitlines()[1:]
    return [shlex.split(line.split("  (")[0])[1:] for line in lines
            if line.strip().startswith("mdlshapemodel ")]


def write_femurs(folder, count: int = 3) -> None:
    """Closed triangle meshes (ellipsoids of different lengths) as STL files, the last named
    ``*_right*``."""
    import vtk

    folder.mkdir()
    for k in range(count):
        sphere = vtk.vtkSphereSource()
        sphere.SetThetaResolution(24)
        sphere.SetPhiResolution(16)
        sphere.SetRadius(10.0)
        scale = vtk.vtkTransform()
        scale.Scale(1.0 + 0.2 * k, 0.8, 0.6)
        stretched = vtk.vtkTransformFilter()
        stretched.SetInputConnection(sphere.GetOutputPort())
        stretched.SetTransform(scale)
        writer = vtk.vtkSTLWriter()
        writer.SetInputConnection(stretched.GetOutputPort())
        side = "right" if k == count - 1 else "left"
        writer.SetFileName(str(folder / f"femur_{k}_{side}.stl"))
        writer.Write()


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """labels/ (six two-label maps: labels 1 and 2), femurs/*.stl, new/ (cases to fit, one
    named case.nii.gz), subjects.csv (diagnosis, age, sex and a site coded 1-3 of the six cases)
    and visits.csv (the six cases as three subjects' pre and post scans)."""
    folder = tmp_path_factory.mktemp("examples")
    paths = write_demo_population(folder / "labels", 6, seed=1, parts=True)
    new = write_demo_population(folder / "new", 2, seed=2, parts=True)
    new[0].rename(folder / "new" / "case.nii.gz")
    write_femurs(folder / "femurs")
    rng = np.random.default_rng(3)
    rows = [f"{path.name.removesuffix('.nii.gz')},{'ad' if k % 2 else 'control'},"
            f"{60 + rng.integers(0, 20)},{'f' if k % 3 else 'm'},{k % 3 + 1}"
            for k, path in enumerate(paths)]
    (folder / "subjects.csv").write_text("case,diagnosis,age,sex,site\n" + "\n".join(rows) + "\n")
    # the six cases as three subjects scanned twice
    visits = [f"{path.name.removesuffix('.nii.gz')},s{k // 2},{'post' if k % 2 else 'pre'}"
              for k, path in enumerate(paths)]
    (folder / "visits.csv").write_text("case,id,visit\n" + "\n".join(visits) + "\n")
    return folder


def test_every_command_has_examples_in_its_help():
    for command in COMMANDS:
        assert help_examples(command), command


@pytest.mark.slow
def test_every_example_of_every_help_runs(workspace):
    for command in COMMANDS:
        for words in help_examples(command):
            assert words[0] == command
            # a path with a wildcard (femurs/*.stl) is the shell's to expand: done here
            expanded = []
            for word in words[1:]:
                matches = sorted(workspace.glob(word)) if "*" in word and "/" in word else []
                expanded += [str(p.relative_to(workspace)) for p in matches] or [word]
            result = run_cli(command, *QUICKER[command], *expanded, cwd=workspace)
            assert result.returncode == 0, (f"mdlshapemodel {shlex.join(words)}:\n"
                                            f"{result.stderr[-3000:]}")
