"""One decomposition of the aligned shapes for a model and its evaluation
(model.space.principal_axes, ShapeModel.from_axes, evaluate's ``axes``), and the jackknife's
subspaces (model.space.subspace_coordinates)."""

import numpy as np
import pytest

from mdlshapemodel.errors import ArgumentError
from mdlshapemodel.model.evaluation import evaluate
from mdlshapemodel.model.shape_model import NEGLIGIBLE_VARIANCE, ShapeModel
from mdlshapemodel.model.space import (ROUNDING_VARIANCE, model_space, principal_axes,
                                       subspace_coordinates)


def population(rng, n_s=12, n_p=20, duplicate=True):
    """Shapes with a few strong modes and, with ``duplicate``, a case that nearly repeats
    another: a direction the model space keeps and the model leaves out."""
    base = rng.normal(size=(n_p, 3)) * 4
    modes = rng.normal(size=(3, n_p, 3)) * np.array([3.0, 1.5, 0.7])[:, None, None]
    shapes = (base + np.einsum("sm,mpd->spd", rng.normal(size=(n_s, 3)), modes)
              + rng.normal(size=(n_s, n_p, 3)) * 0.3)
    if duplicate:
        shapes[1] = shapes[0] + rng.normal(size=(n_p, 3)) * 1e-3
    weights = rng.uniform(0.2, 2.0, size=n_p)
    return shapes, weights / weights.sum()


def test_the_model_is_cut_from_the_model_space_of_the_same_decomposition():
    shapes, weights = population(np.random.default_rng(3))
    axes = principal_axes(shapes, weights)
    model = ShapeModel.from_axes(axes, weights)
    alone = ShapeModel.from_shapes(shapes, weights)
    for name in ("mean", "modes", "variances", "scores"):
        np.testing.assert_array_equal(getattr(model, name), getattr(alone, name))
    # the near-duplicate's direction: in the model space (above the rounding share of the
    # largest variance), not in the model (below NEGLIGIBLE_VARIANCE of the total)
    rank = axes.space.coordinates.shape[1]
    assert model.n_modes == rank - 1 == len(shapes) - 2
    assert axes.singular[rank - 1] ** 2 / np.sum(axes.singular ** 2) < NEGLIGIBLE_VARIANCE
    # the model's modes are the leading rows of the map back to the points, not a copy
    assert np.shares_memory(model.modes, axes.space.to_points)
    np.testing.assert_array_equal(model.scores, axes.space.coordinates[:, :model.n_modes])
    np.testing.assert_array_equal(model_space(shapes, weights).coordinates,
                                  axes.space.coordinates)


def test_an_evaluation_from_the_models_decomposition_is_the_same_as_its_own():
    shapes, weights = population(np.random.default_rng(4))
    axes = principal_axes(shapes, weights)
    model = ShapeModel.from_axes(axes, weights)
    settings = dict(max_modes=4, n_samples=300, jackknife=True)
    own = evaluate(shapes, weights, model.variances, rng=np.random.default_rng(0), **settings)
    shared = evaluate(shapes, weights, model.variances, rng=np.random.default_rng(0),
                      axes=axes, **settings)
    assert set(own) == set(shared)
    for key in own:
        if key == "jackknife":
            np.testing.assert_array_equal(own[key].per_case, shared[key].per_case)
            np.testing.assert_array_equal(own[key].left_out, shared[key].left_out)
        else:
            assert own[key] == shared[key], key


def test_an_evaluation_without_a_model_has_the_compactness_of_the_shapes_model():
    """A baseline's evaluation builds no model: its variances are the model's rule applied to
    the singular values its measures decompose the shapes for (not the model space's modes,
    which hold the near-duplicate's direction too)."""
    shapes, weights = population(np.random.default_rng(5))
    model = ShapeModel.from_shapes(shapes, weights)
    settings = dict(max_modes=len(shapes) - 1, n_samples=200)
    without = evaluate(shapes, weights, None, rng=np.random.default_rng(0), **settings)
    given = evaluate(shapes, weights, model.variances, rng=np.random.default_rng(0), **settings)
    assert without == given
    # the last M counts no variance beyond the model's modes
    assert without["compactness"][-1] == without["compactness"][-2]


def test_the_decomposition_of_other_shapes_or_a_share_below_rounding_is_refused():
    rng = np.random.default_rng(6)
    shapes, weights = population(rng)
    axes = principal_axes(shapes, weights)
    moved = shapes.copy()
    moved[3] += 0.1
    with pytest.raises(ArgumentError, match="not those of the shapes"):
        evaluate(moved, weights, None, max_modes=2, n_samples=20, axes=axes)
    with pytest.raises(ArgumentError, match="not those of the shapes"):
        evaluate(shapes[:-1], weights, None, max_modes=2, n_samples=20, axes=axes)
    with pytest.raises(ArgumentError, match="below the rounding share"):
        ShapeModel.from_axes(axes, weights, negligible=ROUNDING_VARIANCE / 10)


def test_a_subspace_has_the_coordinates_of_the_model_space_of_its_shapes():
    shapes, weights = population(np.random.default_rng(7), n_s=15, duplicate=False)
    keep = np.delete(np.arange(15), [2, 9])
    turned = subspace_coordinates(model_space(shapes, weights), keep)
    direct = model_space(shapes[keep], weights).coordinates
    assert turned.shape == direct.shape
    # the same up to the sign of each axis
    np.testing.assert_allclose(np.abs(turned), np.abs(direct), atol=1e-10)
