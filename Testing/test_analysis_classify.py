"""The classification of groups by their shapes: the nuisance regressed out inside the folds,
more than two groups, the permutation p-value exact where every labeling can be counted, every
held-out value and per-fold measure equal to scikit-learn's, the corrected intervals by their
formula, and `mdlshapemodel analyze` in a subprocess on a real build with analysis.json's
classification recomputed with scikit-learn."""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats
from sklearn.covariance import ledoit_wolf as sklearn_ledoit_wolf
from sklearn.decomposition import PCA
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.linear_model import LinearRegression
from sklearn.metrics import balanced_accuracy_score, roc_auc_score
from sklearn.model_selection import RepeatedStratifiedKFold

from mdlshapemodel.analysis import align, benjamini_hochberg, classify, read_build
from mdlshapemodel.analysis.classification import ledoit_wolf_intensity
from mdlshapemodel.analysis.discriminant import ledoit_wolf

from common import run_cli
from synthetic import thin_and_full_build


def confounded(rng, n: int = 40, points: int = 30):
    """Shapes that change with age only, and a group that is only confounded with age (the
    older half of the cases, age measured with a little noise)."""
    age = rng.normal(size=n)
    group = age + 0.3 * rng.normal(size=n) > np.median(age)
    shapes = rng.normal(size=(n, points, 3))
    shapes[:, :10, 0] += 1.5 * age[:, None]
    return shapes, group, age[:, None]


def sklearn_folds(shapes, weights, groups, nuisance, folds, repeats, seed):
    """The same classification by scikit-learn: per fold, the nuisance regressed out by
    LinearRegression fitted on the training cases, PCA keeping 95% of the variance, shrinkage
    LDA with equal priors; the held-out decision values or probabilities, the fold's AUC and
    balanced accuracy."""
    n = len(shapes)
    features = (shapes * np.sqrt(weights)[None, :, None]).reshape(n, -1)
    levels = np.unique(groups)
    found = []
    splitter = RepeatedStratifiedKFold(n_splits=folds, n_repeats=repeats, random_state=seed)
    for train, test in splitter.split(features, groups):
        if nuisance is None:
            residual_train = features[train] - features[train].mean(axis=0)
            residual_test = features[test] - features[train].mean(axis=0)
        else:
            fitted = LinearRegression().fit(nuisance[train], features[train])
            residual_train = features[train] - fitted.predict(nuisance[train])
            residual_test = features[test] - fitted.predict(nuisance[test])
        pca = PCA(n_components=0.95, svd_solver="full").fit(residual_train)
        lda = LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto",
                                         priors=np.full(len(levels), 1 / len(levels)))
        lda.fit(pca.transform(residual_train), groups[train])
        probabilities = lda.predict_proba(pca.transform(residual_test))
        if len(levels) == 2:
            values = lda.decision_function(pca.transform(residual_test))
            auc = roc_auc_score(groups[test], values)
        else:
            values = probabilities
            auc = roc_auc_score(groups[test], probabilities, multi_class="ovr", average="macro")
        accuracy = balanced_accuracy_score(groups[test], levels[probabilities.argmax(axis=1)])
        found.append((test, values, auc, accuracy))
    return found


def low_rank(rng, groups, points: int = 40, shift: float = 1.0):
    """Shapes of a few modes and little noise (PCA keeps few components, below the cap of
    training cases - 3), the second group moved at five points."""
    n = len(groups)
    shapes = (rng.normal(size=(n, 4)) @ rng.normal(size=(4, points * 3))).reshape(n, points, 3)
    shapes += 0.05 * rng.normal(size=shapes.shape)
    shapes[groups == 1, :5, 0] += shift
    return shapes


