"""Tests of compactness, generalization and specificity (paper IV-B, docs/method.md section 6).

The library works in the (n_s - 1)-dimensional model space; the tests recompute everything in full
point space, (n_s, n_p, 3) arrays, with a PCA written here (eigen-decomposition of the Gram matrix).
The surface-to-surface measures are recomputed with a brute-force point-to-triangle distance (every
point against every triangle) written here; the library uses a VTK cell locator.
"""

import gc
import weakref

import numpy as np
import pytest

from mdlshapemodel.model.evaluation import (SURFACE_GENERALIZATION_POINTS, compactness, evaluate,
                                      generalization, specificity)
from mdlshapemodel.model.surface_measures import (joined_generalization, surface_generalization,
                                                   surface_specificity)
from mdlshapemodel.parallel import process_pool
from mdlshapemodel.prepare.surface import SurfaceDistance, point_surface_distances

from synthetic import radial_population, vertex_areas


def normalised_weights(rng, n_p):
    w = rng.uniform(0.2, 2.0, size=n_p)
    return w / w.sum()


def weighted_sq(a, b, weights):
    """sum_k w_k |a_k - b_k|^2 over the last two axes."""
    return np.sum(weights[:, None] * (a - b) ** 2, axis=(-2, -1))


def weighted_dist(a, b, weights):
    """sum_k w_k |a_k - b_k| over the last two axes."""
    return np.sum(weights * np.linalg.norm(a - b, axis=-1), axis=-1)


def pca(shapes, weights, tolerance=1e-10):
    """Weighted PCA from the eigenvectors of the centred Gram matrix D' (eq. 2, 15).

    Returns mean (n_p, 3), modes (k, n_p, 3) orthonormal in the weighted inner product, and the
    variances (k,) = eigenvalues / n_s, descending.
    """
    n_s = len(shapes)
    mean = shapes.mean(axis=0)
    centred = shapes - mean
    gram = np.einsum("k,ikd,jkd->ij", weights, centred, centred)
    eigenvalues, vectors = np.linalg.eigh(gram)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, vectors = eigenvalues[order], vectors[:, order]
    keep = eigenvalues > tolerance * eigenvalues[0]
    modes = np.einsum("im,ikd->mkd", vectors[:, keep], centred) / np.sqrt(eigenvalues[keep])[:,
                                                                                             None,
                                                                                             None]
    return mean, modes, eigenvalues[keep] / n_s


def project(shape, mean, modes, weights):
    return np.einsum("mkd,kd->m", modes, (shape - mean) * weights[:, None])


def brute_force_generalization(shapes, weights, max_modes):
    n_s = len(shapes)
    squared = np.zeros((n_s, max_modes))
    distance = np.zeros((n_s, max_modes))
    for i in range(n_s):
        mean, modes, _ = pca(np.delete(shapes, i, axis=0), weights)
        b = project(shapes[i], mean, modes, weights)
        for m in range(1, max_modes + 1):
            used = min(m, len(modes))                 # a model has only the modes it has
            rebuilt = mean + np.einsum("m,mkd->kd", b[:used], modes[:used])
            squared[i, m - 1] = weighted_sq(rebuilt, shapes[i], weights)
            distance[i, m - 1] = weighted_dist(rebuilt, shapes[i], weights)
    return squared, distance


def mean_and_se(values):
    n = len(values)
    return values.mean(axis=0), values.std(axis=0, ddof=1) / np.sqrt(n - 1)


def random_population(rng, n_s=7, n_p=25):
    base = rng.normal(size=(n_p, 3)) * 4
    shapes = base + rng.normal(size=(n_s, n_p, 3)) * rng.uniform(0.2, 1.0, size=(1, n_p, 1))
    return shapes, normalised_weights(rng, n_p)


# --- compactness -----------------------------------------------------------------------------------

def test_compactness_by_hand():
    values, errors = compactness([4.0, 2.0, 1.0, 0.5], n_shapes=5, max_modes=6)
    np.testing.assert_allclose(values, [4.0, 6.0, 7.0, 7.5, 7.5, 7.5])
    # SE = sum_{m<=M} sqrt(2/n_s) lambda_m, sqrt(2/5) = 0.6324555320336759
    np.testing.assert_allclose(errors, 0.6324555320336759 * np.array([4.0, 6.0, 7.0, 7.5, 7.5, 7.5]))
    values, errors = compactness(np.array([4.0, 2.0, 1.0, 0.5]), n_shapes=8, max_modes=2)
    np.testing.assert_allclose(values, [4.0, 6.0])
    np.testing.assert_allclose(errors, [2.0, 3.0])                    # sqrt(2/8) = 1/2


# --- generalization --------------------------------------------------------------------------------

def test_generalization_matches_brute_force(rng):
    shapes, weights = random_population(rng)
    n_s = len(shapes)
    result = generalization(shapes, weights, n_s - 2)
    squared, distance = brute_force_generalization(shapes, weights, n_s - 2)
    for key, values in (("squared", squared), ("distance", distance)):
        mean, se = mean_and_se(values)
        np.testing.assert_allclose(result[key], mean, rtol=1e-9)
        np.testing.assert_allclose(result[key + "_se"], se, rtol=1e-7)
    assert np.all(np.diff(result["squared"]) <= 1e-12)        # more modes never reconstruct worse


