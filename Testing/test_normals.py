"""The check of corresponded normals (model/normals.py): the direct formulas on small data, a
planted wrong correspondence found and its case named, and what a build writes of it."""

import json

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.model.normals import (OFF_DEGREES, SPREAD_DEGREES, normal_agreement,
                                         outward_normals)
from mdlshapemodel.prepare.io import read_csv


def ellipsoids(n: int, rng, points=None):
    """n ellipsoids of slightly different axes, point k at the same parameter on each."""
    grid, triangles = icosphere(3)
    grid = grid if points is None else points
    shapes = np.stack([grid * (np.array([30.0, 20.0, 12.0]) * (1 + 0.05 * rng.standard_normal(3)))
                       for _ in range(n)])
    return shapes, triangles


def test_the_measures_match_the_direct_formulas():
    rng = np.random.default_rng(0)
    shapes, triangles = ellipsoids(4, rng)
    shapes = shapes + 0.5 * rng.standard_normal(shapes.shape)
    agreement = normal_agreement(shapes, triangles)
    for k in (0, 17, 300, 641):
        normals = []
        for shape in shapes:     # area-weighted normal of the triangles around point k, outward
            around = triangles[np.any(triangles == k, axis=1)]
            total = sum(np.cross(shape[b] - shape[a], shape[c] - shape[a]) for a, b, c in around)
            if np.dot(total, shape[k] - shape.mean(axis=0)) < 0:
                total = -total
            normals.append(total / np.linalg.norm(total))
        normals = np.array(normals)
        mean = normals.mean(axis=0)
        direction = mean / np.linalg.norm(mean)
        angles = [np.degrees(np.arccos(np.clip(n @ direction, -1, 1))) for n in normals]
        assert agreement.resultant[k] == pytest.approx(np.linalg.norm(mean), abs=1e-12)
        assert agreement.spread_degrees[k] == pytest.approx(np.mean(angles), abs=1e-9)
        np.testing.assert_allclose(agreement.angles_degrees[:, k], angles, atol=1e-9)


def turned_on_one_side(shape: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same ellipsoid with its points where x > 0.3 (on the unit parameter sphere) turned by
    180 degrees about the long axis; and which points the turn reverses the normals of (away
    from the axis and from the seam, 0.45 < x < 0.8) and which it leaves alone (x < 0.15: not
    in a triangle with a turned point)."""
    grid, _ = icosphere(3)
    axes = np.abs(shape).max(axis=0)
    turned = grid.copy()
    turned[grid[:, 0] > 0.3] = grid[grid[:, 0] > 0.3] * [1.0, -1.0, -1.0]
    return turned * axes, (grid[:, 0] > 0.45) & (grid[:, 0] < 0.8), grid[:, 0] < 0.15


def test_a_case_whose_correspondence_is_wrong_is_named():
    rng = np.random.default_rng(1)
    shapes, triangles = ellipsoids(6, rng)
    right = normal_agreement(shapes, triangles)
    assert right.spread_degrees.max() < 5.0 and not right.flagged.any()
    assert not right.cases_off().any()
    shapes[4], reversed_, alone = turned_on_one_side(shapes[4])
    wrong = normal_agreement(shapes, triangles)
    off = wrong.cases_off()
    assert off[4] >= np.count_nonzero(reversed_) and np.all(np.delete(off, 4) == 0)
    assert np.all(wrong.angles_degrees[4, reversed_] > OFF_DEGREES)
    assert np.all(wrong.angles_degrees[:, alone] < 5.0)


def test_points_where_the_correspondence_is_wrong_in_several_cases_are_flagged():
    rng = np.random.default_rng(2)
    shapes, triangles = ellipsoids(6, rng)
    for i in (1, 4):
        shapes[i], reversed_, alone = turned_on_one_side(shapes[i])
    agreement = normal_agreement(shapes, triangles)
    assert np.all(agreement.flagged[reversed_]) and agreement.resultant[reversed_].max() < 0.9
    assert not agreement.flagged[alone].any() and np.all(agreement.resultant[alone] > 0.99)


def test_a_part_turned_inside_out_still_gets_outward_normals():
    grid, triangles = icosphere(2)
    normals = outward_normals(grid * 5.0, triangles[:, ::-1])
    np.testing.assert_allclose(np.einsum("ij,ij->i", normals, grid), 1.0, atol=0.02)


def test_a_build_writes_the_check_per_point_per_case_and_in_its_report(tmp_path):
    from mdlshapemodel import BuildConfig, build_model
    from synthetic import small_mask
    import SimpleITK as sitk

    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, 4)):
        paths.append(tmp_path / f"case_{k}.nii.gz")
        sitk.WriteImage(sitk.GetImageFromArray(small_mask(float(position)).astype(np.uint8)),
                        str(paths[-1]))
    config = BuildConfig(points=162, strategy="none", baselines=[], workers=1,
                         evaluation_modes=1, specificity_samples=50, surface_samples=0)
    output = tmp_path / "out"
    build_model(paths, output, config)
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(output / "mean.vtp"))
    reader.Update()
    data = reader.GetOutput().GetPointData()
    spread = vtk_to_numpy(data.GetArray("normal_spread_degrees"))
    resultant = vtk_to_numpy(data.GetArray("normal_agreement"))
    assert spread.shape == resultant.shape == (162,)
    assert np.all((resultant > 0) & (resultant <= 1 + 1e-12)) and np.all(spread >= 0)
    metrics = json.loads((output / "metrics.json").read_text())["normals"]
    assert metrics["spread_degrees_median"] == pytest.approx(np.median(spread), rel=1e-6)
    assert metrics["flagged_points"] == np.count_nonzero(spread > SPREAD_DEGREES)
    cases = read_csv(output / "cases.csv")
    assert all(int(row["normals_off"]) >= 0 for row in cases)
    report = (output / "report.html").read_text()
    assert "Correspondence check: normals" in report
    assert f"{metrics['flagged_points']} of 162 points" in report
