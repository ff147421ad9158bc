"""The projected L-BFGS of the fast strategy's rounds against SciPy's L-BFGS-B and known minima."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from mdlshapemodel.config import CURVATURE_PAIRS, SINGLE_PRECISION_PAIRS_FROM
from mdlshapemodel.correspondence.strategies.quasi_newton import (minimize_box, pair_dtype,
                                                                   projected_gradient)
from mdlshapemodel.errors import ArgumentError


def bounded_problem(n: int, seed: int):
    """A smooth convex function whose unconstrained minimum lies partly outside the box."""
    rng = np.random.default_rng(seed)
    scale = rng.uniform(1.0, 10.0, n)
    centre = rng.normal(0.0, 0.1, n)
    limit = np.full(n, 0.08)
    limit[::7] = np.inf

    def fun(x):
        r = x - centre
        return float(0.5 * np.sum(scale * r * r) + 0.25 * np.sum(r ** 4)), scale * r + r ** 3
    return fun, -limit, limit, centre


def test_reaches_the_box_minimum_that_scipy_finds():
    fun, lower, upper, centre = bounded_problem(500, 1)
    ours = minimize_box(fun, np.zeros(500), lower, upper, max_iterations=200, ftol=1e-15,
                        gtol=1e-10)
    theirs = minimize(fun, np.zeros(500), jac=True, method="L-BFGS-B",
                      bounds=list(zip(lower, upper)), options={"ftol": 1e-15, "gtol": 1e-10})
    assert np.allclose(ours.x, theirs.x, atol=1e-6)
    # the separable problem's minimum: the unconstrained one clipped into the box
    assert np.allclose(ours.x, np.clip(centre, lower, upper), atol=1e-6)
    assert ours.value <= theirs.fun + 1e-9
    assert np.max(np.abs(projected_gradient(ours.x, ours.gradient, lower, upper))) < 1e-5


def test_never_evaluates_outside_the_box():
    fun, lower, upper, _ = bounded_problem(300, 2)
    seen = []

    def recorded(x):
        seen.append(x.copy())
        return fun(x)

    minimize_box(recorded, np.full(300, 5.0), lower, upper, max_iterations=50)
    points = np.array(seen)
    assert len(points) > 10
    assert np.all(points >= lower) and np.all(points <= upper)


def test_minimises_rosenbrock_without_bounds():
    def rosenbrock(x):
        value = np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)
        gradient = np.zeros_like(x)
        gradient[:-1] = -400.0 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2.0 * (1.0 - x[:-1])
        gradient[1:] += 200.0 * (x[1:] - x[:-1] ** 2)
        return float(value), gradient

    result = minimize_box(rosenbrock, np.full(6, -1.2), np.full(6, -np.inf),
                          np.full(6, np.inf), max_iterations=500, ftol=0.0, gtol=1e-8)
    assert np.allclose(result.x, 1.0, atol=1e-4)
    assert result.stop == "gtol"


def test_stops_on_its_iteration_limit_and_its_tolerances():
    fun, lower, upper, centre = bounded_problem(100, 3)
    limited = minimize_box(fun, np.zeros(100), lower, upper, max_iterations=3, ftol=0.0,
                           gtol=0.0)
    assert (limited.iterations, limited.stop) == (3, "iterations")
    at_minimum = np.clip(centre, lower, upper)
    assert minimize_box(fun, at_minimum, lower, upper, gtol=1e-9).stop == "gtol"
    relaxed = minimize_box(fun, np.zeros(100), lower, upper, max_iterations=1000, ftol=1e-3)
    assert relaxed.stop == "ftol" and relaxed.iterations < 1000


def test_a_wrong_gradient_ends_in_a_failed_line_search_without_moving():
    def uphill(x):      # the gradient's sign is wrong: no step along -g lowers F
        return float(np.sum(x ** 2)), -2.0 * x

    start = np.array([1.0, -2.0, 0.5])
    result = minimize_box(uphill, start, np.full(3, -10.0), np.full(3, 10.0))
    assert result.stop == "line search"
    assert np.array_equal(result.x, start)


def test_a_steep_gradient_valid_over_a_tiny_length_still_gives_a_step():
    """F falls with slope g only up to a kink at x = a, far shorter than the first step of unit
    length, then rises with slope g again (as eq. 14 with many small modes). Every trial beyond
    the kink is above the start: the step must shrink tenfold each time (halving would leave it
    beyond the kink after all its backtracks) and end at the kink."""
    g, a = 1e5, 1e-7

    def kinked(x):
        beyond = x[0] > a
        return float(-g * x[0] + 2 * g * max(x[0] - a, 0.0)), np.array([g if beyond else -g])

    result = minimize_box(kinked, np.zeros(1), np.full(1, -1.0), np.full(1, 1.0))
    assert 0 < result.x[0] <= a * (1 + 1e-9)
    assert result.value < 0


def test_the_same_inputs_give_the_same_iterates_bit_for_bit():
    fun, lower, upper, _ = bounded_problem(2000, 4)
    first = minimize_box(fun, np.zeros(2000), lower, upper)
    second = minimize_box(fun, np.zeros(2000), lower, upper)
    assert np.array_equal(first.x, second.x) and first.value == second.value


def test_a_symmetric_box_without_lower_bounds_gives_the_iterates_of_minus_upper():
    """``lower`` None is the box -upper <= x <= upper: the same evaluations and result bit for
    bit as with the lower bounds given, every point evaluated inside it."""
    fun, lower, upper, _ = bounded_problem(2000, 6)
    runs = []
    for given in (lower, None):
        seen = []

        def recorded(x, seen=seen):
            seen.append(x.copy())
            return fun(x)

        result = minimize_box(recorded, np.full(2000, 0.05), given, upper, max_iterations=40)
        runs.append((result, np.array(seen)))
    (with_lower, points_with), (symmetric, points) = runs
    assert len(points) > 10 and np.array_equal(points, points_with)
    assert np.array_equal(symmetric.x, with_lower.x) and symmetric.value == with_lower.value
    assert np.all(points >= -upper) and np.all(points <= upper)
    assert np.any(symmetric.x == -upper) and np.any(symmetric.x == upper)   # both sides active
    with pytest.raises(ArgumentError, match="symmetric box"):
        minimize_box(fun, np.zeros(2000), None, -upper)


def test_exceptions_of_the_function_pass_through_and_bad_bounds_are_refused():
    class Stop(Exception):
        pass

    calls = []

    def stops_on_the_third_call(x):
        calls.append(1)
        if len(calls) == 3:
            raise Stop
        return float(np.sum(x ** 2)), 2.0 * x

    with pytest.raises(Stop):
        minimize_box(stops_on_the_third_call, np.ones(4), np.full(4, -5.0), np.full(4, 5.0))
    with pytest.raises(ValueError, match="lower bound exceeds"):
        minimize_box(stops_on_the_third_call, np.ones(2), np.array([0.0, 2.0]), np.ones(2))


def test_while_the_function_runs_it_holds_the_pairs_and_six_vectors_more():
    """What the rounds' memory rests on: during an evaluation minimize_box holds its ``memory``
    curvature pairs and at most six vectors of length n more (x, its gradient, the direction, the
    trial point, and what the last step left: a rejected trial's gradient, or a pair not kept);
    the projected gradient goes before the line search."""
    import tracemalloc

    n, memory = 200_000, 3
    fun, lower, upper, _ = bounded_problem(n, 5)
    held = []

    def measured(x):
        held.append(tracemalloc.get_traced_memory()[0])
        return fun(x)

    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        result = minimize_box(measured, np.zeros(n), lower, upper, max_iterations=12,
                              memory=memory, ftol=0.0, gtol=0.0)
    finally:
        tracemalloc.stop()
    assert result.iterations == 12
    vectors = (max(held) - before) / (8 * n)
    # (the bounds are the test's own arrays, made before the count starts)
    assert 2 * memory + 3 < vectors < 2 * memory + 6.5


def test_the_pairs_precision_rule():
    """auto keeps double precision below SINGLE_PRECISION_PAIRS_FROM variables and single from
    there; single and double are what they say at any size; anything else is refused."""
    below, at = SINGLE_PRECISION_PAIRS_FROM - 1, SINGLE_PRECISION_PAIRS_FROM
    assert pair_dtype("auto", below) is np.float64
    assert pair_dtype("auto", at) is np.float32
    assert pair_dtype("single", 10) is np.float32
    assert pair_dtype("double", 10 * at) is np.float64
    assert set(CURVATURE_PAIRS) == {"auto", "single", "double"}
    with pytest.raises(ArgumentError, match="half"):
        pair_dtype("half", 10)


def test_single_precision_pairs_change_the_path_by_rounding_only():
    """Pairs kept in float32 give a direction that differs from double precision's by their
    rounding: the iterates part at about float32's precision, and both reach the box minimum."""
    fun, lower, upper, centre = bounded_problem(400, 4)
    short = {name: minimize_box(fun, np.zeros(400), lower, upper, max_iterations=4, ftol=0.0,
                                gtol=0.0, pairs_dtype=dtype)
             for name, dtype in (("double", np.float64), ("single", np.float32))}
    gap = np.max(np.abs(short["single"].x - short["double"].x))
    assert 0.0 < gap < 1e-5 * np.max(np.abs(short["double"].x))
    assert short["single"].x.dtype == np.float64 and short["single"].gradient.dtype == np.float64
    ends = [minimize_box(fun, np.zeros(400), lower, upper, max_iterations=300, ftol=1e-15,
                         gtol=1e-10, pairs_dtype=dtype) for dtype in (np.float64, np.float32)]
    for end in ends:
        assert np.allclose(end.x, np.clip(centre, lower, upper), atol=1e-6)
    assert abs(ends[0].value - ends[1].value) < 1e-9 * max(abs(ends[0].value), 1.0)


def test_double_precision_pairs_are_the_default():
    """Without pairs_dtype the pairs stay double: the same iterates bit for bit as asking for it."""
    fun, lower, upper, _ = bounded_problem(200, 5)
    default = minimize_box(fun, np.zeros(200), lower, upper, max_iterations=6, ftol=0.0, gtol=0.0)
    double = minimize_box(fun, np.zeros(200), lower, upper, max_iterations=6, ftol=0.0,
                          gtol=0.0, pairs_dtype=np.float64)
    np.testing.assert_array_equal(default.x, double.x)


def test_each_direction_is_the_dense_bfgs_inverse_hessian_of_the_kept_pairs():
    """On a convex quadratic without bounds (every pair kept), the first trial of iteration k+1
    is x_k - H_k g_k, with H_k the BFGS updates of gamma I by the pairs (s_i, y_i) in order
    (gamma = s.y / y.y of the newest): the two-loop recursion against its direct formula."""
    rng = np.random.default_rng(6)
    n = 12
    m = rng.normal(size=(n, n))
    a, b = m @ m.T + n * np.eye(n), rng.normal(size=n)

    def quadratic(x):
        return float(0.5 * x @ a @ x - b @ x), a @ x - b

    free = np.full(n, np.inf)

    def run(iterations):
        seen = []

        def recorded(x):
            seen.append(x.copy())
            return quadratic(x)
        end = minimize_box(recorded, np.zeros(n), -free, free, max_iterations=iterations,
                           ftol=0.0, gtol=0.0)
        return end, seen

    points = [run(k)[0].x for k in range(4)]
    gradients = [quadratic(x)[1] for x in points]
    pairs = [(points[i + 1] - points[i], gradients[i + 1] - gradients[i]) for i in range(3)]
    s_new, y_new = pairs[-1]
    h = (s_new @ y_new) / (y_new @ y_new) * np.eye(n)
    for s, y in pairs:
        rho = 1.0 / (s @ y)
        left = np.eye(n) - rho * np.outer(s, y)
        h = left @ h @ left.T + rho * np.outer(s, s)
    evaluations_to_x3 = len(run(3)[1])
    trial = run(4)[1][evaluations_to_x3]
    expected = points[3] - h @ gradients[3]
    np.testing.assert_allclose(trial, expected, rtol=1e-9, atol=1e-12)
