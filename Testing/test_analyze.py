"""`mdlshapemodel analyze` end to end: the real command in a subprocess on a real build, every
number of analysis.json recomputed here, the files read back by VTK, bad tables refused."""

from __future__ import annotations

import csv
import html
import json
from pathlib import Path

import numpy as np
import pytest
import vtk
from scipy import stats
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel.analyze import AnalysisFolder
from mdlshapemodel.analysis import align, permutation_test
from mdlshapemodel.analysis.glm import drawn_flips, drawn_permutations
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare import io

from common import empirical_null_p, run_cli
from synthetic import thin_and_full_build

# every test here works on one real build (build_model) and the real command line
pytestmark = pytest.mark.slow

N = 12


@pytest.fixture(scope="module")
def build(tmp_path_factory) -> Path:
    """Twelve small bumpy ellipsoids; the 'thin' half is 8% smaller, so groups differ in size."""
    return thin_and_full_build(tmp_path_factory.mktemp("analyze"), N)


def write_table(path: Path, rows: list, header=("case", "group", "age", "sex")) -> Path:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)
    return path


@pytest.fixture(scope="module")
def table(build) -> Path:
    rows = [[f"case_{k:02d}", "thin" if k % 2 else "full", 40 + 3 * k, "F" if k % 3 else "M"]
            for k in range(N)]
    rows[5][1] = ""                                          # no group: left out
    rows.append(["case_99", "full", 50, "F"])                # no such case
    return write_table(build.parent / "subjects.csv", rows)


@pytest.fixture(scope="module")
def analysed(build, table) -> Path:
    output = build.parent / "findings"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "-o", output,
                     "--permutations", "999", "-q")
    assert result.returncode == 0, result.stderr
    assert "page:" in result.stdout
    return output


def read_points(path: Path) -> dict:
    rows = io.read_csv(path)
    return {key: np.array([row[key] for row in rows]) for key in rows[0]}


def shapes_of(build: Path, names: list) -> np.ndarray:
    return np.stack([io.read_mesh(io.case_file(build / "correspondence", n))[0] for n in names])


