"""The analysis's statistics against direct formulas, their calibration under the null and their
power where an effect is planted (mdlshapemodel.analysis, mdlshapemodel.model.outliers)."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest
from scipy import stats

from mdlshapemodel.analysis import benjamini_hochberg, classify, permutation_test
from mdlshapemodel.errors import InputError
from mdlshapemodel.model.outliers import (empirical_null, new_case_distances,
                                            training_distances)
from mdlshapemodel.model.shape_model import ShapeModel, score_outliers

from common import empirical_null_p


def hotelling(a: np.ndarray, b: np.ndarray) -> float:
    """Two-sample Hotelling's T^2 with the pooled covariance, straight from its definition."""
    n1, n2 = len(a), len(b)
    d = b.mean(axis=0) - a.mean(axis=0)
    pooled = ((a - a.mean(0)).T @ (a - a.mean(0)) + (b - b.mean(0)).T @ (b - b.mean(0))) / (
        n1 + n2 - 2)
    return float(n1 * n2 / (n1 + n2) * d @ np.linalg.solve(pooled, d))


def slope_t(y: np.ndarray, covariate: np.ndarray, nuisance: np.ndarray) -> tuple[float, float]:
    """Ordinary least squares of y on [1, nuisance, covariate]: the covariate's slope and t."""
    design = np.column_stack([np.ones(len(y)), nuisance, covariate])
    beta = np.linalg.lstsq(design, y, rcond=None)[0]
    residual = y - design @ beta
    variance = residual @ residual / (len(y) - design.shape[1])
    return beta[-1], beta[-1] / np.sqrt(variance * np.linalg.inv(design.T @ design)[-1, -1])


def pillai(y: np.ndarray, nuisance: np.ndarray, interest: np.ndarray) -> float:
    """Pillai's trace tr(H (H + E)^-1) from the projection matrices."""
    def projection(x):
        return x @ np.linalg.pinv(x)

    n = len(y)
    reduced = np.column_stack([np.ones(n), nuisance])
    full = np.column_stack([reduced, interest])
    total = y.T @ (np.eye(n) - projection(reduced)) @ y
    hypothesis = y.T @ (projection(full) - projection(reduced)) @ y
    return float(np.trace(hypothesis @ np.linalg.inv(total)))


@pytest.fixture
def sample(rng):
    n = 24
    groups = np.repeat([0, 1, 2], 8)
    return {"n": n, "vectors": rng.normal(size=(n, 15, 3)), "groups": groups,
            "two": (groups[:16] == 1).astype(float)[:, None],
            "age": rng.normal(60, 8, n), "sex": rng.integers(0, 2, n).astype(float)}


def test_two_groups_give_hotellings_t2_and_the_mean_difference(sample):
    y, two = sample["vectors"][:16], sample["two"]
    result = permutation_test(y, two, permutations=9)
    first, second = two[:, 0] == 0, two[:, 0] == 1
    for k in range(15):
        assert result.statistic[k] == pytest.approx(hotelling(y[first, k], y[second, k]),
                                                    rel=1e-9)
        np.testing.assert_allclose(result.effect[0, k],
                                   y[second, k].mean(0) - y[first, k].mean(0), atol=1e-12)
    assert result.df == 14


def test_one_number_per_point_gives_t_squared_and_the_one_way_f(sample):
    y, groups = sample["vectors"][..., 0], sample["groups"]
    two = permutation_test(y[:16], sample["two"], permutations=9)
    t = stats.ttest_ind(y[8:16], y[:8]).statistic
    np.testing.assert_allclose(two.statistic, t ** 2, rtol=1e-9)
    three = permutation_test(y, np.column_stack([groups == 1, groups == 2]).astype(float),
                             permutations=9)
    f = stats.f_oneway(*(y[groups == g] for g in range(3))).statistic
    np.testing.assert_allclose(three.statistic, f, rtol=1e-9)


def test_a_covariate_adjusted_for_nuisance_gives_the_ols_slope_and_t(sample):
    y = sample["vectors"][..., 1]
    result = permutation_test(y, sample["age"][:, None], sample["sex"][:, None], permutations=9)
    for k in range(15):
        slope, t = slope_t(y[:, k], sample["age"], sample["sex"])
        assert result.effect[0, k, 0] == pytest.approx(slope, rel=1e-9)
        assert result.statistic[k] == pytest.approx(t ** 2, rel=1e-9)


