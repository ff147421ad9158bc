"""The build folder has one owner: every file name of a build's and a fit's folder is known in
folders.py alone, its readers undo the mirroring, and the faces read a build through it."""

import ast
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mdlshapemodel import folders
from mdlshapemodel.folders import BuildFolder
from mdlshapemodel.model.shape_model import ShapeModel
from common import run_cli
from files import write_label_map
from synthetic import small_mask
from test_guides import write_guided_population

# the source tree's package (the tests may run against an installed copy) and the Slicer module
# beside it
PACKAGE = Path(__file__).resolve().parents[1] / "MDLShapeModel" / "mdlshapemodel"
SOURCES = sorted(PACKAGE.rglob("*.py")) + [PACKAGE.parent / "MDLShapeModel.py"]


def folder_names() -> set:
    """Every name of a build's and a fit's folder, as folders.py lists them."""
    return set(folders.BUILD_FILES) | set(folders.FIT_FILES)


def docstrings(tree) -> set:
    """The ids of the string constants that are docstrings (they may name files)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                found.add(id(body[0].value))
    return found


def mentions(path: Path, names: set) -> set:
    """The names a file's code knows: a file name (one with a suffix) in any string constant but
    a docstring, f-strings' pieces included; a folder's name (no suffix: also an ordinary
    word, as 'correspondence') where a path is joined with it (``folder / "aligned"``)."""
    tree = ast.parse(path.read_text())
    skip = docstrings(tree)
    files = {name for name in names if "." in name}
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            found |= {name for name in files if name in node.value}
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div):
            for side in (node.left, node.right):
                if isinstance(side, ast.Constant) and isinstance(side.value, str):
                    found |= {name for name in names - files if side.value.strip("/") == name}
    return found


def test_every_file_name_of_a_build_is_known_in_folders_alone():
    names = folder_names()
    assert {"model.h5", "metrics.json", "scores.csv", "landmarks.csv", "correspondence"} <= names
    here = PACKAGE / "folders.py"
    tree = ast.parse(here.read_text())
    assert names <= {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant)}
    elsewhere = {f"{path.relative_to(PACKAGE.parent)}: {', '.join(sorted(found))}"
                 for path in SOURCES if path != here
                 for found in [mentions(path, names)] if found}
    assert not elsewhere, "build-folder names known outside folders.py:\n" + "\n".join(
        sorted(elsewhere))


def test_the_checker_sees_a_name_in_code_and_not_in_a_docstring(tmp_path):
    # the grep above must find a name where code uses it, or it would pass vacuously
    source = tmp_path / "room.py"
    source.write_text('"""Reads metrics.json."""\n'
                      'def f(out, name):\n'
                      '    """Writes scores.csv."""\n'
                      '    return out / "aligned" / f"{name}.vtp", f"{out}/cases.csv", "aligned"\n')
    assert mentions(source, folder_names()) == {"aligned", "cases.csv"}


def written_build(folder: Path, mirrored) -> tuple[ShapeModel, np.ndarray]:
    """A build folder written through BuildFolder: a model of four shapes in the model's frame
    and their corresponded meshes in the inputs' space (a mirrored case's reflected)."""
    rng = np.random.default_rng(3)
    base = rng.normal(size=(12, 3)) * [3.0, 2.0, 1.0]
    shapes = np.stack([base + rng.normal(scale=0.2, size=base.shape) for _ in range(4)])
    triangles = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8], [8, 9, 10], [10, 11, 0]])
    names = [f"c{k}" for k in range(4)]
    model = ShapeModel.from_shapes(shapes, np.full(12, 1 / 12), names=names,
                                   triangles=triangles, strategy="none")
    build = BuildFolder(folder)
    folder.mkdir()
    build.write_model(model)
    physical = folders.physical_shapes(shapes, mirrored)
    build.write_case_meshes(model, names, physical, shapes)
    build.write_cases([{"case": name, "mirrored": flag} for name, flag in zip(names, mirrored)])
    return model, shapes


def test_a_builds_shapes_are_read_in_the_models_frame_with_mirrored_cases_reflected_back(
        tmp_path):
    mirrored = [False, True, False, True]
    model, shapes = written_build(tmp_path / "out", mirrored)
    on_disk = folders.mesh_points(BuildFolder(tmp_path / "out").case_mesh("", "c1"))
    np.testing.assert_allclose(on_disk[:, 0], -shapes[1][:, 0], atol=1e-6)   # the input's side
    read = BuildFolder(tmp_path / "out").shapes()
    assert read.model.names == model.names
    np.testing.assert_allclose(read.shapes, shapes, atol=1e-6)


def test_the_vtk_reader_and_compare_take_a_build_folder_or_its_model_file(tmp_path):
    from mdlshapemodel.compare import load_population
    from mdlshapemodel.vtkmodel import ShapeModelReader

    model, _ = written_build(tmp_path / "out", [False] * 4)
    for given in (tmp_path / "out", BuildFolder(tmp_path / "out").model_file):
        reader = ShapeModelReader()
        reader.SetFileName(str(given))
        reader.Update()
        assert reader.GetErrorText() == ""
        assert reader.GetOutput().GetNumberOfPoints() == len(model.mean)
        assert load_population(given).names == model.names
    reader = ShapeModelReader()
    reader.SetFileName(str(tmp_path))             # a folder that holds no build
    reader.Update()
    assert reader.GetErrorText() == f"{tmp_path}: not a build folder (no model.h5)"


def test_landmarks_are_read_back_as_written():
    rows = [folders.CorrespondedLandmark("a", "tip", np.array([1.0, 2.0, 3.0]),
                                         np.array([1.5, 2.0, 3.0])),
            folders.CorrespondedLandmark("b", "tip", np.array([-1.0, 0.25, 3.0]))]
    read = [folders.CorrespondedLandmark.of_row(dict(zip(folders.LANDMARK_COLUMNS, r.row())))
            for r in rows]
    assert [(r.case, r.label, r.distance) for r in read] == [("a", "tip", 0.5),
                                                             ("b", "tip", None)]
    np.testing.assert_array_equal(read[1].point, rows[1].point)



def test_scores_and_measures_are_read_back_as_written(tmp_path):
    """scores.csv keeps six significant digits of every score, whatever its magnitude;
    metrics.json's measures per mode come back with their own standard errors."""
    folder = BuildFolder(tmp_path)
    scores = np.random.default_rng(4).normal(size=(3, 4)) * [2000.0, 30.0, 0.4, 5e-3]
    folder.write_scores(["a", "b", "c"], scores)
    names, read = folder.scores()
    assert names == ["a", "b", "c"]
    np.testing.assert_allclose(read, scores, rtol=5e-6)
    folder.write_metrics({"modes": [1, 2], "compactness": [4.0, 6.5],
                          "compactness_se": [0.25, 0.5], "generalization": [1.5, 1.0]})
    measures = folder.measures()
    assert measures["mode"] == [1.0, 2.0]
    assert measures["C"] == [4.0, 6.5] and measures["C SE"] == [0.25, 0.5]
    assert measures["G"] == [1.5, 1.0] and measures["G SE"] == [1.5, 1.0]   # none written


