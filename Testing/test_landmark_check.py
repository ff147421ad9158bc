"""The landmark check: landmark transfer through a correspondence (a known answer), the rule that
makes its folds, and builds through the command line whose check is recomputed here, from the
files they write, without the library's transfer code."""

import csv
import json

import numpy as np
import pytest
import vtk

from mdlshapemodel.config import LANDMARK_CHECK_FOLDS, BuildConfig
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.model.landmarks import transfer_errors
from mdlshapemodel.prepare.case import prepare_case
from mdlshapemodel.prepare.landmarks import read_landmarks
from common import run_cli
from files import polydata_triangles, write_label_map
from synthetic import SMALL_SHAPE, small_bump_top, small_mask


def turned(points: np.ndarray, degrees: float) -> np.ndarray:
    """``points`` turned about z."""
    angle = np.radians(degrees)
    c, s = np.cos(angle), np.sin(angle)
    return points @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T


def test_a_correspondence_turned_in_one_case_carries_its_landmarks_off_by_the_turn():
    sphere, faces = icosphere(4)
    radius, degrees = 10.0, 10.0
    surface = (radius * sphere, faces)
    shapes = np.stack([radius * sphere] * 4)
    shapes[0] = turned(radius * sphere, degrees)          # case 0's points: turned about z
    t = (1.0 + np.sqrt(5.0)) / 2.0
    equator = radius * np.array([1.0, t, 0.0]) / np.linalg.norm([1.0, t, 0.0])   # a vertex
    other = radius * np.array([0.0, 1.0, t]) / np.linalg.norm([0.0, 1.0, t])
    marks = np.stack([np.stack([equator, other])] * 4)
    marks[2, 1] = np.nan                                   # case 2 lacks the second label
    errors = transfer_errors(shapes, faces, marks, [surface] * 4)
    turn = 2.0 * radius * np.sin(np.radians(degrees) / 2.0)
    # into case 0 every template carries the landmark to the turned place
    assert errors.median[0, 0] == pytest.approx(turn, abs=0.02)
    np.testing.assert_allclose(errors.single[1:, 0, 0], turn, atol=0.02)
    # into the others, case 0 is one template of three: the median does not follow it
    np.testing.assert_allclose(errors.median[1:, 0], 0.0, atol=1e-9)
    assert (errors.single[0, 1:, 0] > 0.5 * turn).all()
    assert np.isnan(errors.single[np.arange(4), np.arange(4)]).all()
    # a case without a label is neither a target nor a template of it
    assert np.isnan(errors.median[2, 1]) and np.isnan(errors.single[2, :, 1]).all()
    assert np.isnan(errors.single[:, 2, 1]).all() and np.isnan(errors.located[2, 1])
    means, cases = errors.per_label()
    assert cases.tolist() == [4, 3]
    assert means[0] == pytest.approx(errors.median[0, 0] / 4)
    np.testing.assert_allclose(errors.located[[0, 1, 3], 1], 0.0, atol=0.02)
    lean = transfer_errors(shapes, faces, marks, [surface] * 4, single=False)
    assert lean.single is None
    np.testing.assert_array_equal(lean.median, errors.median)


def test_the_folds_leave_each_label_out_once_and_their_number_is_bounded():
    guided = BuildConfig(landmarks="marks")
    assert guided.landmark_folds(["c", "a", "b"]) == [("a",), ("b",), ("c",)]
    many = [f"l{k:02d}" for k in range(2 * LANDMARK_CHECK_FOLDS + 1)]
    folds = guided.landmark_folds(many)
    assert len(folds) == LANDMARK_CHECK_FOLDS
    assert sorted(label for fold in folds for label in fold) == many
    assert {len(fold) for fold in folds} == {2, 3}
    # nothing guided, nothing to leave out: the build itself measures every label
    assert BuildConfig(landmarks="marks", landmark_weight=0).landmark_folds(many) == []
    assert BuildConfig(landmarks="marks", correspondence="cpd").landmark_folds(many) == []


