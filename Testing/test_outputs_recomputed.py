"""What build, analyze and fit write, recomputed here from the inputs, with the options few
runs use.

One small real build (10 bumpy ellipsoids in 0.8 mm voxels, two of them given mirrored, strategy
none) serves the module: the build's tables against its model and each other (scores.csv,
cases.csv, metrics.json); the corresponded shapes of mirrored cases (in the model's frame for the
analysis, on their inputs in correspondence/); the real command line of analyze with a tested
covariate beside a group, another covariate and a categorical nuisance column (points.csv,
effects.vtp and analysis.json against ordinary least squares done here), ``--reference`` with
``--displacement vector`` (Hotelling's T^2 per point, the difference's direction),
``--size removed``, each case's departure from its reconstruction; fit.json of a new case (its
reconstruction errors, distance, p-value and departure from a projection done here); 2-D
outlines and two-part objects through the library on models made here (no build)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import stats
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel import BuildConfig, build_model
from mdlshapemodel.analysis import align, analyze_shapes, read_build, subjects
from mdlshapemodel.analyze import analyze_build
from mdlshapemodel.config import AnalysisConfig
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare import io

from common import empirical_null_p, run_cli
from synthetic import small_mask

N = 10
MIRRORED = ("case_03", "case_06")
VOXEL = 0.8         # mm
THIN = [k % 2 == 1 for k in range(N)]


@pytest.fixture(scope="module")
def build(tmp_path_factory) -> Path:
    """Ten small bumpy ellipsoids, the odd ones 8 % smaller ('thin'); case_03 and case_06 are
    written mirrored (x reversed) and built with --mirror, so that all are of one side."""
    folder = tmp_path_factory.mktemp("outputs")
    (folder / "labels").mkdir()
    paths = []
    for k, position in enumerate(np.linspace(-0.5, 0.5, N)):
        mask = small_mask(float(position), 0.92 if THIN[k] else 1.0).astype(np.uint8)
        if f"case_{k:02d}" in MIRRORED:
            mask = mask[:, :, ::-1]
        paths.append(folder / "labels" / f"case_{k:02d}.nii.gz")
        image = sitk.GetImageFromArray(np.ascontiguousarray(mask))
        image.SetSpacing((VOXEL,) * 3)
        sitk.WriteImage(image, str(paths[-1]))
    config = BuildConfig(points=642, strategy="none", baselines=[], workers=1,
                         evaluation_modes=2, specificity_samples=100, surface_samples=0,
                         cache_dir="", mirror=[f"{name}*" for name in MIRRORED])
    build_model(paths, folder / "build", config)
    return folder / "build"


@pytest.fixture(scope="module")
def table(build) -> Path:
    """Groups, two numeric columns and a categorical site, all varying independently enough."""
    path = build.parent / "subjects.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["case", "group", "age", "height", "site"])
        for k in range(N):
            writer.writerow([f"case_{k:02d}", "thin" if THIN[k] else "full",
                             [61, 48, 70, 55, 66, 43, 58, 75, 50, 64][k],
                             [171, 165, 180, 158, 175, 169, 162, 177, 168, 173][k],
                             "north" if k in (0, 2, 5, 7, 8) else "south"])
    return path


def similarity_residual(source: np.ndarray, target: np.ndarray) -> float:
    """The RMS distance left after the best proper similarity transform of source onto target
    (rotation, scale, translation; a reflection is not allowed)."""
    a, b = source - source.mean(0), target - target.mean(0)
    u, s, vt = np.linalg.svd(b.T @ a)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    scale = np.trace(np.diag(s) @ d) / np.sum(a ** 2)
    return float(np.sqrt(np.mean(np.sum((scale * a @ rotation.T - b) ** 2, axis=1))))


def test_mirrored_cases_are_of_the_models_side_for_the_analysis_and_on_their_inputs(build):
    """The analysis reads every case, the mirrored ones included, as a proper similarity
    transform of the model's own aligned case (a mirror image is not one: the correspondence
    tells left from right); correspondence/ holds each case's points on its own input."""
    built = read_build(build)
    model = built.model
    training = model.instance(model.scores)          # the model's own aligned cases
    size = np.sqrt(np.mean(np.sum((model.mean - model.mean.mean(0)) ** 2, axis=1)))
    for i, name in enumerate(model.names):
        assert similarity_residual(built.shapes[i], training[i]) < 1e-3 * size, name
    # correspondence/: every case's points on its own input, mirrored ones included
    for k in range(N):
        image = sitk.ReadImage(str(build.parent / "labels" / f"case_{k:02d}.nii.gz"))
        inside = np.argwhere(sitk.GetArrayFromImage(image) > 0)[:, ::-1] * VOXEL  # x, y, z
        low, high = inside.min(0) - VOXEL, inside.max(0) + VOXEL
        points = io.read_mesh(io.case_file(build / "correspondence", f"case_{k:02d}"))[0]
        assert np.all((points >= low) & (points <= high)), f"case_{k:02d}"


