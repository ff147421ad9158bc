"""The compiled loops against plain numpy statements of the same arithmetic."""

import numpy as np
import pytest

from mdlshapemodel import hotloops
from mdlshapemodel.fields import FieldBasis
from mdlshapemodel.sampling import SphereLocator, icosphere


@pytest.fixture
def locator():
    vertices, faces = icosphere(3)
    return SphereLocator(vertices, faces)


def _unit(rng, n):
    points = rng.normal(size=(n, 3))
    return points / np.linalg.norm(points, axis=1, keepdims=True)


def test_walk_finds_the_containing_face_or_reports_a_miss(locator, rng):
    points = _unit(rng, 500)
    hint = rng.integers(0, len(locator.faces), len(points))
    face = np.full(len(points), -1)
    coords = np.zeros((len(points), 3))
    found = np.zeros(len(points), dtype=bool)
    hotloops.walk(locator.inverse, locator.neighbours, points, hint, 6, -1e-12, face, coords, found)
    # some random starts are too far for 6 steps, some are close enough
    assert 0 < found.sum() < len(points)
    lam = np.einsum("nij,nj->ni", locator.inverse[face[found]], points[found])
    assert np.all(lam >= -1e-12)
    np.testing.assert_allclose(coords[found], lam / lam.sum(axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(coords[found].sum(axis=1), 1.0)
    # a missed point is not inside the face the walk stopped at within its budget: with more
    # steps the walk reaches every point
    more = found.copy()
    hotloops.walk(locator.inverse, locator.neighbours, points, hint, 100, -1e-12, face, coords, more)
    assert more.all()


def test_interpolate_matches_einsum(locator, rng):
    values = rng.normal(size=(len(locator.sphere), 4))
    face = rng.integers(0, len(locator.faces), 300)
    coords = rng.random((300, 3))
    expected = np.einsum("ij,ijd->id", coords, values[locator.faces[face]])
    np.testing.assert_allclose(hotloops.interpolate(values, locator.faces, face, coords), expected,
                               atol=1e-12)


def test_field_apply_matches_the_formula(rng):
    points = _unit(rng, 400)
    basis = FieldBasis.icosphere_level(1, points)
    c = 0.5 * basis.max_coefficient() * rng.normal(size=(basis.n_centres, 3))
    moved = points + basis.displacement(c)
    phi, norms = hotloops.field_apply(basis.weights.indptr, basis.weights.indices,
                                      basis.weights.data, points, c)
    np.testing.assert_allclose(norms, np.linalg.norm(moved, axis=1), atol=1e-12)
    np.testing.assert_allclose(phi, moved / norms[:, None], atol=1e-12)
