"""Effect maps with uncertainty: per-point confidence intervals, Cohen's d, partial eta^2 and the
effect's shapes, against direct formulas, by simulation, and through the real command on a real
build (mdlshapemodel.analysis.effects, analyze_build's points.csv, analysis.json, shapes/)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import vtk
from scipy import stats
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.analysis import align, subjects
from mdlshapemodel.analysis.effects import (PREDICTED_AT, cohens_d, interval,
                                            partial_eta_squared)
from mdlshapemodel.analysis.study import effects_of
from mdlshapemodel.config import AnalysisConfig
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.report.html import html_page
from mdlshapemodel.report.viewer import EffectMap, effects_section

from browser import browser, open_page  # noqa: F401 (browser: a fixture)
from common import run_cli
from test_analyze import N, area_normals, build, read_points, shapes_of, write_table  # noqa: F401


def ols(y: np.ndarray, design: np.ndarray) -> tuple:
    """Ordinary least squares from its definition: coefficients, their covariance
    s^2 (X'X)^-1 and the residual degrees of freedom."""
    inverse = np.linalg.inv(design.T @ design)
    beta = inverse @ design.T @ y
    residual = y - design @ beta
    df = len(y) - design.shape[1]
    return beta, residual @ residual / df * inverse, df


@pytest.fixture
def study(rng):
    """30 cases in three groups with age and sex as nuisance, correlated with the groups."""
    n = 30
    groups = np.repeat([0, 1, 2], 10)
    age = rng.normal(60, 8, n) + 3.0 * groups
    sex = rng.integers(0, 2, n).astype(float)
    indicators = np.column_stack([groups == 1, groups == 2]).astype(float)
    nuisance = np.column_stack([age - age.mean(), sex - sex.mean()])
    data = (rng.normal(size=(n, 20)) * (1.0 + groups)[:, None] + 0.05 * age[:, None]
            + 0.8 * indicators[:, :1])
    return {"n": n, "groups": groups, "indicators": indicators, "nuisance": nuisance,
            "data": data}


def test_the_pooled_interval_is_students_from_the_least_squares_fit_with_nuisance(study):
    design = np.column_stack([np.ones(study["n"]), study["nuisance"], study["indicators"]])
    for vector in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, -1.0])):
        found = interval(study["data"], study["indicators"], vector, study["nuisance"],
                         level=0.9)
        assert found.variance == "pooled" and found.level == 0.9
        for k in range(study["data"].shape[1]):
            beta, covariance, df = ols(study["data"][:, k], design)
            c = np.r_[0.0, 0.0, 0.0, vector]
            half = stats.t.ppf(0.95, df) * np.sqrt(c @ covariance @ c)
            assert found.estimate[k] == pytest.approx(c @ beta, abs=1e-10)
            assert found.lower[k] == pytest.approx(c @ beta - half, abs=1e-10)
            assert found.upper[k] == pytest.approx(c @ beta + half, abs=1e-10)
            assert found.df[k] == df


