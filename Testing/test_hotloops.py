"""The compiled loops against plain numpy statements of the same arithmetic."""

import numpy as np
import pytest

from mdlshapemodel.correspondence import hotloops
from mdlshapemodel.correspondence.fields import FieldBasis, wendland
from mdlshapemodel.geometry import Pose, rotation_from_vector
from mdlshapemodel.correspondence.sampling import SphereLocator, icosphere


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
    hotloops.walk(locator.sphere, locator.faces, locator.neighbours, points, hint, 6, -1e-12,
                  face, coords, found)
    # some random starts are too far for 6 steps, some are close enough
    assert 0 < found.sum() < len(points)
    lam = np.einsum("nij,nj->ni", locator.inverses(face[found]), points[found])
    assert np.all(lam >= -1e-12)
    np.testing.assert_allclose(coords[found], lam / lam.sum(axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(coords[found].sum(axis=1), 1.0)
    # a missed point is not inside the face the walk stopped at within its budget: with more
    # steps the walk reaches every point
    more = found.copy()
    hotloops.walk(locator.sphere, locator.faces, locator.neighbours, points, hint, 100, -1e-12,
                  face, coords, more)
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


def test_bump_matrix_holds_every_bump_within_reach(rng):
    points, centres = _unit(rng, 300), _unit(rng, 40)
    radius = 0.5
    indptr, indices, data = hotloops.bump_matrix(points, centres, radius)
    dense = np.zeros((300, 40))
    for k in range(300):
        row = indices[indptr[k]:indptr[k + 1]]
        assert np.all(np.diff(row) > 0)                  # sorted, no repeats
        dense[k, row] = data[indptr[k]:indptr[k + 1]]
    distance = np.linalg.norm(points[:, None] - centres[None], axis=2) / radius
    np.testing.assert_allclose(dense, wendland(distance), atol=1e-12)
    assert indptr[-1] == np.count_nonzero(distance < 1.0)


def test_apply_poses_matches_pose_apply(rng):
    shapes = rng.normal(size=(4, 50, 3))
    poses = [Pose(float(rng.uniform(0.5, 2)), rotation_from_vector(rng.normal(size=3)),
                  rng.normal(size=3)) for _ in range(4)]
    result = hotloops.apply_poses(shapes, np.array([p.scale for p in poses]),
                                  np.array([p.rotation for p in poses]),
                                  np.array([p.translation for p in poses]))
    for a, pose in enumerate(poses):
        np.testing.assert_allclose(result[a], pose.apply(shapes[a]), atol=1e-12)


def _field_sample(locator, values, basis, c, hint, steps=8):
    n = len(basis.points)
    out = dict(phi=np.empty((n, 3)), norms=np.empty(n), face=np.full(n, -1),
               sampled=np.empty((n, 3)), jac=np.empty((n, 3, 3)), found=np.empty(n, dtype=bool))
    w = basis.weights
    hotloops.field_sample(w.indptr, w.indices, w.data, basis.points, c, locator.sphere,
                          locator.neighbours, locator.faces, values, hint, steps, out["phi"],
                          out["norms"], out["face"], out["sampled"], out["jac"], out["found"])
    return out


def test_field_sample_is_the_field_map_then_locate_interpolate_and_jacobian(locator, rng):
    """One fused pass equals its parts: the field map, point location, interpolation and dS/du."""
    values = rng.normal(size=(len(locator.sphere), 3))
    points = _unit(rng, 400)
    basis = FieldBasis.icosphere_level(1, points)
    c = 0.8 * basis.max_coefficient() * _unit(rng, basis.n_centres)
    hint, _ = locator.locate(points)                     # where the unmoved points are
    out = _field_sample(locator, values, basis, c, hint)
    assert out["found"].all()
    phi, norms = basis.map(c)
    np.testing.assert_allclose(out["phi"], phi, atol=1e-14)
    np.testing.assert_allclose(out["norms"], norms, atol=1e-14)
    face, coords = locator.locate(phi)
    np.testing.assert_array_equal(out["face"], face)
    np.testing.assert_allclose(out["sampled"], locator.interpolate(values, face, coords),
                               atol=1e-12)
    np.testing.assert_allclose(out["jac"], locator.jacobian(values, face, phi), atol=1e-10)
    # from far hints with a single step most points are not reached, and are reported
    far = _field_sample(locator, values, basis, c, rng.integers(0, len(locator.faces), 400), 1)
    assert 0 < (~far["found"]).sum()
    reached = far["found"]
    np.testing.assert_array_equal(far["face"][reached], face[reached])


def test_field_sample_gradient_chains_pose_surface_and_field(locator, rng):
    """dF/dc for X = s R S(phi(u)) + t: (dS/du)^T s R^T g, then the field's chain rule."""
    values = rng.normal(size=(len(locator.sphere), 3))
    points = _unit(rng, 400)
    basis = FieldBasis.icosphere_level(1, points)
    c = 0.5 * basis.max_coefficient() * _unit(rng, basis.n_centres)
    out = _field_sample(locator, values, basis, c, locator.locate(points)[0])
    scale, rotation = 1.7, rotation_from_vector(np.array([0.3, -0.2, 0.9]))
    g = rng.normal(size=(400, 3))
    w = basis.weights
    result = hotloops.field_sample_gradient(w.indptr, w.indices, w.data, points, out["phi"],
                                            out["norms"], out["jac"], scale, rotation, g,
                                            basis.n_centres)
    du = np.einsum("kde,kd->ke", out["jac"], scale * g @ rotation)
    np.testing.assert_allclose(result, basis.coefficient_gradient(c, du), atol=1e-12)


@pytest.mark.parametrize("level", [3, 4])
def test_bump_matrix_of_many_centres_holds_the_pairs_that_pass_the_dot_product_test(rng, level):
    """With many centres the kernel tests only those of nearby cells: its pairs are exactly
    those whose dot product passes the test, in increasing order, also for points a little off
    unit length and at the support's edge, with the Wendland values."""
    centres, triangles = icosphere(level)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]]])
    radius = 2.0 * float(np.mean(np.linalg.norm(centres[edges[:, 0]] - centres[edges[:, 1]],
                                                 axis=1)))
    points = _unit(rng, 1500) * (1.0 + 1e-9 * rng.normal(size=(1500, 1)))
    # points at the support's edge of centre 0, just inside and just outside
    tangent = np.cross(centres[0], [0.0, 0.0, 1.0])
    tangent /= np.linalg.norm(tangent)
    angle = 2.0 * np.arcsin(radius / 2.0)
    edge = [np.cos(a) * centres[0] + np.sin(a) * tangent for a in angle + np.array([-1e-12, 1e-12])]
    points = np.vstack([points, edge])
    indptr, indices, data = hotloops.bump_matrix(points, centres, radius)
    passes = points @ centres.T > 1.0 - 0.5 * radius * radius
    assert indptr[-1] == np.count_nonzero(passes)
    for k in range(len(points)):
        row = indices[indptr[k]:indptr[k + 1]]
        np.testing.assert_array_equal(row, np.flatnonzero(passes[k]))
        distance = np.linalg.norm(points[k] - centres[row], axis=1) / radius
        np.testing.assert_allclose(data[indptr[k]:indptr[k + 1]], wendland(distance),
                                   rtol=1e-12, atol=1e-15)


def test_bump_matrix_rows_longer_than_its_first_guess(rng):
    """Rows of more bumps than the room first set aside (every centre reaches every point):
    the arrays grow and keep every row whole and in order."""
    points, centres = _unit(rng, 200), _unit(rng, 60)
    indptr, indices, data = hotloops.bump_matrix(points, centres, 2.5)
    assert indptr[-1] == 200 * 60
    for k in range(200):
        np.testing.assert_array_equal(indices[indptr[k]:indptr[k + 1]], np.arange(60))
    distance = np.linalg.norm(points[:, None] - centres[None], axis=2) / 2.5
    np.testing.assert_allclose(data.reshape(200, 60), wendland(distance), atol=1e-12)
