"""Threshold-free cluster enhancement (``analyze --tfce``): the enhancement against its formula
summed plainly over the thresholds, its family-wise test against a plain loop over the same
permutations, its power on a smooth effect, and the command's written numbers recomputed from its
files."""

from __future__ import annotations

import json
from collections import deque

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.analysis import permutation_test
from mdlshapemodel.analysis.glm import drawn_permutations
from mdlshapemodel.analysis.tfce import enhance, signed_enhance, surface_of
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare import io

from common import run_cli
from test_analyze import build, table  # noqa: F401  (the small real build and its table)


def sphere(radius: float = 20.0, theta: int = 24, phi: int = 12) -> tuple:
    """A VTK sphere's points (p, 3) and triangles (m, 3)."""
    source = vtk.vtkSphereSource()
    source.SetRadius(radius)
    source.SetThetaResolution(theta)
    source.SetPhiResolution(phi)
    source.Update()
    return mesh_arrays(source.GetOutput())


def mesh_arrays(polydata) -> tuple:
    points = vtk_to_numpy(polydata.GetPoints().GetData()).astype(np.float64)
    cells = polydata.GetPolys()
    connectivity = vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)
    return points, connectivity.reshape(-1, 3)


def direct_tfce(heights, points, triangles, extent, height, step) -> np.ndarray:
    """sum over h = dh, 2 dh, ... of e(v, h)^E h^H dh, e the area of the connected component of
    {u: heights(u) >= h} holding v (a breadth-first search over the triangles' edges), each point
    carrying a third of the area of its triangles."""
    p = len(points)
    areas = np.zeros(p)
    neighbours = [set() for _ in range(p)]
    for a, b, c in triangles:
        area = 0.5 * np.linalg.norm(np.cross(points[b] - points[a], points[c] - points[a]))
        for u, v in ((a, b), (b, c), (c, a)):
            areas[u] += area / 3.0
            neighbours[u].add(v)
            neighbours[v].add(u)
    found = np.zeros(p)
    k = 1
    while k * step <= heights.max():
        h = k * step
        above = heights >= h
        seen = np.zeros(p, bool)
        for start in np.flatnonzero(above):
            if seen[start]:
                continue
            component, queue = [], deque([start])
            seen[start] = True
            while queue:
                u = queue.popleft()
                component.append(u)
                for v in neighbours[u]:
                    if above[v] and not seen[v]:
                        seen[v] = True
                        queue.append(v)
            found[component] += areas[component].sum() ** extent * h ** height * step
        k += 1
    return found


@pytest.mark.parametrize("extent, height, step", [(1.0, 2.0, 0.1), (0.5, 1.0, 0.25)])
def test_enhancement_is_the_sum_over_thresholds(extent, height, step):
    points, triangles = sphere(theta=10, phi=8)
    rng = np.random.default_rng(3)
    # a smooth field with several peaks and flat stretches, heights off the step grid
    centres = points[rng.choice(len(points), 4, replace=False)]
    heights = sum(rng.uniform(1.0, 3.0) * np.exp(-np.sum((points - c) ** 2, axis=1) / 150.0)
                  for c in centres) + rng.normal(scale=0.3, size=len(points)) - 0.4
    heights += 1e-6                                   # no height exactly on a threshold
    surface = surface_of(points, triangles)
    expected = direct_tfce(heights, points, triangles, extent, height, step)
    found = enhance(heights, surface, extent=extent, height=height, step=step)
    assert np.count_nonzero(expected) > 10
    np.testing.assert_allclose(found, expected, rtol=1e-10, atol=1e-12)
    # several maps at once, each as alone; a signed map's signs each on their own
    twice = enhance(np.stack([heights, heights[::-1]]), surface, extent=extent, height=height,
                    step=step)
    np.testing.assert_allclose(twice[1], direct_tfce(heights[::-1], points, triangles, extent,
                                                     height, step), rtol=1e-10, atol=1e-12)
    signed = signed_enhance(-heights, surface, extent=extent, height=height, step=step)
    below = direct_tfce(-heights, points, triangles, extent, height, step)
    assert np.count_nonzero(below) > 0
    np.testing.assert_allclose(signed, below - expected, rtol=1e-10, atol=1e-12)


