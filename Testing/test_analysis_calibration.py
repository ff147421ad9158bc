"""Calibration where the failures live, and the discriminant's numbers by another route.

Small samples (n = 8 to 12), several nuisance columns correlated with the groups, unequal group
sizes: the family-wise error of the per-point test, the false flags of the outlier distances of
training and new cases. Rates are checked two-sided, within a stated number of standard errors
of the level, with fixed seeds. The discriminant and the classification: Ledoit-Wolf's
intensity from its formula written another way, the direction of the discriminant on a
population whose second group is thinner, cross-validation that cannot see the held-out cases
(chance accuracy on noise), each fold's AUC from its held-out values."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from sklearn.model_selection import RepeatedStratifiedKFold

from mdlshapemodel.analysis import classify, permutation_test
from mdlshapemodel.analysis.discriminant import discriminant, ledoit_wolf
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.model.outliers import new_case_distances, training_distances

SES = 3.0       # a rate passes within this many binomial standard errors of its level


def within(rate: float, level: float, trials: int) -> bool:
    return abs(rate - level) <= SES * np.sqrt(level * (1 - level) / trials)


def test_family_wise_error_at_n_12_with_three_nuisance_columns_correlated_with_the_groups():
    """Freedman-Lane must permute the nuisance with the residuals: at n = 12 (5 against 7), with
    three nuisance columns that follow the groups, a test without them in the permuted
    statistics flags a null population about a quarter of the time."""
    rng = np.random.default_rng(40)
    alpha, datasets, n, points = 0.05, 300, 12, 20
    group = (np.arange(n) < 5).astype(float)[:, None]
    flagged = 0
    for _ in range(datasets):
        nuisance = 1.2 * group + rng.normal(size=(n, 3))          # correlated with the groups
        y = nuisance @ rng.normal(size=(3, points)) + rng.normal(size=(n, points))
        result = permutation_test(y, group, nuisance, permutations=199,
                                  seed=int(rng.integers(1 << 30)))
        flagged += bool(np.any(result.p_fwer <= alpha))
    assert within(flagged / datasets, alpha, datasets), flagged / datasets


def gaussian_populations(rng, count: int, n: int, k: int) -> np.ndarray:
    """``count`` samples of n cases of k numbers, each with its own unequal variances."""
    spread = np.sqrt(rng.uniform(0.5, 4.0, size=(count, 1, k)))
    return rng.normal(size=(count, n, k)) * spread


def principal(sample: np.ndarray):
    """(mean, directions (k, k), scores (n, k), variances with divisor n) of a sample."""
    mean = sample.mean(axis=0)
    u, s, vt = np.linalg.svd(sample - mean, full_matrices=False)
    return mean, vt, u * s, s ** 2 / len(sample)


LEVELS = (0.01, 0.05)


def at_most(rate: float, level: float, trials: int) -> bool:
    return rate <= level + SES * np.sqrt(level * (1 - level) / trials)


def test_training_cases_are_flagged_at_the_level_at_n_8():
    """A training case's distance over all k = 3 modes of 3-dimensional Gaussian data at n = 8:
    its Beta reference (p_normal) is exact, so it is below alpha with probability alpha, and the
    p that flags, against the other cases' empirical null, is below alpha at most as often (one
    case per sample, so that the trials are independent)."""
    rng = np.random.default_rng(8)
    samples, normal, flagged = 3000, np.zeros(len(LEVELS)), np.zeros(len(LEVELS))
    for sample in gaussian_populations(rng, samples, 8, 3):
        _, _, scores, variances = principal(sample)
        found = training_distances(scores, variances, 3, alpha=LEVELS[0])
        assert found.outlier[0] == (found.p[0] < LEVELS[0])
        normal += found.p_normal[0] < np.array(LEVELS)
        flagged += found.p[0] < np.array(LEVELS)
    for alpha, count, count_normal in zip(LEVELS, flagged, normal):
        assert within(count_normal / samples, alpha, samples), (alpha, count_normal / samples)
        assert at_most(count / samples, alpha, samples), (alpha, count / samples)


def test_new_cases_are_flagged_at_the_level_at_n_8():
    """A new case from the population of 8 training cases, projected on all k = 3 modes: its F
    reference (Hotelling's T^2 of a prediction, p_normal) is exact; the p that flags, against
    the training cases' empirical null, is below alpha at most as often."""
    rng = np.random.default_rng(9)
    samples, normal, flagged = 3000, np.zeros(len(LEVELS)), np.zeros(len(LEVELS))
    for sample in gaussian_populations(rng, samples, 9, 3):
        mean, directions, training, variances = principal(sample[:8])
        scores = (sample[8:] - mean) @ directions.T
        found = new_case_distances(scores, variances, training, 3, alpha=LEVELS[0])
        assert found.outlier[0] == (found.p[0] < LEVELS[0])
        normal += found.p_normal[0] < np.array(LEVELS)
        flagged += found.p[0] < np.array(LEVELS)
    for alpha, count, count_normal in zip(LEVELS, flagged, normal):
        assert within(count_normal / samples, alpha, samples), (alpha, count_normal / samples)
        assert at_most(count / samples, alpha, samples), (alpha, count / samples)


def scale_mixture(rng, n: int, dims: int = 60, nu: float = 5.0) -> np.ndarray:
    """n cases of ``dims`` numbers with variances 0.85^m, each case scaled by sqrt(nu / chi^2_nu)
    (multivariate t): some cases far out in every mode at once, as real shapes are."""
    x = rng.normal(size=(n, dims)) * 0.85 ** (np.arange(dims) / 2)
    return x / np.sqrt(rng.chisquare(nu, size=(n, 1)) / nu)


def test_training_cases_of_a_scale_mixture_are_flagged_at_most_at_the_level():
    """Training cases of a scale mixture (n = 40, t with 5 degrees of freedom, the modes
    explaining 95%): the normal-theory p flags several times the level; the p against the other
    cases' empirical null flags at most the level at 0.05 (one case per sample)."""
    from mdlshapemodel.model.outliers import modes_explaining

    rng = np.random.default_rng(40)
    samples, normal, flagged = 1500, 0, 0
    for _ in range(samples):
        _, _, scores, variances = principal(scale_mixture(rng, 40))
        found = training_distances(scores, variances, modes_explaining(variances, n_cases=40))
        normal += found.p_normal[0] < LEVELS[1]
        flagged += found.p[0] < LEVELS[1]
    assert normal / samples > 2 * LEVELS[1], normal / samples          # overdispersed indeed
    assert at_most(flagged / samples, LEVELS[1], samples), flagged / samples


def test_training_cases_of_a_heavier_tailed_mixture_are_flagged_at_about_the_level():
    """Training cases of a scale mixture with a heavier tail (n = 82, t with 3 degrees of
    freedom, 81 numbers, the modes explaining 95%): their z-values beyond the 90 % quantile
    fall off more slowly than a normal's, so a normal null fitted there alone flags about twice
    the level at 0.01. With the exponential tail, the cases of 200 samples are flagged at about
    the level: the rates' standard error over the samples (whose cases are not independent) is
    about 0.0015 at 0.01, and the tolerance is 0.005 above each level."""
    from mdlshapemodel.model.outliers import modes_explaining

    rng = np.random.default_rng(82)
    rates = []
    for _ in range(200):
        _, _, scores, variances = principal(scale_mixture(rng, 82, dims=81, nu=3.0))
        found = training_distances(scores, variances, modes_explaining(variances, n_cases=82))
        rates.append([np.mean(found.p_normal < LEVELS[0])]
                     + [np.mean(found.p < alpha) for alpha in LEVELS])
    normal, at_001, at_005 = np.mean(rates, axis=0)
    assert normal > 10 * LEVELS[0], normal                              # heavy-tailed indeed
    assert at_001 <= LEVELS[0] + 0.005, at_001
    assert at_005 <= LEVELS[1] + 0.005, at_005


def test_ledoit_wolf_intensity_is_its_formula():
    """Ledoit and Wolf (2004): intensity min(b^2, d^2) / d^2 with d^2 = |S - mu I|^2 and
    b^2 = (1/n^2) sum_i |x_i x_i' - S|^2, here as (sum_i |x_i|^4) / n^2 - |S|^2 / n."""
    rng = np.random.default_rng(4)
    for n, k in ((10, 6), (30, 4), (12, 9)):
        x = rng.normal(size=(n, k)) * np.linspace(2.0, 0.5, k)
        x -= x.mean(axis=0)
        sample = x.T @ x / n
        mu = np.trace(sample) / k
        d2 = np.sum((sample - mu * np.eye(k)) ** 2)
        b2 = np.sum(np.sum(x ** 2, axis=1) ** 2) / n ** 2 - np.sum(sample ** 2) / n
        expected = min(b2, d2) / d2
        assert 0.0 < expected < 1.0
        shrunk, intensity = ledoit_wolf(x)
        assert intensity == pytest.approx(expected, rel=1e-10)
        np.testing.assert_allclose(shrunk, (1 - expected) * sample + expected * mu * np.eye(k),
                                   rtol=1e-10)


def ellipsoids(rng, n: int, thinner: np.ndarray, points: int = 162) -> tuple:
    """Ellipsoids on one sphere grid with random axes; ``thinner`` ones 10 % narrower in y, z."""
    directions, _ = sphere_grid(points)
    axes = np.array([14.0, 9.0, 7.0]) * (1 + 0.04 * rng.normal(size=(n, 3)))
    axes[thinner, 1:] *= 0.9
    return directions[None] * axes[:, None], directions


def test_the_discriminant_points_from_the_first_group_to_the_second():
    """The second group is thinner: its discriminant scores are higher, and the pattern (the
    shape change towards the second group) points inward, where the thinner shapes lie."""
    rng = np.random.default_rng(3)
    second = np.arange(12) % 2 == 1
    shapes, directions = ellipsoids(rng, 12, second)
    found = discriminant(shapes, np.full(len(directions), 1 / len(directions)), second)
    assert found.scores[second].mean() > found.scores[~second].mean()
    outward = directions            # the ellipsoids' outward normals point away from the origin
    along = np.einsum("pd,pd->p", found.pattern, outward)
    sides = np.abs(directions[:, 0]) < 0.5          # where the groups differ: the y-z sides
    assert np.mean(along[sides] < 0) > 0.9
    # the pattern is the covariance of the shapes with the standardised score
    centred = shapes - shapes.mean(axis=0)
    np.testing.assert_allclose(found.pattern, np.einsum("n,npd->pd", found.scores, centred)
                               / len(shapes), atol=1e-12)


def test_cross_validation_does_not_see_the_held_out_cases():
    """Noise with two labels: held-out balanced accuracy scatters around one half. Fitting the
    principal components or the discriminant on the held-out cases too finds the labels in the
    noise."""
    rng = np.random.default_rng(5)
    accuracies = []
    for _ in range(12):
        shapes = rng.normal(size=(16, 20, 3))
        second = rng.permutation(16) < 8
        accuracies.append(classify(shapes, np.full(20, 1 / 20), second, folds=4, repeats=1,
                                   permutations=0,
                                   seed=int(rng.integers(1 << 30))).balanced_accuracy)
    # each accuracy has SE sqrt(0.25 / 16) = 0.125; their mean over 12 draws 0.036
    assert abs(np.mean(accuracies) - 0.5) <= SES * np.sqrt(0.25 / 16 / 12), accuracies


def test_each_folds_auc_comes_from_its_held_out_values():
    """A fold's AUC is the Mann-Whitney U of its held-out discriminant values over m n (ties
    count half: the shapes come in identical pairs, so cases held out together tie)."""
    rng = np.random.default_rng(6)
    base = rng.normal(size=(10, 15, 3))
    base[:, :5, 0] += np.linspace(-1.0, 1.0, 10)[:, None]
    shapes = np.repeat(base, 2, axis=0)                 # each shape twice, once in each group
    second = np.tile([False, True], 10)
    second[:4] = [False, False, True, True]             # the first two pairs share a label
    result = classify(shapes, np.full(15, 1 / 15), second, folds=4, repeats=1, permutations=0,
                      seed=3)
    held = result.predicted
    splits = RepeatedStratifiedKFold(n_splits=4, n_repeats=1, random_state=3).split(
        shapes[:, 0], second)
    tied = False
    for auc, (_, test) in zip(result.fold_auc, splits):
        positive, negative = held[test][second[test]], held[test][~second[test]]
        tied |= bool(np.any(positive[:, None] == negative[None, :]))
        u = stats.mannwhitneyu(positive, negative, alternative="two-sided").statistic
        assert auc == pytest.approx(u / (len(positive) * len(negative)), rel=1e-12)
    assert tied, "no tie: the test shows nothing"
