"""Eq. 14 and its gradient through the 3 n_p x 3 n_p covariance (more shapes than coordinates):
the same objective as through the n_s x n_s Gram matrix, to rounding."""

import sys
import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from mdlshapemodel.build import correspond
from mdlshapemodel.config import BuildConfig, OptimisationSettings
from mdlshapemodel.correspondence.objective import Objective, covariance_route
from mdlshapemodel.geometry import centroid_size
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.correspondence.state import CorrespondenceState, FixedExample
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.initial import initial_state
from mdlshapemodel.prepare.case import PreparedCase, PreparedPart

from synthetic import build_objectives, small_maps, small_state

OBJECTIVES = [
    Objective("fixed", 10.0, delta=0.05),
    Objective("fixed", 10.0, delta=0.05, free_below_delta=False),
    Objective("integrated", 10.0),
    Objective("integrated", 10.0, delta_min=0.01, delta_max=0.3),
]
IDS = ["fixed", "fixed-no-case3", "integrated", "integrated-other"]


def spread_data(rng, n_s, dim):
    """Centred data (n_s, dim) whose modes spread from sigma ~ 5e-3 to ~1.6: every case of F, and
    ranges inside [Delta_min, Delta_max] (the integrated kind's range term)."""
    x = rng.normal(size=(n_s, dim)) * np.logspace(-2.3, 0.2, dim)
    return x - x.mean(axis=0)


@pytest.mark.parametrize("objective", OBJECTIVES, ids=IDS)
@pytest.mark.parametrize("n_s, dim", [(60, 15), (15, 40), (200, 24)])
def test_both_routes_give_the_same_value_and_gradient(rng, objective, n_s, dim):
    """F(A A^T) and 2 (dF/dD') A through the Gram matrix equal F and dF/dA through A^T A, with
    more shapes than coordinates and fewer (D' has n_s - dim more zero eigenvalues, or fewer)."""
    data = spread_data(rng, n_s, dim)
    value, grad_cov = objective.gradient(data @ data.T)
    value_data, grad_data = objective.data_gradient(data)
    assert value_data == pytest.approx(value, rel=1e-13)
    assert objective.from_data(data) == pytest.approx(value, rel=1e-13)
    expected = 2.0 * grad_cov @ data
    np.testing.assert_allclose(grad_data, expected, atol=1e-9 * np.abs(expected).max())
    if objective.kind == "integrated":                 # the range term is exercised
        ranges = np.ptp(data @ np.linalg.svd(data, full_matrices=False)[2].T, axis=0)
        assert np.any((ranges > objective.delta_min) & (ranges < objective.delta_max))


@pytest.mark.parametrize("objective", OBJECTIVES, ids=IDS)
def test_data_gradient_matches_finite_differences(rng, objective):
    data = spread_data(rng, 50, 12)
    _, grad = objective.data_gradient(data)
    step = 1e-6 * np.abs(data).max()
    for _ in range(6):
        direction = rng.normal(size=data.shape)
        direction /= np.linalg.norm(direction)
        numeric = (objective.from_data(data + step * direction)
                   - objective.from_data(data - step * direction)) / (2 * step)
        assert np.sum(grad * direction) == pytest.approx(numeric, rel=1e-5, abs=1e-6)


def whole_products_value(objective, data):
    """F from A^T A and A W each made by one numpy call on one BLAS thread (the integrated kind:
    D''s zero eigenvalues beyond A^T A's cost nothing)."""
    with threadpool_limits(limits=1, user_api="blas"):
        raw, vectors = np.linalg.eigh(data.T @ data)
        coded = data @ vectors[:, ::-1]
    coded[:, raw[::-1] <= 0] = 0.0
    return objective.from_coded(coded)


@pytest.mark.parametrize("threads", [1, 2])
def test_up_to_the_switch_the_products_are_whole_numpy_calls(rng, threads):
    """With as many shapes as coordinates, F is that of the whole products, to the bit."""
    data = spread_data(rng, 520, 520)
    objective = Objective("integrated", 10.0, threads=threads)
    with threadpool_limits(limits=1, user_api="blas"):
        value, _ = objective.data_gradient(data)
        assert objective.from_data(data) == value
    assert value == whole_products_value(objective, data)