def plain_t(residuals: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Student's two-sample t of each column of ``residuals``, group 1 minus group 0."""
    first, second = residuals[labels == 0], residuals[labels == 1]
    pooled = (((first - first.mean(0)) ** 2).sum(0) + ((second - second.mean(0)) ** 2).sum(0)) \
        / (len(residuals) - 2)
    return (second.mean(0) - first.mean(0)) / np.sqrt(pooled * (1 / len(first)
                                                                + 1 / len(second)))


def test_a_smooth_effect_is_found_by_tfce_where_single_points_are_not():
    # an icosphere of radius 20 mm (642 points about 2.4 mm apart), noise smoothed over 1.5 mm,
    # a Gaussian effect of sigma 8 mm, 1.2 noise SDs at its centre, 10 cases per group
    unit, triangles = icosphere(3)
    points = 20.0 * unit
    surface = surface_of(points, triangles)
    apart = np.linalg.norm(points[:, None] - points[None], axis=2)
    kernel = np.exp(-0.5 * (apart / 1.5) ** 2)
    kernel /= np.sqrt(np.sum(kernel ** 2, axis=1))[:, None]
    rng = np.random.default_rng(1)
    n = 20
    labels = np.repeat([0, 1], n // 2)
    distance = apart[0]
    patch = distance < 10.0
    data = (rng.normal(size=(n, len(points))) @ kernel.T
            + 1.2 * labels[:, None] * np.exp(-0.5 * (distance / 8.0) ** 2))
    found = permutation_test(data, labels[:, None].astype(float), permutations=999, seed=5,
                             surface=surface)
    assert found.tfce_p_fwer[patch].min() <= 0.01 and found.p_fwer[patch].min() > 0.5
    assert np.sum(found.tfce_p_fwer[patch] <= 0.05) >= 10
    assert found.tfce_p_fwer[distance > 25].min() > 0.05
    # the observed map and each permutation's largest enhanced value, from a plain loop over the
    # same permutations: the design's rows permuted against the centred data (Freedman-Lane)
    np.testing.assert_allclose(found.tfce, signed_enhance(found.t, surface), rtol=1e-9)
    residuals = data - data.mean(axis=0)
    maxima = [np.abs(signed_enhance(plain_t(residuals, labels[rows]), surface)).max()
              for chunk in drawn_permutations(n, 999, seed=5) for rows in chunk]
    np.testing.assert_allclose(found.tfce_null, maxima, rtol=1e-8)
    expected = (1 + np.sum(np.array(maxima)[None] >= np.abs(found.tfce)[:, None] * (1 - 1e-10),
                           axis=1)) / 1000
    np.testing.assert_allclose(found.tfce_p_fwer, expected)


def test_one_sided_and_vector_maps_are_enhanced_in_their_direction():
    points, triangles = sphere(theta=24, phi=12)
    surface = surface_of(points, triangles)
    rng = np.random.default_rng(2)
    labels = np.repeat([0.0, 1.0], 8)[:, None]
    near = np.linalg.norm(points - points[0], axis=1) < 10.0
    data = rng.normal(size=(16, len(points))) - 1.5 * labels * near
    inward = permutation_test(data, labels, permutations=199, surface=surface, tail="less")
    outward = permutation_test(data, labels, permutations=199, surface=surface, tail="greater")
    assert np.all(inward.tfce <= 0) and np.all(outward.tfce >= 0)
    np.testing.assert_allclose(inward.tfce, -enhance(-inward.t, surface), rtol=1e-9)
    assert inward.tfce_p_fwer[near].min() < 0.05 < outward.tfce_p_fwer[near].min()
    vector = permutation_test(np.stack([data, rng.normal(size=data.shape)], axis=-1), labels,
                              permutations=199, surface=surface)
    np.testing.assert_allclose(vector.tfce, enhance(np.sqrt(vector.statistic), surface),
                               rtol=1e-9)


@pytest.mark.slow
def test_analyze_tfce_writes_numbers_recomputed_from_its_files(build, table):
    output = build.parent / "tfce"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--variance",
                     "pooled", "--tfce", "-o", output, "--permutations", "199", "-q")
    assert result.returncode == 0, result.stderr
    rows = io.read_csv(output / "points.csv")
    columns = {key: np.array([float(row[key]) for row in rows]) for key in ("t", "tfce",
                                                                           "tfce_p_fwer")}
    polydata = io.read_polydata(output / "effects.vtp")
    points, triangles = mesh_arrays(polydata)
    t = vtk_to_numpy(polydata.GetPointData().GetArray("t"))
    stored = vtk_to_numpy(polydata.GetPointData().GetArray("tfce"))
    np.testing.assert_allclose(stored, signed_enhance(t, surface_of(points, triangles)),
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(columns["tfce"], stored, rtol=1e-5)
    np.testing.assert_allclose(columns["t"], t, rtol=1e-5)
    p_fwer = columns["tfce_p_fwer"]
    assert p_fwer.min() >= 1 / 200 and p_fwer.max() <= 1
    # a larger enhanced value never has a larger family-wise p
    order = np.argsort(-np.abs(stored), kind="stable")
    assert np.all(np.diff(p_fwer[order]) >= -1e-12)
    summary = json.loads((output / "analysis.json").read_text())
    tfce = summary["point_test"]["tfce"]
    assert tfce["enhanced"] == "the signed t" and tfce["height_power"] == 2.0
    assert tfce["significant_points"] == int(np.sum(p_fwer <= 0.05)) > 0
    assert summary["settings"]["tfce"] is True
    page = (output / "analysis.html").read_text()
    assert "-log10 p (FWER, TFCE)" in page and "threshold-free cluster enhancement" in page
    assert f"{tfce['significant_points']} TFCE, of 162" in result.stdout


@pytest.mark.slow
def test_analyze_tfce_maps_each_effect_column(build, table):
    output = build.parent / "tfce_two"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                     "age", "--test", "group", "--test", "age", "--variance", "pooled",
                     "--tfce", "-o", output, "--permutations", "99", "-q")
    assert result.returncode == 0, result.stderr
    rows = io.read_csv(output / "points.csv")
    summary = json.loads((output / "analysis.json").read_text())
    polydata = io.read_polydata(output / "effects.vtp")
    surface = surface_of(*mesh_arrays(polydata))
    for found in summary["effect_tests"]:
        name = found["name"]
        t = np.array([float(row[f"t_{name}"]) for row in rows])
        written = np.array([float(row[f"tfce_{name}"]) for row in rows])
        stored = vtk_to_numpy(polydata.GetPointData().GetArray(f"t_{name}"))
        enhanced = vtk_to_numpy(polydata.GetPointData().GetArray(f"tfce_{name}"))
        np.testing.assert_allclose(t, stored, rtol=1e-5)
        np.testing.assert_allclose(enhanced, signed_enhance(stored, surface), rtol=1e-9,
                                   atol=1e-12)
        np.testing.assert_allclose(written, enhanced, rtol=1e-5)
        p_fwer = np.array([float(row[f"tfce_p_fwer_{name}"]) for row in rows])
        assert found["tfce"]["significant_points"] == int(np.sum(p_fwer <= 0.05))
    # the joint test of two columns: the square root of its F enhanced
    arrays = polydata.GetPointData()
    statistic = vtk_to_numpy(arrays.GetArray("statistic"))
    np.testing.assert_allclose(vtk_to_numpy(arrays.GetArray("tfce")),
                               enhance(np.sqrt(statistic), surface), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose([float(row["tfce"]) for row in rows],
                               vtk_to_numpy(arrays.GetArray("tfce")), rtol=1e-5)
    assert summary["point_test"]["tfce"]["enhanced"] == "the square root of the F"