def test_the_builds_tables_agree_with_its_model_and_with_each_other(build):
    """scores.csv holds the model's scores; cases.csv each case's Mahalanobis distance over the
    modes metrics.json names (recomputed from the scores and the variances), its flag against
    the threshold, its distances in voxels of 0.8 mm, which cases were mirrored; metrics.json
    the mean and the largest of the cases' distances."""
    model = ShapeModel.load(build / "model.h5")
    metrics = json.loads((build / "metrics.json").read_text())
    scores = {row["case"]: row for row in io.read_csv(build / "scores.csv")}
    written = np.array([[float(scores[n][f"mode_{m + 1}"]) for m in range(model.n_modes)]
                        for n in model.names])
    np.testing.assert_allclose(written, model.scores, rtol=1e-5, atol=1e-6)
    outliers, variances = metrics["score_outliers"], np.array(metrics["variances"])
    k = outliers["modes"]
    distance = np.sqrt(np.sum(written[:, :k] ** 2 / variances[:k], axis=1))
    cases = {row["case"]: row for row in io.read_csv(build / "cases.csv")}
    assert metrics["voxel_size_mm"] == pytest.approx(VOXEL)
    for name, d, threshold in zip(model.names, distance, outliers["thresholds"]):
        row = cases[name]
        assert float(row["mahalanobis"]) == pytest.approx(d, rel=1e-4)
        assert (row["score_outlier"] == "True") == (d > threshold)
        assert float(row["mean_distance_voxels"]) == pytest.approx(
            float(row["mean_distance_mm"]) / VOXEL, rel=1e-6)     # the image's float spacing
        assert (row["mirrored"] == "True") == (name in MIRRORED)
    assert outliers["cases"] == [n for n in model.names if cases[n]["score_outlier"] == "True"]
    n = len(model.names)
    p_normal = stats.beta(k / 2, (n - k - 1) / 2).sf(distance ** 2 / (n - 1))
    np.testing.assert_allclose([float(cases[n]["unusual_p_normal"]) for n in model.names],
                               p_normal, rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose([float(cases[n]["unusual_p"]) for n in model.names],
                               empirical_null_p(p_normal), rtol=1e-4, atol=1e-9)
    surface = metrics["surface_distance_mm"]
    assert surface["mean"] == pytest.approx(np.mean([float(c["mean_distance_mm"])
                                                      for c in cases.values()]), rel=1e-9)
    assert surface["max"] == pytest.approx(max(float(c["max_distance_mm"])
                                               for c in cases.values()), rel=1e-9)


def read_points(path: Path) -> dict:
    rows = io.read_csv(path)
    return {key: np.array([float(row[key]) for row in rows]) for key in rows[0]}


def outward_unit_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted point normals of a closed surface, turned to point away from its centre."""
    corners = points[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    summed = np.zeros_like(points)
    for k in range(3):
        np.add.at(summed, triangles[:, k], face)
    if np.sum(np.einsum("pd,pd->p", summed, points - points.mean(0))) < 0:
        summed = -summed
    return summed / np.linalg.norm(summed, axis=1)[:, None]


def aligned_cases(build: Path, size: str = "kept") -> tuple:
    built = read_build(build)
    return built.model, align(built.shapes, built.model.weights, size)


def residual_sum(design: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.sum((y - design @ np.linalg.lstsq(design, y, rcond=None)[0]) ** 2, axis=0)


def test_a_tested_covariate_beside_a_group_another_covariate_and_a_site(build, table, tmp_path):
    """The command line: age tested, adjusted for the group, height and a categorical site.
    Every per-point number written is least squares recomputed here: the F of age at each
    point (normal displacement), the slope of age in mm per year, its normal component."""
    output = tmp_path / "age"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "--covariate",
                     "age", "--covariate", "height", "--nuisance", "site", "--categorical",
                     "site", "--test", "age", "--permutations", "99", "-o", output, "-q")
    assert result.returncode == 0, result.stderr
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["tested"] == ["age"]
    assert summary["adjusted_for"] == ["group", "height", "site"]
    assert summary["degrees_of_freedom"] == N - 5

    model, aligned = aligned_cases(build)
    mean = aligned.mean(0)
    normals = outward_unit_normals(mean, model.triangles)
    rows = {row["case"]: row for row in io.read_csv(table)}
    column = {c: np.array([rows[n][c] for n in model.names]) for c in rows["case_00"]}
    age = column["age"].astype(float)
    others = np.column_stack([np.ones(N), column["group"] == "thin",
                              column["height"].astype(float), column["site"] == "south"])
    full = np.column_stack([age, others]).astype(float)       # age first: a different order
    offsets = (aligned - mean).reshape(N, -1)
    slope = np.linalg.lstsq(full, offsets, rcond=None)[0][0].reshape(-1, 3)
    normal = np.einsum("npd,pd->np", aligned - mean, normals)
    f = ((residual_sum(others.astype(float), normal) - residual_sum(full, normal))
         / (residual_sum(full, normal) / (N - 5)))

    points = read_points(output / "points.csv")
    np.testing.assert_allclose(np.column_stack([points[c] for c in "xyz"]), mean, atol=1e-4)
    np.testing.assert_allclose(points["statistic"], f, rtol=1e-4)
    written = np.column_stack([points[f"difference_{c}"] for c in "xyz"])
    np.testing.assert_allclose(written, slope, atol=1e-6 + 1e-5 * np.abs(slope).max())
    np.testing.assert_allclose(points["normal_difference_mm"],
                               np.einsum("pd,pd->p", slope, normals),
                               atol=1e-6 + 1e-5 * np.abs(slope).max())
    assert summary["significant_points"] == {"fwer": int(np.sum(points["p_fwer"] <= 0.05)),
                                             "fdr": int(np.sum(points["q_fdr"] <= 0.05)),
                                             "of": len(mean)}
    # the global test: Pillai's trace of age on the principal scores explaining 95 % (at most
    # n - 6: one more than the model's columns), adjusted for the others
    root = np.sqrt(model.weights)[None, :, None]
    u, s, _ = np.linalg.svd(((aligned - mean) * root).reshape(N, -1), full_matrices=False)
    explained = np.cumsum(s ** 2) / np.sum(s ** 2)
    k = min(int(np.searchsorted(explained, 0.95)) + 1, N - 6)
    assert summary["global_test"]["modes"] == k
    scores = u[:, :k] * s[:k]

    def projection(x):
        return x @ np.linalg.pinv(x)

    total = scores.T @ (np.eye(N) - projection(others.astype(float))) @ scores
    hypothesis = scores.T @ (projection(full) - projection(others.astype(float))) @ scores
    pillai = np.trace(hypothesis @ np.linalg.inv(total))
    assert summary["global_test"]["statistic"] == pytest.approx(
        (N - 5) * pillai / (1 - pillai), rel=1e-6)
    polydata = io.read_polydata(output / "effects.vtp")
    data = polydata.GetPointData()
    np.testing.assert_allclose(vtk_to_numpy(polydata.GetPoints().GetData()), mean, atol=1e-4)
    np.testing.assert_allclose(vtk_to_numpy(data.GetArray("difference")), written, rtol=1e-5)
    for name in ("statistic", "p_fwer", "q_fdr", "normal_difference_mm"):
        np.testing.assert_allclose(vtk_to_numpy(data.GetArray(name)), points[name], rtol=1e-5)


def hotelling(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Two-sample Hotelling's T^2 per point of vectors a (n1, p, 3), b (n2, p, 3)."""
    n1, n2 = len(a), len(b)
    d = b.mean(0) - a.mean(0)
    ca, cb = a - a.mean(0), b - b.mean(0)
    pooled = (np.einsum("npi,npj->pij", ca, ca) + np.einsum("npi,npj->pij", cb, cb)) / (
        n1 + n2 - 2)
    return n1 * n2 / (n1 + n2) * np.einsum("pi,pi->p", d,
                                                   np.linalg.solve(pooled, d[..., None])[..., 0])


def test_a_reference_group_and_the_displacement_vector(build, table, tmp_path):
    """--reference thin (the level that sorts last): the effect is full's difference from thin,
    which points outward where the larger shapes lie; the statistic is Hotelling's T^2 of the
    displacement vectors."""
    result = analyze_build(build, table, tmp_path / "reference",
                           AnalysisConfig(group="group", reference="thin",
                                          displacement="vector", permutations=99))
    summary = result.summary
    assert summary["effects"] == ["full"] and summary["n_per_group"] == {"thin": 5, "full": 5}
    model, aligned = aligned_cases(build)
    thin = np.array([THIN[int(n[-2:])] for n in model.names])
    difference = aligned[~thin].mean(0) - aligned[thin].mean(0)
    points = read_points(tmp_path / "reference" / "points.csv")
    np.testing.assert_allclose(np.column_stack([points[f"difference_{c}"] for c in "xyz"]),
                               difference, atol=1e-5)
    np.testing.assert_allclose(points["statistic"], hotelling(aligned[thin], aligned[~thin]),
                               rtol=1e-5)
    normals = outward_unit_normals(aligned.mean(0), model.triangles)
    np.testing.assert_allclose(points["normal_difference_mm"],
                               np.einsum("pd,pd->p", difference, normals), atol=1e-5)
    assert np.median(points["normal_difference_mm"]) > 0        # full lies outside thin


def test_size_removed_scales_every_case_to_the_mean_size(build, table, tmp_path):
    result = analyze_build(build, table, tmp_path / "shape",
                           AnalysisConfig(group="group", size="removed", permutations=99))
    built = read_build(build)
    weights = built.model.weights / built.model.weights.sum()

    def size(x):
        centred = x - weights @ x
        return np.sqrt(weights @ np.sum(centred ** 2, axis=1))

    before = np.array([size(x) for x in built.shapes])
    after = np.array([size(x) for x in result.analysis.aligned])
    np.testing.assert_allclose(after, before.mean(), rtol=1e-9)
    # the thin group's 8 % is gone: what is left is far smaller than with the size kept
    kept = analyze_build(build, table, tmp_path / "kept",
                         AnalysisConfig(group="group", permutations=99))
    assert (np.abs(result.analysis.normal_difference).mean()
            < 0.5 * np.abs(kept.analysis.normal_difference).mean())


def test_each_cases_departure_from_its_reconstruction(build, table, tmp_path):
    """unusual.csv: the largest distance of each training case from its reconstruction by the
    k modes of analysis.json, the modes from a weighted PCA done here."""
    output = tmp_path / "unusual"
    analyze_build(build, table, output, AnalysisConfig(group="group", permutations=99))
    k = json.loads((output / "analysis.json").read_text())["unusual"]["modes"]
    model = ShapeModel.load(build / "model.h5")
    shapes = model.instance(model.scores)
    mean = shapes.mean(0)
    root = np.sqrt(model.weights)[None, :, None]
    u, s, vt = np.linalg.svd(((shapes - mean) * root).reshape(N, -1), full_matrices=False)
    reconstructed = mean + (u[:, :k] * s[:k] @ vt[:k]).reshape(shapes.shape) / root
    departure = np.linalg.norm(shapes - reconstructed, axis=2)
    rows = {row["case"]: row for row in io.read_csv(output / "unusual.csv")}
    for name, largest in zip(model.names, departure.max(axis=1)):
        assert float(rows[name]["max_departure_mm"]) == pytest.approx(largest, rel=1e-4,
                                                                      abs=1e-6)
    # the p-value of each distance assuming normality, d^2 / (n - 1) ~ Beta(k / 2, (n - k - 1) / 2),
    # and against the cases' empirical null of those
    squared = np.sum((u[:, :k] * s[:k]) ** 2 / (s[:k] ** 2 / N), axis=1)
    p_normal = stats.beta(k / 2, (N - k - 1) / 2).sf(squared / (N - 1))
    p = empirical_null_p(p_normal)
    for name, d2, expected_normal, expected in zip(model.names, squared, p_normal, p):
        assert float(rows[name]["mahalanobis"]) == pytest.approx(np.sqrt(d2), rel=1e-4)
        assert float(rows[name]["p_normal"]) == pytest.approx(expected_normal, rel=1e-4,
                                                              abs=1e-9)
        assert float(rows[name]["p"]) == pytest.approx(expected, rel=1e-4, abs=1e-9)


def test_fit_json_of_a_new_case(build, tmp_path):
    """A new case fitted to the build: fit.json's reconstruction errors for 0..all modes, its
    Mahalanobis distance, its p-value against F(k, n - k) of (n - k) d^2 / (k (n + 1)) and its
    largest departure from the reconstruction by k modes, all from the written scores and
    the model, with a weighted least-squares projection done here."""
    from mdlshapemodel.fit import fit_cases

    mask = small_mask(0.2, 0.96).astype(np.uint8)
    image = sitk.GetImageFromArray(mask)
    image.SetSpacing((VOXEL,) * 3)
    path = tmp_path / "new_case.nii.gz"
    sitk.WriteImage(image, str(path))
    results, _ = fit_cases(build, [path], tmp_path / "fit", max_time=60, max_sweeps=1)
    entry = json.loads((tmp_path / "fit" / "fit.json").read_text())["new_case"]
    model = ShapeModel.load(build / "model.h5")
    aligned = results[0].aligned                  # the fitted points in the model's frame
    w = model.weights
    basis = (model.modes * np.sqrt(w)[None, :, None]).reshape(model.n_modes, -1)
    scores = np.linalg.lstsq(basis.T, ((aligned - model.mean) * np.sqrt(w)[:, None]).ravel(),
                             rcond=None)[0]
    written = io.read_csv(tmp_path / "fit" / "scores.csv")[0]
    np.testing.assert_allclose([float(written[f"mode_{m + 1}"]) for m in range(model.n_modes)],
                               scores, rtol=1e-4, atol=1e-6)
    squared, distance = [], []
    for m in range(model.n_modes + 1):
        residual = aligned - model.mean - np.einsum("m,mpd->pd", scores[:m], model.modes[:m])
        squared.append(w @ np.sum(residual ** 2, axis=1))
        distance.append(w @ np.linalg.norm(residual, axis=1))
    np.testing.assert_allclose(entry["reconstruction_squared_mm2"], squared, rtol=1e-6)
    np.testing.assert_allclose(entry["reconstruction_distance_mm"], distance, rtol=1e-6)
    assert entry["mahalanobis"] == pytest.approx(np.sqrt(np.sum(scores ** 2 / model.variances)),
                                                 rel=1e-6)
    unusual, n = entry["unusual"], N
    k = unusual["modes"]
    d2 = np.sum(scores[:k] ** 2 / model.variances[:k])
    assert unusual["distance"] == pytest.approx(np.sqrt(d2), rel=1e-6)
    p_normal = stats.f.sf((n - k) * d2 / (k * (n + 1)), k, n - k)
    assert unusual["p_normal"] == pytest.approx(p_normal, rel=1e-5)
    training = np.sum(model.scores[:, :k] ** 2 / model.variances[:k], axis=1)
    training_p = stats.beta(k / 2, (n - k - 1) / 2).sf(training / (n - 1))
    assert unusual["p"] == pytest.approx(float(empirical_null_p(p_normal, training_p)[0]), rel=1e-5)
    reconstructed = model.mean + np.einsum("m,mpd->pd", scores[:k], model.modes[:k])
    departure = np.linalg.norm(aligned - reconstructed, axis=1)
    assert unusual["max_departure_mm"] == pytest.approx(departure.max(), rel=1e-5)
    assert unusual["at_point"] == int(departure.argmax())


def groups_table(path: Path, names: list) -> Path:
    path.write_text("case,group\n" + "".join(f"{n},{'b' if k % 2 else 'a'}\n"
                                             for k, n in enumerate(names)))
    return path


def test_the_global_test_takes_no_more_scores_than_its_model_leaves_room_for(tmp_path):
    """Noise spreads the variance over every mode: the global test takes n - z - r - 1 principal
    scores (12 cases, an intercept, three nuisance columns, one tested column: 6), so that
    Pillai's trace has residual degrees of freedom to spare."""
    rng = np.random.default_rng(8)
    from mdlshapemodel.correspondence.sampling import sphere_grid

    directions, triangles = sphere_grid(42)
    shapes = directions * [10.0, 8.0, 6.0] + rng.normal(0.0, 0.5, (12, 42, 3))
    names = [f"case_{k}" for k in range(12)]
    model = ShapeModel.from_shapes(shapes, np.full(42, 1 / 42), names=names,
                                   triangles=triangles)
    path = tmp_path / "t.csv"
    path.write_text("case,group,a,b,c\n" + "".join(
        f"{n},{'b' if k % 2 else 'a'},{rng.normal():.4f},{rng.normal():.4f},{rng.normal():.4f}\n"
        for k, n in enumerate(names)))
    design = subjects(path, names, "group", nuisance=["a", "b", "c"])
    found = analyze_shapes(model, shapes, design, AnalysisConfig(permutations=19))
    assert found.global_test.modes == 12 - 4 - 1 - 1


def test_a_dent_is_a_negative_normal_difference_where_it_is(tmp_path):
    """Half the ellipsoids have a dent of 1.5 mm around the tip of their long axis: the normal
    difference of that group is negative there, most negative at the dent, and its test
    statistic is largest there."""
    rng = np.random.default_rng(9)
    from mdlshapemodel.correspondence.sampling import sphere_grid

    directions, triangles = sphere_grid(642)
    dent = 1.5 * np.exp(-np.sum((directions - [1.0, 0.0, 0.0]) ** 2, axis=1) / 0.08)
    shapes = []
    for k in range(12):
        radius = np.linalg.norm(directions * [12.0, 8.0, 6.0], axis=1) + 0.1 * rng.normal(
            size=len(directions))
        radius -= dent * (k % 2)
        shapes.append(directions * radius[:, None])
    shapes = np.stack(shapes)
    names = [f"case_{k}" for k in range(12)]
    model = ShapeModel.from_shapes(shapes, np.full(642, 1 / 642), names=names,
                                   triangles=triangles)
    design = subjects(groups_table(tmp_path / "t.csv", names), names, "group")
    found = analyze_shapes(model, shapes, design, AnalysisConfig(permutations=19))
    normal = found.normal_difference[0]
    in_dent = dent > 0.75
    assert np.all(normal[in_dent] < -0.3)
    assert in_dent[np.argmin(normal)] and in_dent[np.argmax(found.points.statistic)]


def test_2d_outlines_are_turned_in_their_plane_never_turned_over(tmp_path):
    """Asymmetric outlines, half of them the mirror images of the others: a rotation in the
    plane cannot match them to the rest, a turn about an in-plane axis could. Each aligned
    outline is a proper rotation of its input."""
    rng = np.random.default_rng(2)
    count, n = 8, 48
    angle = 2 * np.pi * np.arange(n) / n
    shapes = []
    for k in range(count):
        radius = 1 + 0.3 * np.exp(-((angle - 1.0) ** 2) / 0.1) + 0.02 * rng.normal(size=n)
        y = 8.0 * radius * np.sin(angle) * (-1 if k % 2 else 1)
        turn = rng.uniform(0, 2 * np.pi)
        x = 15.0 * radius * np.cos(angle)
        shapes.append(np.column_stack([np.cos(turn) * x - np.sin(turn) * y,
                                       np.sin(turn) * x + np.cos(turn) * y, np.zeros(n)]))
    shapes = np.stack(shapes)
    segments = np.column_stack([np.arange(n), (np.arange(n) + 1) % n])
    names = [f"outline_{k}" for k in range(count)]
    model = ShapeModel.from_shapes(shapes, np.full(n, 1 / n), names=names, triangles=segments)
    design = subjects(groups_table(tmp_path / "t.csv", names), names, "group")
    found = analyze_shapes(model, shapes, design, AnalysisConfig(permutations=19))
    for source, aligned in zip(shapes, found.aligned):
        a, b = source[:, :2] - source[:, :2].mean(0), aligned[:, :2] - aligned[:, :2].mean(0)
        linear = np.linalg.lstsq(a, b, rcond=None)[0]
        assert np.linalg.det(linear) > 0
        np.testing.assert_allclose(aligned[:, 2], 0.0, atol=1e-9)


def test_two_parts_aligned_each_on_its_own(tmp_path):
    """--parts each: every case's parts are centred on the same places; as one object, the
    parts keep their cases' differing relative places."""
    rng = np.random.default_rng(7)
    from mdlshapemodel.correspondence.sampling import sphere_grid

    directions, triangles = sphere_grid(42)
    shapes = []
    for k in range(8):
        gap = 30.0 + 3.0 * rng.normal()
        shapes.append(np.concatenate([directions * [8.0, 6.0, 5.0] * (1 + 0.05 * rng.normal()),
                                      directions * [6.0, 5.0, 5.0] + [gap, 2 * rng.normal(), 0]]))
    shapes = np.stack(shapes)
    names = [f"case_{k}" for k in range(8)]
    model = ShapeModel.from_shapes(shapes, np.full(84, 1 / 84), names=names,
                                   triangles=np.concatenate([triangles, triangles + 42]),
                                   part_sizes=[42, 42], part_names=["left", "right"])
    design = subjects(groups_table(tmp_path / "t.csv", names), names, "group")
    each = analyze_shapes(model, shapes, design, AnalysisConfig(permutations=19, parts="each"))
    for rows in model.part_slices():
        centres = np.einsum("p,npd->nd", model.weights[rows] / model.weights[rows].sum(),
                            each.aligned[:, rows])
        np.testing.assert_allclose(centres, np.broadcast_to(centres[0], centres.shape),
                                   atol=1e-9)