def test_a_resumable_builds_checkpoint_is_not_replaced_unasked(tmp_path):
    """A folder that holds only a checkpoint (a build stopped before its model) is an earlier
    build: a new build into it is refused, naming the checkpoint, and leaves it; what a failed
    start leaves (its log and settings) is no earlier build."""
    labels = tmp_path / "labels"
    labels.mkdir()
    for k, position in enumerate((-0.4, 0.0, 0.4)):
        write_label_map(labels / f"s{k}.nii.gz", small_mask(position))
    output = tmp_path / "out"
    output.mkdir()
    for name in (folders.LOG, folders.CONFIG):
        (output / name).write_text("left by a failed start")
    assert BuildFolder(output).earlier_build() == []
    (output / folders.CHECKPOINT).write_bytes(b"a stopped build's")
    result = run_cli("build", labels, "-o", output, "--workers", 1, "--no-cache")
    assert result.returncode != 0
    assert f"holds an earlier build ({folders.CHECKPOINT})" in result.stderr
    assert (output / folders.CHECKPOINT).read_bytes() == b"a stopped build's"

@pytest.mark.slow
def test_build_and_fit_write_landmarks_csv_and_scores_csv_in_one_schema(tmp_path):
    data = write_guided_population(tmp_path)
    built = run_cli("build", data / "labels", "-o", tmp_path / "guided", "--landmarks",
                    data / "marks", "--points", 162, "--coarse-points", 42, "--workers", 1,
                    "--max-sweeps", 3, "--specificity-samples", 200, "--surface-samples", 0,
                    "--evaluation-modes", 2, "--no-cache", "-q")
    assert built.returncode == 0, built.stderr
    new = write_label_map(tmp_path / "n1.nii.gz", small_mask(0.3))
    fitted = run_cli("fit", tmp_path / "guided", new, "-o", tmp_path / "fitted",
                     "--max-sweeps", 2)
    assert fitted.returncode == 0, fitted.stderr

    def header(path):
        with open(path, newline="") as handle:
            return next(csv.reader(handle))

    for name in ("landmarks.csv", "scores.csv"):
        assert header(tmp_path / "fitted" / name) == header(tmp_path / "guided" / name), name
    fit_marks = BuildFolder(tmp_path / "fitted").landmarks()
    assert sorted(r.label for r in fit_marks) == ["end", "tip"]
    assert all(r.case == "n1" and r.given is None for r in fit_marks)