def test_the_welch_interval_of_two_groups_is_scipys_and_with_nuisance_satterthwaites(study):
    two = study["groups"] < 2
    data, groups = study["data"][two], study["groups"][two]
    found = interval(data, groups[:, None].astype(float), np.ones(1), groups=groups)
    pooled = interval(data, groups[:, None].astype(float), np.ones(1))
    for k in range(data.shape[1]):
        welch = stats.ttest_ind(data[groups == 1, k], data[groups == 0, k], equal_var=False)
        plain = stats.ttest_ind(data[groups == 1, k], data[groups == 0, k])
        np.testing.assert_allclose([found.lower[k], found.upper[k]],
                                   welch.confidence_interval(), rtol=1e-10)
        np.testing.assert_allclose([pooled.lower[k], pooled.upper[k]],
                                   plain.confidence_interval(), rtol=1e-10)
        assert found.df[k] == pytest.approx(welch.df, rel=1e-10)

    # with nuisance and three groups: the least-squares estimate, its variance with one
    # variance per group (each from the group's residuals over sum of 1 - h_ii) and
    # Satterthwaite's degrees of freedom, written out here case by case
    n, groups = study["n"], study["groups"]
    design = np.column_stack([np.ones(n), study["nuisance"], study["indicators"]])
    found = interval(study["data"], study["indicators"], np.array([0.0, 1.0]),
                     study["nuisance"], groups=groups)
    hat = design @ np.linalg.inv(design.T @ design) @ design.T
    a = (np.linalg.inv(design.T @ design) @ design.T)[-1]
    for k in range(study["data"].shape[1]):
        y = study["data"][:, k]
        residual = y - hat @ y
        terms, shares = 0.0, 0.0
        for g in range(3):
            members = groups == g
            nu = np.sum(1 - np.diag(hat)[members])
            part = np.sum(residual[members] ** 2) / nu * np.sum(a[members] ** 2)
            terms += part
            shares += part ** 2 / nu
        half = stats.t.ppf(0.975, terms ** 2 / shares) * np.sqrt(terms)
        assert found.estimate[k] == pytest.approx(a @ y, abs=1e-10)
        assert found.upper[k] - found.lower[k] == pytest.approx(2 * half, rel=1e-9)
        assert found.df[k] == pytest.approx(terms ** 2 / shares, rel=1e-9)


def test_cohens_d_and_partial_eta2_are_the_plain_formulas(study):
    two = study["groups"] < 2
    data, groups = study["data"][two], study["groups"][two]
    a, b = data[groups == 0], data[groups == 1]
    pooled_sd = np.sqrt(((len(a) - 1) * a.var(0, ddof=1) + (len(b) - 1) * b.var(0, ddof=1))
                        / (len(a) + len(b) - 2))
    column = groups[:, None].astype(float)
    np.testing.assert_allclose(cohens_d(interval(data, column, np.ones(1))),
                               (b.mean(0) - a.mean(0)) / pooled_sd, rtol=1e-10)
    mean_variance = np.sqrt((a.var(0, ddof=1) + b.var(0, ddof=1)) / 2)
    np.testing.assert_allclose(
        cohens_d(interval(data, column, np.ones(1), groups=groups), (0, 1)),
        (b.mean(0) - a.mean(0)) / mean_variance, rtol=1e-10)

    # with nuisance: the adjusted difference over the adjusted residual SD; partial eta^2 of
    # one column t^2 / (t^2 + df), of two columns 1 - SSE_full / SSE_reduced
    n = study["n"]
    reduced = np.column_stack([np.ones(n), study["nuisance"]])
    design = np.column_stack([reduced, study["indicators"]])
    found = interval(study["data"], study["indicators"], np.array([0.0, 1.0]),
                     study["nuisance"])
    both = partial_eta_squared(study["data"], study["indicators"], study["nuisance"])
    one = partial_eta_squared(study["data"], study["indicators"][:, 1:],
                              np.column_stack([study["nuisance"], study["indicators"][:, :1]]))
    for k in range(study["data"].shape[1]):
        y = study["data"][:, k]
        beta, covariance, df = ols(y, design)
        residual = y - design @ beta
        assert cohens_d(found)[k] == pytest.approx(
            beta[-1] / np.sqrt(residual @ residual / df), rel=1e-10)
        t2 = beta[-1] ** 2 / covariance[-1, -1]
        assert one[k] == pytest.approx(t2 / (t2 + df), rel=1e-9)
        small = y - reduced @ np.linalg.lstsq(reduced, y, rcond=None)[0]
        assert both[k] == pytest.approx(1 - (residual @ residual) / (small @ small), rel=1e-9)


