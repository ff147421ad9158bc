"""Tests of the area-weighted point distribution model (METHOD.md section 1)."""

import numpy as np
import pytest

from mdlshapemodel.model import ShapeModel


def random_population(rng, n_s=8, n_p=30):
    shapes = rng.normal(size=(1, n_p, 3)) * 5 + rng.normal(size=(n_s, n_p, 3))
    weights = rng.uniform(0.2, 2.0, size=n_p)
    return shapes, weights / weights.sum()


def weighted_inner(a, b, weights):
    """sum_k w_k a_k . b_k of two (n_p, 3) arrays."""
    return float(np.sum(weights[:, None] * a * b))


def test_mean_and_mode_count(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    np.testing.assert_allclose(model.mean, shapes.mean(axis=0))
    assert model.n_modes == len(shapes) - 1
    assert model.modes.shape == (len(shapes) - 1,) + shapes.shape[1:]
    assert model.scores.shape == (len(shapes), len(shapes) - 1)
    assert model.part_sizes == [shapes.shape[1]]
    assert model.names == [f"case_{i}" for i in range(len(shapes))]


def test_modes_are_orthonormal_in_the_weighted_inner_product(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    gram = np.array([[weighted_inner(a, b, weights) for b in model.modes] for a in model.modes])
    np.testing.assert_allclose(gram, np.eye(model.n_modes), atol=1e-10)
    # ... and not in the plain Euclidean one (the weights matter)
    plain = np.einsum("mkd,nkd->mn", model.modes, model.modes)
    assert not np.allclose(plain, np.eye(model.n_modes), atol=1e-3)


def test_variances_are_eigenvalues_of_the_centred_weighted_gram(rng):
    shapes, weights = random_population(rng)
    n_s = len(shapes)
    model = ShapeModel.from_shapes(shapes, weights)
    centred = shapes - shapes.mean(axis=0)
    gram = np.array([[weighted_inner(a, b, weights) for b in centred] for a in centred])  # D'
    eigenvalues = np.sort(np.linalg.eigvalsh(gram))[::-1] / n_s
    np.testing.assert_allclose(model.variances, eigenvalues[:n_s - 1], rtol=1e-10)
    assert abs(eigenvalues[-1]) < 1e-12 * eigenvalues[0]           # centring removes one
    assert np.all(np.diff(model.variances) <= 0)
    # total variance = mean weighted squared distance to the mean
    total = np.mean([weighted_inner(c, c, weights) for c in centred])
    assert model.variances.sum() == pytest.approx(total, rel=1e-10)


def test_training_scores(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    np.testing.assert_allclose(model.scores.mean(axis=0), 0.0, atol=1e-10)
    covariance = model.scores.T @ model.scores / len(shapes)          # divisor n_s
    np.testing.assert_allclose(covariance, np.diag(model.variances), atol=1e-10)
    for i, shape in enumerate(shapes):
        np.testing.assert_allclose(model.instance(model.scores[i]), shape, atol=1e-10)
        np.testing.assert_allclose(model.project(shape), model.scores[i], atol=1e-10)


def test_project_inverts_instance(rng):
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    b = rng.normal(size=model.n_modes) * np.sqrt(model.variances)
    np.testing.assert_allclose(model.project(model.instance(b)), b, atol=1e-10)
    np.testing.assert_allclose(model.project(model.instance(b[:3]), n_modes=3), b[:3],
                               atol=1e-10)
    np.testing.assert_allclose(model.instance(np.zeros(0)), model.mean)
    # the instance is mean + sum_m b_m mode_m
    expected = model.mean + sum(bm * mode for bm, mode in zip(b, model.modes))
    np.testing.assert_allclose(model.instance(b), expected, atol=1e-12)


def test_projection_is_the_weighted_least_squares_fit(rng):
    """For a shape outside the model, the projected instance minimises the weighted error."""
    shapes, weights = random_population(rng)
    model = ShapeModel.from_shapes(shapes, weights)
    outside = shapes[0] + rng.normal(size=shapes[0].shape)
    b = model.project(outside, n_modes=4)
    design = (model.modes[:4] * np.sqrt(weights)[None, :, None]).reshape(4, -1).T
    rhs = ((outside - model.mean) * np.sqrt(weights)[:, None]).ravel()
    expected, *_ = np.linalg.lstsq(design, rhs, rcond=None)
    np.testing.assert_allclose(b, expected, atol=1e-10)


def test_population_with_two_true_modes(rng):
    n_p = 40
    weights = rng.uniform(0.5, 1.5, size=n_p)
    weights /= weights.sum()
    mean = rng.normal(size=(n_p, 3))
    directions = rng.normal(size=(2, n_p, 3))
    coefficients = rng.normal(size=(12, 2)) * [3.0, 1.0]
    shapes = mean + np.einsum("im,mkd->ikd", coefficients, directions)
    model = ShapeModel.from_shapes(shapes, weights)
    assert model.n_modes == 2
    # the model's modes span the true directions
    for d in directions:
        residual = d - sum(weighted_inner(d, m, weights) * m for m in model.modes)
        assert weighted_inner(residual, residual, weights) < 1e-20 * weighted_inner(d, d, weights)


def test_save_load_round_trip(rng, tmp_path):
    shapes, weights = random_population(rng, n_s=5, n_p=12)
    names = ["left/ünïcode case", "b", "c", "d", "e"]
    triangles = rng.integers(0, 12, size=(20, 3))
    model = ShapeModel.from_shapes(shapes, weights, names=names, triangles=triangles,
                                   part_sizes=[7, 5], delta=0.1, strategy="one-at-a-time")
    path = tmp_path / "model.h5"
    model.save(path)
    loaded = ShapeModel.load(path)
    for key in ("mean", "modes", "variances", "weights", "scores", "triangles"):
        np.testing.assert_array_equal(getattr(loaded, key), getattr(model, key))
    assert loaded.names == names
    assert loaded.part_sizes == [7, 5]
    assert loaded.metadata["delta"] == 0.1
    assert str(loaded.metadata["strategy"]) == "one-at-a-time"
    assert "format" not in loaded.metadata
    np.testing.assert_array_equal(loaded.instance(loaded.scores[2]), model.instance(model.scores[2]))


def test_save_load_without_triangles(rng, tmp_path):
    shapes, weights = random_population(rng, n_s=4, n_p=6)
    model = ShapeModel.from_shapes(shapes, weights)
    path = tmp_path / "plain.h5"
    model.save(path)
    loaded = ShapeModel.load(path)
    assert loaded.triangles is None
    assert loaded.names == model.names
    np.testing.assert_array_equal(loaded.modes, model.modes)