def test_the_baselines_evaluations_are_read_back_bit_for_bit_for_the_same_build_only(tmp_path):
    """baselines.json gives back every number of an evaluation (its jackknife arrays too, and
    an evaluation without one), for the fingerprint it was written with; for another build's
    fingerprint, or from a file cut short, nothing (the baselines are then evaluated again)."""
    from mdlshapemodel.model.evaluation import evaluate

    rng = np.random.default_rng(4)
    shapes = rng.normal(size=(12, 20, 3))
    weights = np.full(20, 1 / 20)
    measured = evaluate(shapes, weights, None, max_modes=3, n_samples=40, rng=rng,
                        jackknife=True)
    measured["specificity_se"][0] = float("nan")       # a value JSON writes as NaN
    small = evaluate(shapes[:3], weights, None, max_modes=1, n_samples=10)
    assert "jackknife" in measured and "jackknife" not in small
    folder = BuildFolder(tmp_path)
    fingerprint = {"settings": {"seed": 0}, "cases": [["a", "d1"], ["b", "d2"]]}
    folder.write_baselines({"none": measured, "cpd": small}, fingerprint)
    back = folder.baselines({"cases": [["a", "d1"], ["b", "d2"]], "settings": {"seed": 0}})
    assert set(back) == {"none", "cpd"} and back["cpd"] == small
    jackknife = back["none"].pop("jackknife")
    expected = dict(measured)
    original = expected.pop("jackknife")
    assert np.isnan(back["none"]["specificity_se"][0])
    back["none"]["specificity_se"][0] = expected["specificity_se"][0] = 0.0
    assert back["none"] == expected
    assert np.array_equal(jackknife.per_case, original.per_case)
    assert np.array_equal(jackknife.left_out, original.left_out)
    assert folder.baselines({**fingerprint, "settings": {"seed": 1}}) == {}
    text = folder.baselines_file.read_text()
    listed = json.loads(text)
    folder.baselines_file.write_text(json.dumps({**listed, "baselines": list(listed["baselines"])}))
    assert folder.baselines(fingerprint) == {}        # whole JSON, not a baselines' file
    folder.baselines_file.write_text(text[: len(text) // 2])
    assert folder.baselines(fingerprint) == {}
    assert BuildFolder(tmp_path / "none").baselines(fingerprint) == {}