def test_the_multivariate_partial_eta2_is_pillais_trace_over_min_q_r(rng):
    n = 25
    y = rng.normal(size=(n, 4, 3))
    x = rng.normal(size=(n, 2))
    y[:, 0] += x @ rng.normal(size=(2, 3))
    found = partial_eta_squared(y, x)
    for k in range(4):
        centred = y[:, k] - y[:, k].mean(0)
        full = np.column_stack([np.ones(n), x])
        error = centred - full @ np.linalg.lstsq(full, centred, rcond=None)[0]
        total, residual = centred.T @ centred, error.T @ error
        assert found[k] == pytest.approx(
            np.trace((total - residual) @ np.linalg.inv(total)) / 2, rel=1e-9)


@pytest.mark.parametrize("sizes, spreads, groups", [((10, 10), (1.0, 1.0), False),
                                                    ((6, 24), (3.0, 1.0), True),
                                                    ((10, 30), (1.5, 1.0), True)])
def test_the_interval_covers_the_planted_truth_at_its_level(rng, sizes, spreads, groups):
    """4000 independent points, a planted group difference of 0.7 and a nuisance covariate
    correlated with the group: the 95 % interval covers 0.7 at 95 % +- 3 binomial SE (with
    unequal variances and sizes by the Welch interval)."""
    points, truth = 4000, 0.7
    group = np.repeat([0, 1], sizes)
    age = rng.normal(size=len(group)) + 0.8 * group
    noise = rng.normal(size=(len(group), points)) * np.repeat(spreads, sizes)[:, None]
    data = truth * group[:, None] + 0.5 * age[:, None] + noise
    found = interval(data, group[:, None].astype(float), np.ones(1),
                     (age - age.mean())[:, None], groups=group if groups else None)
    covered = np.mean((found.lower <= truth) & (truth <= found.upper))
    se = np.sqrt(0.95 * 0.05 / points)
    assert abs(covered - 0.95) < 3 * se, covered


def test_each_covariate_and_contrast_gets_its_interval_adjusted_for_the_rest(rng, tmp_path):
    """Two covariates and a site nuisance from a real table: each covariate's interval and
    partial eta^2 are those of its coefficient with the other covariate and the site in the
    model; three groups with a contrast: Welch-type intervals, and d only for the levels."""
    n = 36
    names = [f"c{k}" for k in range(n)]
    age, volume = rng.normal(60, 8, n), rng.normal(3, 0.4, n)
    site = rng.integers(1, 4, n)
    group = np.array(["control", "mild", "severe"])[np.arange(n) % 3]
    data = (rng.normal(size=(n, 15)) + 0.04 * age[:, None] - 0.8 * volume[:, None]
            + 0.3 * (site == 2)[:, None])
    table = write_table(tmp_path / "subjects.csv",
                        [[c, g, a, v, s] for c, g, a, v, s in zip(names, group, age, volume,
                                                                  site)],
                        header=("case", "group", "age", "volume", "site"))
    design = subjects(table, names, covariates=["age", "volume"], nuisance=["site"],
                      categorical=["site"])
    config = AnalysisConfig(covariates=["age", "volume"], nuisance=["site"],
                            categorical=["site"], alpha=0.1)
    found = effects_of(data, design, config)
    assert [e.name for e in found] == ["age", "volume"]
    matrix = np.column_stack([np.ones(n), site == 2, site == 3, age, volume])
    for column, effect in zip((3, 4), found):
        assert effect.d is None and effect.interval.level == pytest.approx(0.9)
        for k in range(data.shape[1]):
            beta, covariance, df = ols(data[:, k], matrix)
            half = stats.t.ppf(0.95, df) * np.sqrt(covariance[column, column])
            assert effect.interval.lower[k] == pytest.approx(beta[column] - half, abs=1e-10)
            assert effect.interval.upper[k] == pytest.approx(beta[column] + half, abs=1e-10)
            t2 = beta[column] ** 2 / covariance[column, column]
            assert effect.partial_eta2[k] == pytest.approx(t2 / (t2 + df), rel=1e-9)

    design = subjects(table, names, group="group", nuisance=["age"])
    config = AnalysisConfig(group="group", nuisance=["age"], contrasts=["severe-mild"])
    found = effects_of(data, design, config)
    assert [e.name for e in found] == ["mild", "severe", "severe-mild"]
    assert all(e.interval.variance == "groups" for e in found)
    codes = np.searchsorted(["control", "mild", "severe"], group)
    indicators = np.column_stack([codes == 1, codes == 2]).astype(float)
    contrast = interval(data, indicators, np.array([-1.0, 1.0]),
                        (age - age.mean())[:, None], groups=codes)
    np.testing.assert_allclose(found[2].interval.lower, contrast.lower, atol=1e-10)
    np.testing.assert_allclose(found[2].interval.upper, contrast.upper, atol=1e-10)
    np.testing.assert_allclose(found[2].d, contrast.estimate / np.sqrt(
        (contrast.spread[1] + contrast.spread[2]) / 2), rtol=1e-10)
    severe = interval(data, indicators, np.array([0.0, 1.0]), (age - age.mean())[:, None],
                      groups=codes)
    np.testing.assert_allclose(found[1].d, severe.estimate / np.sqrt(
        (severe.spread[0] + severe.spread[2]) / 2), rtol=1e-10)