def test_the_nuisance_is_regressed_out_inside_the_folds():
    """A group only confounded with age is classified well from shapes that change with age;
    with age regressed out in each training fold the AUC falls to chance and the permutation
    p-value is not small."""
    rng = np.random.default_rng(11)
    without, adjusted = [], []
    for _ in range(4):
        shapes, group, age = confounded(rng)
        weights = np.full(shapes.shape[1], 1 / shapes.shape[1])
        plain = classify(shapes, weights, group, folds=5, repeats=2, permutations=0)
        with_age = classify(shapes, weights, group, age, folds=5, repeats=2, permutations=0)
        without.append(plain.auc)
        adjusted.append(with_age.auc)
        assert with_age.adjusted_for == 1 and plain.adjusted_for == 0
    assert min(without) > 0.8, without
    # 4 data sets of 40 cases: the mean held-out AUC of no signal has an SE about 0.05
    assert abs(np.mean(adjusted) - 0.5) < 0.12, adjusted
    shapes, group, age = confounded(rng)
    weights = np.full(shapes.shape[1], 1 / shapes.shape[1])
    found = classify(shapes, weights, group, age, folds=5, repeats=2, permutations=99)
    plain = classify(shapes, weights, group, folds=5, repeats=2, permutations=99)
    assert plain.p == 0.01 and found.p > 0.05


def test_more_than_two_groups_are_classified_with_the_macro_auc():
    rng = np.random.default_rng(12)
    groups = np.repeat(["a", "b", "c"], 12)
    shapes = rng.normal(size=(36, 20, 3))
    shapes[groups == "b", :4, 0] += 2.0
    shapes[groups == "c", :4, 1] += 2.0
    found = classify(shapes, np.full(20, 0.05), groups, folds=4, repeats=3, permutations=49)
    assert found.levels == ["a", "b", "c"]
    assert found.predicted.shape == (36, 3)
    np.testing.assert_allclose(found.predicted.sum(axis=1), 1.0)
    assert found.auc > 0.9 and found.balanced_accuracy > 0.8 and found.p == 0.02
    assert len(found.fold_auc) == 12
    # no effect: chance is one half for the AUC and one third for the balanced accuracy
    noise = classify(rng.normal(size=(36, 20, 3)), np.full(20, 0.05), groups, folds=4,
                     repeats=3, permutations=0)
    assert abs(noise.auc - 0.5) < 0.15 and abs(noise.balanced_accuracy - 1 / 3) < 0.15


def test_a_subjects_cases_are_held_out_and_permuted_together():
    """16 subjects of two nearly identical cases each, the group a subject's (no effect): with
    the subjects as blocks the AUC is at chance; taking the cases as independent, a held-out
    case's twin in the training folds gives its group away."""
    rng = np.random.default_rng(18)
    blocked, independent = [], []
    blocks = np.repeat(np.arange(16), 2)
    for _ in range(8):
        shapes = np.repeat(rng.normal(size=(16, 20, 3)), 2, axis=0)
        shapes += 0.05 * rng.normal(size=shapes.shape)
        groups = np.repeat(rng.permutation(16) < 8, 2)
        found = classify(shapes, np.full(20, 0.05), groups, folds=4, repeats=3, permutations=0,
                         blocks=blocks)
        assert not found.exact
        blocked.append(found.auc)
        independent.append(classify(shapes, np.full(20, 0.05), groups, folds=4, repeats=3,
                                    permutations=0).auc)
    assert np.mean(independent) > 0.75, independent
    assert abs(np.mean(blocked) - 0.5) < 0.15, blocked
    mixed = groups.copy()
    mixed[0] = not mixed[1]
    with pytest.raises(ValueError, match="more than one group"):
        classify(shapes, np.full(20, 0.05), mixed, blocks=blocks, permutations=0)


def test_the_permutation_p_is_exact_when_every_labeling_is_counted():
    """4 against 4 cases: 70 labelings. With at least 69 permutations asked for, every other
    labeling is cross-validated once; the p-value is the share of all 70 whose AUC reaches the
    observed one, each counted here by its own classification."""
    rng = np.random.default_rng(13)
    shapes = rng.normal(size=(8, 6, 3))
    labels = np.array([0, 1, 0, 1, 0, 1, 0, 1])
    shapes[labels == 1, :2, 0] += 0.8
    weights = np.full(6, 1 / 6)
    found = classify(shapes, weights, labels, folds=2, repeats=2, permutations=100, seed=4)
    assert found.exact and found.permutations == 70 and len(found.null_auc) == 69
    every = []
    for chosen in itertools.combinations(range(8), 4):
        relabelled = np.zeros(8, dtype=int)
        relabelled[list(chosen)] = 1
        every.append(classify(shapes, weights, relabelled, folds=2, repeats=2, permutations=0,
                              seed=4).auc)
    every = np.array(every)
    # the other 69 labelings' AUCs are the null values
    observed_index = list(itertools.combinations(range(8), 4)).index((1, 3, 5, 7))
    others = np.delete(every, observed_index)
    np.testing.assert_allclose(np.sort(found.null_auc), np.sort(others), atol=1e-12)
    assert found.p == pytest.approx(np.sum(every >= found.auc - 1e-12) / 70)
    # exact: over all 70 labelings as the observed one, P(p <= u) <= u at every u
    p_all = np.array([np.sum(every >= a - 1e-12) / 70 for a in every])
    for u in np.unique(p_all):
        assert np.mean(p_all <= u) <= u + 1e-12


