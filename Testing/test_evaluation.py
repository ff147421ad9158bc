"""Tests of compactness, generalization and specificity (paper IV-B, METHOD.md section 6).

The library works in the (n_s - 1)-dimensional model space; the tests recompute everything in full
point space, (n_s, n_p, 3) arrays, with a PCA written here (eigen-decomposition of the Gram matrix).
"""

import numpy as np
import pytest

from mdlshapemodel.evaluation import compactness, evaluate, generalization, specificity


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


def test_specificity_on_a_population_with_known_modes(rng):
    shapes, weights, mean, modes, variances = sign_symmetric_population(rng)
    n_samples, seed, max_modes = 3000, 7, 4
    result = specificity(shapes, weights, max_modes, n_samples, np.random.default_rng(seed))
    # the library draws all standard normals at once, one column per model-space axis (rank 3)
    normal = np.random.default_rng(seed).standard_normal((n_samples, len(modes)))
    squared, distance = brute_force_specificity(shapes, weights, mean, modes, variances, normal,
                                                max_modes)
    for key, values in (("squared", squared), ("distance", distance)):
        expected, se = mean_and_se(values)
        np.testing.assert_allclose(result[key], expected, rtol=1e-8)
        np.testing.assert_allclose(result[key + "_se"], se, rtol=1e-6)
    # beyond the rank of the population, more modes change nothing
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
    from mdlshapemodel.model import ShapeModel

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
    from mdlshapemodel.model import ShapeModel

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