def test_landmarks_only_measured_with_weight_0_and_the_check_needs_landmarks():
    measured = BuildConfig(landmarks="marks", landmark_weight=0).validate()
    assert not measured.landmarks_guide() and measured.checks_landmarks()
    asked = BuildConfig(landmarks="marks", check_landmarks=True).validate()
    assert asked.landmarks_guide() and asked.checks_landmarks()
    assert not BuildConfig(landmarks="marks").checks_landmarks()
    with pytest.raises(ConfigError, match="check_landmarks: needs --landmarks"):
        BuildConfig(check_landmarks=True).validate()
    with pytest.raises(ConfigError, match="landmark_weight"):
        BuildConfig(landmarks="marks", landmark_weight=-1.0).validate()


def test_check_landmarks_without_landmarks_is_refused_before_anything_is_written(tmp_path):
    (tmp_path / "labels").mkdir()
    for k, position in enumerate((-0.5, 0.0, 0.5)):
        write_label_map(tmp_path / "labels" / f"s{k}.nii.gz", small_mask(position))
    result = run_cli("build", tmp_path / "labels", "-o", tmp_path / "out", "--check-landmarks")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "check_landmarks: needs --landmarks" in result.stderr
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- builds through the CLI

POSITIONS = np.linspace(-0.6, 0.6, 5)
LABELS = ("bottom", "end", "tip", "west")
COMMON = ["--points", 162, "--coarse-points", 42, "--workers", 1, "--max-sweeps", 5,
          "--specificity-samples", 200, "--surface-samples", 0, "--evaluation-modes", 2,
          "--baselines", "", "--no-cache", "-q"]


def write_population(folder):
    """Five bumpy ellipsoids (label maps, 1 mm voxels) and a landmark folder: the bump's top
    (tip), the ends of the long axis (end, west) and the bottom; the last case lacks ``end``."""
    (folder / "labels").mkdir(parents=True)
    (folder / "marks").mkdir()
    centre = np.array([(SMALL_SHAPE[2] - 1) / 2.0, (SMALL_SHAPE[1] - 1) / 2.0,
                       (SMALL_SHAPE[0] - 1) / 2.0])
    for k, position in enumerate(POSITIONS):
        write_label_map(folder / "labels" / f"s{k}.nii.gz", small_mask(float(position)))
        points = {"bottom": centre - [0.0, 6.0, 0.0], "end": centre + [10.0, 0.0, 0.0],
                  "tip": small_bump_top(float(position)), "west": centre - [10.0, 0.0, 0.0]}
        if k == len(POSITIONS) - 1:
            del points["end"]
        write_marks(folder / "marks" / f"s{k}.csv", points)
    return folder


def write_marks(path, points: dict):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["label", "x", "y", "z"])
        writer.writerows([label, *(repr(float(v)) for v in point)]
                         for label, point in points.items())


def given_landmarks(data) -> dict:
    """case -> label -> the landmark written for it."""
    found = {}
    for k in range(len(POSITIONS)):
        marks = read_landmarks(data / "marks" / f"s{k}.csv")
        found[f"s{k}"] = dict(zip(marks.labels, marks.points))
    return found


def prepared_surfaces(data) -> dict:
    """case -> the surface the build prepared from its label map (the check projects to it)."""
    config = BuildConfig(points=162)
    return {f"s{k}": prepare_case(data / "labels" / f"s{k}.nii.gz", config).surface()
            for k in range(len(POSITIONS))}


def closest_points(vertices, faces, points) -> np.ndarray:
    """The closest points of a triangle mesh, found by VTK's cell locator."""
    polydata = vtk.vtkPolyData()
    array = vtk.vtkPoints()
    for vertex in vertices:
        array.InsertNextPoint(*vertex)
    cells = vtk.vtkCellArray()
    for face in faces:
        cells.InsertNextCell(3, [int(i) for i in face])
    polydata.SetPoints(array)
    polydata.SetPolys(cells)
    locator = vtk.vtkCellLocator()
    locator.SetDataSet(polydata)
    locator.BuildLocator()
    found = []
    for point in points:
        closest, cell, sub, distance = [0.0, 0.0, 0.0], vtk.reference(0), vtk.reference(0), \
            vtk.reference(0.0)
        locator.FindClosestPoint(list(point), closest, cell, sub, distance)
        found.append((closest, int(cell)))
    return found