def test_generalization_of_a_larger_population_matches_brute_force(rng):
    """40 shapes: each left-out model comes from the others' scatter as a rank-one change of the
    whole population's (the secular equation), and equals the model built from the others."""
    shapes, weights = random_population(rng, n_s=40, n_p=30)
    result = generalization(shapes, weights, 10)
    squared, distance = brute_force_generalization(shapes, weights, 10)
    np.testing.assert_allclose(result["squared_per_case"], squared, rtol=1e-8)
    np.testing.assert_allclose(result["distance_per_case"], distance, rtol=1e-8)


def test_generalization_with_repeated_variances_matches_brute_force():
    """Shapes on a circle in two directions (equal variances: the rank-one route cannot tell the
    two apart) and along a third: still the brute force's errors."""
    n_s, n_p = 12, 10
    angles = 2 * np.pi * np.arange(n_s) / n_s
    rng = np.random.default_rng(3)
    base = rng.normal(size=(n_p, 3))
    # orthonormal directions (equal weights): the circle's two variances are equal
    e1, e2, e3 = np.linalg.qr(rng.normal(size=(3 * n_p, 3)))[0].T.reshape(3, n_p, 3)
    shapes = (base + 2.0 * np.cos(angles)[:, None, None] * e1
              + 2.0 * np.sin(angles)[:, None, None] * e2
              + 0.3 * np.cos(2 * angles)[:, None, None] * e3)
    weights = np.full(n_p, 1.0 / n_p)
    result = generalization(shapes, weights, 4)
    squared, distance = brute_force_generalization(shapes, weights, 4)
    np.testing.assert_allclose(result["squared_per_case"], squared, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(result["distance_per_case"], distance, rtol=1e-8, atol=1e-12)


def test_generalization_per_case_errors(rng):
    """Each left-out shape's errors: they are the brute-force ones, and their means are G(M)."""
    shapes, weights = random_population(rng)
    n_s = len(shapes)
    result = generalization(shapes, weights, n_s - 1)
    squared, distance = brute_force_generalization(shapes, weights, n_s - 1)
    assert result["squared_per_case"].shape == result["distance_per_case"].shape == (n_s, n_s - 1)
    np.testing.assert_allclose(result["squared_per_case"], squared, rtol=1e-9)
    np.testing.assert_allclose(result["distance_per_case"], distance, rtol=1e-9)
    np.testing.assert_allclose(result["squared_per_case"].mean(axis=0), result["squared"],
                               rtol=1e-14)
    np.testing.assert_allclose(result["distance_per_case"].mean(axis=0), result["distance"],
                               rtol=1e-14)


def test_generalization_with_all_modes_uses_only_the_left_out_models_modes(rng):
    """A model built without x_i has n_s - 2 modes, so G(n_s - 1) must equal G(n_s - 2).

    The reconstruction of x_i must not use any direction learnt from x_i itself; a zero error at
    M = n_s - 1 means the left-out shape leaked into its own reconstruction.
    """
    shapes, weights = random_population(rng)
    n_s = len(shapes)
    result = generalization(shapes, weights, n_s - 1)
    squared, distance = brute_force_generalization(shapes, weights, n_s - 1)
    assert squared[:, -1] == pytest.approx(squared[:, -2])        # the reference itself
    assert result["squared"][-1] == pytest.approx(squared.mean(axis=0)[-1], rel=1e-9)
    assert result["distance"][-1] == pytest.approx(distance.mean(axis=0)[-1], rel=1e-9)


def test_a_case_and_its_copy_give_the_same_generalization_as_the_models_reconstruction(rng):
    """Two inputs that are one case (a copy, apart from rounding) span a direction of negligible
    variance. It is no mode of the model, nor of a leave-one-out model: G of the aligned shapes
    equals G of the model's reconstruction of them (what ``compare`` reads from model.h5), and
    the brute force's, at every M."""
    from mdlshapemodel.model.shape_model import ShapeModel

    shapes, weights = random_population(rng, n_s=10, n_p=40)
    shapes[7] = shapes[6] + 1e-9 * rng.normal(size=shapes[6].shape)
    model = ShapeModel.from_shapes(shapes, weights)
    assert model.n_modes == 8                   # the copy adds no mode
    alone = generalization(shapes, weights, 8)["squared"]
    rebuilt = generalization(model.instance(model.scores), weights, 8)["squared"]
    squared, _ = brute_force_generalization(shapes, weights, 8)
    np.testing.assert_allclose(alone, squared.mean(axis=0), rtol=1e-7)
    np.testing.assert_allclose(rebuilt, alone, rtol=1e-7)


# --- specificity -----------------------------------------------------------------------------------

def sign_symmetric_population(rng, n_p=30, scales=(3.0, 1.7, 0.8), n_base=2):
    """mean + sum_m s_m c_jm e_m for every sign pattern s and a few coefficient vectors c_j.

    Mode e_m moves only the points of group m (disjoint groups), so the modes are orthonormal in
    the weighted inner product and the covariance is diagonal in their basis: the PCA modes are
    +-e_m with variances mean_j c_jm^2. The population is symmetric under each sign flip, and with
    disjoint supports a flip changes no point-to-point distance: specificity (squared and mm) does
    not depend on the signs a PCA gives its modes.
    """
    weights = normalised_weights(rng, n_p)
    mean = rng.normal(size=(n_p, 3)) * 3
    groups = np.array_split(rng.permutation(n_p), len(scales) + 1)  # the last group never moves
    modes = np.zeros((len(scales), n_p, 3))
    for m, group in enumerate(groups[:-1]):
        modes[m, group] = rng.normal(size=(len(group), 3))
        modes[m] /= np.sqrt(np.sum(weights[:, None] * modes[m] ** 2))
    coefficients = rng.uniform(0.5, 1.5, size=(n_base, len(scales))) * scales
    r = len(scales)
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * r, indexing="ij")).reshape(r, -1).T
    all_coefficients = np.concatenate([signs * c for c in coefficients])
    shapes = mean + np.einsum("im,mkd->ikd", all_coefficients, modes)
    variances = np.mean(coefficients ** 2, axis=0)
    order = np.argsort(variances)[::-1]
    return shapes, weights, mean, modes[order], variances[order]


