"""Smooth tangent displacement fields: homeomorphisms of the sphere with many parameters."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.fields import FieldBasis, apply_field, wendland
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.correspondence.warps import FieldWarp
from mdlshapemodel.prepare.sphere import orientation


@pytest.fixture
def grid():
    return sphere_grid(2562)


def random_coefficients(rng, basis, fraction=1.0):
    directions = rng.normal(size=(basis.n_centres, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return directions * basis.max_coefficient() * fraction


def test_wendland_bump():
    d = np.linspace(0, 1.5, 301)
    g = wendland(d)
    assert g[0] == 1.0 and np.all(g[d >= 1.0] == 0.0) and np.all(np.diff(g) <= 1e-15)
    slope = np.max(np.abs(np.diff(g) / np.diff(d)))
    assert slope == pytest.approx(135 / 64, rel=1e-3)


def test_zero_field_is_the_identity(grid):
    points, _ = grid
    basis = FieldBasis.icosphere_level(1, points)
    np.testing.assert_allclose(basis.apply(np.zeros((basis.n_centres, 3))), points, atol=1e-15)


@pytest.mark.parametrize("level", [0, 1, 2])
def test_largest_allowed_fields_never_fold_the_grid(grid, level, rng):
    points, triangles = grid
    basis = FieldBasis.icosphere_level(level, points)
    for _ in range(5):
        moved = basis.apply(random_coefficients(rng, basis))
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
        assert np.all(orientation(moved, triangles) > 0)
        assert np.max(np.linalg.norm(moved - points, axis=1)) > 0.0


def test_the_lipschitz_bound_holds(rng):
    points = rng.normal(size=(3000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    basis = FieldBasis.icosphere_level(1, points)
    v = basis.displacement(random_coefficients(rng, basis))
    i, j = rng.integers(0, len(points), (2, 20000))
    keep = i != j
    ratio = (np.linalg.norm(v[i[keep]] - v[j[keep]], axis=1)
             / np.linalg.norm(points[i[keep]] - points[j[keep]], axis=1))
    assert ratio.max() < 0.5                      # the default safety factor
    assert np.allclose(np.einsum("kd,kd->k", v, points), 0.0, atol=1e-12)   # tangent


def test_coefficient_gradient_matches_finite_differences(grid, rng):
    points, _ = grid
    basis = FieldBasis.icosphere_level(1, points)
    coefficients = random_coefficients(rng, basis, 0.5)
    target = rng.normal(size=points.shape)

    def objective(c):
        return float(np.sum(target * basis.apply(c)) + 0.5 * np.sum(basis.apply(c) ** 3))

    phi = basis.apply(coefficients)
    analytic = basis.coefficient_gradient(coefficients, target + 1.5 * phi ** 2)
    step = 1e-6
    for j, d in [(0, 0), (5, 1), (17, 2), (30, 0)]:
        plus, minus = coefficients.copy(), coefficients.copy()
        plus[j, d] += step
        minus[j, d] -= step
        numeric = (objective(plus) - objective(minus)) / (2 * step)
        assert analytic[j, d] == pytest.approx(numeric, rel=1e-5, abs=1e-7)


@pytest.mark.parametrize("level", [0, 1, 2, 3, 4])
def test_a_field_applied_once_is_the_bases_map_bit_for_bit(grid, level, rng):
    """``apply_field`` (each point's bumps found and summed in one pass, no matrix) gives the
    basis's map to the last bit, at every level (level 3 on the centres' cells, out of order),
    also for points a little off unit length; a ``FieldWarp`` replays with it."""
    points = grid[0] * (1.0 + 1e-9 * rng.normal(size=(len(grid[0]), 1)))
    basis = FieldBasis.icosphere_level(level, points)
    c = random_coefficients(rng, basis)
    phi = apply_field(level, points, c)
    np.testing.assert_array_equal(phi, basis.apply(c))
    np.testing.assert_array_equal(FieldWarp(level, 2.0, c).apply(points), phi)
    wider = FieldBasis.icosphere_level(level, points, 3.0)
    np.testing.assert_array_equal(apply_field(level, points, c, 3.0), wider.apply(c))