def carried_error(correspondence, surfaces: dict, given: dict, label: str) -> tuple[float, int]:
    """The mean over the cases of the median-of-templates error of ``label``: each other case's
    landmark located on its corresponded mesh (a triangle and the weights of its corners), put
    at the same weights of the target's, projected to the target's surface; the coordinate-wise
    median of those, projected again, against the target's landmark. And the number of cases."""
    names = sorted(surfaces)
    meshes = {name: polydata_triangles(correspondence / f"{name}.vtp") for name in names}
    errors = []
    for target in names:
        if label not in given[target]:
            continue
        predictions = []
        for template in names:
            if template == target or label not in given[template]:
                continue
            points, faces = meshes[template]
            (closest, cell), = closest_points(points, faces, [given[template][label]])
            corners = points[faces[cell]]
            weights = np.linalg.lstsq(np.vstack([corners.T, np.ones(3)]),
                                      np.append(closest, 1.0), rcond=None)[0]
            carried = weights @ meshes[target][0][faces[cell]]
            predictions.append(closest_points(*surfaces[target], [carried])[0][0])
        consensus = closest_points(*surfaces[target], [np.median(predictions, axis=0)])[0][0]
        errors.append(np.linalg.norm(np.array(consensus) - given[target][label]))
    return float(np.mean(errors)), len(errors)


@pytest.mark.slow
def test_the_landmark_check_of_a_build_is_that_of_builds_without_each_label(tmp_path):
    data = write_population(tmp_path)
    checked = run_cli("build", data / "labels", "-o", tmp_path / "checked", "--landmarks",
                      data / "marks", "--check-landmarks", *COMMON)
    assert checked.returncode == 0, checked.stderr
    assert "left out of the guides" in checked.stdout
    check = json.loads((tmp_path / "checked" / "metrics.json").read_text())["landmark_check"]
    assert check["guided"] and check["folds"] == [[label] for label in LABELS]
    surfaces = prepared_surfaces(data)
    given = given_landmarks(data)
    for label in LABELS:
        guided, cases = carried_error(tmp_path / "checked" / "correspondence", surfaces, given,
                                      label)
        # (recomputed from the written meshes: equal to a nanometre)
        assert check["per_label"][label]["guided_mm"] == pytest.approx(guided, rel=1e-6,
                                                                        abs=1e-6)
        assert check["per_label"][label]["cases"] == cases == (4 if label == "end" else 5)
    # the build guided by the other labels, as a user would run it: its error of the label
    # left out is the check's
    left_out = "end"
    (tmp_path / "without").mkdir()
    for name, points in given.items():
        write_marks(tmp_path / "without" / f"{name}.csv",
                    {label: point for label, point in points.items() if label != left_out})
    without = run_cli("build", data / "labels", "-o", tmp_path / "without-build", "--landmarks",
                      tmp_path / "without", *COMMON)
    assert without.returncode == 0, without.stderr
    held_out, _ = carried_error(tmp_path / "without-build" / "correspondence", surfaces, given,
                                left_out)
    assert check["per_label"][left_out]["held_out_mm"] == pytest.approx(held_out, rel=1e-6,
                                                                         abs=1e-6)
    assert held_out > check["per_label"][left_out]["guided_mm"]     # guiding, it lands closer
    assert check["mean"]["held_out_mm"] == pytest.approx(
        np.mean([check["per_label"][label]["held_out_mm"] for label in LABELS]))
    report = (tmp_path / "checked" / "report.html").read_text()
    assert "Landmarks left out of the guides" in report
    assert "<th>left out of the guides [mm]</th><th>guiding [mm]</th>" in report
    row = check["per_label"][left_out]
    assert (f"<tr><td>end</td><td>4</td><td>{row['held_out_mm']:.2f}</td>"
            f"<td>{row['guided_mm']:.2f}</td></tr>") in report
    # without --check-landmarks: no check
    metrics = json.loads((tmp_path / "without-build" / "metrics.json").read_text())
    assert metrics["landmark_check"] is None and metrics["landmarks"] is not None
    assert "left out of the guides" not in (tmp_path / "without-build" / "report.html").read_text()
    assert "left out of the guides" not in without.stdout


