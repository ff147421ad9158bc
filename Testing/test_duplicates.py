"""A case given twice: named and refused before the optimisation unless --allow-duplicates; with
it allowed, the model drops the copy's mode of no variance, so that no distance divides by it.
Through the command line, on the shared hippocampi (hippocampus_010 and hippocampus_011 are one
label map twice)."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel import ShapeModel
from mdlshapemodel.model.shape_model import NEGLIGIBLE_VARIANCE

from common import HIPPOCAMPI, needs_hippocampi, run_cli_quietly as run
from files import read_csv_rows

pytestmark = needs_hippocampi

FAST = ["--points", "162", "--baselines", "", "--specificity-samples", "200",
        "--surface-samples", "0", "--workers", "2"]


def hippocampus(number: int):
    return HIPPOCAMPI / f"hippocampus_{number:03d}.nii.gz"


def moved_copy(source, destination, shift_mm: float = 7.3):
    """The label map ``source`` written to ``destination`` (another format) with its origin
    moved: the same voxels, other bytes."""
    image = sitk.ReadImage(str(source))
    image.SetOrigin(tuple(o + shift_mm for o in image.GetOrigin()))
    sitk.WriteImage(image, str(destination))
    return destination


def test_identical_files_are_named_and_refused_before_anything_is_prepared(tmp_path):
    output = tmp_path / "out"
    inputs = [hippocampus(k) for k in (1, 3, 4, 10, 11)]
    refused = run("build", *inputs, "-o", output, *FAST)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip().splitlines()[-1]
    assert str(hippocampus(10)) in line and str(hippocampus(11)) in line
    assert "identical files" in line and "--allow-duplicates" in line
    assert "remove all but one" in line
    assert "prepar" not in refused.stderr and "Traceback" not in refused.stderr
    assert not output.exists()                         # nothing written


@pytest.mark.slow
def test_a_moved_copy_in_another_format_is_refused_as_the_same_shape(tmp_path):
    """Other bytes, the same voxels: found by its shape in the initial correspondence, and the
    build stops before the optimisation starts."""
    copy = moved_copy(hippocampus(10), tmp_path / "moved.nrrd")
    output = tmp_path / "out"
    refused = run("build", *(hippocampus(k) for k in (1, 3, 4, 10)), copy, "-o", output, *FAST)
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip().splitlines()[-1]
    assert str(hippocampus(10)) in line and str(copy) in line
    assert "the same shape" in line and "--allow-duplicates" in line
    assert "initial objective" not in refused.stderr and "Traceback" not in refused.stderr
    assert not (output / "model.h5").exists()


@pytest.mark.slow
def test_allowed_duplicates_leave_no_mode_of_no_variance_and_fit_distances_ordinary(tmp_path):
    """With the copy allowed, the model of 8 cases has 6 modes (not 7: the pair's is dropped,
    every kept mode holds more than NEGLIGIBLE_VARIANCE of the variance), and a new ordinary
    case's Mahalanobis distance in fit.json is the distance over those modes, of the size of
    its distance over the modes explaining 95 % (``unusual``), not one divided by a variance
    of almost nothing."""
    copy = moved_copy(hippocampus(10), tmp_path / "moved.nii.gz")
    build = tmp_path / "build"
    built = run("build", *(hippocampus(k) for k in (1, 3, 4, 6, 7, 8, 10)), copy, "-o", build,
                "--allow-duplicates", "--strategy", "none", *FAST)
    assert built.returncode == 0, built.stderr
    assert "the same shape" in built.stderr and "--allow-duplicates" in built.stderr
    model = ShapeModel.load(build / "model.h5")
    assert len(model.names) == 8 and model.n_modes == 6
    assert model.variances.min() > NEGLIGIBLE_VARIANCE * model.variances.sum()

    fitted = run("fit", build, hippocampus(14), "-o", tmp_path / "fit")
    assert fitted.returncode == 0, fitted.stderr
    summary = json.loads((tmp_path / "fit" / "fit.json").read_text())["hippocampus_014"]
    (row,) = read_csv_rows(tmp_path / "fit" / "scores.csv")
    scores = np.array([float(row[f"mode_{m + 1}"]) for m in range(model.n_modes)])
    assert summary["mahalanobis"] == pytest.approx(
        np.sqrt(np.sum(scores ** 2 / model.variances)), rel=1e-4)
    assert summary["mahalanobis"] < 3 * summary["unusual"]["distance"]


def test_close_shapes_are_found_without_the_pairwise_distances_of_all_cases():
    """same_shapes finds planted copies (a moved one and one a hair away, and a group of three)
    among 3000 cases, and none of two shapes just beyond the limit, holding nothing n_s x n_s:
    its traced memory stays within a few copies of the shapes (the 3000 x 3000 distances
    alone are 72 MB)."""
    import tracemalloc

    from mdlshapemodel.prepare.duplicates import same_shapes

    rng = np.random.default_rng(3)
    n, points = 3000, 100
    shapes = rng.normal(size=(n, points, 3)) + rng.normal(size=(n, 1, 3)) * 10.0
    weights = np.full(points, 1.0 / points)
    shapes[2500] = shapes[10] + [5.0, -2.0, 1.0]                 # moved
    shapes[700] = shapes[20] + rng.normal(size=(points, 3)) * 1e-5
    shapes[701] = shapes[20] + rng.normal(size=(points, 3)) * 1e-5
    shapes[1800] = shapes[1200] + rng.normal(size=(points, 3)) * 0.1   # far beyond 0.1 %
    tracemalloc.start()
    found = same_shapes(shapes, weights, [f"case{i}" for i in range(n)])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert [d.files for d in found] == [("case10", "case2500"), ("case20", "case700", "case701")]
    assert peak < 4 * shapes.nbytes                               # 7.2 MB of shapes


def test_close_pairs_are_those_of_all_pairwise_distances(rng):
    from mdlshapemodel.prepare.duplicates import close_pairs

    rows = rng.normal(size=(400, 30))
    rows[5] = rows[300] + 0.01
    rows[6] = rows[5] + 0.02
    brute = np.sum((rows[:, None] - rows[None]) ** 2, axis=2)
    fourth, fifth = np.sort(brute[np.triu_indices(400, 1)])[3:5]
    for radius, pairs in ((0.06, 1), (0.12, 2), (0.2, 3), (np.sqrt((fourth + fifth) / 2), 4)):
        expected = np.argwhere(np.triu(brute < radius ** 2, k=1))
        assert len(expected) == pairs
        np.testing.assert_array_equal(close_pairs(rows, radius), expected)