def brute_force_specificity(shapes, weights, mean, modes, variances, normal, max_modes):
    squared = np.zeros((len(normal), max_modes))
    distance = np.zeros((len(normal), max_modes))
    for m in range(1, max_modes + 1):
        used = min(m, len(modes))
        scores = normal[:, :used] * np.sqrt(variances[:used])
        samples = mean + np.einsum("jm,mkd->jkd", scores, modes[:used])
        d2 = weighted_sq(samples[:, None], shapes[None], weights)           # (N, n_s)
        nearest = np.argmin(d2, axis=1)
        squared[:, m - 1] = d2[np.arange(len(normal)), nearest]
        distance[:, m - 1] = weighted_dist(samples, shapes[nearest], weights)
    return squared, distance


@pytest.mark.parametrize("max_modes", [4, 2])
def test_specificity_on_a_population_with_known_modes(rng, max_modes):
    """Against the direct formula with every sample's normals from one draw; with more modes
    than the rank (4) and fewer (2: each sample's first normals, not others of its row)."""
    shapes, weights, mean, modes, variances = sign_symmetric_population(rng)
    n_samples, seed = 3000, 7
    result = specificity(shapes, weights, max_modes, n_samples, np.random.default_rng(seed))
    # the library's samples are those of one draw of all standard normals, one column per
    # model-space axis (rank 3), though it draws them a block of samples at a time
    normal = np.random.default_rng(seed).standard_normal((n_samples, len(modes)))
    squared, distance = brute_force_specificity(shapes, weights, mean, modes, variances, normal,
                                                max_modes)
    for key, values in (("squared", squared), ("distance", distance)):
        expected, se = mean_and_se(values)
        np.testing.assert_allclose(result[key], expected, rtol=1e-8)
        np.testing.assert_allclose(result[key + "_se"], se, rtol=1e-6)
    if max_modes > len(modes):      # beyond the rank of the population, more modes change nothing
        assert result["squared"][3] == result["squared"][2]


def test_specificity_agrees_statistically_on_a_random_population(rng):
    """A general population: our own PCA (other signs) and other draws give the same S(M) within
    a few standard errors."""
    shapes, weights = random_population(rng, n_s=8, n_p=20)
    n_samples = 4000
    result = specificity(shapes, weights, 5, n_samples, np.random.default_rng(1))
    mean, modes, variances = pca(shapes, weights)
    normal = np.random.default_rng(2).standard_normal((n_samples, len(modes)))
    squared, _ = brute_force_specificity(shapes, weights, mean, modes, variances, normal, 5)
    expected, se = mean_and_se(squared)
    assert np.all(np.abs(result["squared"] - expected)
                  < 5 * np.sqrt(se ** 2 + result["squared_se"] ** 2))


def test_specificity_default_rng_is_reproducible(rng):
    shapes, weights = random_population(rng, n_s=6, n_p=10)
    first = specificity(shapes, weights, 3, n_samples=500)
    second = specificity(shapes, weights, 3, n_samples=500)
    np.testing.assert_array_equal(first["squared"], second["squared"])
    chunked = specificity(shapes, weights, 3, n_samples=500, chunk=64)
    np.testing.assert_allclose(chunked["squared"], first["squared"], rtol=1e-12)


# --- a population with exactly two modes --------------------------------------------------------------

@pytest.fixture
def two_mode_population(rng):
    n_s, n_p = 10, 30
    weights = normalised_weights(rng, n_p)
    mean = rng.normal(size=(n_p, 3)) * 3
    first = rng.normal(size=(n_p, 3))
    second = rng.normal(size=(n_p, 3))
    second -= np.sum(weights[:, None] * first * second) / np.sum(weights[:, None] * first ** 2) * first
    a, b = rng.normal(size=n_s) * 2.0, rng.normal(size=n_s) * 0.7
    shapes = mean + a[:, None, None] * first + b[:, None, None] * second
    return shapes, weights


def test_two_mode_population(two_mode_population):
    from mdlshapemodel.model.shape_model import ShapeModel

    shapes, weights = two_mode_population
    n_s = len(shapes)
    model = ShapeModel.from_shapes(shapes, weights)
    assert model.n_modes == 2
    total = np.mean(weighted_sq(shapes, shapes.mean(axis=0), weights))
    values, _ = compactness(model.variances, n_s, n_s - 1)
    assert values[0] < 0.99 * total
    np.testing.assert_allclose(values[1:], total, rtol=1e-10)          # saturates at M = 2
    g = generalization(shapes, weights, n_s - 2)
    assert g["squared"][0] > 1e-3 * total
    assert np.all(g["squared"][1:] < 1e-20 + 1e-12 * total)
    assert np.all(g["distance"][1:] < 1e-6)
    s = specificity(shapes, weights, 4, n_samples=2000)
    assert s["squared"][2] == s["squared"][1] == s["squared"][3]


