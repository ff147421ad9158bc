"""Side-by-side evaluation of models of the same cases."""

import json

import numpy as np
import pytest

from threadpoolctl import threadpool_limits

from mdlshapemodel.compare import compare_builds, load_population, write_comparison
from mdlshapemodel.report.compare import Population, compare_populations, comparison_rows
from mdlshapemodel.errors import InputError
from mdlshapemodel.model.evaluation import (evaluate, generalization, generalization_difference,
                                           generalization_jackknife, measure_differences)
from mdlshapemodel.model.space import model_space
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.correspondence.sampling import sphere_grid


def two_mode_population(n=12, seed=0):
    rng = np.random.default_rng(seed)
    points, triangles = sphere_grid(162)
    base = points * np.array([20.0, 10.0, 8.0])
    first = np.zeros_like(base)
    first[:, 0] = base[:, 0]
    second = np.zeros_like(base)
    second[:, 1] = base[:, 1]
    scores = rng.standard_normal((n, 2)) * np.array([0.2, 0.1])
    shapes = base + scores[:, 0, None, None] * first + scores[:, 1, None, None] * second
    weights = np.full(len(points), 1.0 / len(points))
    return shapes, weights, triangles


def test_identical_models_never_differ():
    shapes, weights, _ = two_mode_population()
    names = [f"c{k}" for k in range(len(shapes))]
    result = compare_populations([Population("a", names, shapes, weights),
                                  Population("b", names, shapes, weights)], 4, 500)
    for measure in ("compactness", "generalization", "specificity"):
        d = result["differences"]["b"][measure]
        np.testing.assert_allclose(d["difference"], 0.0, atol=1e-12)
        assert not any(d["significant"])


def test_a_noisier_correspondence_is_significantly_worse():
    shapes, weights, _ = two_mode_population(n=15)
    noisy = shapes + np.random.default_rng(1).normal(0, 0.6, shapes.shape)
    names = [f"c{k}" for k in range(len(shapes))]
    result = compare_populations([Population("clean", names, shapes, weights),
                                  Population("noisy", names, noisy, weights)], 3, 2000)
    g = result["differences"]["noisy"]["generalization"]
    assert all(g["significant"]) and all(v > 0 for v in g["difference"])
    verdicts = {(r[0], r[1]): r[7] for r in comparison_rows(result) if r[2] == "noisy"}
    assert verdicts[("generalization", 2)] == "worse"
    # the values equal an evaluation of each population on its own
    alone = evaluate(noisy, weights, ShapeModel.from_shapes(noisy, weights).variances, 3, 2000,
                     np.random.default_rng(0))
    np.testing.assert_allclose(result["models"]["noisy"]["generalization"],
                               alone["generalization"])


def noisy_pair(rng, n, ratio, sigma=0.3):
    """Two correspondences of one population of ``n`` shapes (four modes): each the true points
    plus independent noise, sd ``sigma`` and ``ratio * sigma``; ratio 1 makes them equally good."""
    points, _ = sphere_grid(162)
    base = points * np.array([20.0, 10.0, 8.0])
    modes = np.zeros((4,) + base.shape)
    for k in range(3):
        modes[k, :, k] = base[:, k]
    modes[3, :, 0] = base[:, 0] * points[:, 0]
    scores = rng.standard_normal((n, 4)) * np.array([0.2, 0.1, 0.06, 0.04])
    shapes = base + np.einsum("nk,kpd->npd", scores, modes)
    weights = np.full(len(points), 1.0 / len(points))
    names = [f"c{k}" for k in range(n)]
    return (Population("a", names, shapes + rng.normal(0, sigma, shapes.shape), weights),
            Population("b", names, shapes + rng.normal(0, ratio * sigma, shapes.shape), weights))


def generalization_verdicts(ratio, populations, n=15, modes=3, seed=5):
    """How often compare calls generalization significantly different, per M, over
    ``populations`` independent pairs of correspondences (noise ratio ``ratio``)."""
    rng = np.random.default_rng(seed)
    count = np.zeros(modes)
    for _ in range(populations):
        a, b = noisy_pair(rng, n, ratio)
        result = compare_populations([a, b], modes, 50)
        count += result["differences"]["b"]["generalization"]["significant"]
    return count / populations


