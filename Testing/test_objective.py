"""Tests of the MDL objective (docs/method.md section 2; paper eq. 13-14)."""

import math

import numpy as np
import pytest
from scipy import integrate

from mdlshapemodel.errors import ConfigError
from mdlshapemodel.correspondence.objective import (Objective, coded_values_from_gram, description_length,
                               integrated_description_length, mode_costs)

LN2PI = math.log(2 * math.pi)


def written_out_cost(y, delta, data_range, variant="continuous"):
    """Per-mode description length transcribed from docs/method.md section 2, one scalar at a time."""
    y = [float(v) for v in y]
    n_s = len(y)
    sum_squares = sum(v * v for v in y)
    sigma = math.sqrt(sum_squares / n_s)
    if max(y) - min(y) < delta:                      # case 3
        return 0.0
    sigma_min, sigma_max = 2 * delta, data_range / 2
    if sigma > sigma_min:                            # case 1
        small = min(1.0, sigma * math.sqrt(12 / n_s))
        data = (-n_s * math.log(delta) + n_s / 2 * math.log(2 * math.pi * sigma ** 2) + n_s / 2
                + n_s * small ** 2 / (12 * sigma ** 2))
    else:                                            # case 2
        small = min(1.0, sigma_min * math.sqrt(12 / n_s))
        base = -n_s * math.log(delta) + n_s / 2 * math.log(2 * math.pi * sigma_min ** 2)
        if variant == "continuous":
            data = (base + sum_squares / (2 * sigma_min ** 2)
                    + n_s * small ** 2 / (12 * sigma_min ** 2))
        else:
            quantised = [delta * round(v / delta) for v in y]
            data = base + sum(v * v for v in quantised) / (2 * sigma_min ** 2)
    param = math.log((sigma_max - sigma_min) / small) + 1 + abs(math.log(small))
    return param + data