def test_past_the_switch_the_result_is_the_same_on_any_number_of_threads(rng):
    """Past the switch (several blocks of rows and of columns) F and dF/dA are the same bits on
    1, 2 and 3 threads, whatever the caller's BLAS threads, and agree with the whole products and
    with the Gram route to rounding."""
    data = spread_data(rng, 521, 520)
    results = []
    for threads, blas in [(1, 1), (2, 1), (3, 1), (1, 2), (2, 2)]:
        objective = Objective("integrated", 10.0, threads=threads)
        with threadpool_limits(limits=blas, user_api="blas"):
            results.append(objective.data_gradient(data) + (objective.from_data(data),))
    value, grad, value_only = results[0]
    assert value_only == value
    for other in results[1:]:
        assert other[0] == value and other[2] == value
        assert np.array_equal(other[1], grad)
    assert value == pytest.approx(whole_products_value(objective, data), rel=1e-12)
    gram_value, grad_cov = objective.gradient(data @ data.T)
    assert value == pytest.approx(gram_value, rel=1e-12)
    expected = 2.0 * grad_cov @ data
    np.testing.assert_allclose(grad, expected, atol=1e-9 * np.abs(expected).max())


def threads_started(run) -> tuple:
    """(the result of ``run()``, the names of the threads it started)."""
    started = []
    previous = threading.gettrace()

    def seen(frame, event, arg):
        """Called at the start of every thread started through ``threading``."""
        started.append(threading.current_thread().name)
        sys.settrace(previous)

    threading.settrace(seen)
    try:
        return run(), started
    finally:
        threading.settrace(previous)


def optimised_past_the_switch(workers: int) -> tuple:
    """A short fast-strategy optimisation of 40 surfaces on 12 points (36 coordinates: past the
    switch) with objectives of ``workers`` threads: (final F, evaluations, names of the threads
    it started, the threads running before it, those running after it)."""
    state = small_state(n=40, points=12)
    assert state.by_covariance
    objectives = build_objectives(state, BuildConfig(workers=workers))
    settings = OptimisationSettings(strategy="fast", max_time=1e6, max_sweeps=2)
    before = set(threading.enumerate())
    final, started = threads_started(
        lambda: optimise(state, objectives, settings, np.random.default_rng(0), Trace()))
    return final, state.evaluations, started, before, set(threading.enumerate())


def test_an_optimisation_keeps_one_pool_of_threads_per_objective_and_ends_them():
    """Past the switch, each objective's threads are one pool for the whole optimisation (the
    fixed-Delta phase's objective, the full one; the fast strategy's phase coding every mode has
    one of its own), not a pool per evaluation; no thread outlives the optimisation, and the
    result is the same bits as on one thread."""
    final, evaluations, started, before, after = optimised_past_the_switch(workers=2)
    assert evaluations > 20
    assert len(started) <= 3 * 2, started
    assert after == before
    assert final == optimised_past_the_switch(workers=1)[0]


def pools_started(run) -> tuple:
    """(the result of ``run()``, how many pools of threads it started threads of)."""
    result, started = threads_started(run)
    # a ThreadPoolExecutor's threads are named after it: "ThreadPoolExecutor-<pool>_<thread>"
    return result, len({name.rsplit("_", 1)[0] for name in started})


def test_a_build_measures_eq14_before_and_after_on_its_optimisations_pool():
    """Past the switch, correspond measures eq. 14 before and after the optimisation on the
    threads of the optimisation's own objective (no pool of their own), with the bits of a
    measure on a pool of its own."""
    config = BuildConfig(points=12, workers=2, max_sweeps=1, baselines=[])
    prepared = [PreparedCase(f"case_{k}", [PreparedPart("", f"case_{k}", sphere_map)], 1.0)
                for k, sphere_map in enumerate(small_maps(40))]
    state, objectives = initial_state(prepared, config)[:2]
    assert state.by_covariance
    initial = state.objective_parts(objectives[1]).total    # a pool of its own
    settings = config.optimisation_settings()
    _, optimisation_pools = pools_started(lambda: optimise(
        state, objectives, settings, np.random.default_rng(config.seed), Trace()))
    state.rebuild()                  # as correspond does once the optimisation has ended
    final = state.objective_parts(objectives[1]).total

    result, pools = pools_started(lambda: correspond(prepared, config))
    assert state.evaluations > 20 and optimisation_pools >= 2
    assert pools == optimisation_pools
    assert result.initial_objective == initial
    assert result.final_objective == final
    np.testing.assert_array_equal(result.state.aligned_shapes(), state.aligned_shapes())