def direct_difference(a, b, keep, modes):
    """G_b - G_a (M = 1..modes) of the cases ``keep`` alone, from their shapes."""
    errors = [generalization(p.shapes[keep], p.weights, modes)["squared_per_case"]
              for p in (a, b)]
    return (errors[1] - errors[0]).mean(axis=0)


def test_the_generalization_difference_is_paired_and_its_error_a_jackknife_over_the_cases():
    """The difference is the mean of the per-case differences of the leave-one-out errors; its
    standard error the jackknife's, each case left out of both populations and G computed again
    from the shapes, as written out here."""
    a, b = noisy_pair(np.random.default_rng(3), 8, 1.0)
    modes = 4
    result = compare_populations([a, b], modes, 100)
    g = result["differences"]["b"]["generalization"]
    n = 8
    left_out = np.array([direct_difference(a, b, np.delete(np.arange(n), j), modes)
                         for j in range(n)])
    jackknife = np.sqrt((n - 1) / n * np.sum((left_out - left_out.mean(axis=0)) ** 2, axis=0))
    np.testing.assert_allclose(g["difference"], direct_difference(a, b, np.arange(n), modes),
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g["se"], jackknife, rtol=1e-7)
    assert g["paired"] and not result["differences"]["b"]["specificity"]["paired"]
    # the unpaired SE counts the spread between cases, which both share: far larger
    unpaired = np.hypot(result["models"]["a"]["generalization_se"],
                        result["models"]["b"]["generalization_se"])
    assert np.all(np.asarray(g["se"]) < 0.5 * unpaired)


def test_beyond_its_groups_the_jackknife_leaves_out_a_group_at_a_time():
    """12 cases in 4 groups (case k in group k mod 4): each group left out of both populations
    in turn, G computed again from the shapes, SE^2 = 3/4 sum_g (D_(g) - mean)^2."""
    a, b = noisy_pair(np.random.default_rng(4), 12, 1.2)
    modes = 3
    spaces = [model_space(p.shapes, p.weights) for p in (a, b)]
    result = generalization_difference(*[generalization_jackknife(space, modes, groups=4)
                                         for space in spaces])
    group = np.arange(12) % 4
    left_out = np.array([direct_difference(a, b, np.flatnonzero(group != g), modes)
                         for g in range(4)])
    expected = np.sqrt(3 / 4 * np.sum((left_out - left_out.mean(axis=0)) ** 2, axis=0))
    np.testing.assert_allclose(result["se"], expected, rtol=1e-7)
    np.testing.assert_allclose(result["difference"], direct_difference(a, b, np.arange(12), modes),
                               rtol=1e-9)
    with pytest.raises(ValueError, match="at least 2 groups"):
        generalization_jackknife(spaces[0], modes, groups=1)
    with pytest.raises(ValueError, match="the same cases, groups and modes"):
        generalization_difference(generalization_jackknife(spaces[0], modes, groups=4),
                                  generalization_jackknife(spaces[1], modes, groups=3))


def test_equally_good_correspondences_are_called_different_at_most_at_the_nominal_rate():
    """False positives: two correspondences with independent noise of the same size, 100
    populations of 15 cases, are called different at M = 1..3 at most about as often as two
    standard errors allow (4.6 %; the binomial spread of 100 draws is 2 %). The per-case
    differences' own spread, which ignores that each case's error depends on the others' model,
    called 11-19 % of them different."""
    rate = generalization_verdicts(1.0, 100)
    assert np.all(rate <= 0.08), rate


def test_a_correspondence_with_a_tenth_more_noise_is_found_worse():
    """Power: 10 % more noise in one correspondence is found in most populations of 15 cases
    (the unpaired rule, which counts the cases' spread as noise, in 0-23 %)."""
    rate = generalization_verdicts(1.1, 30)
    assert np.all(rate >= 0.6), rate


