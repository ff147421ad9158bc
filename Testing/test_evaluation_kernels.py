"""The evaluation's compiled loops (model/evaluation_kernels.py) and the search built on them
(surface_measures.MeshSearch), against direct formulas written here: closest points searched from any
guessed triangle equal testing every triangle, bit for bit; the specificity samples' point
distances equal building each sample and measuring it; farthest-point samples and triangle boxes
equal numpy's; the secular equation's roots and the sums in them equal numpy's bisection and
sums, bit for bit."""

import numpy as np
import pytest

from mdlshapemodel.correspondence import hotloops
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.model import surface_measures
from mdlshapemodel.model.evaluation import specificity
from mdlshapemodel.model.space import model_space
from mdlshapemodel.model.surface_measures import MeshSearch
from mdlshapemodel.model.evaluation_kernels import (closest_from, farthest_points, pairwise_sum,
                                                    sample_distances, secular_roots,
                                                    triangle_boxes)
from mdlshapemodel.prepare.nearest import TriangleGrid, closest_on_triangles
from mdlshapemodel.prepare.surface import SurfaceDistance


def every_triangle(points, vertices, faces):
    """(squared distance (k,), squared distance to each triangle (k, m)) by testing them all."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    each = np.stack([closest_on_triangles(points, vertices, faces, np.array([f]))[1]
                     for f in range(len(faces))], axis=1)
    return each.min(axis=1), each


def search_from(points, guess, vertices, faces):
    grid = TriangleGrid(vertices, faces)
    boxes, extent = triangle_boxes(grid.vertices, grid.faces)
    return closest_from(np.ascontiguousarray(points, dtype=np.float64),
                        np.asarray(guess, dtype=np.int64), grid.vertices, grid.faces, boxes,
                        grid.origin, grid.cell, grid.shape, grid.start, grid.triangles, extent)


def ellipsoid_and_points(level, rng):
    vertices, faces = icosphere(level)
    vertices = vertices * [30.0, 12.0, 5.0] + [100.0, -40.0, 7.0]
    near = vertices[rng.integers(0, len(vertices), 300)] + rng.normal(size=(300, 3)) * 0.7
    centre = np.array([100.0, -40.0, 7.0])
    points = np.concatenate([near, vertices[:30], centre + 0.2 * (near[:50] - centre),
                             centre + rng.normal(size=(40, 3)) * 200.0])
    return vertices, faces, points


@pytest.mark.parametrize("level", [1, 3])
def test_closest_from_any_guess_equals_every_triangle(level):
    """An ellipsoid away from the origin; points near it, on it, inside and far outside; guesses
    the nearest triangle, random triangles, and the farthest one: the squared distance is the
    minimum over all triangles exactly, and the triangle returned is at that distance."""
    rng = np.random.default_rng(level)
    vertices, faces, points = ellipsoid_and_points(level, rng)
    expected, each = every_triangle(points, vertices, faces)
    rows = np.arange(len(points))
    for guess in (each.argmin(axis=1), rng.integers(0, len(faces), len(points)),
                  each.argmax(axis=1)):
        squared, face = search_from(points, guess, vertices, faces)
        np.testing.assert_array_equal(squared, expected)
        np.testing.assert_array_equal(each[rows, face], expected)


def test_closest_from_on_flat_and_degenerate_meshes():
    """A mesh with no extent along one axis, and one of zero-area triangles (collinear points):
    the same as testing every triangle, from random guesses."""
    rng = np.random.default_rng(2)
    faces = np.array([[k, k + 1, k + 2] for k in range(27)])
    points = rng.uniform(-5, 15, (200, 3))
    for vertices in (np.c_[rng.uniform(0, 10, (30, 2)), np.zeros(30)],
                     np.c_[np.linspace(0, 9, 30), np.zeros(30), np.zeros(30)]):
        expected, _ = every_triangle(points, vertices, faces)
        squared, _ = search_from(points, rng.integers(0, len(faces), len(points)), vertices,
                                 faces)
        np.testing.assert_array_equal(squared, expected)


@pytest.mark.parametrize("tree_after", [10_000, 50])
def test_mesh_search_follows_a_moving_mesh(rng, monkeypatch, tree_after):
    """A mesh moved a little at a time, each question starting from the last answers, some points
    without a guess (searched on the grid, or from the centroids' tree once enough were): always
    SurfaceDistance's distances, bit for bit."""
    monkeypatch.setattr(surface_measures, "CENTROID_TREE_POINTS", tree_after)
    base, faces = icosphere(2)
    base = base * [20.0, 9.0, 6.0]
    points = base[rng.integers(0, len(base), 200)] + rng.normal(size=(200, 3)) * 0.5
    search = None
    guess = np.full(len(points), -1)
    for step in range(6):
        vertices = base * (1.0 + 0.02 * step) + rng.normal(size=base.shape) * 0.05
        if search is None:
            search = MeshSearch(vertices, faces)
        else:
            search.move(vertices)
        unknown = rng.random(len(points)) < 0.3
        guess[unknown] = -1
        squared, guess = search.squared(points, guess)
        reference = SurfaceDistance(vertices, faces)
        np.testing.assert_array_equal(np.sqrt(squared), reference(points))
        np.testing.assert_array_equal(squared, every_triangle(points, vertices, faces)[0])
    with pytest.raises(ValueError):
        MeshSearch(base, np.zeros((0, 3), dtype=int))


def test_sample_distances_equal_building_each_sample(rng):
    """Each sample's points built from its scores and measured against the training shape chosen
    for each number of modes (kept modes 1, 2, 2, 4: a repeated column is the same samples)."""
    n_p, rank, n_s, k = 40, 5, 6, 30
    scores = rng.normal(size=(k, rank))
    to_points = rng.normal(size=(rank, 3 * n_p))
    train_points = rng.normal(size=(n_s, 3 * n_p)) * 2.0
    weights = rng.uniform(0.5, 2.0, n_p)
    kept = np.array([1, 2, 2, 4])
    nearest = rng.integers(0, n_s, (k, len(kept)))
    out = np.zeros((k, len(kept)))
    sample_distances(scores, to_points, train_points, nearest, kept, weights, out)
    for c, used in enumerate(kept):
        difference = scores[:, :used] @ to_points[:used] - train_points[nearest[:, c]]
        norms = np.linalg.norm(difference.reshape(k, n_p, 3), axis=2)
        np.testing.assert_allclose(out[:, c], norms @ weights, rtol=1e-13)
    # one mode: the displacements are single products, so the arithmetic is exactly that of
    # weighted_point_norms
    single = scores[:, :1] * to_points[0] - train_points[nearest[:, 0]]
    np.testing.assert_array_equal(out[:, 0], hotloops.weighted_point_norms(single, weights))


def test_specificity_equals_sampling_in_point_space(rng):
    """S(M) and its point-to-point version against samples built point by point from the same
    standard normals in the same basis, each measured against its nearest training shape found
    by comparing it with every one."""
    n_s, n_p, max_modes, n_samples = 9, 25, 4, 400
    shapes = rng.normal(size=(1, n_p, 3)) * 5 + rng.normal(size=(n_s, n_p, 3))
    weights = rng.uniform(0.5, 2.0, n_p)
    weights /= weights.sum()
    result = specificity(shapes, weights, max_modes, n_samples, np.random.default_rng(3))
    space = model_space(shapes, weights)
    sd = np.sqrt(np.sum(space.coordinates ** 2, axis=0) / n_s)
    normal = np.random.default_rng(3).standard_normal((n_samples, space.coordinates.shape[1]))
    mean = shapes.mean(axis=0)
    for m in range(1, max_modes + 1):
        samples = mean + ((normal[:, :m] * sd[:m]) @ space.to_points[:m]).reshape(-1, n_p, 3)
        squared = np.einsum("k,sjkd->sj", weights, (samples[:, None] - shapes[None]) ** 2)
        nearest = np.argmin(squared, axis=1)
        distance = np.linalg.norm(samples - shapes[nearest], axis=2) @ weights
        np.testing.assert_allclose(result["squared"][m - 1], squared.min(axis=1).mean(),
                                   rtol=1e-12)
        np.testing.assert_allclose(result["distance"][m - 1], distance.mean(), rtol=1e-12)
        np.testing.assert_allclose(result["distance_se"][m - 1],
                                   distance.std(ddof=1) / np.sqrt(n_samples - 1), rtol=1e-10)


def test_farthest_points_as_numpy_computes_them(rng):
    """The numpy loop the sampler used: the same indices, ties (a regular grid) to the first."""
    def by_numpy(points, size):
        centres = np.zeros(size, dtype=np.int64)
        distance = np.linalg.norm(points - points[0], axis=1)
        for h in range(1, size):
            centres[h] = np.argmax(distance)
            np.minimum(distance, np.linalg.norm(points - points[centres[h]], axis=1),
                       out=distance)
        return centres

    grid = np.stack(np.meshgrid(*[np.arange(6.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    for points in (rng.normal(size=(500, 3)) * 10, grid):
        np.testing.assert_array_equal(farthest_points(points, 40), by_numpy(points, 40))


def test_triangle_boxes(rng):
    vertices = rng.normal(size=(30, 3)) * 5
    faces = rng.integers(0, 25, (40, 3))           # vertices 25..29 in no triangle
    vertices[27] = 1000.0
    boxes, extent = triangle_boxes(vertices, faces)
    corners = vertices[faces]
    np.testing.assert_array_equal(boxes[:, :3], corners.min(axis=1))
    np.testing.assert_array_equal(boxes[:, 3:], corners.max(axis=1))
    assert extent == np.abs(corners).max()


@pytest.mark.parametrize("n", [1, 7, 8, 9, 81, 128, 129, 300, 1000, 4097])
def test_pairwise_sum_equals_numpy_sum_bit_for_bit(rng, n):
    values = rng.standard_normal(n) * 10.0 ** rng.uniform(-8, 8, n)
    assert pairwise_sum(values) == np.sum(values)


def numpy_bisection(d, v, rho, count):
    """The roots of 1 - rho sum_j v_j^2 / (d_j - x) in (d[k+1], d[k]), all bisected at once with
    numpy until every midpoint is an end of its bracket."""
    low, high = d[1:count + 1].copy(), d[:count].copy()
    for _ in range(200):
        middle = 0.5 * (low + high)
        if np.all((middle <= low) | (middle >= high)):
            break
        value = 1.0 - rho * np.sum(v * v / (d[None, :] - middle[:, None]), axis=1)
        low = np.where(value > 0.0, middle, low)
        high = np.where(value > 0.0, high, middle)
    return 0.5 * (low + high)


@pytest.mark.parametrize("n_s", [6, 40, 82, 200])
def test_secular_roots_equal_numpys_bisection(rng, n_s):
    """The leave-one-out models' eigenvalues (space.leave_one_out): diag(d) - rho x_i x_i^T for
    principal scores x, each case in turn."""
    shapes = rng.standard_normal((n_s, 30, 3)) * rng.uniform(0.1, 3.0, (1, 30, 3))
    coordinates = model_space(shapes, np.full(30, 1.0 / 30)).coordinates
    d = np.sum(coordinates ** 2, axis=0)
    rho = n_s / (n_s - 1.0)
    count = min(10, len(d) - 1)
    for v in coordinates:
        roots = secular_roots(d, v, rho, count)
        np.testing.assert_array_equal(roots, numpy_bisection(d, v, rho, count))
        assert np.all((d[1:count + 1] < roots) & (roots < d[:count]))