def test_evaluate_collects_everything(two_mode_population):
    from mdlshapemodel.model.shape_model import ShapeModel

    shapes, weights = two_mode_population
    n_s = len(shapes)
    variances = ShapeModel.from_shapes(shapes, weights).variances
    report = evaluate(shapes, weights, variances, max_modes=50, n_samples=300,
                      rng=np.random.default_rng(3))
    assert report["modes"] == list(range(1, n_s))                   # at most n_s - 1 modes
    for key in ("compactness", "compactness_se", "generalization", "generalization_se",
                "generalization_mm", "generalization_mm_se", "specificity", "specificity_se",
                "specificity_mm", "specificity_mm_se"):
        assert len(report[key]) == n_s - 1
        assert all(isinstance(v, float) for v in report[key])
    assert report["specificity_samples"] == 300
    np.testing.assert_allclose(report["compactness"], compactness(variances, n_s, n_s - 1)[0])
    g = generalization(shapes, weights, 3)
    np.testing.assert_allclose(report["generalization"][:3], g["squared"], rtol=1e-12)
    s = specificity(shapes, weights, n_s - 1, 300, np.random.default_rng(3))
    np.testing.assert_allclose(report["specificity_mm"], s["distance"], rtol=1e-12)


# --- surface-to-surface measures ---------------------------------------------------------------------
#
# Shapes are radial functions on the sphere, r_i(u) = 1 + sum_j c_ij f_j(u), scaled by fixed semi-axes.
# The corresponded shapes sample them on an icosphere (the correspondence grid); the true surfaces
# sample them on the next finer icosphere, whose first vertices ARE the coarse grid's vertices, so
# every corresponded point lies on its true surface. Points are linear in c: K functions give a
# population with at most K modes.

def brute_point_triangle(points, vertices, faces):
    """Exact distance (n,) from each point to the nearest of all triangles (points x triangles).

    Per triangle: the distance to its plane when the point projects inside, else the distance to
    the nearest of its three edges (segments).
    """
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    result = np.empty(len(points))
    for start in range(0, len(points), 256):
        p = points[start:start + 256, None, :]                         # (n, 1, 3) against (m, 3)
        height = np.sum((p - a) * normal, axis=2)
        foot = p - height[..., None] * normal
        inside = np.ones(height.shape, dtype=bool)
        for u, v in ((a, b), (b, c), (c, a)):        # the foot is left of every edge (seen along n)
            inside &= np.sum(np.cross(v - u, foot - u) * normal, axis=2) >= 0
        edge = np.full(height.shape, np.inf)
        for u, v in ((a, b), (b, c), (c, a)):
            t = np.clip(np.sum((p - u) * (v - u), axis=2) / np.sum((v - u) ** 2, axis=1), 0, 1)
            edge = np.minimum(edge, np.linalg.norm(p - u - t[..., None] * (v - u), axis=2))
        result[start:start + 256] = np.where(inside, np.abs(height), edge).min(axis=1)
    return result


def brute_symmetric(points, triangles, weights, vertices, faces):
    """(plain, area-weighted, (a) weighted, (b) weighted) symmetric surface distance, brute force."""
    to_surface = brute_point_triangle(points, vertices, faces)         # (a) mesh points -> truth
    from_surface = brute_point_triangle(vertices, points, triangles)   # (b) true vertices -> mesh
    areas = vertex_areas(vertices, faces)
    a_weighted = to_surface @ weights / weights.sum()
    b_weighted = from_surface @ areas / areas.sum()
    return np.array([0.5 * (to_surface.mean() + from_surface.mean()),
                     0.5 * (a_weighted + b_weighted), a_weighted, b_weighted])


def test_brute_point_triangle_against_dense_sampling(rng):
    """The reference distance itself: never above the distance to a dense sampling of the triangles,
    and within its spacing."""
    vertices = rng.normal(size=(5, 3)) * 3
    faces = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [0, 4, 1]])
    points = rng.normal(size=(60, 3)) * 4
    exact = brute_point_triangle(points, vertices, faces)
    n = 150
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = i + j <= n
    s, t = i[keep] / n, j[keep] / n
    dense = np.concatenate([vertices[f[0]] + s[:, None] * (vertices[f[1]] - vertices[f[0]])
                            + t[:, None] * (vertices[f[2]] - vertices[f[0]]) for f in faces])
    sampled = np.min(np.linalg.norm(points[:, None] - dense[None], axis=2), axis=1)
    longest = max(np.linalg.norm(vertices[f[k]] - vertices[f[(k + 1) % 3]])
                  for f in faces for k in range(3))
    assert np.all(exact <= sampled + 1e-12)
    assert np.all(sampled - exact <= longest / n)