def test_the_switch_is_where_shapes_outnumber_coordinates():
    assert not covariance_route(1926, 3 * 642)
    assert covariance_route(1927, 3 * 642)


def many_shapes(n_s: int = 90, points: int = 12, seed: int = 4) -> CorrespondenceState:
    """A state of n_s given shapes on a ``points``-point sphere grid (3 points < n_s): an
    ellipsoid with random smooth deformations of many scales, posed at random."""
    rng = np.random.default_rng(seed)
    grid, triangles = sphere_grid(points)
    examples = []
    for k in range(n_s):
        axes = np.array([3.0, 2.0, 1.5]) * (1.0 + 0.05 * rng.normal(size=3))
        shape = grid * axes + 0.3 * np.logspace(-2, 0, 3 * points)[::-1].reshape(
            points, 3) * rng.normal(size=(points, 3))
        examples.append(FixedExample(f"case_{k}", shape + rng.normal(size=3)))
    return CorrespondenceState(examples, [(grid, triangles)])


def covariance_by_hand(shapes, weights, target_size):
    """D' from scratch (n_s x n_s), on the population rescaled to the target mean size."""
    mean = shapes.mean(axis=0)
    factor = target_size / centroid_size(mean, weights)
    flat = ((shapes - mean) * factor * np.sqrt(weights)[None, :, None]).reshape(len(shapes), -1)
    return flat @ flat.T


def test_a_state_with_more_shapes_than_coordinates_keeps_no_gram_matrix():
    state = many_shapes()
    assert state.by_covariance and state.gram is None
    for objective in build_objectives(state):
        state.objective = objective
        expected = objective(covariance_by_hand(state.shapes, state.weights, state.target_size))
        assert state.value() == pytest.approx(expected, rel=1e-12)
        assert state.description_length(objective) == pytest.approx(expected, rel=1e-12)
        value, _ = state.shape_gradient()
        assert value == pytest.approx(expected, rel=1e-12)


def derivative_along(state, i, base, direction, step=1e-6):
    scale = step * np.abs(state.shapes).max()

    def central(h):
        return (state.value(i, base + h * direction)
                - state.value(i, base - h * direction)) / (2 * h)
    return (4 * central(scale) - central(2 * scale)) / 3


def test_the_state_gradient_past_the_switch_matches_finite_differences():
    state = many_shapes()
    rng = np.random.default_rng(9)
    for objective in build_objectives(state)[::-1]:
        state.objective = objective
        value, grad = state.shape_gradient()
        for i in (0, 41, 89):
            direction = rng.normal(size=state.shapes[i].shape)
            numeric = derivative_along(state, i, state.shapes[i], direction)
            assert np.sum(grad[i] * direction) == pytest.approx(numeric, rel=1e-6)
            value_i, grad_i = state.example_gradient(i)
            assert value_i == pytest.approx(value, rel=1e-12)
            np.testing.assert_allclose(grad_i, grad[i], atol=1e-12 * np.abs(grad).max())
        trial = state.shapes[5] + rng.normal(scale=0.05, size=state.shapes[5].shape)
        value_t, grad_t = state.example_gradient(5, trial)
        assert value_t == pytest.approx(state.value(5, trial), rel=1e-12)
        direction = rng.normal(size=trial.shape)
        numeric = derivative_along(state, 5, trial, direction)
        assert np.sum(grad_t * direction) == pytest.approx(numeric, rel=1e-6)


def test_commits_and_trial_shapes_past_the_switch():
    state = many_shapes()
    state.objective = build_objectives(state)[1]
    rng = np.random.default_rng(2)
    moved = state.examples[7].points + rng.normal(scale=0.1, size=state.examples[7].points.shape)
    trial = state.examples[7].pose.apply(moved)
    expected = state.value(7, trial)
    state.examples[7].points = moved
    state.commit_shape(7)
    assert state.gram is None
    assert state.value() == pytest.approx(expected, rel=1e-12)
    shapes = state.shapes * 1.0
    shapes[3] += 0.05
    with state.trial_shapes(shapes):
        inside = state.value()
    assert inside == pytest.approx(
        state.objective(covariance_by_hand(shapes, state.weights, state.target_size)), rel=1e-12)
    assert state.value() == pytest.approx(expected, rel=1e-12)
