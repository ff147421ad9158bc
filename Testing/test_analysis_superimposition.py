"""The analysis's resistant superimposition (iteratively reweighted generalized Procrustes): with
unit weights it is the least-squares alignment, a local change planted in some cases moves it far
less than the least-squares one, and ``analyze --superimposition resistant`` uses it; the effect
on centroid size is written beside the shape test."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

from mdlshapemodel.analysis import align, analyze_shapes, subjects
from mdlshapemodel.analysis.superimposition import BIWEIGHT, biweight, resistant_procrustes
from mdlshapemodel.config import AnalysisConfig
from mdlshapemodel.geometry import centroid_size
from mdlshapemodel.errors import InputError
from mdlshapemodel.model.shape_model import ShapeModel

from common import run_cli
from synthetic import two_sized_ellipsoids
from test_analyze import build, read_points, shapes_of, table  # noqa: F401 (fixtures)


def ellipsoids(n: int, seed: int, points: int = 600, planar: bool = False) -> np.ndarray:
    """n noisy copies of one ellipsoid (or ellipse in z = 0), each rotated and moved."""
    rng = np.random.default_rng(seed)
    if planar:
        angle = np.linspace(0, 2 * np.pi, points, endpoint=False)
        base = np.column_stack([30 * np.cos(angle), 12 * np.sin(angle), np.zeros(points)])
    else:
        direction = rng.normal(size=(points, 3))
        base = 0.5 * direction / np.linalg.norm(direction, axis=1)[:, None] * [60, 24, 20]
    shapes = []
    for _ in range(n):
        noisy = base + rng.normal(scale=0.5, size=base.shape) * [1, 1, 0 if planar else 1]
        rotation = (Rotation.from_euler("z", rng.uniform(-1, 1)) if planar
                    else Rotation.from_rotvec(rng.normal(scale=0.5, size=3)))
        shift = rng.normal(scale=5, size=3) * [1, 1, 0 if planar else 1]
        shapes.append(rotation.apply(noisy) + shift)
    return np.stack(shapes)


@pytest.mark.parametrize("planar", [False, True])
def test_unit_weights_give_the_least_squares_alignment(planar):
    shapes = ellipsoids(8, seed=1, planar=planar)
    weights = np.random.default_rng(2).uniform(0.5, 1.5, shapes.shape[1])
    least_squares = align(shapes, weights, planar=planar, superimposition="least-squares")
    unit = resistant_procrustes(shapes, weights, tuning=np.inf, planar=planar)
    np.testing.assert_allclose(unit.aligned, least_squares, atol=1e-6)
    assert np.all(unit.robust == 1)
    # the resistant one on shapes with no outlying points is close to it, but not equal
    resistant = align(shapes, weights, planar=planar, superimposition="resistant")
    assert 0 < np.abs(resistant - least_squares).max() < 0.2


def test_a_local_change_moves_the_least_squares_superimposition_not_the_resistant_one():
    shapes = ellipsoids(20, seed=3)
    weights = np.full(shapes.shape[1], 1.0)
    changed = shapes.copy()
    planted = np.arange(20) % 2 == 1
    # in the frame of each case, the points of one end (first axis above 20 of 30) retracted
    # by 8 along that axis: found from the unrotated ellipsoid's coordinates
    reference = align(shapes, weights, superimposition="least-squares")   # with no change
    tip = reference.mean(axis=0)[:, 0] > 20
    for i in np.flatnonzero(planted):
        axis = np.linalg.lstsq(reference[i] - reference[i].mean(0),
                               shapes[i] - shapes[i].mean(0), rcond=None)[0][0]
        changed[i, tip] -= 8 * axis / np.linalg.norm(axis)

    def group_difference_away_from_the_change(method):
        aligned = align(changed, weights, superimposition=method)
        unchanged = align(shapes, weights, superimposition=method)
        moved = aligned - unchanged
        gap = moved[planted].mean(axis=0) - moved[~planted].mean(axis=0)
        return np.linalg.norm(gap[~tip], axis=1)

    least_squares = group_difference_away_from_the_change("least-squares")
    resistant = group_difference_away_from_the_change("resistant")
    assert least_squares.mean() > 0.3                  # the change pulls the poses
    assert resistant.mean() < 0.2 * least_squares.mean()
    assert resistant.max() < least_squares.max()
    # the changed points are the ones the resistant fit gave up on
    robust = resistant_procrustes(changed, weights).robust
    assert robust[planted][:, tip].mean() < 0.3 < 0.7 < robust[:, ~tip].mean()



@pytest.mark.parametrize("dimensions", [2, 3])
def test_the_biweights_scale_is_the_standard_deviation_of_a_coordinate(dimensions):
    """Residual norms of normal errors with a standard deviation s per coordinate, and a few
    points at known multiples of s: the biweight's scale comes out as s (from the median norm),
    so a point at r weighs (1 - (r / 4.685 s)^2)^2 and one beyond 4.685 s nothing."""
    s = 0.7
    rng = np.random.default_rng(5)
    residuals = np.linalg.norm(rng.normal(scale=s, size=(2, 40001, dimensions)), axis=2)
    at = np.array([0.5, 2.0, 3.5, 4.0, 5.0, 9.0]) * s
    residuals[:, :len(at)] = at
    weights = biweight(residuals, dimensions=dimensions)[:, :len(at)]
    u = at / (BIWEIGHT * s)
    expected = np.where(u < 1, (1 - u ** 2) ** 2, 0.0)
    np.testing.assert_allclose(weights, np.broadcast_to(expected, weights.shape), atol=0.02)
    assert np.all(weights[:, -2:] == 0)


@pytest.mark.parametrize("planar", [False, True])
def test_each_cases_median_point_weighs_what_a_normal_residual_of_median_norm_does(planar):
    """Noisy copies of one shape (no outlying points): in each case, the point of median
    residual norm is at u = sqrt(median of chi^2 with d degrees of freedom) / 4.685, d = 2 in
    the plane, so half its points weigh more than (1 - u^2)^2 and half less."""
    shapes = ellipsoids(6, seed=7, points=601, planar=planar)
    found = resistant_procrustes(shapes, np.ones(shapes.shape[1]), planar=planar)
    u2 = stats.chi2.median(2 if planar else 3) / BIWEIGHT ** 2
    np.testing.assert_allclose(np.median(found.robust, axis=1), (1 - u2) ** 2, atol=1e-6)


def test_the_effect_on_size_is_of_the_cases_before_their_scaling(tmp_path):
    """With size="removed" the shapes are tested at one size; the effect on centroid size is
    still of the cases' own sizes (mm, of the shapes as given), the thin group's smaller."""
    model, shapes, table = two_sized_ellipsoids(tmp_path)
    design = subjects(table, model.names, group="group")
    found = analyze_shapes(model, shapes, design,
                           AnalysisConfig(group="group", size="removed", permutations=19))
    unit = model.weights / model.weights.sum()
    sizes = np.array([centroid_size(x, unit) for x in shapes[design.indices]])
    np.testing.assert_allclose(found.size.sizes, sizes, rtol=1e-12)
    thin = np.array([group == "thin" for group in design.groups])
    assert found.size.effects[0] == pytest.approx(sizes[thin].mean() - sizes[~thin].mean(),
                                                  rel=1e-9)
    assert found.size.effects[0] < 0

def test_bad_input_to_the_resistant_superimposition_is_refused():
    shapes = ellipsoids(3, seed=4, points=20)
    with pytest.raises(InputError, match="tuning"):
        resistant_procrustes(shapes, np.ones(20), tuning=0)
    with pytest.raises(InputError, match="20 non-negative"):
        resistant_procrustes(shapes, np.ones(19))
    with pytest.raises(InputError, match="superimposition must be one of"):
        align(shapes, np.ones(20), superimposition="robust")


@pytest.mark.slow
def test_analyze_superimposition_resistant_by_the_real_command(build, table, tmp_path):  # noqa: F811
    output = tmp_path / "resistant"
    result = run_cli("analyze", build, "--table", table, "--group", "group", "-o", output,
                     "--permutations", "199", "--superimposition", "resistant", "-q")
    assert result.returncode == 0, result.stderr
    summary = json.loads((output / "analysis.json").read_text())
    assert summary["settings"]["superimposition"] == "resistant"
    used = [f"case_{k:02d}" for k in range(12) if k != 5]           # case_05 has no group
    model = ShapeModel.load(build / "model.h5")
    shapes = shapes_of(build, used)
    points = read_points(output / "points.csv")
    written = np.column_stack([points[c].astype(float) for c in "xyz"])
    resistant = align(shapes, model.weights).mean(axis=0)            # the default
    least_squares = align(shapes, model.weights, superimposition="least-squares").mean(axis=0)
    np.testing.assert_allclose(written, resistant, atol=5e-5 * np.abs(resistant).max())
    assert np.abs(written - least_squares).max() > 1e-3

    # the effect on centroid size beside it: the thin group's is smaller, Welch's v^2
    thin = np.array([int(n[-2:]) % 2 == 1 for n in used])
    sizes = np.array([centroid_size(x, model.weights / model.weights.sum()) for x in shapes])
    size = summary["centroid_size"]
    assert size["mean_mm"] == pytest.approx(sizes.mean())
    assert size["per_group_mm"] == pytest.approx({"full": sizes[~thin].mean(),
                                                  "thin": sizes[thin].mean()})
    assert size["effects_mm"]["thin"] == pytest.approx(sizes[thin].mean() - sizes[~thin].mean())
    assert size["effects_mm"]["thin"] < 0
    welch = stats.ttest_ind(sizes[thin], sizes[~thin], equal_var=False).statistic
    assert size["statistic"] == pytest.approx(welch ** 2, rel=1e-6)
    assert size["p"] < 0.05
    page = (output / "analysis.html").read_text()
    assert "Centroid size" in page and "superimposed by resistant" in page

    refused = run_cli("analyze", build, "--table", table, "--group", "group", "-o",
                      tmp_path / "bad", "--superimposition", "robust", "-q")
    assert refused.returncode == 2 and "--superimposition" in refused.stderr
    assert not (tmp_path / "bad").exists()