def test_vectors_with_nuisance_and_three_groups_give_pillais_trace(sample):
    groups = sample["groups"]
    interest = np.column_stack([groups == 1, groups == 2]).astype(float)
    nuisance = np.column_stack([sample["age"], sample["sex"]])
    result = permutation_test(sample["vectors"], interest, nuisance, permutations=9)
    for k in range(15):
        assert result.value[k] == pytest.approx(
            pillai(sample["vectors"][:, k], nuisance, interest), rel=1e-9)


def test_permutation_p_values_count_the_observed_labelling_and_match_the_exact_ones(rng):
    # 3 + 3 cases: all 20 labellings can be enumerated, so the exact permutation p is known
    y = rng.normal(size=(6, 4))
    y[3:, 0] += 2.0
    labels = np.array([0, 0, 0, 1, 1, 1], dtype=float)[:, None]
    permutations = 20_000
    result = permutation_test(y, labels, permutations=permutations, seed=3)
    observed = permutation_test(y, labels, permutations=1).statistic
    splits = [np.isin(np.arange(6), chosen).astype(float)[:, None]
              for chosen in combinations(range(6), 3)]
    statistics = np.array([permutation_test(y, s, permutations=1).statistic for s in splits])
    exact = np.mean(statistics >= observed * (1 - 1e-9), axis=0)
    np.testing.assert_allclose(result.p, exact, atol=0.015)
    exact_max = np.mean(statistics.max(axis=1)[:, None] >= observed * (1 - 1e-9), axis=0)
    np.testing.assert_allclose(result.p_fwer, exact_max, atol=0.015)
    counts = result.p * (1 + permutations)
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)      # (1 + k) / (1 + B)
    assert np.all(result.p >= 1 / (1 + permutations))
    expected_fwer = (1 + np.sum(result.family_null[:, None] >= result.value * (1 - 1e-10),
                                axis=0)) / (1 + permutations)
    np.testing.assert_allclose(result.p_fwer, expected_fwer)
    assert np.all(result.p_fwer >= result.p)


def test_the_same_seed_gives_the_same_p_values_and_another_seed_other_ones(rng):
    y = rng.normal(size=(12, 30))
    labels = np.repeat([0.0, 1.0], 6)[:, None]
    a, b = (permutation_test(y, labels, permutations=500, seed=s) for s in (1, 1))
    c = permutation_test(y, labels, permutations=500, seed=2)
    assert np.array_equal(a.p, b.p) and np.array_equal(a.p_fwer, b.p_fwer)
    assert np.array_equal(a.q_fdr, b.q_fdr)
    assert not np.array_equal(a.p, c.p)


def test_benjamini_hochberg_equals_scipys(rng):
    p = rng.uniform(size=300) ** 3
    np.testing.assert_allclose(benjamini_hochberg(p),
                               stats.false_discovery_control(p, method="bh"), rtol=1e-12)


def test_too_few_cases_or_collinear_columns_are_refused_in_one_line(rng):
    with pytest.raises(InputError, match="too few cases"):
        permutation_test(rng.normal(size=(4, 10, 3)), np.array([0, 0, 1, 1.0]))
    age = rng.normal(size=12)
    with pytest.raises(InputError, match="collinear"):
        permutation_test(rng.normal(size=(12, 10)), age, np.column_stack([2 * age]))


def smooth_null(rng, n: int, points: int = 120) -> np.ndarray:
    """Spatially correlated noise along a line of points (n, points), like neighbouring surface
    points."""
    white = rng.normal(size=(n, points + 20))
    kernel = np.exp(-0.5 * (np.arange(-10, 11) / 4.0) ** 2)
    return np.stack([np.convolve(row, kernel, mode="valid") for row in white])


@pytest.mark.parametrize("nuisance", [False, True])
def test_family_wise_and_fdr_rates_under_the_null_are_alpha(rng, nuisance):
    alpha, datasets = 0.05, 400
    fwer = fdr = 0
    for _ in range(datasets):
        n = 20
        y = smooth_null(rng, n)
        labels = (rng.permutation(n) < 10).astype(float)[:, None]
        extra = rng.normal(size=(n, 1)) if nuisance else None
        if nuisance:
            y = y + 2.0 * extra            # a nuisance effect that must not leak into the test
        result = permutation_test(y, labels, extra, permutations=199,
                                  seed=int(rng.integers(1 << 30)))
        fwer += bool(np.any(result.p_fwer <= alpha))
        fdr += bool(np.any(result.q_fdr <= alpha))
    se = np.sqrt(alpha * (1 - alpha) / datasets)
    assert abs(fwer / datasets - alpha) < 2.5 * se, fwer / datasets
    # under the complete null every discovery is false: the FDR is the chance of any discovery;
    # on positively correlated points Benjamini-Hochberg keeps it at or below alpha
    assert fdr / datasets < alpha + 2.5 * se, fdr / datasets


