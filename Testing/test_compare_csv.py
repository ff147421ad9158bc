"""compare.csv recomputed: each model evaluated alone on the shared cases, matched by name (the
second model lists them in another order and has a case the first lacks), the differences
against the first model with their standard errors (sqrt(SE_a^2 + SE_b^2) for compactness and
specificity; for generalization the mean of the per-case differences) and the verdict rule."""

from __future__ import annotations

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.model.evaluation import evaluate, generalization
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare import io
from mdlshapemodel.compare import write_comparison
from mdlshapemodel.report.compare import Population, compare_populations

MODES, SAMPLES = 3, 300


def populations():
    """A clean population of 12 and a noisier copy of it in reversed order with one case more."""
    rng = np.random.default_rng(21)
    points, _ = sphere_grid(162)
    base = points * [20.0, 10.0, 8.0]
    scores = rng.standard_normal((13, 3)) * [0.2, 0.1, 0.05]
    shapes = base * (1 + scores[:, None, :])
    weights = np.full(len(points), 1 / len(points))
    names = [f"c{k:02d}" for k in range(13)]
    clean = Population("clean", names[:12], shapes[:12], weights)
    noisy = shapes + rng.normal(0.0, 0.4, shapes.shape)
    other = Population("noisy", names[::-1], noisy[::-1], weights)
    return clean, other, shapes[:12], noisy[:12], weights


def test_compare_csv_holds_each_models_own_measures_and_the_differences(tmp_path):
    clean, other, shapes, noisy, weights = populations()
    result = compare_populations([clean, other], MODES, SAMPLES)
    write_comparison(result, tmp_path / "cmp")
    rows = io.read_csv(tmp_path / "cmp" / "compare.csv")
    alone = {label: evaluate(x, weights, ShapeModel.from_shapes(x, weights).variances, MODES,
                             SAMPLES, np.random.default_rng(0))
             for label, x in (("clean", shapes), ("noisy", noisy))}
    per_case = [generalization(x, weights, MODES)["squared_per_case"] for x in (shapes, noisy)]
    paired = (per_case[1] - per_case[0]).mean(axis=0)
    assert result["cases"] == clean.names and result["excluded_cases"]["noisy"] == ["c12"]
    seen = set()
    for row in rows:
        measure, k, label = row["measure"], int(row["M"]) - 1, row["model"]
        own = alone[label]
        assert float(row["value_mm2"]) == pytest.approx(own[measure][k], rel=1e-9)
        assert float(row["se"]) == pytest.approx(own[measure + "_se"][k], rel=1e-9)
        seen.add((measure, label))
        if label == "clean":
            assert row["verdict"] == "reference"
            continue
        reference = alone["clean"]
        difference = float(row["difference"])
        if measure == "generalization":
            assert difference == pytest.approx(paired[k], rel=1e-9)
        else:
            assert difference == pytest.approx(own[measure][k] - reference[measure][k],
                                               rel=1e-9)
            assert float(row["difference_se"]) == pytest.approx(
                np.sqrt(own[measure + "_se"][k] ** 2 + reference[measure + "_se"][k] ** 2),
                rel=1e-9)
        se = float(row["difference_se"])
        expected = ("worse" if difference > 2 * se else "better" if difference < -2 * se
                    else "same (within 2 SE)")
        assert row["verdict"] == expected
    assert seen == {(m, label) for m in ("compactness", "generalization", "specificity")
                    for label in ("clean", "noisy")}
    assert {row["verdict"] for row in rows if row["measure"] == "generalization"
            and row["model"] == "noisy"} == {"worse"}