def test_the_mean_change_has_the_paired_interval_and_d_and_whole_subjects_none(rng,
                                                                                tmp_path):
    """Two scans per subject, nothing else tested: the interval of the mean change is the
    one-sample t interval of the subjects' changes, d their mean over their SD (Cohen's d_z);
    a subject's columns on all its cases (--subject alone): no interval (cases not
    independent)."""
    n = 12
    names = [f"s{k}_{visit}" for k in range(n) for visit in ("pre", "post")]
    table = write_table(tmp_path / "visits.csv",
                        [[f"s{k}_{visit}", k, visit, k % 2] for k in range(n)
                         for visit in ("pre", "post")], header=("case", "id", "visit", "arm"))
    data = rng.normal(size=(2 * n, 8))
    data[1::2] += 0.5
    design = subjects(table, names, subject="id", time="visit", baseline="pre")
    config = AnalysisConfig(subject="id", time="visit", baseline="pre")
    (found,) = effects_of(data, design, config)
    change = data[1::2] - data[0::2]
    paired = stats.ttest_1samp(change, 0.0).confidence_interval()
    np.testing.assert_allclose(found.interval.lower, paired.low, rtol=1e-10)
    np.testing.assert_allclose(found.interval.upper, paired.high, rtol=1e-10)
    np.testing.assert_allclose(found.d, change.mean(0) / change.std(0, ddof=1), rtol=1e-10)

    whole = subjects(table, names, covariates=["arm"], subject="id")
    assert effects_of(data, whole, AnalysisConfig(covariates=["arm"], subject="id")) == []


@pytest.fixture(scope="module")
def findings(build, tmp_path_factory):
    """The real command on the fixture build: a group with age as nuisance, and age alone."""
    folder = tmp_path_factory.mktemp("effects")
    rows = [[f"case_{k:02d}", "thin" if k % 2 else "full", 40 + 3 * k + 2 * (k % 3), "F"]
            for k in range(N)]
    table = write_table(folder / "subjects.csv", rows)
    outputs = {}
    for name, options in (("group", ("--group", "group", "--nuisance", "age")),
                          ("age", ("--covariate", "age"))):
        outputs[name] = folder / name
        result = run_cli("analyze", build, "--table", table, *options, "--permutations", "99",
                         "-o", outputs[name], "-q")
        assert result.returncode == 0, result.stderr
    return outputs


def recomputed(build, output) -> tuple:
    """The analysis's aligned shapes, mean and its normals recomputed from the build's files."""
    model = ShapeModel.load(build / "model.h5")
    names = [f"case_{k:02d}" for k in range(N)]
    aligned = align(shapes_of(build, names), model.weights)
    mean = aligned.mean(axis=0)
    normals = area_normals(mean, model.triangles)
    return model, aligned, mean, normals / np.linalg.norm(normals, axis=1)[:, None]