def test_on_independent_points_the_fdr_under_the_null_is_alpha(rng):
    # Benjamini-Hochberg keeps P(any discovery) = alpha under the complete null exactly when the
    # points are independent (on correlated ones it is lower): this checks the per-point
    # p-values, with permutations enough to resolve alpha / points
    alpha, datasets, found = 0.05, 400, 0
    for _ in range(datasets):
        y = rng.normal(size=(20, 100))
        labels = (rng.permutation(20) < 10).astype(float)[:, None]
        result = permutation_test(y, labels, permutations=3999, seed=int(rng.integers(1 << 30)))
        found += bool(np.any(result.q_fdr <= alpha))
    se = np.sqrt(alpha * (1 - alpha) / datasets)
    assert abs(found / datasets - alpha) < 2.5 * se, found / datasets


def test_a_planted_effect_is_found_where_it_was_planted_and_nowhere_far(rng):
    found_at, found_far = [], []
    for _ in range(20):
        n = 30
        y = smooth_null(rng, n)
        labels = (np.arange(n) < 15).astype(float)[:, None]
        bump = 4.0 * np.exp(-0.5 * ((np.arange(120) - 40) / 5.0) ** 2)
        y = y + labels * bump
        result = permutation_test(y, labels, permutations=199, seed=int(rng.integers(1 << 30)))
        significant = result.p_fwer <= 0.05
        found_at.append(significant[35:46].any())
        found_far.append(significant[np.abs(np.arange(120) - 40) > 25].any())
    assert np.mean(found_at) >= 0.8
    assert np.mean(found_far) <= 0.15


def test_classification_is_near_chance_without_an_effect_and_high_with_one(rng):
    null_auc = []
    for _ in range(20):
        shapes = rng.normal(size=(40, 30, 3)) * np.linspace(3, 0.2, 30)[None, :, None]
        null_auc.append(classify(shapes, np.full(30, 1 / 30), np.arange(40) >= 20,
                                 permutations=0, seed=int(rng.integers(1 << 30))).auc)
    assert abs(np.mean(null_auc) - 0.5) < 0.1
    shapes = rng.normal(size=(40, 30, 3))
    second = np.arange(40) >= 20
    shapes[second, :10, 2] += 1.0
    result = classify(shapes, np.full(30, 1 / 30), second, permutations=99)
    assert result.balanced_accuracy > 0.7 and result.auc > 0.8 and result.p == 0.01
    low, high = result.auc_interval
    assert low < result.auc < high and high - low < 0.3


