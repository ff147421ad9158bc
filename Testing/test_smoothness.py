"""The prior on smooth correspondence: the thin-plate bending energy of each example's
displacement from the mean, its incremental updates and its gradient."""

import numpy as np
import pytest

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.correspondence.smoothness import Smoothness, bending_matrix
from mdlshapemodel.correspondence.strategies.fast import FieldRound, gradient_at
from common import central_difference
from synthetic import build_objectives, small_state


def smooth_state(weight: float = 0.5):
    state = small_state()
    state.smoothness = Smoothness(weight, 0.8)
    state.objective = build_objectives(state)[1]
    state.rebuild()
    return state


def test_the_bending_energy_is_zero_for_affine_maps_and_positive_otherwise():
    points = icosphere(2)[0] * [12.0, 7.0, 4.0]
    b = bending_matrix(points)
    np.testing.assert_allclose(b, b.T)
    eigenvalues = np.linalg.eigvalsh(b)
    assert np.sum(np.abs(eigenvalues) < 1e-9 * eigenvalues.max()) == 4     # 1, x, y, z
    assert eigenvalues.min() > -1e-9 * eigenvalues.max()
    bumpy = np.exp(-np.sum((points - points[0]) ** 2, axis=1) / 20.0)[:, None] * [0, 0, 1.0]
    assert np.trace(bumpy.T @ b @ bumpy) > 1e-3
    # the same shape twice the size: the same matrix (scaled by the RMS radius)
    np.testing.assert_allclose(bending_matrix(2.0 * points), b, rtol=1e-8, atol=1e-12)



def test_the_bending_matrix_is_the_block_of_the_inverse_bit_for_bit(rng):
    """B~ is s times the upper-left block of [[K, P], [P^T, 0]]^-1 (symmetrised), K_jk = -|m_j -
    m_k|, P = [1, m], to the last bit of the statement in numpy (the prior, and so F, of a
    build does not depend on how K is filled)."""
    points = icosphere(3)[0] * [30.0, 12.0, 10.0] + rng.normal(size=(642, 3))
    n = len(points)
    system = np.zeros((n + 4, n + 4))
    system[:n, :n] = -np.linalg.norm(points[:, None] - points[None], axis=2)
    system[:n, n] = system[n, :n] = 1.0
    system[:n, n + 1:] = points
    system[n + 1:, :n] = points.T
    radius = np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))
    block = np.linalg.inv(system)[:n, :n] * radius
    np.testing.assert_array_equal(bending_matrix(points), 0.5 * (block + block.T))

def test_the_energy_is_the_direct_sum_and_trials_and_commits_agree_with_it():
    state = smooth_state()
    terms = state.smoothness_terms
    d = state.shapes - state.shapes.mean(axis=0)
    direct = 0.5 * 0.5 / 0.8 ** 2 * sum(np.trace(d[i].T @ terms.matrix @ d[i])
                                        for i in range(state.n_shapes))
    assert state.smoothness_energy() == pytest.approx(direct, rel=1e-10)
    assert state.value() == pytest.approx(state.objective(state.covariance()) + direct, rel=1e-12)
    # a trial of one example, incrementally, against the energy of the trial shapes
    trial = state.shapes[2] + np.random.default_rng(1).normal(0.0, 0.3, state.shapes[2].shape)
    shapes = state.shapes.copy()
    shapes[2] = trial
    with state.trial_shapes(shapes):
        from_scratch = state.smoothness_energy()
    assert state.smoothness_energy(2, trial) == pytest.approx(from_scratch, rel=1e-10)
    # committing a change updates the kept B~ D incrementally, as a refresh computes it
    example = state.examples[2]
    example.parts[0].points = example.parts[0].points + 0.2
    state.commit_shape(2)
    kept = state.smoothness_energy(), state.bent.copy()
    state.refresh()
    assert kept[0] == pytest.approx(state.smoothness_energy(), rel=1e-10)
    np.testing.assert_allclose(kept[1], state.bent, atol=1e-10)


def test_the_gradients_with_the_prior_match_finite_differences():
    state = smooth_state()
    round_ = FieldRound(state, [0, 2, 4], level=1, support=2.0)
    rng = np.random.default_rng(2)
    x = rng.uniform(-0.3, 0.3, round_.size) * np.where(np.isfinite(round_.limit), round_.limit,
                                                       0.05)

    def value(x):
        trial = round_.trial(x)
        return gradient_at(state, trial.shapes)[0]

    trial = round_.trial(x)
    analytic = round_.gradient(trial, gradient_at(state, trial.shapes)[1])
    for k in np.concatenate([rng.choice(round_.size, 10, replace=False),
                             round_.pose_index.ravel()]):
        assert analytic[k] == pytest.approx(central_difference(value, x, k), rel=2e-5, abs=1e-6)
    # one example's gradient, with its shape replaced
    shape = state.shapes[1] + 0.1
    value_i, gradient_i = state.example_gradient(1, shape)
    assert value_i == pytest.approx(state.value(1, shape), rel=1e-12)
    flat = shape.ravel()
    for k in rng.choice(flat.size, 6, replace=False):
        def along(v, k=k):
            moved = flat.copy()
            moved[k] = v[0]
            return state.value(1, moved.reshape(shape.shape))
        numeric = central_difference(along, np.array([flat[k]]), 0)
        assert gradient_i.ravel()[k] == pytest.approx(numeric, rel=1e-4, abs=1e-6)


def test_the_smoothness_option_is_checked():
    assert BuildConfig(smoothness=0.1).validate().smoothness == 0.1
    with pytest.raises(Exception, match="smoothness"):
        BuildConfig(smoothness=-1.0).validate()
