"""The spherical conformal map (prepare/conformal.py): harmonic map onto the plane, rescaled,
inverse stereographic projection."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare.conformal import cotangents, spherical_conformal_map
from mdlshapemodel.prepare.sphere import check_bijective


def corner_angles(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))

    def angle(p, q, r):
        u, w = q - p, r - p
        cosine = np.sum(u * w, axis=1) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1)
        return np.arccos(np.clip(cosine, -1, 1))

    return np.stack([angle(a, b, c), angle(b, c, a), angle(c, a, b)], axis=1)


def test_cotangents_of_known_triangles():
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, np.sqrt(3) / 2, 0]])
    cot = cotangents(points, np.array([[0, 1, 2], [0, 1, 3]]))
    np.testing.assert_allclose(cot[0], [0.0, 1.0, 1.0], atol=1e-12)          # right isosceles
    np.testing.assert_allclose(cot[1], [1 / np.sqrt(3)] * 3, atol=1e-12)     # equilateral


def test_the_map_of_a_sphere_keeps_its_angles():
    # the unit sphere's conformal map is a Moebius transformation of itself: the triangles keep
    # their angles, up to the discretisation (worst next to the pinned triangle)
    points, faces = icosphere(4)
    sphere = spherical_conformal_map(points, faces)
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.0, atol=1e-12)
    assert check_bijective(sphere, faces) == 0
    difference = np.abs(corner_angles(sphere, faces) - corner_angles(points, faces))
    assert np.median(difference) < 0.05 and np.percentile(difference, 99) < 0.4
    # while the areas change (it is not the identity)
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    assert area.max() / area.min() > 2


def test_the_map_is_conformal_on_an_ellipsoid_with_a_bump(bump_surface, bump_map):
    vertices, faces = bump_surface
    sphere = spherical_conformal_map(vertices, faces)
    assert check_bijective(sphere, faces) == 0
    # conformal: chord triangles keep the surface triangles' angles (to the discretisation), far
    # better than the final map, which trades angles for areas
    difference = np.abs(corner_angles(sphere, faces) - corner_angles(vertices, faces))
    final = np.abs(corner_angles(bump_map.sphere, faces) - corner_angles(vertices, faces))
    assert np.median(difference) < 0.1 and np.median(difference) < 0.5 * np.median(final)
    # the cotangents given or computed, the same map
    np.testing.assert_array_equal(spherical_conformal_map(vertices, faces,
                                                          cotangents(vertices, faces)), sphere)


def test_a_map_that_cannot_be_computed_is_none():
    points, faces = icosphere(2)
    collapsed = np.zeros_like(points)             # no triangle has an area
    assert spherical_conformal_map(collapsed, faces) is None


@pytest.mark.parametrize("stretch", [2.0, 5.0])
def test_elongated_surfaces_crowd_the_ends(stretch):
    # conformal maps crush elongated ends exponentially: the reason for the distortion
    # minimisation (and, beyond double precision, the multilevel map)
    points, faces = icosphere(4)
    sphere = spherical_conformal_map(points * [stretch, 1.0, 1.0], faces)
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    assert area.max() / area.min() > stretch ** 2


def test_the_cotangent_laplacian_is_symmetric_with_zero_row_sums(bump_surface):
    from mdlshapemodel.prepare.conformal import cotangent_laplacian, diagonal_positions

    vertices, faces = bump_surface
    laplacian = cotangent_laplacian(faces, cotangents(vertices, faces), len(vertices))
    dense = laplacian.toarray()
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    np.testing.assert_allclose(dense.sum(axis=1), 0.0, atol=1e-10)
    assert np.linalg.eigvalsh(dense)[0] > -1e-9                       # positive semi-definite
    np.testing.assert_array_equal(laplacian.data[diagonal_positions(laplacian)],
                                  np.diag(dense))
    # x^T L x is the Dirichlet energy: zero for constants, |grad x|^2 area for a linear field
    x = vertices[:, 0]
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    tangential = 1.0 - normal[:, 0] ** 2       # |grad x|^2 on each triangle's plane
    assert x @ (laplacian @ x) == pytest.approx(np.sum(area * tangential), rel=1e-9)