def gaussian_model(rng, n: int, dims: int = 60):
    spread = 3.0 * 0.7 ** np.arange(dims)
    shapes = (rng.normal(size=(n, dims)) * spread).reshape(n, dims // 3, 3)
    return shapes, spread


def test_training_distances_are_bounded_and_flag_a_planted_outlier_at_small_n(rng):
    for n, modes in ((5, 2), (10, 3)):
        shapes, spread = gaussian_model(rng, n)
        shapes[0] += 20 * (spread.reshape(-1, 3))           # 20 SD away along every direction
        model = ShapeModel.from_shapes(shapes, np.full(20, 1 / 20))
        result = training_distances(model.scores, model.variances, modes)
        assert np.all(result.distance <= np.sqrt(n - 1) + 1e-9)
        assert result.outlier[0] and result.p[0] == result.p.min()


def test_outlier_false_positive_rates_are_alpha(rng):
    flagged = normal = total = new_flagged = new_total = 0
    for _ in range(300):
        shapes, _ = gaussian_model(rng, 25)
        model = ShapeModel.from_shapes(shapes[:20], np.full(20, 1 / 20))
        result = score_outliers(model)
        flagged += result["outlier"].sum()
        normal += np.sum(result["p_normal"] < 0.01)
        total += 20
        scores = np.stack([model.project(s) for s in shapes[20:]])
        new = new_case_distances(scores, model.variances, model.scores, result["modes"])
        new_flagged += new.outlier.sum()
        new_total += 5
    rate, se = normal / total, np.sqrt(0.01 * 0.99 / total)
    assert abs(rate - 0.01) < 3 * se, rate            # the scaled Beta: exact under normality
    assert flagged / total <= 0.01 + 3 * se, flagged / total
    # a new case's reference is exact for a fixed subspace; the leading modes, chosen on the
    # same data, make it conservative, and so does the empirical null
    assert new_flagged / new_total <= 0.01 + 3 * np.sqrt(0.01 * 0.99 / new_total)


def test_a_new_case_far_away_is_flagged(rng):
    shapes, spread = gaussian_model(rng, 20)
    model = ShapeModel.from_shapes(shapes, np.full(20, 1 / 20))
    far = model.mean + 6 * np.sqrt(model.variances[0]) * model.modes[0]
    k = score_outliers(model)["modes"]
    result = new_case_distances(model.project(far)[None], model.variances, model.scores, k)
    assert result.outlier[0] and result.distance[0] == pytest.approx(6.0, rel=1e-9)


def test_a_fitted_case_is_scored_against_the_new_case_reference(rng):
    from mdlshapemodel.geometry import Pose
    from mdlshapemodel.model.fitting import FitResult, unusual_fit

    shapes, _ = gaussian_model(rng, 30)
    model = ShapeModel.from_shapes(shapes, np.full(20, 1 / 20))
    k = score_outliers(model)["modes"]
    usual = model.mean + 0.5 * np.sqrt(model.variances[0]) * model.modes[0]
    far = model.mean + 8 * np.sqrt(model.variances[1]) * model.modes[1]
    far[3] += [0.0, 0.0, 5.0]                           # and one point off the model
    found = []
    for shape in (usual, far):
        scores = model.project(shape)
        result = FitResult("new", "new.vtp", shape, shape, Pose(), scores, np.zeros(1),
                           np.zeros(1))
        found.append(unusual_fit(model, result))
    expected = new_case_distances(model.project(far)[None], model.variances, model.scores, k)
    assert found[1]["distance"] == pytest.approx(expected.distance[0])
    assert found[1]["p"] == pytest.approx(expected.p[0]) and found[1]["flagged"]
    assert found[1]["p_normal"] == pytest.approx(expected.p_normal[0])
    assert not found[0]["flagged"] and found[0]["p"] > 0.5
    assert found[1]["at_point"] == 3


def test_training_cases_p_values_with_a_tail_are_those_of_each_cases_own_null():
    """Forty heavy-tailed training cases, enough for the null's tail: every case's p is that of
    the empirical null of the other 39 written out (body and tail, docs/analysis.md item 9), the
    largest-tenth cases' (each reading a different tail) as the others', and p is alpha at each
    case's threshold."""
    rng = np.random.default_rng(11)
    x = rng.standard_t(3, size=(40, 6)) * [3.0, 2.0, 1.5, 1.0, 0.7, 0.5]
    u, s, _ = np.linalg.svd(x - x.mean(0), full_matrices=False)
    scores, variances, k, n = u * s, s ** 2 / 40, 4, 40
    found = training_distances(scores, variances, k, alpha=0.05)
    p_normal = found.p_normal
    np.testing.assert_allclose(found.p, empirical_null_p(p_normal), rtol=1e-10)
    for i in np.argsort(p_normal)[:6]:                    # the cases in and near the tail
        at = stats.beta(k / 2, (n - k - 1) / 2).sf(found.threshold[i] ** 2 / (n - 1))
        assert empirical_null_p(at, np.delete(p_normal, i))[0] == pytest.approx(0.05, rel=1e-6)


def test_unusual_p_values_are_their_formulas_on_small_data():
    """Seven training cases and two new ones: each p_normal from the scaled Beta (training) or
    the F (new), each p from the empirical null written out (docs/analysis.md item 9: a
    training case against the other six's z-values, a new case against all seven's), the
    thresholds where p crosses alpha."""
    rng = np.random.default_rng(7)
    x = rng.standard_t(3, size=(9, 4)) * [3.0, 2.0, 1.0, 0.5]
    mean = x[:7].mean(0)
    u, s, vt = np.linalg.svd(x[:7] - mean, full_matrices=False)
    scores, variances, k, n = u * s, s ** 2 / 7, 3, 7
    found = training_distances(scores, variances, k, alpha=0.05)
    squared = np.sum(scores[:, :k] ** 2 / variances[:k], axis=1)
    p_normal = stats.beta(k / 2, (n - k - 1) / 2).sf(squared / (n - 1))
    np.testing.assert_allclose(found.p_normal, p_normal, rtol=1e-12)
    np.testing.assert_allclose(found.p, empirical_null_p(p_normal), rtol=1e-10)
    for i in range(n):                                    # p is 0.05 exactly at the threshold
        at = stats.beta(k / 2, (n - k - 1) / 2).sf(found.threshold[i] ** 2 / (n - 1))
        assert empirical_null_p(at, np.delete(p_normal, i))[0] == pytest.approx(0.05, rel=1e-6)
    new = new_case_distances((x[7:] - mean) @ vt.T, variances, scores, k, alpha=0.05)
    new_squared = np.sum(((x[7:] - mean) @ vt[:k].T) ** 2 / variances[:k], axis=1)
    new_normal = stats.f.sf((n - k) * new_squared / (k * (n + 1)), k, n - k)
    np.testing.assert_allclose(new.p_normal, new_normal, rtol=1e-12)
    np.testing.assert_allclose(new.p, empirical_null_p(new_normal, p_normal), rtol=1e-10)
    np.testing.assert_array_equal(new.outlier, new.distance > new.threshold)


def test_the_empirical_null_tail_by_hand():
    """Fifteen z-values: r = 15 / 10 rounded half up = 2, u = 6 (the third largest), S =
    (10 - 6) + (8 - 6) = 6, the tail's p at u 3 / 16; a case at z = 12 has the tail's p
    (3 / 16) exp(-2 (12 - 6) / 6), above the body's 1 - Phi((12 - 1) / ((7.2 - 1) / z_0.9))
    (median 1, 90 % quantile 7.2). Without the smallest z-value (14 left) there is no tail."""
    z = np.array([-1.0, -0.5, 0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0, 3.0, 6.0, 8.0, 10.0])
    null = empirical_null(stats.norm.sf(z))
    assert (null.tail_cases, null.tail_share) == (2, pytest.approx(3 / 16))
    assert null.tail_from == pytest.approx(6.0) and null.tail_excess == pytest.approx(6.0)
    body = stats.norm.sf((12.0 - 1.0) / ((7.2 - 1.0) / stats.norm.isf(0.1)))
    assert body == pytest.approx(0.0115, abs=1e-4)
    tail = 3 / 16 * np.exp(-2.0)
    assert null.p(stats.norm.sf(np.array([12.0])))[0] == pytest.approx(tail, rel=1e-8)
    # the normal-theory p at which p is 0.05: z = 6 + (6 / 2) log((3 / 16) / 0.05)
    at = 6.0 + 3.0 * np.log((3 / 16) / 0.05)
    assert null.p_normal_at(0.05) == pytest.approx(stats.norm.sf(at), rel=1e-8)
    fewer = empirical_null(stats.norm.sf(z[1:]))
    assert fewer.tail_cases == 0
    assert fewer.p(stats.norm.sf(np.array([12.0])))[0] == pytest.approx(
        stats.norm.sf((12.0 - 1.1) / ((float(np.quantile(z[1:], 0.9)) - 1.1)
                                      / stats.norm.isf(0.1))), rel=1e-8)


def test_a_planted_unusual_case_among_heavy_tailed_ones_is_found_and_they_are_not(rng):
    """Forty shapes whose cases each have their own spread (a scale mixture: t with 5 degrees of
    freedom), the first deformed by a bump of 2 mm at 3 of its 20 points: it is flagged in
    nearly every sample, while the other cases are flagged at about the level, not at the
    several times the level of the normal-theory p."""
    found, others, others_normal = [], [], []
    for _ in range(60):
        x = rng.normal(size=(40, 60)) * 0.6 * 0.8 ** np.arange(60)
        shapes = (x / np.sqrt(rng.chisquare(5, size=(40, 1)) / 5)).reshape(40, 20, 3)
        shapes[0, :3, 2] += 2.0
        model = ShapeModel.from_shapes(shapes, np.full(20, 1 / 20))
        result = score_outliers(model, alpha=0.05)
        found.append(result["p"][0] < 0.01)
        others.append(np.mean(result["p"][1:] < 0.05))
        others_normal.append(np.mean(result["p_normal"][1:] < 0.05))
    assert np.mean(found) >= 0.9, np.mean(found)
    assert np.mean(others_normal) > 0.1, np.mean(others_normal)     # a heavy tail indeed
    assert np.mean(others) <= 0.075, np.mean(others)