@pytest.mark.parametrize("count", [2, 3])
def test_every_held_out_value_and_fold_measure_is_scikit_learns(count):
    rng = np.random.default_rng(14 + count)
    groups = np.arange(36) % count
    shapes = low_rank(rng, groups)
    age = rng.normal(size=(36, 1))
    shapes[:, :, 2] += 0.3 * age
    weights = rng.uniform(0.5, 1.5, 40)
    for nuisance in (None, age):
        found = classify(shapes, weights, groups, nuisance, folds=4, repeats=2, permutations=0,
                         seed=3)
        reference = sklearn_folds(shapes, weights, groups, nuisance, 4, 2, 3)
        assert len(reference) == len(found.fold_auc) == 8
        for j, (test, values, auc, accuracy) in enumerate(reference):
            if j < 4:       # the first repeat's held-out values
                np.testing.assert_allclose(found.predicted[test], values, atol=1e-9)
            assert found.fold_auc[j] == pytest.approx(auc, abs=1e-12)
            assert found.fold_balanced_accuracy[j] == pytest.approx(accuracy, abs=1e-12)
        assert found.auc == pytest.approx(np.mean([r[2] for r in reference]), abs=1e-12)


def nadeau_bengio(values, folds):
    """The corrected resampled t interval (Nadeau and Bengio 2003) of a mean over folds."""
    j = len(values)
    half = stats.t.ppf(0.975, j - 1) * np.sqrt((1 / j + 1 / (folds - 1))
                                               * np.var(values, ddof=1))
    return max(0.0, np.mean(values) - half), min(1.0, np.mean(values) + half)


def test_the_intervals_are_the_corrected_resampled_t_and_wider_than_the_naive_one():
    rng = np.random.default_rng(15)
    groups = np.arange(40) % 2
    shapes = rng.normal(size=(40, 20, 3))
    shapes[groups == 1, :3, 0] += 0.6
    found = classify(shapes, np.full(20, 0.05), groups, folds=5, repeats=4, permutations=0)
    np.testing.assert_allclose(found.auc_interval, nadeau_bengio(found.fold_auc, 5))
    np.testing.assert_allclose(found.balanced_accuracy_interval,
                               nadeau_bengio(found.fold_balanced_accuracy, 5))
    naive = stats.t.ppf(0.975, 19) * np.std(found.fold_auc, ddof=1) / np.sqrt(20)
    assert found.auc_interval[1] - found.auc_interval[0] > 2 * naive * 1.5


def test_ledoit_wolf_is_scikit_learns():
    rng = np.random.default_rng(16)
    for n, k in ((10, 3), (20, 15), (8, 30)):
        x = rng.normal(size=(n, k)) @ rng.normal(size=(k, k))
        x -= x.mean(axis=0)
        shrunk, intensity = ledoit_wolf(x)
        expected, expected_intensity = sklearn_ledoit_wolf(x, assume_centered=True)
        assert intensity == pytest.approx(expected_intensity, rel=1e-10)
        assert ledoit_wolf_intensity(x) == pytest.approx(expected_intensity, rel=1e-10)
        np.testing.assert_allclose(shrunk, expected, rtol=1e-10, atol=1e-12)