def column(sigma, n_s, rng=None):
    """A column of n_s coded values with root mean square exactly ``sigma``."""
    if rng is None:
        y = np.array([1.0, -1.0] * (n_s // 2) + [0.0] * (n_s % 2))
    else:
        y = rng.normal(size=n_s)
    return y * sigma / np.sqrt(np.mean(y ** 2))


# --- mode_costs against numbers worked out by hand (n_s = 4, sqrt(12/n_s) = sqrt(3)) ---------------

def test_case1_small_delta_by_hand():
    """sigma = 0.5 > 2 Delta = 0.2; delta = 0.5 sqrt(3) < 1."""
    y = np.array([[0.5], [-0.5], [0.5], [-0.5]])
    small = 0.5 * math.sqrt(3)
    expected = (math.log((5.0 - 0.2) / small) + 1 + abs(math.log(small))
                - 4 * math.log(0.1) + 2 * math.log(2 * math.pi * 0.25) + 2
                + 4 * small ** 2 / (12 * 0.25))
    for variant in ("continuous", "reference"):
        assert mode_costs(y, 0.1, 10.0, variant)[0] == pytest.approx(expected, rel=1e-13)


def test_case1_delta_one_by_hand():
    """sigma = 2: sigma sqrt(12/4) > 1 so delta = 1 and |ln delta| = 0."""
    y = np.array([[2.0], [-2.0], [2.0], [-2.0]])
    expected = (math.log(20.0 - 0.2) + 1 - 4 * math.log(0.1) + 2 * math.log(2 * math.pi * 4.0)
                + 2 + 4 / (12 * 4.0))
    assert mode_costs(y, 0.1, 40.0)[0] == pytest.approx(expected, rel=1e-13)


def test_case2_small_delta_by_hand():
    """Y = (0.33, -0.27, 0.31, -0.37): sigma = sqrt(0.4148 / 4) = 0.322 <= 2 Delta = 0.4; range 0.7.

    delta = 0.4 sqrt(3) < 1.  Reference variant: Y / Delta = (1.65, -1.35, 1.55, -1.85) rounds to
    (2, -1, 2, -2), so sum Yhat^2 = 0.16 + 0.04 + 0.16 + 0.16 = 0.52.
    """
    y = np.array([0.33, -0.27, 0.31, -0.37])[:, None]
    small = 0.4 * math.sqrt(3)
    common = (math.log((5.0 - 0.4) / small) + 1 + abs(math.log(small))
              - 4 * math.log(0.2) + 2 * math.log(2 * math.pi * 0.16))
    continuous = common + 0.4148 / (2 * 0.16) + 4 * small ** 2 / (12 * 0.16)
    reference = common + 0.52 / (2 * 0.16)
    assert mode_costs(y, 0.2, 10.0)[0] == pytest.approx(continuous, rel=1e-13)
    assert mode_costs(y, 0.2, 10.0, "reference")[0] == pytest.approx(reference, rel=1e-13)
    # the precision term is exactly one nat when delta < 1
    assert 4 * small ** 2 / (12 * 0.16) == pytest.approx(1.0)


def test_case2_delta_one_by_hand():
    """Delta = 0.4: sigma_min = 0.8 and 0.8 sqrt(3) > 1, so delta = 1.

    Y = (0.62, -0.45, 0.5, -0.58): sum Y^2 = 1.1733, sigma = 0.542 <= 0.8, range 1.2 >= 0.4;
    Y / Delta = (1.55, -1.125, 1.25, -1.45) rounds to (2, -1, 1, -1): sum Yhat^2 = 1.12.
    """
    y = np.array([0.62, -0.45, 0.5, -0.58])[:, None]
    common = math.log(5.0 - 0.8) + 1 - 4 * math.log(0.4) + 2 * math.log(2 * math.pi * 0.64)
    continuous = common + 1.1733 / (2 * 0.64) + 4 / (12 * 0.64)
    reference = common + 1.12 / (2 * 0.64)
    assert mode_costs(y, 0.4, 10.0)[0] == pytest.approx(continuous, rel=1e-13)
    assert mode_costs(y, 0.4, 10.0, "reference")[0] == pytest.approx(reference, rel=1e-13)


def test_case3_range_below_delta_costs_nothing():
    y = np.array([0.03, -0.02, 0.01, -0.04])[:, None]   # range 0.07 < Delta = 0.1
    for variant in ("continuous", "reference"):
        assert mode_costs(y, 0.1, 10.0, variant)[0] == 0.0
    # ... but the same values cost something once Delta is below their range
    assert mode_costs(y, 0.05, 10.0)[0] > 0.0


def test_costs_are_per_column_and_description_length_sums_them():
    columns = [[0.5, -0.5, 0.5, -0.5], [2.0, -2.0, 2.0, -2.0], [0.03, -0.02, 0.01, -0.04],
               [0.13, -0.07, 0.11, -0.17]]
    coded = np.array(columns).T
    costs = mode_costs(coded, 0.1, 40.0)
    expected = [written_out_cost(c, 0.1, 40.0) for c in columns]
    np.testing.assert_allclose(costs, expected, rtol=1e-13)
    assert costs[2] == 0.0
    assert description_length(coded, 0.1, 40.0) == pytest.approx(sum(expected), rel=1e-13)


@pytest.mark.parametrize("variant", ["continuous", "reference"])
def test_mode_costs_match_written_out_formula_on_random_data(rng, variant):
    """Random coded values spread over all three cases and both regimes of delta."""
    for n_s in (3, 4, 9, 20):
        coded = rng.normal(size=(n_s, 30)) * np.logspace(-2.5, 0.7, 30)
        delta = 0.07
        costs = mode_costs(coded, delta, 25.0, variant)
        expected = [written_out_cost(coded[:, m], delta, 25.0, variant) for m in range(30)]
        np.testing.assert_allclose(costs, expected, rtol=1e-12)


# --- eq. 13 and the behaviour at sigma = sigma_min ---------------------------------------------------

def eq13_f(n_s, data_range, delta):
    return (1 + math.log(data_range / 2 - 2 * delta) + math.log(n_s / 12) - n_s * math.log(delta)
            + n_s / 2 * LN2PI)


@pytest.mark.parametrize("n_s", [4, 7, 12, 40])
def test_case1_equals_closed_form_eq13(rng, n_s):
    """Case 1 with delta < 1: f + (n_s - 2) ln sigma + n_s/2 + 1 (eq. 13)."""
    delta, data_range = 0.05, 30.0
    top = 1 / math.sqrt(12 / n_s)                          # delta < 1 below this sigma
    for sigma in np.linspace(2 * delta * 1.01, top * 0.99, 7):
        y = column(sigma, n_s, rng)[:, None]
        expected = eq13_f(n_s, data_range, delta) + (n_s - 2) * math.log(sigma) + n_s / 2 + 1
        assert mode_costs(y, delta, data_range)[0] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("n_s", [4, 12, 40])
def test_case2_continuous_closed_form(rng, n_s):
    """Continuous case 2 (delta < 1): f + (n_s - 2) ln sigma_min + (n_s/2)(sigma/sigma_min)^2 + 1."""
    delta, data_range = 0.05, 30.0
    sigma_min = 2 * delta
    for sigma in np.linspace(0.6 * delta, sigma_min, 5):
        y = column(sigma, n_s, rng)
        if np.ptp(y) < delta:
            continue
        expected = (eq13_f(n_s, data_range, delta) + (n_s - 2) * math.log(sigma_min)
                    + n_s / 2 * (sigma / sigma_min) ** 2 + 1)
        assert mode_costs(y[:, None], delta, data_range)[0] == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("delta", [0.125, 0.5])   # delta < 1 and delta = 1 at sigma = sigma_min
def test_continuous_variant_is_continuous_at_sigma_min(delta):
    """Approaching sigma = 2 Delta from below (case 2) and above (case 1) gives the same cost."""
    n_s, data_range = 4, 20.0
    pattern = np.array([1.0, -1.0, 1.0, -1.0])[:, None]
    sigma_min = 2 * delta                    # exact in binary: pattern * sigma_min has sigma_min
    at = mode_costs(pattern * sigma_min, delta, data_range)[0]
    for eps in (1e-6, 1e-9):
        below = mode_costs(pattern * sigma_min * (1 - eps), delta, data_range)[0]
        above = mode_costs(pattern * sigma_min * (1 + eps), delta, data_range)[0]
        # the slope d cost / d ln sigma is n_s (sigma / sigma_min)^2 = 4 on both sides: no jump
        assert abs(below - at) < 10 * eps + 1e-12
        assert abs(above - at) < 10 * eps + 1e-12
    # the closed forms of both cases meet at f + (n_s - 2) ln sigma_min + n_s/2 + 1 (delta < 1)
    if sigma_min * math.sqrt(12 / n_s) < 1:
        expected = eq13_f(n_s, data_range, delta) + (n_s - 2) * math.log(sigma_min) + n_s / 2 + 1
        assert at == pytest.approx(expected, rel=1e-12)


def test_reference_variant_jumps_by_one_nat_at_sigma_min():
    """The published code's case 2 lacks n_s delta^2 / (12 sigma_min^2) = 1 nat (delta < 1)."""
    delta, data_range = 0.125, 20.0
    pattern = np.array([1.0, -1.0, 1.0, -1.0])[:, None]
    at = pattern * 0.25                      # sigma = sigma_min exactly, Y / Delta = +-2 (no rounding)
    above = pattern * 0.25 * (1 + 1e-9)
    reference_at = mode_costs(at, delta, data_range, "reference")[0]
    reference_above = mode_costs(above, delta, data_range, "reference")[0]
    assert reference_above - reference_at == pytest.approx(1.0, abs=1e-6)
    assert (mode_costs(at, delta, data_range)[0] - reference_at) == pytest.approx(1.0, abs=1e-12)
    # case 1 is the same in both variants
    assert reference_above == pytest.approx(mode_costs(above, delta, data_range)[0], rel=1e-14)


# --- eq. 14: the average over Delta --------------------------------------------------------------------

def averaged_by_quadrature(coded, delta_min, delta_max, data_range, cost=None):
    """Mean of F_MDL(Delta) over [delta_min, delta_max] by adaptive quadrature, split at the breaks."""
    n_s = coded.shape[0]
    sigma = np.sqrt(np.mean(coded ** 2, axis=0))
    breaks = np.concatenate([sigma / 2, np.ptp(coded, axis=0), [1 / (2 * math.sqrt(12 / n_s))]])
    breaks = np.unique(breaks[(breaks > delta_min) & (breaks < delta_max)])
    if cost is None:
        def cost(d):
            return description_length(coded, d, data_range)
    edges = np.concatenate([[delta_min], breaks, [delta_max]])
    total = 0.0
    for a, b in zip(edges[:-1], edges[1:]):  # integrate piece by piece: each piece is smooth
        value, _ = integrate.quad(cost, a, b, epsabs=0.0, epsrel=1e-13, limit=200)
        total += value
    return total / (delta_max - delta_min)


@pytest.mark.parametrize("n_s", [5, 10, 16])
def test_integrated_description_length_equals_quadrature(rng, n_s):
    for trial in range(3):
        # mode scales from well below Delta_min to well above 2 Delta_max: every piece is visited
        coded = rng.normal(size=(n_s, 12)) * np.logspace(-4.3, 0.4, 12)[rng.permutation(12)]
        sigma = np.sqrt(np.mean(coded ** 2, axis=0))
        data_range = float(rng.uniform(2.5, 10.0) * max(1.0, sigma.max()))   # every sigma < R / 2
        exact = integrated_description_length(coded, 1e-4, 0.5, data_range)
        numeric = averaged_by_quadrature(coded, 1e-4, 0.5, data_range)
        assert exact == pytest.approx(numeric, rel=1e-8)


def test_integrated_description_length_with_a_mode_wider_than_sigma_max():
    """sigma = 3 > sigma_max = R / 2 = 2: F_MDL(Delta) is finite for every Delta (case 1 all along),
    so its average must be finite too and equal the quadrature."""
    coded = np.array([[3.0], [-3.0], [3.0], [-3.0]])
    fixed = [description_length(coded, d, 4.0) for d in (1e-4, 0.1, 0.5)]
    assert np.all(np.isfinite(fixed))
    exact = integrated_description_length(coded, 1e-4, 0.5, 4.0)
    assert np.isfinite(exact)
    assert exact == pytest.approx(averaged_by_quadrature(coded, 1e-4, 0.5, 4.0), rel=1e-8)


def test_integrated_description_length_other_interval(rng):
    coded = rng.normal(size=(8, 7)) * np.array([1e-3, 0.02, 0.05, 0.1, 0.3, 0.7, 2.0])
    exact = integrated_description_length(coded, 0.01, 0.3, 5.0)
    assert exact == pytest.approx(averaged_by_quadrature(coded, 0.01, 0.3, 5.0), rel=1e-8)


def test_integrated_description_length_of_negligible_modes_is_zero():
    coded = np.array([[1e-5, -2e-5], [-1e-5, 1e-5], [0.0, 1e-5]])   # ranges below Delta_min
    assert integrated_description_length(coded, 1e-4, 0.5, 10.0) == 0.0


# --- coded values and the Objective -------------------------------------------------------------------

def centred_data(rng, n_s, dim):
    x = rng.normal(size=(n_s, dim)) * rng.uniform(0.2, 3.0, size=dim)
    return x - x.mean(axis=0)


def test_coded_values_from_gram(rng):
    n_s = 9
    x = centred_data(rng, n_s, 40)
    gram = x @ x.T
    variances, coded = coded_values_from_gram(gram)
    singular = np.linalg.svd(x, compute_uv=False)
    expected = np.zeros(n_s)
    expected[:len(singular)] = singular ** 2 / n_s
    np.testing.assert_allclose(variances, expected, rtol=1e-10, atol=1e-12 * expected[0])
    assert np.all(np.diff(variances) <= 0)
    np.testing.assert_allclose(np.sum(coded ** 2, axis=0) / n_s, variances, rtol=1e-10,
                               atol=1e-12 * expected[0])
    np.testing.assert_allclose(coded @ coded.T, gram, rtol=1e-10, atol=1e-10 * np.abs(gram).max())
    # columns are the projections of the shapes on the principal axes, up to sign
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    for m in range(n_s - 1):
        projection = x @ vt[m]
        sign = np.sign(projection @ coded[:, m])
        np.testing.assert_allclose(coded[:, m], sign * projection, atol=1e-9)


def test_coded_values_of_rank_deficient_gram(rng):
    x = centred_data(rng, 8, 3)               # at most 3 non-zero modes
    variances, coded = coded_values_from_gram(x @ x.T)
    assert np.all(variances >= 0)
    assert np.all(variances[3:] < 1e-12 * variances[0])
    assert np.all(np.abs(coded[:, 3:]) < 1e-6)


def test_fixed_objective_from_gram_matches_svd_of_the_data(rng):
    n_s, data_range, delta = 10, 12.0, 0.1
    x = centred_data(rng, n_s, 25) * 0.3
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    coded = x @ vt.T                         # Y_im = x_i . v_m
    expected = sum(written_out_cost(coded[:, m], delta, data_range) for m in range(coded.shape[1]))
    objective = Objective("fixed", data_range, delta=delta)
    assert objective(x @ x.T) == pytest.approx(expected, rel=1e-9)
    reference = Objective("fixed", data_range, delta=delta, variant="reference")
    expected_ref = sum(written_out_cost(coded[:, m], delta, data_range, "reference")
                       for m in range(coded.shape[1]))
    assert reference(x @ x.T) == pytest.approx(expected_ref, rel=1e-9)


def test_integrated_objective_from_gram_matches_quadrature(rng):
    n_s, data_range = 7, 8.0
    x = centred_data(rng, n_s, 20) * 0.2
    _, _, vt = np.linalg.svd(x, full_matrices=False)
    coded = x @ vt.T
    objective = Objective("integrated", data_range, delta_min=1e-3, delta_max=0.4)
    expected = averaged_by_quadrature(coded, 1e-3, 0.4, data_range)
    assert objective(x @ x.T) == pytest.approx(expected, rel=1e-8)


def test_objective_does_not_depend_on_the_order_of_the_shapes(rng):
    x = centred_data(rng, 8, 15) * 0.4
    gram = x @ x.T
    order = rng.permutation(8)
    for objective in (Objective("fixed", 10.0, delta=0.05), Objective("integrated", 10.0)):
        assert objective(gram[np.ix_(order, order)]) == pytest.approx(objective(gram), rel=1e-10)


def test_objective_grows_when_a_shape_moves_away(rng):
    """Adding variation to the population (a spread-out shape) costs more description length."""
    x = centred_data(rng, 8, 15) * 0.4
    y = x.copy()
    y[0] *= 3.0
    y -= y.mean(axis=0)
    objective = Objective("integrated", 20.0)
    assert objective(y @ y.T) > objective(x @ x.T)


# --- configuration errors -------------------------------------------------------------------------------

def test_delta_too_large_for_the_data_range_raises():
    y = np.array([[1.0], [-1.0], [0.5], [-0.5]])
    with pytest.raises(ConfigError, match="delta"):
        mode_costs(y, 2.5, 10.0)                 # sigma_max = 5 = sigma_min
    with pytest.raises(ConfigError, match="delta"):
        description_length(y, 3.0, 10.0)
    assert np.isfinite(mode_costs(y, 2.4, 10.0)[0])
    with pytest.raises(ConfigError, match="delta"):
        integrated_description_length(y, 1e-4, 2.5, 10.0)
    with pytest.raises(ConfigError):
        Objective("fixed", 10.0, delta=2.5)(np.eye(4))


@pytest.mark.parametrize("bounds", [(0.0, 0.5), (-1e-4, 0.5), (0.5, 0.5), (0.4, 0.1)])
def test_bad_delta_interval_raises(bounds):
    with pytest.raises(ConfigError, match="delta_range"):
        integrated_description_length(np.ones((4, 1)), *bounds, 10.0)


def test_unknown_variant_and_kind_raise():
    y = np.array([[1.0], [-1.0], [0.5], [-0.5]])
    with pytest.raises(ConfigError, match="variant"):
        mode_costs(y, 0.1, 10.0, variant="thesis")
    with pytest.raises(ConfigError, match="objective"):
        Objective("average", 10.0)(np.eye(4))


# --- the gradient dF/dD' ----------------------------------------------------------------------------

def covariance_with_spectrum(rng, eigenvalues):
    """A random symmetric matrix with the given eigenvalues (random orthonormal eigenvectors)."""
    q, _ = np.linalg.qr(rng.normal(size=(len(eigenvalues), len(eigenvalues))))
    return (q * eigenvalues) @ q.T


def relative_margin(values, breaks):
    """Smallest relative distance of any of ``values`` to any of ``breaks``."""
    values, breaks = np.asarray(values, float), np.atleast_1d(np.asarray(breaks, float))
    return float(np.min(np.abs(values[:, None] - breaks[None, :]) / np.abs(breaks[None, :])))


def clear_of_breaks(objective, gram, margin=1e-2):
    """Whether every mode is well inside one piece of F: no case switch, kink of delta, break of
    the Delta integral, tie for the extreme coded value or near-repeated eigenvalue nearby."""
    n_s = gram.shape[0]
    variances, coded = coded_values_from_gram(gram)
    sigma, ranges = np.sqrt(variances), np.ptp(coded, axis=0)
    saturation = 1 / math.sqrt(12 / n_s)            # delta = sigma sqrt(12 / n_s) reaches 1
    if objective.kind == "fixed":
        checks = [(sigma, [2 * objective.delta, saturation]), (ranges, [objective.delta])]
    else:
        limits = [objective.delta_min, objective.delta_max]
        checks = [(sigma / 2, limits + [saturation / 2]), (ranges, limits)]
    if not all(relative_margin(v, b) > margin for v, b in checks):
        return False
    if np.min(-np.diff(variances)) < margin * variances[-1]:
        return False
    ordered = np.sort(coded, axis=0)
    gaps = np.minimum(ordered[-1] - ordered[-2], ordered[1] - ordered[0])
    return bool(np.all(gaps > margin * ranges))


def spread_covariance(rng, objective, n_s, log_sigma):
    """A covariance with n_s mode standard deviations spread over 10^log_sigma, clear of breaks."""
    spacing = (log_sigma[1] - log_sigma[0]) / (n_s - 1)
    for _ in range(1000):
        exponents = np.linspace(*log_sigma, n_s) + rng.uniform(-0.3, 0.3, n_s) * spacing
        gram = covariance_with_spectrum(rng, n_s * 10 ** (2 * exponents))
        if clear_of_breaks(objective, gram):
            return gram
    raise AssertionError("no covariance clear of the breaks of F")


def finite_difference_step(gram):
    """1e-3 of the smallest eigenvalue or eigenvalue gap: F curves on that scale (log sigma,
    eigenvectors turning), and eigh rounds every eigenvalue to ~eps |D'|, so a much smaller step
    measures rounding (checked: the agreement is best between 1e-3 and 1e-2 of that scale)."""
    eigenvalues = np.linalg.eigvalsh(gram)
    return 1e-3 * min(eigenvalues[0], np.min(np.diff(eigenvalues)))


def rounding_bound(value, grad, gram, step):
    """Absolute error of a central difference from rounding: of F itself (~eps |F|) and of the
    eigenvalues (~eps |D'|) times the steepest slope of F (~|G|). It limits the agreement in
    directions with small derivatives."""
    eps = np.finfo(float).eps
    return 4 * eps * (abs(value) + np.linalg.norm(grad) * np.linalg.norm(gram, 2)) / step


def directional_derivative(function, x, direction, step):
    """Central differences at steps h and 2h, Richardson-extrapolated: truncation error O(h^4)."""
    def central(h):
        return (function(x + h * direction) - function(x - h * direction)) / (2 * h)
    return (4 * central(step) - central(2 * step)) / 3


def check_gradient_by_finite_differences(objective, gram, rng, directions=6, tol=1e-5):
    value, grad = objective.gradient(gram)
    assert value == pytest.approx(objective(gram), rel=1e-12)
    np.testing.assert_allclose(grad, grad.T, atol=1e-12 * np.abs(grad).max())
    n_s = gram.shape[0]
    step = finite_difference_step(gram)
    perturbations = []
    for _ in range(directions):
        p = rng.normal(size=(n_s, n_s))
        perturbations.append(p + p.T)
    for i, j in [(0, 0), (1, n_s - 1), (n_s - 1, n_s - 1)]:
        p = np.zeros((n_s, n_s))
        p[i, j] = p[j, i] = 1.0
        perturbations.append(p)
    for p in perturbations:
        p = p / np.linalg.norm(p)
        numeric = directional_derivative(objective, gram, p, step)
        analytic = float(np.sum(grad * p))
        bound = tol * abs(analytic) + rounding_bound(value, grad, gram, step)
        assert abs(numeric - analytic) <= bound, (numeric, analytic, bound)


@pytest.mark.parametrize("n_s", [5, 8, 12])
@pytest.mark.parametrize("objective", [
    Objective("fixed", 10.0, delta=0.1),
    Objective("fixed", 10.0, delta=0.1, free_below_delta=False),
    Objective("fixed", 10.0, delta=0.1, variant="reference"),
    Objective("integrated", 10.0),
    Objective("integrated", 10.0, delta_min=0.01, delta_max=0.3),
], ids=["fixed", "fixed-no-case3", "fixed-reference", "integrated", "integrated-other"])
def test_objective_gradient_matches_finite_differences(rng, objective, n_s):
    """Modes from sigma = 3e-3 (case 3 of "fixed") to 2 (case 1 with delta = 1)."""
    gram = spread_covariance(rng, objective, n_s, (-2.5, 0.3))
    check_gradient_by_finite_differences(objective, gram, rng)


@pytest.mark.parametrize("kind", ["fixed", "integrated"])
def test_objective_gradient_with_small_modes(rng, kind):
    """Every mode below sigma_min = 2 Delta but above Delta in range: case 2 throughout (fixed);
    modes with ranges inside [Delta_min, Delta_max], whose upper limit moves (integrated)."""
    objective = Objective(kind, 4.0, delta=0.02)
    gram = spread_covariance(rng, objective, 10, (-1.9, -1.45))
    variances, coded = coded_values_from_gram(gram)
    if kind == "fixed":
        assert np.all(np.sqrt(variances) < 0.04) and np.all(np.ptp(coded, axis=0) > 0.02)
    else:
        assert np.all(np.ptp(coded, axis=0) < objective.delta_max)
    check_gradient_by_finite_differences(objective, gram, rng)


def test_objective_gradient_along_pure_rotations_of_the_eigenvectors(rng):
    """D' -> D' + t (A D' - D' A), A antisymmetric, keeps the eigenvalues to first order: the fixed
    objective sees only eigenvalues (its gradient is flat there); the integrated one also sees the
    ranges of the coded values, which do change: its analytic derivative must match."""
    fixed = Objective("fixed", 10.0, delta=0.1)
    integrated = Objective("integrated", 10.0)
    gram = spread_covariance(rng, integrated, 8, (-2.5, -0.5))
    a = rng.normal(size=(8, 8))
    a = a - a.T
    p = a @ gram - gram @ a
    p /= np.linalg.norm(p)
    _, grad = fixed.gradient(gram)
    assert abs(np.sum(grad * p)) < 1e-10 * np.linalg.norm(grad)
    _, grad = integrated.gradient(gram)
    step = finite_difference_step(gram)
    numeric = directional_derivative(integrated, gram, p, step)
    bound = rounding_bound(integrated(gram), grad, gram, step)
    assert abs(numeric) > 100 * bound
    assert abs(np.sum(grad * p) - numeric) < 1e-5 * abs(numeric) + bound


def test_objective_gradient_of_a_centred_rank_deficient_covariance(rng):
    """A centred covariance (null vector 1, eigenvalue ~0 clipped): the gradient is finite and
    matches finite differences along centred perturbations H P H."""
    n_s = 9
    x = centred_data(rng, n_s, 30) * np.logspace(-1.5, 0, 30)
    gram = x @ x.T
    h = np.eye(n_s) - 1.0 / n_s
    for objective in (Objective("fixed", 10.0, delta=0.05), Objective("integrated", 10.0)):
        value, grad = objective.gradient(gram)
        assert np.all(np.isfinite(grad))
        for _ in range(4):
            p = rng.normal(size=(n_s, n_s))
            p = h @ (p + p.T) @ h
            p /= np.linalg.norm(p)
            step = 1e-6 * np.linalg.eigvalsh(gram)[1]
            numeric = (objective(gram + step * p) - objective(gram - step * p)) / (2 * step)
            assert np.sum(grad * p) == pytest.approx(numeric, rel=1e-5, abs=1e-9 * value)


def test_objective_gradient_of_repeated_eigenvalues_is_basis_independent(rng):
    """Two equal mode variances: the gradient is the same whichever eigenvectors eigh returns.
    (Without case 3, F depends on the eigenvalues only, so F(Q D' Q^T) = F(D') for rotations Q.)"""
    objective = Objective("fixed", 10.0, delta=0.05, free_below_delta=False)
    sigma = np.array([1.0, 0.5, 0.5, 0.2, 0.08, 0.03])
    gram = covariance_with_spectrum(rng, 6 * sigma ** 2)
    q = np.linalg.qr(rng.normal(size=(6, 6)))[0]
    _, grad = objective.gradient(gram)
    _, rotated = objective.gradient(q @ gram @ q.T)
    np.testing.assert_allclose(q @ grad @ q.T, rotated, atol=1e-8 * np.abs(grad).max())


def test_a_builds_objectives_take_fixed_delta_and_delta_range_in_voxels(rng):
    """``objectives(config, voxel, R)`` makes the build's two objectives: eq. 13 at
    ``--fixed-delta`` and eq. 14 over ``--delta-range``, both given in voxels and so scaled by the
    mean voxel size, over the data range R of the aligned shapes; their products with the data
    past the switch run on the build's ``--workers`` threads."""
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.correspondence.objective import objectives

    coded = rng.normal(size=(12, 5)) * np.array([4.0, 1.5, 0.6, 0.2, 0.03])
    coded -= coded.mean(axis=0)
    config = BuildConfig(fixed_delta=0.3, delta_range=(0.002, 0.4), workers=3)
    for voxel in (1.0, 0.5, 2.5):
        fixed, integrated = objectives(config, voxel, 20.0)
        assert (fixed.kind, integrated.kind) == ("fixed", "integrated")
        assert fixed.threads == integrated.threads == 3
        assert fixed.data_range == integrated.data_range == 20.0
        assert fixed.delta == pytest.approx(0.3 * voxel, rel=1e-15)
        assert (integrated.delta_min, integrated.delta_max) == pytest.approx(
            (0.002 * voxel, 0.4 * voxel), rel=1e-15)
        assert fixed.from_coded(coded) == pytest.approx(
            description_length(coded, 0.3 * voxel, 20.0), rel=1e-12)
        assert integrated.from_coded(coded) == pytest.approx(
            integrated_description_length(coded, 0.002 * voxel, 0.4 * voxel, 20.0), rel=1e-12)
    # the voxel size changes what the build minimises: a finer accuracy costs more nats
    assert objectives(config, 0.5, 20.0)[0].from_coded(coded) > \
        objectives(config, 1.0, 20.0)[0].from_coded(coded)
    # the defaults: --fixed-delta 0.1, --delta-range 1e-4 0.5
    fixed, integrated = objectives(BuildConfig(), 1.0, 20.0)
    assert (fixed.delta, integrated.delta_min, integrated.delta_max) == (0.1, 1e-4, 0.5)
