"""The designs of the analysis beyond independent cases and one joint test: repeated measures
(each subject's change between two times, by sign flips; the effect of time within subjects,
permuted within subjects), signed and one-sided tests of one effect column, each against scipy,
a least-squares formula written out here and plain loops over the same resamples; a small
longitudinal simulation where the paired test finds a change that the unpaired one misses."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from scipy import stats

from mdlshapemodel.analysis import permutation_test, subjects
from mdlshapemodel.analysis.glm import drawn_flips, drawn_signs, drawn_whole_blocks
from mdlshapemodel.analysis.study import design_rows, point_test, signed_maps
from mdlshapemodel.config import AnalysisConfig
from mdlshapemodel.errors import ConfigError, InputError


def write(path, header, rows):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


def ols_t(y: np.ndarray, design: np.ndarray, column: int = -1) -> np.ndarray:
    """Student's t of one coefficient of ordinary least squares, per column of ``y``, from the
    textbook formula: b_j / sqrt(s^2 [(X'X)^-1]_jj), s^2 = e'e / (n - rank)."""
    coefficients = np.linalg.lstsq(design, y, rcond=None)[0]
    errors = y - design @ coefficients
    variance = np.sum(errors ** 2, axis=0) / (len(y) - design.shape[1])
    return coefficients[column] / np.sqrt(variance * np.linalg.inv(design.T @ design)[column,
                                                                                        column])


def longitudinal(tmp_path, n_subjects: int, points: int, seed: int, change: float = 3.0,
                 between: float = 3.0, within: float = 0.3):
    """Two scans per subject: a subject's own shape (SD ``between``) plus scan noise (SD
    ``within``); in every other subject the second scan moved by ``change`` at the first 10
    points. The table: case, id, visit (pre/post), age (varies between subjects)."""
    rng = np.random.default_rng(seed)
    own = rng.normal(scale=between, size=(n_subjects, points))
    names, rows, data = [], [], []
    for s in range(n_subjects):
        for visit in ("pre", "post"):
            shift = change * (visit == "post" and s % 2 == 0) * (np.arange(points) < 10)
            data.append(own[s] + rng.normal(scale=within, size=points) + shift)
            names.append(f"s{s:02d}_{visit}")
            rows.append([names[-1], f"s{s:02d}", visit, 40 + (7 * s) % 23])
    table = write(tmp_path / "longitudinal.csv", ["case", "id", "visit", "age"], rows)
    return table, names, np.array(data)


def test_the_mean_change_is_the_paired_t_of_scipy_and_its_p_counts_its_sign_flips(tmp_path):
    table, names, data = longitudinal(tmp_path, 9, 30, seed=1, change=1.0)
    design = subjects(table, names, subject="id", time="visit", baseline="pre")
    assert design.mean_change_tested and design.tested == ["visit"]
    assert design.repeated.design == "change" and design.repeated.times == ["pre", "post"]
    post, pre = data[1::2], data[0::2]
    np.testing.assert_array_equal(design_rows(data, design), post - pre)
    permutations, seed = 300, 3
    config = AnalysisConfig(subject="id", time="visit", permutations=permutations, seed=seed)
    found = point_test(data, design, config)
    np.testing.assert_allclose(found.t, stats.ttest_rel(post, pre).statistic, rtol=1e-10)
    np.testing.assert_allclose(found.t, stats.ttest_1samp(post - pre, 0.0).statistic,
                               rtol=1e-10)
    assert found.resampling == "sign-flipped" and found.df == 8
    # every resample flips whole subjects' changes: recompute each t with scipy
    signs = np.vstack([np.ones(9)] + [s for _, s in drawn_signs(9, permutations, seed)])
    flipped = np.array([stats.ttest_1samp(s[:, None] * (post - pre), 0.0).statistic
                        for s in signs]) ** 2
    expected = np.mean(flipped >= flipped[0] * (1 - 1e-9), axis=0)
    np.testing.assert_allclose(found.p, expected, rtol=1e-12)
    largest = flipped[1:].max(axis=1)
    np.testing.assert_allclose(found.p_fwer, np.maximum(
        (1 + np.sum(largest[:, None] >= flipped[0] * (1 - 1e-9), axis=0)) / (permutations + 1),
        expected), rtol=1e-12)


def test_the_mean_change_adjusted_for_a_subject_column_is_its_intercept_at_the_mean(tmp_path):
    table, names, data = longitudinal(tmp_path, 11, 20, seed=2, change=1.0)
    design = subjects(table, names, subject="id", time="visit", nuisance=["age"])
    assert design.repeated.times == ["post", "pre"]        # sorted: --baseline chooses
    design = subjects(table, names, subject="id", time="visit", nuisance=["age"],
                      baseline="pre")
    change = data[1::2] - data[0::2]
    ages = np.array([40 + (7 * s) % 23 for s in range(11)], dtype=float)
    found = point_test(data, design, AnalysisConfig(subject="id", time="visit",
                                                    nuisance=["age"], permutations=99))
    centred = np.column_stack([ages - ages.mean(), np.ones(11)])
    np.testing.assert_allclose(found.t, ols_t(change, centred), rtol=1e-10)
    np.testing.assert_allclose(found.effect[0, :, 0],
                               np.linalg.lstsq(centred, change, rcond=None)[0][1], rtol=1e-10)
    assert found.df == 9



def test_the_mean_change_adjusted_for_a_categorical_column_is_the_mean_of_the_changes(tmp_path):
    """A subject's sex adjusted for (indicators, centred like a numeric column): the mean change
    is the change at the nuisance's mean, which least squares with a centred column puts at the
    mean of the subjects' changes; its t is that of the intercept beside the centred column."""
    table, names, data = longitudinal(tmp_path, 11, 20, seed=3, change=1.0)
    rows = [row for row in csv.reader(open(table))][1:]
    sexes = write(tmp_path / "sexes.csv", ["case", "id", "visit", "sex"],
                  [[c, i, v, "M" if int(i[1:]) % 3 == 0 else "F"] for c, i, v, _ in rows])
    options = dict(subject="id", time="visit", nuisance=["sex"], categorical=["sex"])
    design = subjects(sexes, names, baseline="pre", **options)
    assert design.mean_change_tested and design.adjusted_for == ["sex"]
    found = point_test(data, design, AnalysisConfig(permutations=99, **options))
    change = data[1::2] - data[0::2]
    male = np.array([s % 3 == 0 for s in range(11)], dtype=float)
    np.testing.assert_allclose(found.effect[0, :, 0], change.mean(axis=0), rtol=1e-10)
    centred = np.column_stack([male - male.mean(), np.ones(11)])
    np.testing.assert_allclose(found.t, ols_t(change, centred), rtol=1e-10)

def test_a_group_tested_on_the_change_is_welchs_v_of_the_subjects_changes(tmp_path):
    table, names, data = longitudinal(tmp_path, 12, 25, seed=4, change=1.0)
    rows = [row for row in csv.reader(open(table))][1:]
    grouped = write(tmp_path / "grouped.csv", ["case", "id", "visit", "arm"],
                    [[c, i, v, "treated" if int(i[1:]) % 2 == 0 else "placebo"]
                     for c, i, v, _ in rows])
    design = subjects(grouped, names, group="arm", subject="id", time="visit", baseline="pre",
                      reference="placebo")
    assert design.n_per_group() == {"placebo": 6, "treated": 6}   # subjects, not cases
    assert not design.mean_change_tested
    change = data[1::2] - data[0::2]
    treated = np.arange(12) % 2 == 0
    welch = point_test(data, design, AnalysisConfig(group="arm", subject="id", time="visit",
                                                    permutations=99))
    expected = stats.ttest_ind(change[treated], change[~treated], equal_var=False).statistic
    np.testing.assert_allclose(welch.t, expected, rtol=1e-10)
    pooled = point_test(data, design, AnalysisConfig(group="arm", subject="id", time="visit",
                                                     variance="pooled", permutations=99))
    np.testing.assert_allclose(pooled.t, stats.ttest_ind(change[treated],
                                                         change[~treated]).statistic,
                               rtol=1e-10)


def within_table(tmp_path, n_subjects=8, times=(0, 1, 2), seed=5):
    rng = np.random.default_rng(seed)
    names, rows = [], []
    for s in range(n_subjects):
        for t in times:
            names.append(f"s{s}_t{t}")
            rows.append([names[-1], f"s{s}", t, round(0.5 * t + rng.normal(), 3)])
    table = write(tmp_path / "within.csv", ["case", "id", "year", "weight"], rows)
    data = (np.repeat(rng.normal(scale=4.0, size=(n_subjects, 15)), len(times), axis=0)
            + rng.normal(size=(n_subjects * len(times), 15))
            + 0.4 * np.tile(times, n_subjects)[:, None])
    return table, names, data


def test_time_within_subjects_is_the_fixed_effects_t_permuted_within_each_subject(tmp_path):
    table, names, data = within_table(tmp_path)
    design = subjects(table, names, subject="id", time="year", nuisance=["weight"])
    assert design.repeated.design == "within" and design.tested == ["year"]
    blocks = design.repeated.blocks
    np.testing.assert_array_equal(blocks, np.repeat(np.arange(8), 3))
    permutations, seed = 200, 9
    config = AnalysisConfig(subject="id", time="year", nuisance=["weight"],
                            permutations=permutations, seed=seed)
    found = point_test(data, design, config)
    assert found.resampling == "permuted within the blocks"
    # the fixed-effects model: an intercept, an indicator per subject after the first, weight
    weight = np.array([float(row[3]) for row in csv.reader(open(table)) if row[0] != "case"])
    own = (blocks[:, None] == np.arange(1, 8)).astype(float)
    years = np.tile([0.0, 1.0, 2.0], 8)
    full = np.column_stack([np.ones(24), own, weight, years])
    np.testing.assert_allclose(found.t, ols_t(data, full), rtol=1e-9)
    # Freedman-Lane by hand: the reduced model's residuals, permuted within each subject
    reduced = full[:, :-1]
    residuals = data - reduced @ np.linalg.lstsq(reduced, data, rcond=None)[0]
    draws = np.vstack([np.arange(24)] + [r for r, _ in drawn_flips(blocks, permutations, seed)])
    assert np.all(blocks[draws] == blocks)
    # case i of resample b gets residual rows[b, i]'s design row: the same as permuting the
    # residuals the other way round
    values = np.array([ols_t(residuals[np.argsort(rows)], full) for rows in draws]) ** 2
    np.testing.assert_allclose(found.p, np.mean(values >= values[0] * (1 - 1e-9), axis=0),
                               rtol=1e-12)


def test_a_categorical_time_within_subjects_is_one_test_over_its_levels(tmp_path):
    table, names, data = within_table(tmp_path)
    design = subjects(table, names, subject="id", time="year", categorical=["year"])
    assert design.interest_names == ["year=1", "year=2"]
    found = point_test(data, design, AnalysisConfig(subject="id", time="year",
                                                    categorical=["year"], permutations=99))
    assert found.t is None and found.effect.shape[0] == 2
    own = (design.repeated.blocks[:, None] == np.arange(1, 8)).astype(float)
    reduced = np.column_stack([np.ones(24), own])
    full = np.column_stack([reduced, design.interest])
    sums = [np.sum((data - x @ np.linalg.lstsq(x, data, rcond=None)[0]) ** 2, axis=0)
            for x in (reduced, full)]
    f = (sums[0] - sums[1]) / 2 / (sums[1] / (24 - full.shape[1]))
    np.testing.assert_allclose(found.statistic, f, rtol=1e-9)


@pytest.mark.parametrize("variance", ["pooled", "groups"])
def test_one_sided_p_values_are_the_two_tails_of_the_signed_statistic(variance):
    rng = np.random.default_rng(11)
    groups = np.repeat([0, 1], [7, 11])
    data = rng.normal(size=(18, 40)) + 1.5 * groups[:, None] * (np.arange(40) < 5)
    kinds = {}
    for tail in ("both", "greater", "less"):
        kinds[tail] = permutation_test(data, groups[:, None].astype(float), permutations=499,
                                       seed=2, variance_groups=groups if variance == "groups"
                                       else None, tail=tail)
    expected = stats.ttest_ind(data[groups == 1], data[groups == 0],
                               equal_var=variance == "pooled").statistic
    for found in kinds.values():
        np.testing.assert_allclose(found.t, expected, rtol=1e-10)
    greater, less = kinds["greater"], kinds["less"]
    # the same resamples: each permuted statistic is counted by one tail or the other (no
    # ties), so the two one-sided p-values add up to (B + 2) / (B + 1)
    np.testing.assert_allclose(greater.p + less.p, 501 / 500, rtol=1e-12)
    assert np.all(greater.p[:5] < 0.05) and np.all(less.p[:5] > 0.95)
    assert np.all(greater.p[:5] <= kinds["both"].p[:5])


def test_a_one_sided_test_of_several_columns_is_refused():
    data = np.random.default_rng(0).normal(size=(12, 5))
    with pytest.raises(InputError, match="one-sided test.*needs one effect column"):
        permutation_test(data, np.eye(12)[:, :2], tail="less")


def test_repeated_measures_tables_are_checked_naming_the_subject(tmp_path):
    header = ["case", "id", "visit", "arm"]
    names = [f"c{k}" for k in range(8)]
    twice = write(tmp_path / "twice.csv", header,
                  [[f"c{k}", f"s{k // 2}", "pre" if k % 2 == 0 or k == 1 else "post", "a"]
                   for k in range(8)])
    with pytest.raises(InputError, match="subject 's0' has two cases at visit='pre' "
                                         r"\(c0, c1\)"):
        subjects(twice, names, subject="id", time="visit")
    moved = write(tmp_path / "moved.csv", header,
                  [[f"c{k}", f"s{k // 2}", "pre" if k % 2 == 0 else "post",
                    "b" if k == 3 else "a" if k < 4 else "b"] for k in range(8)])
    with pytest.raises(InputError, match="'arm' differs between the times of subject 's1'"):
        subjects(moved, names, group="arm", subject="id", time="visit")
    rows = [[f"c{k}", f"s{k // 2}", "pre" if k % 2 == 0 else "post", "a"] for k in range(7)]
    rows.append(["c7", "s4", "post", "a"])                  # s3 has only pre, s4 only post
    alone = subjects(write(tmp_path / "alone.csv", header, rows), names, subject="id",
                     time="visit", baseline="pre")
    assert [(o.case, o.reason) for o in alone.left_out] == [
        ("c6", "subject 's3' has no case at visit='post'"),
        ("c7", "subject 's4' has no case at visit='pre'")]
    assert alone.repeated.subjects == ["s0", "s1", "s2"]
    with pytest.raises(ConfigError, match="--time visit needs --subject"):
        AnalysisConfig(time="visit").validate()
    with pytest.raises(ConfigError, match="tail: must be one of"):
        AnalysisConfig(group="arm", tail="left").validate()


def test_paired_finds_a_change_in_half_the_subjects_that_the_unpaired_test_misses(tmp_path):
    """Two scans of 24 subjects, the subjects differing far more than their scans: a change of
    3 in every other subject at 10 of 100 points, found family-wise by the test of each
    subject's change; the same scans compared as two independent groups (post against pre,
    Welch) find nothing."""
    table, names, data = longitudinal(tmp_path, 24, 100, seed=0)
    paired = subjects(table, names, subject="id", time="visit", baseline="pre")
    found = point_test(data, paired, AnalysisConfig(subject="id", time="visit",
                                                    permutations=999))
    unpaired = subjects(table, names, group="visit", reference="pre")
    missed = point_test(data, unpaired, AnalysisConfig(group="visit", permutations=999))
    assert np.sum(found.p_fwer[:10] <= 0.05) >= 5
    assert np.sum(found.p_fwer[10:] <= 0.05) == 0
    assert np.sum(missed.p_fwer <= 0.05) == 0


def three_groups(tmp_path, seed=12):
    rng = np.random.default_rng(seed)
    groups = ["control"] * 7 + ["mild"] * 6 + ["severe"] * 8
    ages = np.round(rng.normal(60, 8, size=len(groups)), 3)   # as written to the table
    names = [f"c{k:02d}" for k in range(len(groups))]
    table = write(tmp_path / "three.csv", ["case", "stage", "age"],
                  [[n, g, f"{a:.3f}"] for n, g, a in zip(names, groups, ages)])
    spread = np.array([{"control": 1.0, "mild": 1.5, "severe": 3.0}[g] for g in groups])
    data = (rng.normal(size=(len(groups), 30)) * spread[:, None]
            + 0.05 * (ages - 60)[:, None] + 1.2 * (np.array(groups) == "severe")[:, None])
    return table, names, np.array(groups), ages, data


def test_a_contrast_of_levels_is_the_t_of_its_combination_of_coefficients(tmp_path):
    table, names, groups, ages, data = three_groups(tmp_path)
    design = subjects(table, names, group="stage", covariates=["age"])
    config = AnalysisConfig(group="stage", covariates=["age"], variance="pooled",
                            contrasts=["severe-mild", "mild+severe-2*control"],
                            permutations=199)
    maps = signed_maps(data, design, config)
    assert [m.name for m in maps] == ["mild", "severe", "severe-mild", "mild+severe-2*control"]
    assert maps[3].contrast == {"mild": 1.0, "severe": 1.0, "control": -2.0}
    full = np.column_stack([np.ones(len(names)), ages - ages.mean(), groups == "mild",
                            groups == "severe"]).astype(float)
    coefficients = np.linalg.lstsq(full, data, rcond=None)[0]
    errors = data - full @ coefficients
    variance = np.sum(errors ** 2, axis=0) / (len(names) - 4)
    inverse = np.linalg.inv(full.T @ full)
    for found, c in ((maps[2], [0, 0, -1, 1]), (maps[3], [0, 0, 1, 1])):
        c = np.array(c, dtype=float)
        expected = c @ coefficients / np.sqrt(variance * (c @ inverse @ c))
        np.testing.assert_allclose(found.test.t, expected, rtol=1e-9)
        assert found.column == "stage" and found.test.df == len(names) - 4
    # each level's own map is the contrast against the reference
    np.testing.assert_allclose(maps[1].test.t, ols_t(data, full, column=3), rtol=1e-9)


def test_a_contrast_with_a_variance_per_group_is_welchs_t_of_the_two_groups(tmp_path):
    table, names, groups, _, data = three_groups(tmp_path)
    design = subjects(table, names, group="stage")
    maps = signed_maps(data, design, AnalysisConfig(group="stage", contrasts=["severe-mild"],
                                                    tail="greater", permutations=199))
    expected = stats.ttest_ind(data[groups == "severe"], data[groups == "mild"],
                               equal_var=False).statistic
    np.testing.assert_allclose(maps[-1].test.t, expected, rtol=1e-9)
    assert maps[-1].test.variance == "groups" and maps[-1].test.tail == "greater"


def test_contrasts_that_name_no_tested_levels_or_do_not_compare_are_refused(tmp_path):
    table, names, *_ = three_groups(tmp_path)
    design = subjects(table, names, group="stage")
    with pytest.raises(InputError, match="contrast 'severe-moderate': its levels are not all "
                                         "levels of one tested categorical column \\(levels: "
                                         "stage: control, mild, severe\\)"):
        signed_maps(np.zeros((len(names), 3)), design,
                    AnalysisConfig(group="stage", contrasts=["severe-moderate"]))
    with pytest.raises(ConfigError, match="contrast 'severe': write levels joined by"):
        AnalysisConfig(group="stage", contrasts=["severe"]).validate()
    with pytest.raises(ConfigError, match="add up to 1, not 0"):
        AnalysisConfig(group="stage", contrasts=["2*severe-mild"]).validate()
    with pytest.raises(ConfigError, match="'x' is not a number"):
        AnalysisConfig(group="stage", contrasts=["x*severe-mild"]).validate()


def test_a_subjects_group_on_all_their_cases_permutes_whole_subjects(tmp_path):
    """Two cases per subject (left and right, say) and no time: the group, each subject's own,
    tested on every case with the subjects' cases permuted together."""
    rng = np.random.default_rng(21)
    names = [f"s{s}_{side}" for s in range(10) for side in "lr"]
    arms = ["a" if s < 4 else "b" for s in range(10)]
    table = write(tmp_path / "sides.csv", ["case", "id", "arm", "side"],
                  [[f"s{s}_{side}", f"s{s}", arms[s], side] for s in range(10) for side in "lr"])
    design = subjects(table, names, group="arm", nuisance=["side"], categorical=["side"],
                      subject="id")
    assert design.repeated.design == "blocks" and design.tested == ["arm"]
    blocks = design.repeated.blocks
    data = np.repeat(rng.normal(scale=3.0, size=(10, 12)), 2, axis=0) + rng.normal(size=(20, 12))
    config = AnalysisConfig(group="arm", nuisance=["side"], categorical=["side"],
                            subject="id", permutations=150, seed=4)
    assert not config.variance_groups()                  # whole subjects: the pooled statistic
    found = point_test(data, design, config)
    assert found.resampling == "permuted in whole blocks" and found.variance == "pooled"
    b = np.repeat(np.array(arms) == "b", 2).astype(float)
    right = np.tile([0.0, 1.0], 10)
    full = np.column_stack([np.ones(20), right, b])
    np.testing.assert_allclose(found.t, ols_t(data, full), rtol=1e-9)
    draws = np.vstack([np.arange(20)] + [r for r, _ in drawn_whole_blocks(blocks, 150, 4)])
    assert np.all(blocks[draws][:, 0::2] == blocks[draws][:, 1::2])   # pairs stay together
    assert np.all(right[draws] == right)                 # each side keeps its place
    reduced = full[:, :-1]
    residuals = data - reduced @ np.linalg.lstsq(reduced, data, rcond=None)[0]
    values = np.array([ols_t(residuals, full[rows]) for rows in draws]) ** 2
    np.testing.assert_allclose(found.p, np.mean(values >= values[0] * (1 - 1e-9), axis=0),
                               rtol=1e-12)
    moved = write(tmp_path / "moved.csv", ["case", "id", "arm", "side"],
                  [[f"s{s}_{side}", f"s{s}", "b" if (s, side) == (2, "r") else arms[s], side]
                   for s in range(10) for side in "lr"])
    with pytest.raises(InputError, match="'arm' varies within subject 's2' \\(a, b\\)"):
        subjects(moved, names, group="arm", subject="id")


def test_the_mean_change_of_a_vector_is_the_one_sample_hotelling_t2(tmp_path):
    table, names, _ = longitudinal(tmp_path, 12, 4, seed=8)
    design = subjects(table, names, subject="id", time="visit", baseline="pre")
    rng = np.random.default_rng(8)
    vectors = rng.normal(size=(24, 4, 3)) + np.repeat(rng.normal(size=(12, 4, 3)), 2, axis=0)
    vectors[1::2, 0] += [0.8, 0.0, -0.5]                   # every post scan moves at point 0
    found = point_test(vectors, design, AnalysisConfig(subject="id", time="visit",
                                                       permutations=99))
    change = vectors[1::2] - vectors[0::2]
    for k in range(4):
        mean = change[:, k].mean(axis=0)
        covariance = np.cov(change[:, k], rowvar=False)
        np.testing.assert_allclose(found.statistic[k],
                                   12 * mean @ np.linalg.solve(covariance, mean), rtol=1e-9)
    assert found.t is None and found.name == "Hotelling's T^2 (one pooled covariance)"
    np.testing.assert_allclose(found.effect[0], change.mean(axis=0), rtol=1e-10)


def test_an_interaction_is_the_t_of_the_product_with_both_columns_adjusted_for(tmp_path):
    table, names, groups, ages, data = three_groups(tmp_path)
    two = groups != "mild"
    names, ages, data = [n for n, k in zip(names, two) if k], ages[two], data[two]
    design = subjects(table, names, group="stage", covariates=["age"],
                      interactions=["stage:age"])
    assert design.tested == ["stage:age"] and design.adjusted_for == ["stage", "age"]
    assert design.interest_names == ["severe:age"]
    found = point_test(data, design, AnalysisConfig(group="stage", covariates=["age"],
                                                    interactions=["stage:age"],
                                                    permutations=99))
    assert found.variance == "pooled"                    # the group is adjusted for
    severe = (groups[two] == "severe").astype(float)
    centred = ages - ages.mean()
    full = np.column_stack([np.ones(len(names)), severe, centred, severe * centred])
    np.testing.assert_allclose(found.t, ols_t(data, full), rtol=1e-9)
    with pytest.raises(ConfigError, match="interaction 'stage:height': write two different"):
        AnalysisConfig(group="stage", covariates=["age"], interactions=["stage:height"]).roles()