def test_surface_distance_is_exact(rng):
    """Points near, on, inside and far from a surface: the locator's distance is the brute force's."""
    shapes, triangles, _, surfaces = radial_population(rng, 2, 3)
    vertices, faces = surfaces[0]
    near = shapes[1] + rng.normal(size=shapes[1].shape) * 0.5
    points = np.concatenate([near, vertices[:20], 0.3 * near[:40], near[:40] * 3.0])
    expected = brute_point_triangle(points, vertices, faces)
    distance = SurfaceDistance(vertices, faces)
    np.testing.assert_allclose(distance(points), expected, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(distance(points[:7]), expected[:7], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(point_surface_distances(points, vertices, faces), expected,
                               rtol=1e-10, atol=1e-10)
    assert np.all(distance(vertices) < 1e-12)
    with pytest.raises(ValueError):
        SurfaceDistance(vertices, np.zeros((0, 3), dtype=int))
    # moved to another shape (same faces): the locator follows
    moved = surfaces[1][0] * 1.3 + 2.0
    distance.move(moved)
    np.testing.assert_allclose(distance(points), brute_point_triangle(points, moved, faces),
                               rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError):
        distance.move(moved[:-1])


def brute_force_surface_generalization(shapes, triangles, weights, surfaces, max_modes):
    """(n_s, max_modes, 4) values of :func:`brute_symmetric` for each leave-one-out reconstruction."""
    n_s = len(shapes)
    values = np.zeros((n_s, max_modes, 4))
    for i in range(n_s):
        mean, modes, _ = pca(np.delete(shapes, i, axis=0), weights)
        b = project(shapes[i], mean, modes, weights)
        for m in range(1, max_modes + 1):
            used = min(m, len(modes))
            if used < m:                                  # no more modes: the same reconstruction
                values[i, m - 1] = values[i, m - 2]
                continue
            rebuilt = mean + np.einsum("m,mkd->kd", b[:used], modes[:used])
            values[i, m - 1] = brute_symmetric(rebuilt, triangles, weights, *surfaces[i])
    return values


def test_surface_generalization_matches_brute_force(rng):
    shapes, triangles, weights, surfaces = radial_population(rng, 5, 8)
    n_s = len(shapes)
    result = surface_generalization(shapes, weights, triangles, surfaces, n_s - 1)
    expected = brute_force_surface_generalization(shapes, triangles, weights, surfaces, n_s - 1)
    for k, key in enumerate(("distance_per_case", "weighted_per_case", "to_surface_per_case",
                             "from_surface_per_case")):
        np.testing.assert_allclose(result[key], expected[..., k], rtol=1e-9, atol=1e-10)
    for k, key in enumerate(("distance", "weighted")):
        mean, se = mean_and_se(expected[..., k])
        np.testing.assert_allclose(result[key], mean, rtol=1e-9)
        np.testing.assert_allclose(result[key + "_se"], se, rtol=1e-7)
    assert np.all(result["distance"] > 0.01)
    # the last mode repeats: the model without shape i has n_s - 2 modes
    np.testing.assert_array_equal(result["distance_per_case"][:, -1],
                                  result["distance_per_case"][:, -2])


def test_surface_distance_bounded_by_point_distance(rng):
    """Every corresponded point lies on its (finer) true surface, so the distance of a reconstructed
    point to the true surface is at most the distance to its corresponding point: direction (a) of
    the surface measure never exceeds the point-to-point measure, case by case."""
    shapes, triangles, weights, surfaces = radial_population(rng, 7, 8)
    n_s = len(shapes)
    on_surface = [brute_point_triangle(shape, *surface) for shape, surface in zip(shapes, surfaces)]
    assert max(d.max() for d in on_surface) < 1e-12
    surface = surface_generalization(shapes, weights, triangles, surfaces, n_s - 2)
    point = generalization(shapes, weights, n_s - 2)
    assert np.all(surface["to_surface_per_case"] <= point["distance_per_case"] * (1 + 1e-12))
    assert np.all(surface["to_surface_per_case"] < point["distance_per_case"] * 0.99)
    # the finer surfaces differ from the correspondence meshes: even the symmetric distance of a
    # training shape's own mesh to its true surface is not zero
    assert brute_symmetric(shapes[0], triangles, weights, *surfaces[0])[0] > 1e-3


def test_surface_measures_on_a_population_with_two_modes(rng):
    """True surfaces = the corresponded meshes, two modes: with M >= 2 a left-out shape is rebuilt
    exactly (surface distance 0); with M = 1 it is not. Specificity samples do not change beyond
    M = 2, and with uniform weights a sample's surface distance is at most the point-to-point one."""
    shapes, triangles, _, _ = radial_population(rng, 8, 2, coarse=162)
    n_s, n_p = shapes.shape[:2]
    weights = np.full(n_p, 1.0 / n_p)
    surfaces = [(shape, triangles) for shape in shapes]
    g = surface_generalization(shapes, weights, triangles, surfaces, 4)
    g_point = generalization(shapes, weights, 4)
    assert g["distance"][0] > 0.1 * g_point["distance"][0] > 1e-3
    assert g["weighted"][0] > 1e-3
    assert np.all(g["distance"][1:] < 1e-9) and np.all(g["weighted"][1:] < 1e-9)
    s = surface_specificity(shapes, weights, triangles, surfaces, 4, n_samples=40,
                            rng=np.random.default_rng(4), max_points=None)
    assert s["distance"][1] == s["distance"][2] == s["distance"][3]
    assert np.all(s["distance"] > 1e-3)
    # the same samples measured point to point: the nearest shape in model space is among the
    # candidates, and (a) and (b) are each at most the mean distance of corresponding points (the
    # surfaces' vertices are the corresponded points; uniform weights make that mean the mm measure)
    s_point = specificity(shapes, weights, 4, 40, np.random.default_rng(4))
    assert np.all(s["distance"] <= s_point["distance"] * (1 + 1e-12))
    assert np.all(s["distance"] < 0.99 * s_point["distance"])


def brute_force_surface_specificity(shapes, triangles, weights, surfaces, samples, candidates):
    """Per-sample (plain, weighted) distance to the nearest of the ``candidates`` training shapes
    nearest in point space, and that shape's index, for samples (N, n_p, 3)."""
    plain, area = np.zeros(len(samples)), np.zeros(len(samples))
    nearest = np.zeros(len(samples), dtype=int)
    for s, sample in enumerate(samples):
        order = np.argsort(weighted_sq(sample, shapes, weights), kind="stable")[:candidates]
        values = [brute_symmetric(sample, triangles, weights, *surfaces[j]) for j in order]
        best = int(np.argmin([v[0] for v in values]))
        plain[s], area[s], nearest[s] = values[best][0], values[best][1], order[best]
    return plain, area, nearest


@pytest.mark.parametrize("candidates", [2, 5])
def test_surface_specificity_matches_brute_force(rng, candidates):
    """Exact mode (all points) against samples rebuilt here from the same standard normals.

    Our PCA may give a mode the opposite sign, which changes a sample's surface distances: the
    sign of mode 1 is the one that reproduces M = 1, then that of mode 2 the one for M = 2."""
    shapes, triangles, weights, surfaces = radial_population(rng, 5, 2, coarse=42, fine=162)
    n_samples, seed, max_modes = 16, 11, 3
    result = surface_specificity(shapes, weights, triangles, surfaces, max_modes, n_samples,
                                 np.random.default_rng(seed), candidates=candidates,
                                 max_points=None)
    mean, modes, variances = pca(shapes, weights)
    assert len(modes) == 2
    normal = np.random.default_rng(seed).standard_normal((n_samples, 2))
    scores = normal * np.sqrt(variances)
    for m in range(2):
        errors = {}
        for sign in (1.0, -1.0):
            trial = scores.copy()
            trial[:, m] *= sign
            samples = mean + np.einsum("jm,mkd->jkd", trial[:, :m + 1], modes[:m + 1])
            plain, area, nearest = brute_force_surface_specificity(
                shapes, triangles, weights, surfaces, samples, candidates)
            errors[sign] = max(np.abs(result["distance_per_sample"][:, m] - plain).max(),
                               np.abs(result["weighted_per_sample"][:, m] - area).max())
            if errors[sign] < 1e-9:
                break
        assert min(errors.values()) < 1e-9, errors
        scores[:, m] *= min(errors, key=errors.get)
        np.testing.assert_array_equal(result["nearest"][:, m], nearest)
        for key, values in (("distance", plain), ("weighted", area)):
            expected, se = mean_and_se(values)
            np.testing.assert_allclose(result[key][m], expected, rtol=1e-9)
            np.testing.assert_allclose(result[key + "_se"][m], se, rtol=1e-7)
    for key in ("distance_per_sample", "weighted_per_sample", "nearest"):   # only two modes
        np.testing.assert_array_equal(result[key][:, 2], result[key][:, 1])


def test_surface_specificity_subsampling_agrees_with_all_points(rng):
    """With ``max_points`` each distance is a Monte Carlo estimate over random points: on the same
    samples it stays close to the exact one, per sample and on average."""
    shapes, triangles, weights, surfaces = radial_population(rng, 6, 8)
    exact = surface_specificity(shapes, weights, triangles, surfaces, 2, 60,
                                np.random.default_rng(2), candidates=2, max_points=None)
    estimate = surface_specificity(shapes, weights, triangles, surfaces, 2, 60,
                                   np.random.default_rng(2), candidates=2, max_points=48)
    difference = estimate["distance_per_sample"] - exact["distance_per_sample"]
    assert np.all(np.abs(difference.mean(axis=0)) < 0.03 * exact["distance"])
    assert np.all(np.sqrt(np.mean(difference ** 2, axis=0)) < 0.2 * exact["distance"])
    again = surface_specificity(shapes, weights, triangles, surfaces, 2, 60,
                                np.random.default_rng(2), candidates=2, max_points=48)
    np.testing.assert_array_equal(again["distance"], estimate["distance"])


def test_stratified_sampling_is_unbiased(rng):
    """The strata partition the points; one random point per stratum, weighted by the stratum's
    share, estimates the mean over all points without bias, with less noise than a random subset."""
    from mdlshapemodel.model.surface_measures import weighted_means, RandomPoints, StratifiedPoints

    _, _, _, surfaces = radial_population(rng, 1, 4)
    vertices = surfaces[0][0]
    values = np.linalg.norm(vertices - vertices[0], axis=1)             # a smooth field
    weights = rng.uniform(0.5, 2.0, len(vertices))
    strata = StratifiedPoints(vertices, 40)
    assert np.array_equal(np.sort(strata.order), np.arange(len(vertices)))
    assert strata.counts.sum() == len(vertices) and len(strata.counts) == 40
    np.testing.assert_allclose(strata.fraction.sum(), 1.0)
    draws = [weighted_means(values[i], f, weights[i]) for i, f in (strata.draw(rng) for _ in range(4000))]
    plain, weighted = np.array(draws).T
    assert abs(plain.mean() - values.mean()) < 4 * plain.std() / np.sqrt(len(plain))
    assert abs(weighted.mean() - values @ weights / weights.sum()) < 0.01 * values.mean()
    subset = RandomPoints(len(vertices), 40)
    random_plain = [weighted_means(values[i], f, weights[i])[0]
                    for i, f in (subset.draw(rng) for _ in range(4000))]
    assert abs(np.mean(random_plain) - values.mean()) < 4 * np.std(random_plain) / np.sqrt(4000)
    assert plain.std() < 0.5 * np.std(random_plain)


def test_surface_generalization_with_random_subsets(rng):
    """``max_points`` (uniform random subsets, for very large surfaces) estimates the exact values."""
    shapes, triangles, weights, surfaces = radial_population(rng, 6, 8)
    exact = surface_generalization(shapes, weights, triangles, surfaces, 4)
    estimate = surface_generalization(shapes, weights, triangles, surfaces, 4, max_points=100,
                                      rng=np.random.default_rng(1))
    for key in ("distance_per_case", "weighted_per_case"):
        np.testing.assert_allclose(estimate[key], exact[key], rtol=0.2)
    np.testing.assert_allclose(estimate["distance"], exact["distance"], rtol=0.05)


def test_evaluate_with_surfaces(rng):
    shapes, triangles, weights, surfaces = radial_population(rng, 6, 8)
    n_s = len(shapes)
    variances = np.linalg.svd((shapes - shapes.mean(axis=0)).reshape(n_s, -1) *
                              np.repeat(np.sqrt(weights), 3), compute_uv=False)[:n_s - 1] ** 2 / n_s
    plain = evaluate(shapes, weights, variances, 3, 300, np.random.default_rng(5))
    report = evaluate(shapes, weights, variances, 3, 300, np.random.default_rng(5),
                      triangles=triangles, surfaces=surfaces, surface_samples=20)
    for key, value in plain.items():                      # the point measures do not change
        assert report[key] == value
    surface_keys = ("generalization_surface_mm", "generalization_surface_mm_se",
                    "specificity_surface_mm", "specificity_surface_mm_se")
    assert not any(key in plain for key in surface_keys)
    for key in surface_keys:
        assert len(report[key]) == 3 and all(isinstance(v, float) for v in report[key])
    assert report["specificity_surface_samples"] == 20
    assert len(shapes[0]) <= SURFACE_GENERALIZATION_POINTS
    g = surface_generalization(shapes, weights, triangles, surfaces, 3)
    np.testing.assert_allclose(report["generalization_surface_mm"], g["distance"], rtol=1e-12)
    # the surface samples are the first samples of the point measure, from the same generator
    s = surface_specificity(shapes, weights, triangles, surfaces, 3, 20, np.random.default_rng(5))
    np.testing.assert_allclose(report["specificity_surface_mm"], s["distance"], rtol=1e-12)
    np.testing.assert_allclose(report["specificity_surface_mm_se"], s["distance_se"], rtol=1e-12)
    with pytest.raises(ValueError):
        evaluate(shapes, weights, variances, 3, 300, surfaces=surfaces)
    with pytest.raises(ValueError):
        surface_generalization(shapes, weights, triangles, surfaces[:-1], 3)
    # with a process pool doing the surface generalization meanwhile: the same numbers
    with process_pool(2) as pool:
        pooled = evaluate(shapes, weights, variances, 3, 300, np.random.default_rng(5),
                          triangles=triangles, surfaces=surfaces, surface_samples=20, pool=pool)
    assert pooled == report


def test_evaluate_calls_meanwhile_once_with_the_callers_blas_threads(rng):
    """meanwhile (a build writes its files there) runs once, with BLAS on the caller's threads
    (its numbers must not depend on the evaluation's one thread), and changes no measure."""
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas():
        return sorted(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")

    shapes, triangles, weights, surfaces = radial_population(rng, 6, 8)
    arguments = (shapes, weights, np.ones(5), 3, 100, None, triangles, surfaces, 10)
    with threadpool_limits(limits=2, user_api="blas"):
        caller = blas()
        if not caller or max(caller) < 2:
            pytest.skip("BLAS runs on one thread here")
        seen = []
        with process_pool(2) as pool:
            measured = evaluate(*arguments, pool=pool, meanwhile=lambda: seen.append(blas()))
        assert seen == [caller] and blas() == caller
    assert measured == evaluate(*arguments)


def test_surface_generalization_measured_in_runs_and_joined_is_one_run(rng):
    """joined_generalization of runs over consecutive cases: the one run's result, bit for bit
    (each case's distances are exact wherever its searches start)."""
    shapes, triangles, weights, surfaces = radial_population(rng, 7, 8)
    whole = surface_generalization(shapes, weights, triangles, surfaces, 3)
    runs = [np.array([0, 1]), np.array([2, 3, 4]), np.array([5, 6])]
    joined = joined_generalization([surface_generalization(shapes, weights, triangles, surfaces,
                                                           3, cases=run) for run in runs])
    assert joined.keys() == whole.keys()
    for key, value in whole.items():
        np.testing.assert_array_equal(joined[key], value)
    with pytest.raises(ValueError):
        joined_generalization([])


def test_surface_closest_points_lie_on_their_faces(rng):
    """closest(): the point is on the returned triangle, at the returned distance, and far
    points (which need more candidate vertices than the first search) are exact too."""
    shapes, triangles, _, surfaces = radial_population(rng, 2, 3)
    vertices, faces = surfaces[0]
    points = np.concatenate([shapes[1] + rng.normal(size=shapes[1].shape) * 0.5,
                             rng.normal(size=(30, 3)) * 50.0])
    found, distance, holder = SurfaceDistance(vertices, faces).closest(points)
    np.testing.assert_allclose(distance, np.linalg.norm(points - found, axis=1), atol=1e-12)
    np.testing.assert_allclose(distance, brute_point_triangle(points, vertices, faces),
                               rtol=1e-10, atol=1e-10)
    a, b, c = (vertices[faces[holder, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    # on the triangle's plane, and inside it (non-negative barycentric coordinates)
    np.testing.assert_allclose(np.einsum("ij,ij->i", found - a, normal), 0.0, atol=1e-8)
    for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
        assert np.all(np.einsum("ij,ij->i", np.cross(q - p, found - p), normal) >= -1e-8)


def test_surface_specificity_keeps_a_bounded_number_of_surfaces_with_the_same_result(
        rng, monkeypatch):
    """Past SPECIFICITY_SURFACES_KEPT built surfaces the least recently used one goes (and is
    built again when a later sample's candidates meet it): at most that many searches live at
    once beside the samples' own and the one being built, more surfaces fetched, and the same
    numbers as keeping all."""
    from mdlshapemodel.model import surface_measures

    shapes, triangles, weights, surfaces = radial_population(rng, 12, 3, coarse=42, fine=162)

    class Fetched(list):
        def __init__(self, items):
            super().__init__(items)
            self.count = 0

        def __getitem__(self, i):
            self.count += 1
            return super().__getitem__(i)

    live, most = weakref.WeakSet(), [0]

    class CountedSearch(surface_measures.MeshSearch):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            gc.collect()
            live.add(self)
            most[0] = max(most[0], len(live))

    monkeypatch.setattr(surface_measures, "MeshSearch", CountedSearch)
    results, fetched = [], []
    for kept in (None, 2):
        monkeypatch.setattr(surface_measures, "SPECIFICITY_SURFACES_KEPT", kept)
        live.clear()
        most[0] = 0
        wrapped = Fetched(surfaces)
        results.append(surface_specificity(shapes, weights, triangles, wrapped, 3, 30,
                                           np.random.default_rng(7), candidates=3))
        fetched.append((wrapped.count, most[0]))
    (all_kept, most_unbounded), (bounded, most_bounded) = fetched
    assert most_bounded <= 2 + 2 < most_unbounded
    assert bounded > all_kept
    for key in ("distance", "distance_se", "weighted", "weighted_se", "nearest"):
        np.testing.assert_array_equal(results[1][key], results[0][key])


# --- more shapes than coordinates: the axes from the covariance ---------------------------------

def test_principal_axes_past_the_switch_are_the_svds_to_rounding(rng):
    """60 shapes of 6 points (18 coordinates): the axes come from Z^T Z; every singular value,
    and each kept mode's scores and axis (up to its sign), as the SVD of Z gives them."""
    from mdlshapemodel.model.space import axes_route, principal_axes

    n_s, n_p = 60, 6
    weights = normalised_weights(rng, n_p)
    shapes = rng.normal(size=(n_s, n_p, 3)) * np.linspace(3.0, 0.2, 3 * n_p).reshape(n_p, 3)
    assert axes_route(n_s, 3 * n_p) == "covariance" and axes_route(18, 18) == "svd"
    axes = principal_axes(shapes, weights)
    root = np.repeat(np.sqrt(weights), 3)
    z = (shapes - shapes.mean(axis=0)).reshape(n_s, -1) * root
    u, singular, vt = np.linalg.svd(z, full_matrices=False)
    np.testing.assert_allclose(axes.singular, singular, rtol=1e-10)
    coordinates, to_points = axes.space.coordinates, axes.space.to_points
    assert coordinates.shape == (n_s, 3 * n_p)
    signs = np.sign(np.sum(coordinates * u * singular, axis=0))
    np.testing.assert_allclose(coordinates * signs, u * singular, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(to_points * signs[:, None], vt / root, rtol=1e-9, atol=1e-12)


def test_evaluation_past_the_switch_agrees_with_the_svd_route(rng, monkeypatch):
    """Compactness and G of 50 shapes of 5 points through the covariance route equal those
    through the SVD (forced) to rounding. S samples each axis with its sign, which the two
    decompositions choose alike only by chance: on a population symmetric under every sign
    (32 shapes of 4 points) S is the same to rounding too, and on the general one it agrees
    within its standard errors."""
    import mdlshapemodel.model.space as space

    def both(shapes, weights):
        ours = evaluate(shapes, weights, None, max_modes=6, n_samples=2000,
                        rng=np.random.default_rng(3))
        with monkeypatch.context() as patch:
            patch.setattr(space, "axes_route", lambda n_shapes, dimension: "svd")
            theirs = evaluate(shapes, weights, None, max_modes=6, n_samples=2000,
                              rng=np.random.default_rng(3))
        return ours, theirs

    weights = normalised_weights(rng, 5)
    shapes = rng.normal(size=(50, 5, 3)) * np.linspace(2.0, 0.3, 15).reshape(5, 3)
    ours, theirs = both(shapes, weights)
    for name in ("compactness", "generalization", "generalization_mm", "generalization_se"):
        np.testing.assert_allclose(ours[name], theirs[name], rtol=1e-9, err_msg=name)
    gap = np.abs(np.array(ours["specificity"]) - theirs["specificity"])
    se = np.hypot(ours["specificity_se"], theirs["specificity_se"])
    assert np.all(gap < 4 * se)
    symmetric, weights, *_ = sign_symmetric_population(rng, n_p=4, n_base=4)
    assert len(symmetric) == 32
    ours, theirs = both(symmetric, weights)
    for name in ("specificity", "specificity_mm", "generalization"):
        np.testing.assert_allclose(ours[name], theirs[name], rtol=1e-9, atol=1e-12,
                                   err_msg=name)