def test_benjamini_hochberg_is_its_step_up_formula():
    """q_(i) = min over j >= i of p_(j) m / j, capped at 1, written out here (ties included)."""
    rng = np.random.default_rng(17)
    p = np.round(rng.uniform(size=200) ** 2, 3)
    order = np.argsort(p)
    m = len(p)
    expected = np.empty(m)
    for rank, i in enumerate(order, start=1):
        expected[i] = min(1.0, min(p[order[j]] * m / (j + 1) for j in range(rank - 1, m)))
    np.testing.assert_allclose(benjamini_hochberg(p), expected, rtol=1e-12)


# -- the command line on a real build ------------------------------------------------------

N = 16


@pytest.fixture(scope="module")
def build(tmp_path_factory) -> Path:
    """Sixteen small bumpy ellipsoids, the odd ones 8% smaller."""
    return thin_and_full_build(tmp_path_factory.mktemp("classify"), N)


@pytest.mark.slow
def test_the_command_line_classification_is_recomputed_by_scikit_learn(build):
    table = build.parent / "subjects.csv"
    ages = 40 + 2.0 * np.arange(N)
    with open(table, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["case", "group", "age"])
        writer.writerows([f"case_{k:02d}", "thin" if k % 2 else "full", ages[k]]
                         for k in range(N))
    output = build.parent / "findings"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                     "age", "--permutations", "99", "--folds", "4", "--repeats", "3",
                     "--classification-permutations", "199", "-o", output, "-q")
    assert result.returncode == 0, result.stderr
    assert "classification (3 x 4-fold): AUC" in result.stdout
    summary = json.loads((output / "analysis.json").read_text())
    c = summary["classification"]
    assert c["levels"] == ["full", "thin"] and c["adjusted_for"] == ["age"]
    assert (c["folds"], c["repeats"], c["permutations"], c["exact"]) == (4, 3, 200, False)

    # every fold again with scikit-learn: the resistant superimposition of the analysis, age
    # regressed out in each training fold
    built = read_build(build)
    aligned = align(built.shapes, built.model.weights)
    groups = np.arange(N) % 2
    reference = sklearn_folds(aligned, built.model.weights, groups, (ages - ages.mean())[:, None],
                              4, 3, 0)
    np.testing.assert_allclose(c["fold_auc"], [r[2] for r in reference], atol=1e-9)
    np.testing.assert_allclose(c["fold_balanced_accuracy"], [r[3] for r in reference],
                               atol=1e-9)
    assert c["auc"] == pytest.approx(np.mean(c["fold_auc"]))
    assert c["balanced_accuracy"] == pytest.approx(np.mean(c["fold_balanced_accuracy"]))
    np.testing.assert_allclose(c["auc_interval"], nadeau_bengio(c["fold_auc"], 4))
    np.testing.assert_allclose(c["balanced_accuracy_interval"],
                               nadeau_bengio(c["fold_balanced_accuracy"], 4))
    null = np.array(c["null_auc"])
    assert len(null) == 199
    assert c["p"] == pytest.approx((1 + np.sum(null >= c["auc"] - 1e-12)) / 200)
    # the groups differ in size: found, against a null centred on chance
    assert c["auc"] > 0.9 and c["p"] <= 0.01 and abs(np.mean(null) - 0.5) < 0.1
    page = (output / "analysis.html").read_text()
    assert "corrected resampled t" in page and "age regressed out" in page


@pytest.mark.slow
def test_the_command_line_holds_out_whole_subjects(build):
    """--subject alone: two cases per subject, the group a subject's; the classification holds
    each subject out whole and says so."""
    table = build.parent / "subjects-pairs.csv"
    with open(table, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["case", "id", "arm"])
        writer.writerows([f"case_{k:02d}", f"s{k // 2}", "a" if (k // 2) % 2 else "b"]
                         for k in range(N))
    output = build.parent / "findings-pairs"
    result = run_cli("analyze", build, "--table", table, "--group", "arm", "--subject", "id",
                     "--permutations", "99", "--folds", "4", "--repeats", "2",
                     "--classification-permutations", "49", "-o", output, "-q")
    assert result.returncode == 0, result.stderr
    c = json.loads((output / "analysis.json").read_text())["classification"]
    assert c["subject"] == "id" and c["folds"] == 4 and c["permutations"] == 50
    assert not c["exact"] and len(c["fold_auc"]) == 8
    assert "held out and permuted whole" in (output / "analysis.html").read_text()