def read_vtp(path) -> tuple:
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    polydata = reader.GetOutput()
    cells = vtk_to_numpy(polydata.GetPolys().GetConnectivityArray()).reshape(-1, 3)
    data = polydata.GetPointData()
    arrays = {data.GetArrayName(k): vtk_to_numpy(data.GetArray(k))
              for k in range(data.GetNumberOfArrays())}
    return vtk_to_numpy(polydata.GetPoints().GetData()), cells, arrays


@pytest.mark.slow
def test_the_commands_intervals_and_d_are_recomputed_from_the_files(build, findings):
    output = findings["group"]
    _, aligned, mean, normals = recomputed(build, output)
    normal = np.einsum("npd,pd->np", aligned - mean, normals)
    thin = np.array([k % 2 for k in range(N)])
    age = np.array([40 + 3 * k + 2 * (k % 3) for k in range(N)], dtype=float)
    design = np.column_stack([np.ones(N), age, thin])
    hat = design @ np.linalg.inv(design.T @ design) @ design.T
    a = (np.linalg.inv(design.T @ design) @ design.T)[-1]
    residual = normal - hat @ normal
    variances = np.stack([np.sum(residual[thin == g] ** 2, axis=0)
                          / np.sum(1 - np.diag(hat)[thin == g]) for g in (0, 1)])
    parts = variances * np.array([np.sum(a[thin == g] ** 2) for g in (0, 1)])[:, None]
    nu = np.array([np.sum(1 - np.diag(hat)[thin == g]) for g in (0, 1)])
    df = parts.sum(0) ** 2 / np.sum(parts ** 2 / nu[:, None], axis=0)
    estimate = a @ normal
    half = stats.t.ppf(0.975, df) * np.sqrt(parts.sum(0))
    points = read_points(output / "points.csv")
    scale = np.abs(estimate).max()
    np.testing.assert_allclose(points["normal_difference_mm"].astype(float), estimate,
                               atol=1e-5 * scale)
    np.testing.assert_allclose(points["ci_lower_mm"].astype(float), estimate - half,
                               atol=1e-4 * scale)
    np.testing.assert_allclose(points["ci_upper_mm"].astype(float), estimate + half,
                               atol=1e-4 * scale)
    d = estimate / np.sqrt(variances.mean(0))
    np.testing.assert_allclose(points["cohens_d"].astype(float), d, rtol=1e-4, atol=1e-6)
    reduced = design[:, :2]
    small = normal - reduced @ np.linalg.lstsq(reduced, normal, rcond=None)[0]
    eta = 1 - np.sum(residual ** 2, 0) / np.sum(small ** 2, 0)
    np.testing.assert_allclose(points["partial_eta2"].astype(float), eta, rtol=1e-4, atol=1e-7)

    summary = json.loads((output / "analysis.json").read_text())
    sizes = summary["effect_sizes"]
    assert sizes["intervals"] == {"kind": "Welch-Satterthwaite, a variance per group",
                                  "level": 0.95}
    (entry,) = sizes["maps"]
    written = points["cohens_d"].astype(float)
    assert entry["cohens_d"]["largest_abs"] == pytest.approx(np.abs(written).max(), rel=1e-5)
    assert entry["cohens_d"]["median_abs"] == pytest.approx(np.median(np.abs(written)),
                                                            rel=1e-4)
    assert entry["half_width_mm"]["median"] == pytest.approx(np.median(half), rel=1e-4)
    page = (output / "analysis.html").read_text()
    assert "Cohen" in page and "confidence interval" in page