def test_only_shared_cases_are_compared():
    shapes, weights, _ = two_mode_population(n=10)
    names = [f"c{k}" for k in range(10)]
    # b lacks c0 and has its cases in another order
    order = np.arange(9, 0, -1)
    b = Population("b", [names[i] for i in order], shapes[order], weights)
    result = compare_populations([Population("a", names, shapes, weights), b], 3, 300)
    assert result["cases"] == names[1:]
    assert result["excluded_cases"] == {"a": ["c0"], "b": []}
    np.testing.assert_allclose(result["differences"]["b"]["generalization"]["difference"], 0.0,
                               atol=1e-12)


def test_too_few_shared_cases_is_an_error():
    shapes, weights, _ = two_mode_population(n=5)
    with pytest.raises(InputError, match="share only 3 case.*at least 4"):
        compare_populations([Population("a", list("abcde"), shapes, weights),
                             Population("b", list("abcyz"), shapes, weights)])


def test_write_comparison_and_load_population(tmp_path):
    shapes, weights, triangles = two_mode_population(n=8)
    for name, population in (("one", shapes), ("two", shapes[::-1])):
        folder = tmp_path / name
        folder.mkdir()
        ShapeModel.from_shapes(population, weights, names=[f"c{k}" for k in range(8)][
            ::(1 if name == "one" else -1)], triangles=triangles, strategy="none").save(
            folder / "model.h5")
    populations = [load_population(tmp_path / "one"), load_population(tmp_path / "two")]
    assert populations[0].label == "one (none)"
    np.testing.assert_allclose(populations[0].shapes, shapes, atol=1e-9)
    result = compare_populations(populations, 2, 200)
    page = write_comparison(result, tmp_path / "cmp")
    text = page.read_text()
    assert text.count("<img src='data:image/png;base64") == 1    # the measures' plot
    # what was run: a table of version and date with no empty header row
    run = text[text.index("<h2>What was run</h2>"):]
    run = run[:run.index("</table>")]
    assert "<th>" not in run and "<td>version</td>" in run and "<td>date</td>" in run
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["n_cases"] == 8
    assert (tmp_path / "cmp" / "compare.csv").read_text().startswith("measure,M,model")
    with pytest.raises(InputError, match="no model.h5"):
        load_population(tmp_path / "cmp")


def test_one_decomposition_per_population_gives_the_numbers_of_a_model_and_its_own_measures(
        tmp_path, monkeypatch):
    """compare decomposes each population's n_s x 3 n_p shapes once, for the model's variances,
    the measures and the generalization's jackknife, where a model of the shapes, its
    evaluation and the jackknife's model space made one each; the numbers are theirs (computed
    here on one BLAS thread, as evaluate computes its measures: threaded BLAS may change the
    last bits of a decomposition beyond about 200 shapes)."""
    a, b = noisy_pair(np.random.default_rng(8), 9, 1.5)
    for population in (a, b):
        folder = tmp_path / population.label
        folder.mkdir()
        ShapeModel.from_shapes(population.shapes, population.weights, names=population.names,
                               strategy="none").save(folder / "model.h5")
    populations = [load_population(tmp_path / p.label) for p in (a, b)]
    modes, samples = 4, 300
    decomposed = []
    svd = np.linalg.svd

    def counted(matrix, *args, **kwargs):
        if np.shape(matrix) == (len(a.names), a.shapes[0].size):
            decomposed.append(np.shape(matrix))
        return svd(matrix, *args, **kwargs)

    monkeypatch.setattr(np.linalg, "svd", counted)
    result, _ = compare_builds([tmp_path / "a", tmp_path / "b"], tmp_path / "cmp", modes, samples)
    assert len(decomposed) == 2
    monkeypatch.undo()

    expected, jackknifes = {}, {}
    with threadpool_limits(limits=1, user_api="blas"):
        for population in populations:
            shapes, weights = population.shapes, population.weights
            expected[population.label] = evaluate(
                shapes, weights, ShapeModel.from_shapes(shapes, weights).variances, modes,
                samples, np.random.default_rng(0))
            jackknifes[population.label] = generalization_jackknife(
                model_space(shapes, weights), modes)
    assert result["models"] == expected
    first, second = (p.label for p in populations)
    assert result["differences"] == {second: measure_differences(
        expected[first], expected[second], jackknifes[first], jackknifes[second])}
    assert any(result["differences"][second]["generalization"]["significant"])