def vtk_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Point normals computed by VTK's own filter (outward for the model's orientation; it
    averages unit face normals, where the analysis weights them by area)."""
    from mdlshapemodel.prepare.surface import arrays_to_polydata

    normals = vtk.vtkPolyDataNormals()
    normals.SetInputData(arrays_to_polydata(points, triangles))
    normals.SplittingOff()
    normals.ConsistencyOff()
    normals.AutoOrientNormalsOff()
    normals.ComputePointNormalsOn()
    normals.Update()
    return vtk_to_numpy(normals.GetOutput().GetPointData().GetNormals()).astype(np.float64)


def area_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Point normals as the sums of the area-weighted normals of the triangles around them."""
    corners = points[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    summed = np.zeros_like(points)
    for k in range(3):
        np.add.at(summed, triangles[:, k], face)
    return summed


def test_every_number_of_analysis_json_is_recomputed(build, table, analysed):
    summary = json.loads((analysed / "analysis.json").read_text())
    used = [f"case_{k:02d}" for k in range(N) if k != 5]
    assert summary["n_cases"] == 11
    assert summary["n_per_group"] == {"full": 6, "thin": 5}
    assert summary["left_out"] == [{"case": "case_05", "reason": "no value for 'group'",
                                    "missing": {"group": ""}}]
    assert summary["unmatched_rows"] == ["case_99"]
    points = read_points(analysed / "points.csv")
    assert summary["significant_points"] == {
        "fwer": int(np.sum(points["p_fwer"].astype(float) <= 0.05)),
        "fdr": int(np.sum(points["q_fdr"].astype(float) <= 0.05)), "of": 162}

    # the per-point statistic: Welch's v^2 of the normal displacement (a variance per group,
    # the default), normals from VTK's filter
    model = ShapeModel.load(build / "model.h5")
    aligned = align(shapes_of(build, used), model.weights)
    mean = aligned.mean(axis=0)
    np.testing.assert_allclose(np.column_stack([points[c].astype(float) for c in "xyz"]), mean,
                               atol=5e-5 * np.abs(mean).max())
    thin = np.array([int(n[-2:]) % 2 == 1 for n in used])
    written = points["statistic"].astype(float)
    for normals, exact in ((area_normals(mean, model.triangles), True),
                           (vtk_normals(mean, model.triangles), False)):
        unit = normals / np.linalg.norm(normals, axis=1)[:, None]
        normal = np.einsum("npd,pd->np", aligned - mean, unit)
        t = stats.ttest_ind(normal[thin], normal[~thin], equal_var=False).statistic
        if exact:
            np.testing.assert_allclose(written, t ** 2, rtol=1e-5)
        else:   # VTK's normals are another average of the triangles' around each point
            relative = np.abs(written - t ** 2) / t ** 2
            assert np.median(relative) < 0.01 and np.mean(relative < 0.05) > 0.9
    difference = aligned[thin].mean(0) - aligned[~thin].mean(0)
    np.testing.assert_allclose(
        np.column_stack([points[f"difference_{c}"].astype(float) for c in "xyz"]), difference,
        atol=1e-5)

    # the global test: Hotelling's T^2 on the principal scores explaining 95 %
    root = np.sqrt(model.weights)[None, :, None]
    centred = ((aligned - mean) * root).reshape(len(used), -1)
    u, s, _ = np.linalg.svd(centred, full_matrices=False)
    k = summary["global_test"]["modes"]
    explained = np.cumsum(s ** 2) / np.sum(s ** 2)
    assert k == min(int(np.searchsorted(explained, 0.95) + 1), len(used) - 3)
    scores = u[:, :k] * s[:k]
    a, b = scores[~thin], scores[thin]
    pooled = ((a - a.mean(0)).T @ (a - a.mean(0)) + (b - b.mean(0)).T @ (b - b.mean(0))) / (
        len(used) - 2)
    d = b.mean(0) - a.mean(0)
    t2 = len(a) * len(b) / len(used) * d @ np.linalg.solve(pooled, d)
    assert summary["global_test"]["statistic"] == pytest.approx(t2, rel=1e-6)
    # its p: the permutation test (B = 999, the default seed) of the scores computed here
    again = permutation_test(scores[:, None, :], thin[:, None].astype(float), permutations=999,
                             seed=0)
    assert summary["global_test"]["p"] == pytest.approx(float(again.p[0]), rel=1e-9)

    # unusual cases: the distance at which p, against the empirical null of the scaled Beta's
    # p-values over the model's own modes, is 0.01
    unusual = summary["unusual"]
    n, m = len(model.names), unusual["modes"]
    rows = io.read_csv(analysed / "unusual.csv")
    distance = np.sqrt(np.sum(model.scores[:, :m] ** 2 / model.variances[:m], axis=1))
    np.testing.assert_allclose([float(r["mahalanobis"]) for r in rows], distance, rtol=1e-5)
    reference = stats.beta(m / 2, (n - m - 1) / 2)
    p_normal = reference.sf(distance ** 2 / (n - 1))
    at = np.sqrt((n - 1) * reference.isf(np.geomspace(1e-12, 0.5, 4001)))
    for i, threshold in enumerate(unusual["thresholds"]):          # each case against the others
        p = empirical_null_p(reference.sf(at ** 2 / (n - 1)), np.delete(p_normal, i))
        assert threshold == pytest.approx(at[np.argmin(np.abs(p - 0.01))], rel=1e-2)
    assert unusual["flagged"] == [r["case"] for r in rows if r["flagged"] == "True"]

    classification = summary["classification"]
    assert classification["auc"] == pytest.approx(np.mean(classification["fold_auc"]))
    assert classification["balanced_accuracy"] == pytest.approx(
        np.mean(classification["fold_balanced_accuracy"]))
    assert classification["folds"] == 5             # the smaller group has 5 cases


def test_the_groups_that_differ_in_size_are_found_with_the_size_kept(analysed):
    summary = json.loads((analysed / "analysis.json").read_text())
    assert summary["global_test"]["p"] < 0.01
    assert summary["significant_points"]["fwer"] > 0
    normal = read_points(analysed / "points.csv")["normal_difference_mm"].astype(float)
    assert np.median(normal) < 0               # the thin group lies inside the full one


def test_effects_vtp_holds_the_points_csv_values_for_vtk(analysed):
    polydata = io.read_polydata(analysed / "effects.vtp")
    points = read_points(analysed / "points.csv")
    assert polydata.GetNumberOfPoints() == 162 and polydata.GetNumberOfPolys() == 320
    data = polydata.GetPointData()
    for name in ("statistic", "p_fwer", "q_fdr", "normal_difference_mm"):
        np.testing.assert_allclose(vtk_to_numpy(data.GetArray(name)),
                                   points[name].astype(float), rtol=1e-5)
    assert data.GetArray("difference").GetNumberOfComponents() == 3
    significant = vtk_to_numpy(data.GetArray("significant_fwer"))
    assert significant.sum() == np.sum(points["p_fwer"].astype(float) <= 0.05)
    summary = json.loads((analysed / "analysis.json").read_text())
    page = (analysed / "analysis.html").read_text()
    counts, overall = summary["significant_points"], summary["global_test"]
    assert (f"<p>{counts['fwer']} of 162 points significant at &alpha; = 0.05 after "
            f"family-wise correction, {counts['fdr']} after FDR correction") in page
    assert (f"statistic {overall['statistic']:.4g}, permutation p = {overall['p']:.4g}."
            in page)
    departures = list((analysed / "unusual").iterdir())
    assert len(departures) == N


def test_the_analysis_folder_reads_what_the_analysis_wrote(analysed):
    folder = AnalysisFolder(analysed)
    assert folder.summary() == json.loads((analysed / "analysis.json").read_text())
    assert folder.effect_meshes() == [analysed / "effects.vtp"]
    assert folder.page_file == analysed / "analysis.html" and folder.page_file.is_file()
    columns = folder.points()
    with open(analysed / "points.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(columns) == list(rows[0]) and len(columns["p_fwer"]) == len(rows) == 162
    assert columns["point"] == list(range(162)) and set(columns["part"]) == {0}
    np.testing.assert_array_equal(columns["p_fwer"], [float(r["p_fwer"]) for r in rows])


def normal_displacement(build: Path, names: list) -> np.ndarray:
    """Each case's displacement from the mean along the mean's area-weighted normals (n, p)."""
    model = ShapeModel.load(build / "model.h5")
    aligned = align(shapes_of(build, names), model.weights)
    mean = aligned.mean(axis=0)
    normals = area_normals(mean, model.triangles)
    unit = normals / np.linalg.norm(normals, axis=1)[:, None]
    return np.einsum("npd,pd->np", aligned - mean, unit)


def own_p(values: np.ndarray) -> np.ndarray:
    """Each row's per-point p among all rows (smaller values: more extreme), by column."""
    return np.mean(values[None] <= values[:, None] + 1e-9 * np.abs(values[:, None]), axis=1)


def test_points_csv_p_is_each_points_own_and_recomputed_by_plain_loops(build, table, analysed,
                                                                       tmp_path):
    used = [f"case_{k:02d}" for k in range(N) if k != 5]
    y = normal_displacement(build, used)
    thin = np.array([int(n[-2:]) % 2 == 1 for n in used])
    points = read_points(analysed / "points.csv")
    summary = json.loads((analysed / "analysis.json").read_text())
    assert summary["point_test"]["variance"] == "groups"
    assert summary["point_test"]["variance_groups"] == {"full": 6, "thin": 5}
    assert summary["point_test"]["smallest_p"] == pytest.approx(1 / 1000)
    # the default: Welch's p of the sign-flipped residuals of a weighted mean, seed 0
    a, b = y[~thin], y[thin]
    wa, wb = len(a) / a.var(axis=0, ddof=1), len(b) / b.var(axis=0, ddof=1)
    residuals = y - (wa * a.mean(0) + wb * b.mean(0)) / (wa + wb)
    signs = np.vstack([np.ones(len(y))] + [s for _, s in drawn_flips(thin.astype(int), 999, 0)])
    welch = np.array([stats.ttest_ind((s[:, None] * residuals)[thin],
                                      (s[:, None] * residuals)[~thin], equal_var=False).pvalue
                      for s in signs])
    p = points["p"].astype(float)
    expected = own_p(welch)[0]
    assert np.mean(np.abs(p - expected) < 1e-9) > 0.95 and np.abs(p - expected).max() <= 0.003
    np.testing.assert_allclose(points["q_fdr"].astype(float),
                               stats.false_discovery_control(p, method="bh"), rtol=1e-4)
    assert summary["point_test"]["uncorrected_significant"] == int(np.sum(p <= 0.05))

    # the pooled statistic and min-p, asked for by name
    output = tmp_path / "pooled"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "-o", output,
                     "--variance", "pooled", "--family-wise", "min-p", "--permutations", "199",
                     "-q")
    assert result.returncode == 0, result.stderr
    points = read_points(output / "points.csv")
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["point_test"]["variance"] == "pooled"
    assert summary["point_test"]["family_wise"] == "min-p"
    student = stats.ttest_ind(y[thin], y[~thin]).statistic ** 2
    np.testing.assert_allclose(points["statistic"].astype(float), student, rtol=1e-5)
    rows = np.vstack([np.arange(len(y))] + list(drawn_permutations(len(y), 199, 0)))
    squares = np.array([stats.ttest_ind(y[thin[order]], y[~thin[order]]).statistic ** 2
                        for order in rows])
    every = own_p(-squares)
    p, p_fwer = points["p"].astype(float), points["p_fwer"].astype(float)
    assert np.mean(np.abs(p - every[0]) < 1e-9) > 0.95 and np.abs(p - every[0]).max() <= 0.015
    smallest = every[1:].min(axis=1)
    expected = (1 + np.sum(smallest[:, None] <= every[0] * (1 + 1e-9), axis=0)) / 200
    assert np.mean(np.abs(p_fwer - expected) < 1e-9) > 0.95


def test_a_covariate_with_nuisance_writes_its_effect_per_unit(build, table, tmp_path):
    result = run_cli("analyze", build, "--table", table, "--covariate", "age", "--nuisance",
                     "sex", "--categorical", "sex", "--displacement", "vector",
                     "--permutations", "99", "-o", tmp_path / "age", "-q")
    assert result.returncode == 0, result.stderr
    summary = json.loads((tmp_path / "age" / "analysis.json").read_text())
    assert summary["n_cases"] == 12 and summary["n_per_group"] is None
    assert summary["tested"] == ["age"] and summary["adjusted_for"] == ["sex"]
    assert summary["classification"] is None


def test_an_earlier_analysis_is_refused_without_overwrite(build, table, analysed):
    before = (analysed / "analysis.json").read_bytes()
    refused = run_cli("analyze", build, "--table", table, "--group", "group", "-o", analysed,
                      "--permutations", "9", "-q")
    assert refused.returncode == 2 and "--overwrite" in refused.stderr
    assert (analysed / "analysis.json").read_bytes() == before


@pytest.mark.parametrize("content, arguments, message", [
    ("subject,group\ncase_00,a\n", ["--group", "group"], "no 'case' column"),
    ("case,group\n" + "".join(f"case_{k:02d},same\n" for k in range(N)), ["--group", "group"],
     "has one level ('same')"),
    ("case,group\n" + "".join(f"case_{k:02d},{'a' if k else 'b'}\n" for k in range(N)),
     ["--group", "group"], "group group='b' has 1 case(s); each group needs at least 3"),
    ("case,age\n" + "".join(f"case_{k:02d},{'old' if k % 2 else 'young'}\n"
                            for k in range(N)),
     ["--covariate", "age"], "covariate 'age' is not numeric: 12 of 12 values are not numbers "
                             "('young', 'old')"),
    ("case,group,sex\n" + "".join(f"case_{k:02d},{k % 2},{'F' if k % 3 else 'M'}\n"
                                  for k in range(N)),
     ["--group", "group", "--nuisance", "sex"], "nuisance column 'sex' is not numeric"),
    ("case,group,age\n" + "".join(f"case_{k:02d},{k % 2},{k}\n" for k in range(N)),
     ["--group", "group", "--nuisance", "age", "--test", "age"],
     "test: 'age' is not the group or a covariate"),
    ("case,group\n" + "".join(f"other_{k},a\n" for k in range(N)), ["--group", "group"],
     "no row matches a case of the build"),
    ("case,group\ncase_00,a\n", ["--group", "diagnosis"], "no column 'diagnosis'"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", ["--group", "group"], "not a CSV text table"),
])
def test_bad_tables_are_refused_in_one_line_and_nothing_is_written(build, tmp_path, content,
                                                                   arguments, message):
    path = tmp_path / "table.csv"
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    output = tmp_path / "out"
    result = run_cli("analyze", build, "--table", path, *arguments, "-o", output, "-q")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], result.stderr
    assert not output.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["table.csv"]


def test_a_folder_that_is_not_a_build_is_refused(table, tmp_path):
    result = run_cli("analyze", tmp_path, "--table", table, "--group", "group", "-o",
                     tmp_path / "out", "-q")
    assert result.returncode == 2 and "not a build folder (no model.h5)" in result.stderr
    assert not (tmp_path / "out").exists()


def ages_table(path: Path, missing: str | None = None, drop: bool = False) -> Path:
    """Groups thin/full alternating and ages of four values that repeat (40 to 55); case_04's
    age is ``missing`` (when given), or its row is left out of the table (``drop``)."""
    rows = [[f"case_{k:02d}", "thin" if k % 2 else "full", 40 + 5 * (k // 3)]
            for k in range(N)]
    if missing is not None:
        rows[4][2] = missing
    return write_table(path, [r for r in rows if not (drop and r[0] == "case_04")],
                       header=("case", "group", "age"))


def test_a_missing_age_leaves_its_case_out_and_changes_nothing_else(build, tmp_path):
    """The issue's scenario: --group with --covariate age, one age NA. The case is left out and
    listed; the analysis is the one of the table without that row (age one numeric column,
    N - 1 cases, N - 4 residual degrees of freedom), not one with age as a factor."""
    outputs = {}
    for name, table in (("marked", ages_table(tmp_path / "marked.csv", missing="NA")),
                        ("dropped", ages_table(tmp_path / "dropped.csv", drop=True))):
        result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                         "age", "--permutations", "999", "-o", tmp_path / name)
        assert result.returncode == 0, result.stderr
        assert "tested: group; adjusted for: age (8 residual degrees of freedom)" in result.stdout
        outputs[name] = (result, json.loads((tmp_path / name / "analysis.json").read_text()))
    result, marked = outputs["marked"]
    assert "left out case_04: 'age' is missing ('NA')" in result.stderr
    assert marked["left_out"] == [{"case": "case_04", "reason": "'age' is missing ('NA')",
                                   "missing": {"age": "NA"}}]
    assert marked["tested"] == ["group"] and marked["adjusted_for"] == ["age"]
    assert marked["degrees_of_freedom"] == (N - 1) - 3          # intercept, group, age
    dropped = outputs["dropped"][1]
    for key in ("n_cases", "n_per_group", "tested", "adjusted_for", "effects", "global_test",
                "significant_points", "degrees_of_freedom", "classification", "discriminant"):
        assert marked[key] == dropped[key], key
    assert ((tmp_path / "marked" / "points.csv").read_bytes()
            == (tmp_path / "dropped" / "points.csv").read_bytes())
    page = html.unescape((tmp_path / "marked" / "analysis.html").read_text())
    assert "<td>case_04</td><td>'age' is missing ('NA')</td>" in page


def test_a_covariate_beside_a_group_is_tested_with_test(build, tmp_path):
    """--test age: the statistic at each point is the F of age added to a model of the group
    (ordinary least squares, recomputed here), the effect its slope; the page says so."""
    table = ages_table(tmp_path / "ages.csv")
    output = tmp_path / "age"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                     "age", "--test", "age", "--permutations", "999", "-o", output)
    assert result.returncode == 0, result.stderr
    assert "tested: age; adjusted for: group (9 residual degrees of freedom)" in result.stdout
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["tested"] == ["age"] and summary["adjusted_for"] == ["group"]
    assert summary["effects"] == ["age"] and summary["classification"] is None

    names = [f"case_{k:02d}" for k in range(N)]
    model = ShapeModel.load(build / "model.h5")
    aligned = align(shapes_of(build, names), model.weights)
    mean = aligned.mean(axis=0)
    normals = area_normals(mean, model.triangles)
    normal = np.einsum("npd,pd->np", aligned - mean,
                       normals / np.linalg.norm(normals, axis=1)[:, None])
    thin = np.array([k % 2 for k in range(N)], dtype=float)
    age = np.array([40 + 5 * (k // 3) for k in range(N)], dtype=float)
    reduced = np.column_stack([np.ones(N), thin])
    full = np.column_stack([reduced, age])

    def residual_sum(design, y):
        return np.sum((y - design @ np.linalg.lstsq(design, y, rcond=None)[0]) ** 2, axis=0)

    f = ((residual_sum(reduced, normal) - residual_sum(full, normal))
         / (residual_sum(full, normal) / (N - 3)))
    points = read_points(output / "points.csv")
    np.testing.assert_allclose(points["statistic"].astype(float), f, rtol=2e-5)
    slope = np.linalg.lstsq(full, (aligned - mean).reshape(N, -1), rcond=None)[0][-1]
    np.testing.assert_allclose(
        np.column_stack([points[f"difference_{c}"].astype(float) for c in "xyz"]),
        slope.reshape(-1, 3), atol=1e-6)
    page = (output / "analysis.html").read_text()
    assert "Tested: <b>age</b>; adjusted for: group <b>group</b>." in page
    assert "Where the shapes differ by <b>age</b>" in page
    assert "effect of age, per unit" in page and "Discriminant" not in page


def ols_t(y: np.ndarray, design: np.ndarray) -> np.ndarray:
    """Student's t of the last coefficient of ordinary least squares per column of ``y``:
    b / sqrt(s^2 [(X'X)^-1]_last), s^2 = e'e / (n - columns)."""
    coefficients = np.linalg.lstsq(design, y, rcond=None)[0]
    errors = y - design @ coefficients
    variance = np.sum(errors ** 2, axis=0) / (len(y) - design.shape[1])
    return coefficients[-1] / np.sqrt(variance * np.linalg.inv(design.T @ design)[-1, -1])


def test_two_scans_per_subject_by_the_real_command_test_each_subjects_change(build, tmp_path):
    """The twelve cases as six subjects scanned twice (pre: even cases, post: odd, the thinner
    ones), a site coded 1, 2, 3 declared categorical: the mean change, by sign flips."""
    rows = [[f"case_{k:02d}", f"s{k // 2}", "post" if k % 2 else "pre", 1 + (k // 2) % 3]
            for k in range(N)]
    table = write_table(tmp_path / "visits.csv", rows, header=("case", "id", "visit", "site"))
    output = tmp_path / "change"
    result = run_cli("analyze", build, "--table", table, "--subject", "id", "--time", "visit",
                     "--baseline", "pre", "--nuisance", "site", "--categorical", "site",
                     "--permutations", "199", "-o", output)
    assert result.returncode == 0, result.stderr
    assert "change between two times (6 subjects, visit pre, post)" in result.stdout
    assert "sign-flipped" in result.stdout and "takes only the values" not in result.stderr
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["design"] == {"kind": "change between two times", "subject": "id",
                                 "time": "visit", "times": ["pre", "post"], "n_subjects": 6,
                                 "mean_change_tested": True}
    assert summary["tested"] == ["visit"] and summary["adjusted_for"] == ["site"]
    assert summary["point_test"]["resampling"] == "sign-flipped"
    assert summary["degrees_of_freedom"] == 6 - 2 - 1 and summary["classification"] is None
    y = normal_displacement(build, [row[0] for row in rows])
    change = y[1::2] - y[0::2]
    sites = np.array([1 + s % 3 for s in range(6)])
    indicators = np.column_stack([sites == 2, sites == 3]).astype(float)
    design = np.column_stack([indicators - indicators.mean(axis=0), np.ones(6)])
    points = read_points(output / "points.csv")
    t = points["t"].astype(float)
    expected = ols_t(change, design)
    assert np.median(np.abs(t - expected) / np.abs(expected)) < 1e-3
    np.testing.assert_allclose(points["statistic"].astype(float), t ** 2, rtol=3e-5)  # 6 digits
    found = summary["effect_tests"]
    assert [(e["name"], e["the_point_test"], e["statistic"]) for e in found] == [
        ("change", True, "Student's t")]
    assert found[0]["significant_points"]["fwer"] == int(np.sum(
        points["p_fwer"].astype(float) <= 0.05))
    page = (output / "analysis.html").read_text()
    assert "Repeated measures: 6 subjects (<code>id</code>) at <code>visit</code> pre, post" in page
    assert "signed t, mean change: visit post minus pre" in html.unescape(page)
    # without --categorical the site is one slope, and the command says so naming the column
    numeric = run_cli("analyze", build, "--table", table, "--subject", "id", "--time", "visit",
                      "--nuisance", "site", "--permutations", "9", "-o", tmp_path / "numeric")
    assert numeric.returncode == 0, numeric.stderr
    assert "numeric column 'site' takes only the values 1, 2, 3" in numeric.stderr


def test_each_covariate_gets_its_own_signed_map_adjusted_for_the_others(build, tmp_path):
    """Age and height tested together (one joint test) with sex and a scanner coded 1, 2
    adjusted for (``--categorical sex,scanner``), one-sided (inward): per covariate t, p,
    p_fwer, q_fdr in points.csv, each against least squares and a plain loop over the same
    permutations."""
    heights = [171, 165, 180, 158, 175, 169, 162, 177, 168, 173, 160, 183]
    rows = [[f"case_{k:02d}", 40 + (5 * k) % 17, heights[k], "F" if k % 3 else "M",
             1 + k % 2] for k in range(N)]
    table = write_table(tmp_path / "people.csv", rows,
                        header=("case", "age", "height", "sex", "scanner"))
    output = tmp_path / "both"
    result = run_cli("analyze", build, "--table", table, "--covariate", "age", "--covariate",
                     "height", "--nuisance", "sex", "--nuisance", "scanner", "--categorical",
                     "sex,scanner", "--tail", "less", "--permutations", "199", "-o", output,
                     "-q")
    assert result.returncode == 0, result.stderr
    summary = json.loads((output / "analysis.json").read_text())
    points = read_points(output / "points.csv")
    assert summary["effects"] == ["age", "height"]
    assert [(e["name"], e["tail"], e["the_point_test"]) for e in summary["effect_tests"]] == [
        ("age", "less", False), ("height", "less", False)]
    y = normal_displacement(build, [row[0] for row in rows])
    age = np.array([row[1] for row in rows], dtype=float)
    height = np.array(heights, dtype=float)
    male = np.array([row[3] == "M" for row in rows], dtype=float)
    second = np.array([row[4] == 2 for row in rows], dtype=float)
    assert summary["adjusted_for"] == ["sex", "scanner"]
    for name, tested, other in (("age", age, height), ("height", height, age)):
        full = np.column_stack([np.ones(N), male, second, other - other.mean(),
                                tested - tested.mean()])
        expected = ols_t(y, full)
        t = points[f"t_{name}"].astype(float)
        assert np.median(np.abs(t - expected) / np.abs(expected)) < 1e-3
        # Freedman-Lane, one-sided towards negative t: the residuals of the model without the
        # covariate against each permutation's design rows
        reduced = full[:, :-1]
        residuals = y - reduced @ np.linalg.lstsq(reduced, y, rcond=None)[0]
        draws = np.vstack([np.arange(N)] + list(drawn_permutations(N, 199, 0)))
        values = -np.array([ols_t(residuals, full[order]) for order in draws])
        p = points[f"p_{name}"].astype(float)
        recomputed = np.mean(values >= values[0] - 1e-9 * np.abs(values[0]), axis=0)
        assert np.mean(np.abs(p - recomputed) < 1e-9) > 0.95
        entry = next(e for e in summary["effect_tests"] if e["name"] == name)
        assert entry["significant_points"]["fwer"] == int(np.sum(
            points[f"p_fwer_{name}"].astype(float) <= 0.05))
        assert entry["significant_points"]["fdr"] == int(np.sum(
            points[f"q_fdr_{name}"].astype(float) <= 0.05))


def test_long_csv_has_a_row_per_case_and_point_for_r_or_pandas(build, table, tmp_path):
    output = tmp_path / "long"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--long-table",
                     "--permutations", "9", "-o", output, "-q")
    assert result.returncode == 0, result.stderr
    rows = io.read_csv(output / "long.csv")
    used = [f"case_{k:02d}" for k in range(N) if k != 5]    # case_05 has no group: left out
    model = ShapeModel.load(build / "model.h5")
    points = len(model.mean)
    assert len(rows) == len(used) * points
    assert [rows[k * points]["case"] for k in range(len(used))] == used
    assert [int(row["point"]) for row in rows[:points]] == list(range(points))
    k = sum(key.startswith("score_") for key in rows[0])
    assert list(rows[0])[:4 + k + 3] == (["case", "point", "part", "normal_displacement_mm"]
                                         + [f"score_{j + 1}" for j in range(k)]
                                         + ["group", "age", "sex"])
    normal = np.array([float(row["normal_displacement_mm"]) for row in rows]).reshape(
        len(used), points)
    expected = normal_displacement(build, used)
    assert np.median(np.abs(normal - expected)) < 1e-4 * np.abs(expected).max()
    # the principal scores: the area-weighted PCA of the aligned shapes, up to each mode's sign
    aligned = align(shapes_of(build, used), model.weights)
    centred = ((aligned - aligned.mean(axis=0)) * np.sqrt(model.weights)[None, :, None])
    u, singular, _ = np.linalg.svd(centred.reshape(len(used), -1), full_matrices=False)
    scores = np.array([[float(rows[i * points][f"score_{j + 1}"]) for j in range(k)]
                       for i in range(len(used))])
    np.testing.assert_allclose(np.abs(scores), np.abs(u[:, :k] * singular[:k]), rtol=1e-3,
                               atol=1e-4 * singular[0])
    written = {row[0]: row for row in csv.reader(open(table))}
    for row in rows[::points]:
        assert [row["group"], row["age"], row["sex"]] == written[row["case"]][1:]


def test_a_contrast_by_the_real_command_gets_its_map_and_a_bad_one_is_refused(build, table,
                                                                             tmp_path):
    output = tmp_path / "contrast"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--contrast",
                     "full-thin", "--permutations", "99", "-o", output)
    assert result.returncode == 0, result.stderr
    assert "signed map of full-thin (Welch's v)" in result.stdout
    points = read_points(output / "points.csv")
    # full minus thin is the group's map (thin minus full, the reference) with its sign turned
    np.testing.assert_allclose(points["t_full-thin"].astype(float),
                               -points["t"].astype(float), rtol=2e-5)
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["effect_tests"][1]["contrast"] == {"full": 1.0, "thin": -1.0}
    refused = run_cli("analyze", build, "--table", table, "--group", "group", "--contrast",
                      "thin-fat", "-o", tmp_path / "refused")
    assert refused.returncode == 2
    assert "contrast 'thin-fat': its levels are not all levels of one tested" in refused.stderr
    assert "Traceback" not in refused.stderr and not (tmp_path / "refused").exists()


def test_an_interaction_by_the_real_command_is_tested_with_its_columns_adjusted_for(
        build, table, tmp_path):
    output = tmp_path / "interaction"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                     "age", "--interaction", "group:age", "--permutations", "99", "-o", output,
                     "-q")
    assert result.returncode == 0, result.stderr
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["tested"] == ["group:age"] and summary["adjusted_for"] == ["group", "age"]
    assert summary["effects"] == ["thin:age"] and summary["point_test"]["variance"] == "pooled"
    used = [f"case_{k:02d}" for k in range(N) if k != 5]
    y = normal_displacement(build, used)
    thin = np.array([int(n[-2:]) % 2 for n in used], dtype=float)
    age = np.array([40 + 3 * int(n[-2:]) for n in used], dtype=float)
    product = thin * (age - age.mean())
    full = np.column_stack([np.ones(len(used)), thin, age - age.mean(),
                            product - product.mean()])
    t = read_points(output / "points.csv")["t"].astype(float)
    expected = ols_t(y, full)
    assert np.median(np.abs(t - expected) / np.abs(expected)) < 1e-3
