"""2-D models end to end: the real CLI on generated outlines, bad curves among them, parts."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.demo import demo_curve, write_demo_curves
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.folders import load_checkpoint
from mdlshapemodel.prepare.io import read_csv

from common import run_cli
from files import read_polydata

# real builds (the command line or build_model): deselected by -m "not slow"
pytestmark = pytest.mark.slow


cli = run_cli


def polyline(path):
    """(points, the vtkPolyData) of a .vtp polyline."""
    output = read_polydata(path)
    return vtk_to_numpy(output.GetPoints().GetData()), output


def assert_in_order(positions: np.ndarray):
    """Sample parameters that wind once round the circle, strictly increasing: no fold."""
    steps = np.diff(np.concatenate([positions, [positions[0] + 2 * np.pi]]))
    assert np.all(steps > 0) and np.isclose(steps.sum(), 2 * np.pi)


@pytest.fixture(scope="module")
def curve_build(tmp_path_factory):
    """A 2-D build of eight generated outlines and three bad curve files."""
    folder = tmp_path_factory.mktemp("curves")
    inputs = folder / "inputs"
    write_demo_curves(inputs, 8, seed=1)
    rng = np.random.default_rng(4)
    open_curve = demo_curve(6.0, 1.0, rng)[:300]                   # a quarter missing
    np.savetxt(inputs / "open.csv", open_curve, delimiter=",")
    crossing = np.array([[0, 0], [10, 0], [10, 10], [5, -5], [0, 10]], float)
    np.savetxt(inputs / "crossing.csv", np.repeat(crossing, 3, axis=0)
               + np.linspace(0, 1e-3, 15)[:, None], delimiter=",")
    two = np.zeros((40, 60), np.uint8)
    two[5:20, 5:25] = 1
    two[25:35, 30:55] = 1
    sitk.WriteImage(sitk.GetImageFromArray(two), str(inputs / "two_regions.png"))
    output = folder / "model"
    run = cli("build", inputs, "-o", output, "--workers", "1", "--specificity-samples", "500")
    return run, output


def test_a_2d_build_writes_polylines_and_rejects_bad_curves_in_one_line(curve_build):
    run, output = curve_build
    assert run.returncode == 0, run.stderr
    rejected = {row["case"]: row["reason"] for row in read_csv(output / "rejected.csv")}
    assert set(rejected) == {"open", "crossing", "two_regions"}
    assert rejected["open"].startswith("the curve is open")
    assert rejected["crossing"].startswith("the curve crosses itself near (")
    assert rejected["two_regions"].startswith("2 separate regions")
    for name, reason in rejected.items():
        assert "\n" not in reason
        assert f"{name}." in run.stderr and reason in run.stderr
    model = ShapeModel.load(output / "model.h5")
    assert model.triangles.shape == (128, 2) and np.all(model.mean[:, 2] == 0)
    points, mean = polyline(output / "mean.vtp")
    assert mean.GetNumberOfLines() == 128 and mean.GetNumberOfPolys() == 0
    for name in model.names:
        points, data = polyline(output / "correspondence" / f"{name}.vtp")
        assert points.shape == (128, 3) and data.GetNumberOfLines() == 128
    assert "modes of variation" in (output / "report.html").read_text()


def test_the_2d_model_beats_equal_arc_length_and_no_correspondence_folds(curve_build):
    run, output = curve_build
    metrics = json.loads((output / "metrics.json").read_text())
    baseline = metrics["baselines"]["none"]
    for key, modes in (("generalization", 1), ("specificity", 3)):   # 8 cases: G(1) only
        difference = np.array(baseline[key][:modes]) - np.array(metrics[key][:modes])
        se = np.hypot(baseline[key + "_se"][:modes], metrics[key + "_se"][:modes])
        assert np.all(difference > 2 * se), key
    record = load_checkpoint(output / "checkpoint.npz")
    for i in range(len(record["names"])):
        assert_in_order(record[f"positions_{i}_0"])


def test_two_part_curves_from_a_manifest(tmp_path):
    """An inner and an outer outline per case (endocardium and epicardium, say), one file per
    part: a two-part 2-D model with one pose per case."""
    rng = np.random.default_rng(2)
    rows = ["case,part,file"]
    for k in range(6):
        outer = demo_curve(4.0 + 2.0 * k, 1.0, rng)
        inner = 0.6 * demo_curve(2.0 + k, 1.0, rng)
        for name, points in (("inner", inner), ("outer", outer)):
            np.savetxt(tmp_path / f"c{k}_{name}.csv", points, delimiter=",")
            rows.append(f"c{k},{name},c{k}_{name}.csv")
    (tmp_path / "cases.csv").write_text("\n".join(rows) + "\n")
    run = cli("build", "--manifest", tmp_path / "cases.csv", "-o", tmp_path / "model",
              "--points", "64", "--workers", "1", "--specificity-samples", "200")
    assert run.returncode == 0, run.stderr
    model = ShapeModel.load(tmp_path / "model" / "model.h5")
    assert model.part_names == ["inner", "outer"] and model.part_sizes == [64, 64]
    inner, _ = polyline(tmp_path / "model" / "correspondence" / "inner" / "c0.vtp")
    outer, _ = polyline(tmp_path / "model" / "correspondence" / "outer" / "c0.vtp")
    assert inner.shape == outer.shape == (64, 3)
    assert np.ptp(inner[:, 0]) < np.ptp(outer[:, 0])
    record = load_checkpoint(tmp_path / "model" / "checkpoint.npz")
    for j in (0, 1):
        assert_in_order(record[f"positions_0_{j}"])


def test_a_stray_curve_among_surfaces_is_rejected_and_the_rest_go_on(tmp_path):
    from mdlshapemodel import BuildConfig
    from mdlshapemodel.build import one_kind
    from mdlshapemodel.prepare import prepare_case
    from synthetic import small_mask

    paths = []
    for k in range(2):
        paths.append(tmp_path / f"s{k}.nii.gz")
        sitk.WriteImage(sitk.GetImageFromArray(small_mask(0.2 * k).astype(np.uint8)),
                        str(paths[-1]))
    np.savetxt(tmp_path / "outline.csv", demo_curve(5.0, 1.0, np.random.default_rng(0)),
               delimiter=",")
    paths.append(tmp_path / "outline.csv")
    prepared = [prepare_case(path, BuildConfig(points=42)) for path in paths]
    kept, rejected = one_kind(prepared)
    assert [case.name for case in kept] == ["s0", "s1"]
    assert [(r.name, r.reason) for r in rejected] == [
        ("outline", "a 2-D curve, but most inputs are surfaces (a model is of one kind)")]


def test_a_new_outline_is_fitted_to_a_2d_model(curve_build, tmp_path):
    run, output = curve_build
    assert run.returncode == 0, run.stderr
    np.savetxt(tmp_path / "new.csv", demo_curve(9.0, 1.02, np.random.default_rng(9)),
               delimiter=",")
    fitted = tmp_path / "fitted"
    result = cli("fit", output, tmp_path / "new.csv", "-o", fitted, "--max-sweeps", "3")
    assert result.returncode == 0, result.stderr
    summary = json.loads((fitted / "fit.json").read_text())["new"]
    squared = summary["reconstruction_squared_mm2"]
    assert squared[-1] < 0.5 * squared[0]          # the modes explain much of the new outline
    points, data = polyline(fitted / "reconstruction" / "new.vtp")
    assert points.shape == (128, 3) and data.GetNumberOfLines() == 128
    surface = tmp_path / "surface.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.pad(np.ones((4, 5, 6), np.uint8), 1)),
                    str(surface))
    refused = cli("fit", output, surface, "-o", tmp_path / "refused")
    assert refused.returncode == 2
    assert "a 3-D input; the model is of 2-D curves" in refused.stderr


def test_a_2d_model_reads_into_vtk_as_polylines_and_compares(curve_build, tmp_path):
    from mdlshapemodel.vtkmodel import ShapeModelReader, polydata_to_model

    run, output = curve_build
    reader = ShapeModelReader()
    reader.SetFileName(str(output / "model.h5"))
    reader.Update()
    polydata = reader.GetOutput()
    assert polydata.GetNumberOfLines() == 128 and polydata.GetNumberOfPolys() == 0
    model = polydata_to_model(polydata)
    assert model.of_curves and np.array_equal(model.triangles,
                                              ShapeModel.load(output / "model.h5").triangles)
    result = cli("compare", output, output, "-o", tmp_path / "cmp", "--samples", "200",
                 "--modes", "2")
    assert result.returncode == 0, result.stderr
    assert "on 8 shared cases" in result.stdout


def test_a_case_whose_parts_are_a_curve_and_a_surface_is_rejected(tmp_path):
    from mdlshapemodel import BuildConfig
    from mdlshapemodel.prepare import preprocess
    from mdlshapemodel.prepare.parts import read_manifest
    from synthetic import small_mask

    sitk.WriteImage(sitk.GetImageFromArray(small_mask(0.0).astype(np.uint8)),
                    str(tmp_path / "body.nii.gz"))
    np.savetxt(tmp_path / "outline.csv", demo_curve(5.0, 1.0, np.random.default_rng(0)),
               delimiter=",")
    (tmp_path / "cases.csv").write_text("case,part,file\nc,body,body.nii.gz\nc,outline,outline.csv\n")
    config = BuildConfig(points=42, workers=1, cache_dir="")
    prepared, rejected = preprocess(read_manifest(tmp_path / "cases.csv", config), config)
    assert not prepared and len(rejected) == 1
    assert rejected[0].reason == ("part outline is a 2-D curve and part body a surface: the "
                                  "parts of an object are of one kind")