@pytest.mark.slow
def test_the_group_mean_shapes_read_back_with_vtk_are_the_aligned_groups_means(build,
                                                                               findings):
    output = findings["group"]
    model, aligned, _, normals = recomputed(build, output)
    thin = np.array([k % 2 for k in range(N)]) == 1
    means = {"full": aligned[~thin].mean(0), "thin": aligned[thin].mean(0)}
    summary = json.loads((output / "analysis.json").read_text())
    assert [s["file"] for s in summary["shapes"]] == ["shapes/group=full.vtp",
                                                      "shapes/group=thin.vtp"]
    change = means["thin"] - means["full"]
    for level in means:
        points, cells, arrays = read_vtp(output / "shapes" / f"group={level}.vtp")
        np.testing.assert_allclose(points, means[level], atol=1e-5)
        np.testing.assert_array_equal(cells, model.triangles)
        np.testing.assert_allclose(arrays["displacement"], change, atol=1e-9)
        np.testing.assert_allclose(arrays["normal_displacement_mm"],
                                   np.einsum("pd,pd->p", change, normals), atol=1e-9)


@pytest.mark.slow
def test_a_covariates_predicted_shapes_are_at_its_percentiles(build, findings):
    output = findings["age"]
    _, aligned, mean, normals = recomputed(build, output)
    age = np.array([40 + 3 * k + 2 * (k % 3) for k in range(N)], dtype=float)
    design = np.column_stack([np.ones(N), age])
    slope = np.linalg.lstsq(design, (aligned - mean).reshape(N, -1), rcond=None)[0][1]
    slope = slope.reshape(-1, 3)
    summary = json.loads((output / "analysis.json").read_text())
    low, high = np.percentile(age, PREDICTED_AT)
    assert [(s["file"], s["value"]) for s in summary["shapes"]] == [
        ("shapes/age_p10.vtp", pytest.approx(low)), ("shapes/age_p90.vtp", pytest.approx(high))]
    for name, value in (("age_p10", low), ("age_p90", high)):
        points, _, arrays = read_vtp(output / "shapes" / f"{name}.vtp")
        np.testing.assert_allclose(points, mean + (value - age.mean()) * slope, atol=1e-5)
        np.testing.assert_allclose(arrays["normal_displacement_mm"],
                                   (high - low) * np.einsum("pd,pd->p", slope, normals),
                                   atol=1e-8)
    points = read_points(output / "points.csv")
    assert "cohens_d" not in points           # a covariate has no d: partial eta^2 only
    eta = points["partial_eta2"].astype(float)
    normal = np.einsum("npd,pd->np", aligned - mean, normals)
    r = np.array([np.corrcoef(age, normal[:, k])[0, 1] for k in range(normal.shape[1])])
    np.testing.assert_allclose(eta, r ** 2, rtol=1e-4, atol=1e-7)


def test_choosing_a_shapes_map_in_a_browser_draws_that_shape(browser, tmp_path):
    """The viewer draws a map with its own points on them (a group's mean shape) and goes back
    to the mean surface for a map without."""
    mean, triangles = sphere_grid(162)
    mean = 10.0 * mean
    stretched = mean * np.array([1.3, 1.0, 0.8])
    section = effects_section(mean, triangles, [
        EffectMap("effect [mm]", mean[:, 0], diverging=True),
        EffectMap("mean shape of group b", stretched[:, 0] - mean[:, 0], diverging=True,
                  points=stretched)])
    path = tmp_path / "shapes.html"
    path.write_text(html_page("shapes", section), encoding="utf-8")
    page, errors, requests = open_page(browser, path, drawn="#effects-plot canvas")

    def drawn() -> np.ndarray:
        page.wait_for_timeout(300)
        return np.array(page.evaluate(
            "(() => { var d = document.getElementById('effects-plot').data[0];"
            " return [d.x, d.y, d.z]; })()")).T

    np.testing.assert_allclose(drawn(), mean, atol=1e-4)
    page.select_option("#effects-map", "1")
    np.testing.assert_allclose(drawn(), stretched, atol=1e-4)
    page.select_option("#effects-map", "0")
    np.testing.assert_allclose(drawn(), mean, atol=1e-4)
    assert errors == [] and requests == []
    page.close()