@pytest.mark.slow
def test_landmarks_with_weight_0_guide_nothing_and_are_measured(tmp_path):
    data = write_population(tmp_path)
    measured = run_cli("build", data / "labels", "-o", tmp_path / "measured", "--landmarks",
                       data / "marks", "--landmark-weight", 0, *COMMON)
    assert measured.returncode == 0, measured.stderr
    plain = run_cli("build", data / "labels", "-o", tmp_path / "plain", *COMMON)
    assert plain.returncode == 0, plain.stderr
    for k in range(len(POSITIONS)):
        np.testing.assert_array_equal(
            polydata_triangles(tmp_path / "measured" / "correspondence" / f"s{k}.vtp")[0],
            polydata_triangles(tmp_path / "plain" / "correspondence" / f"s{k}.vtp")[0])
    assert not (tmp_path / "measured" / "landmarks.csv").exists()
    metrics = json.loads((tmp_path / "measured" / "metrics.json").read_text())
    check = metrics["landmark_check"]
    assert metrics["landmarks"] is None and not check["guided"] and check["folds"] == []
    surfaces = prepared_surfaces(data)
    given = given_landmarks(data)
    for label in LABELS:
        error, cases = carried_error(tmp_path / "plain" / "correspondence", surfaces, given, label)
        assert check["per_label"][label]["held_out_mm"] == pytest.approx(error, rel=1e-6)
        assert check["per_label"][label]["guided_mm"] is None
        assert check["per_label"][label]["cases"] == cases
    report = (tmp_path / "measured" / "report.html").read_text()
    assert "The landmarks did not guide this correspondence" in report
    assert "Landmarks that guided the correspondence" not in report
    assert "(not guiding)" in measured.stdout
    assert ("the landmarks of 5 cases measure the correspondence, they do not guide it"
            in (tmp_path / "measured" / "build.log").read_text())


@pytest.mark.slow
def test_a_landmark_check_cancelled_leaves_the_build_whole_and_says_so(tmp_path):
    from mdlshapemodel import build_model

    data = write_population(tmp_path)
    config = BuildConfig(landmarks=str(data / "marks"), check_landmarks=True, points=162,
                         coarse_points=42, workers=1, max_sweeps=5, specificity_samples=200,
                         surface_samples=0, evaluation_modes=2, baselines=[], cache_dir="")
    checks = []

    def progress(fraction, message):
        if message.startswith("landmark check"):
            checks.append(message)
            return len(checks) < 2               # the second fold is cancelled as it starts
        return None

    result = build_model([data / "labels"], tmp_path / "out", config, progress=progress)
    assert checks == ["landmark check 1 of 4: bottom left out of the guides",
                      "landmark check 2 of 4: end left out of the guides"]
    assert not result.interrupted and result.metrics["landmark_check"] is None
    warning = "the landmark check was interrupted: the outputs have none"
    assert warning in result.metrics["warnings"]
    assert warning in (tmp_path / "out" / "report.html").read_text()
    assert (tmp_path / "out" / "model.h5").exists()


@pytest.mark.slow
def test_a_build_resumed_with_the_check_asked_for_carries_on_and_checks(tmp_path):
    data = write_population(tmp_path)
    options = [o for o in COMMON if o not in ("--max-sweeps", 5)]
    stopped = run_cli("build", data / "labels", "-o", tmp_path / "out", "--landmarks",
                      data / "marks", "--max-sweeps", 1, *options)
    assert stopped.returncode == 0, stopped.stderr
    assert json.loads((tmp_path / "out" / "metrics.json").read_text())["landmark_check"] is None
    resumed = run_cli("build", data / "labels", "-o", tmp_path / "out", "--landmarks",
                      data / "marks", "--max-sweeps", 5, "--check-landmarks", "--resume",
                      *options)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming from" in (tmp_path / "out" / "build.log").read_text()
    check = json.loads((tmp_path / "out" / "metrics.json").read_text())["landmark_check"]
    assert check["folds"] == [[label] for label in LABELS]
