"""Closest points on triangle meshes (prepare/nearest.py): the grid search is exact."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare.nearest import TriangleGrid, closest_on_triangles


def brute(points, vertices, faces):
    return closest_on_triangles(np.ascontiguousarray(points, dtype=np.float64),
                                np.ascontiguousarray(vertices, dtype=np.float64),
                                np.ascontiguousarray(faces, dtype=np.int64),
                                np.arange(len(faces)))


def sampled_distance(points, vertices, faces, n=40):
    """Distance to a dense sampling of the triangles (an upper bound, close to exact)."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    s, t = i[keep] / n, j[keep] / n
    dense = np.concatenate([vertices[f[0]] + s[:, None] * (vertices[f[1]] - vertices[f[0]])
                            + t[:, None] * (vertices[f[2]] - vertices[f[0]]) for f in faces])
    return np.min(np.linalg.norm(points[:, None] - dense[None], axis=2), axis=1)


def test_one_triangle_every_region():
    """Near each vertex, each edge and the inside, above and in the plane: the distance is at
    most the dense sampling's and within its resolution; the closest point lies on the triangle."""
    vertices = np.array([[0.0, 0, 0], [4, 0, 0], [1, 3, 0]])
    faces = np.array([[0, 1, 2]])
    rng = np.random.default_rng(1)
    points = rng.uniform(-3, 7, size=(400, 3)) * [1, 1, 0.5]
    found, squared, face = TriangleGrid(vertices, faces).closest(points)
    exact = np.sqrt(squared)
    sampled = sampled_distance(points, vertices, faces)
    assert np.all(exact <= sampled + 1e-12) and np.all(sampled - exact < 0.15)
    np.testing.assert_allclose(exact, np.linalg.norm(points - found, axis=1), atol=1e-12)
    assert np.all(face == 0)
    assert np.all(np.abs(found[:, 2]) < 1e-12)


@pytest.mark.parametrize("level", [1, 3])
def test_grid_search_equals_brute_force(level):
    """An ellipsoid: points near it, on it, inside, and far outside its box; every distance and
    face equals testing all triangles."""
    vertices, faces = icosphere(level)
    vertices = vertices * [30.0, 12.0, 5.0]
    rng = np.random.default_rng(level)
    near = vertices[rng.integers(0, len(vertices), 500)] + rng.normal(size=(500, 3)) * 0.7
    points = np.concatenate([near, vertices[:30], 0.2 * near[:50],
                             rng.normal(size=(40, 3)) * 200.0])
    found, squared, face = TriangleGrid(vertices, faces).closest(points)
    b_found, b_squared, b_face = brute(points, vertices, faces)
    np.testing.assert_allclose(squared, b_squared, rtol=1e-12, atol=1e-20)
    same = face == b_face     # a tie may pick another face, at the same distance
    np.testing.assert_allclose(found[same], b_found[same], atol=1e-12)
    assert np.all(np.sqrt(squared[500:530]) < 1e-12)     # the vertices are on the mesh


def test_flat_and_degenerate_meshes():
    """A mesh with no extent along one axis, and one with zero-area triangles (three points on
    a line): the grid still builds, and the distances are the brute force's."""
    rng = np.random.default_rng(2)
    flat = np.c_[rng.uniform(0, 10, (30, 2)), np.zeros(30)]
    faces = np.array([[k, k + 1, k + 2] for k in range(27)])
    points = rng.uniform(-5, 15, (200, 3))
    for vertices in (flat, np.c_[np.linspace(0, 9, 30), np.zeros(30), np.zeros(30)]):
        _, squared, _ = TriangleGrid(vertices, faces).closest(points)
        np.testing.assert_allclose(squared, brute(points, vertices, faces)[1], rtol=1e-12)
        sampled = sampled_distance(points, vertices, faces, n=20)
        assert np.all(np.sqrt(squared) <= sampled + 1e-12)
        assert np.all(sampled - np.sqrt(squared) < 0.5)


def test_move_rebuilds_the_grid():
    vertices, faces = icosphere(2)
    grid = TriangleGrid(vertices, faces)
    moved = vertices * 3.0 + [50.0, 0, 0]
    grid.move(moved)
    points = moved[:20] * 1.1
    np.testing.assert_allclose(grid.closest(points)[1], brute(points, moved, faces)[1],
                               rtol=1e-12)
