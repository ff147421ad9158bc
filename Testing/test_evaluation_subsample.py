"""Tests of the generalization of a large population from a random subset of left-out cases
(model.evaluation.leave_out_cases, BuildConfig.generalization_cases).

The subset's estimate is checked against the exact leave-one-out generalization of a population
small enough to leave out every case, and its standard error against the spread of the estimate
over many subsets.
"""

import numpy as np
import pytest

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.model.evaluation import (SURFACE_GENERALIZATION_POINTS, evaluate,
                                             generalization, generalization_jackknife,
                                             leave_out_cases)
from mdlshapemodel.model.space import model_space
from mdlshapemodel.model.surface_measures import surface_generalization

from synthetic import radial_population


def random_population(rng, n_s, n_p=20):
    base = rng.normal(size=(n_p, 3)) * 4
    # a few strong directions and noise, so that the modes differ in size
    modes = rng.normal(size=(4, n_p, 3)) * np.array([3.0, 2.0, 1.0, 0.5])[:, None, None]
    shapes = (base + np.einsum("sm,mpd->spd", rng.normal(size=(n_s, 4)), modes)
              + rng.normal(size=(n_s, n_p, 3)) * 0.3)
    weights = rng.uniform(0.2, 2.0, size=n_p)
    return shapes, weights / weights.sum()


def variances_of(shapes, weights):
    n_s = len(shapes)
    centred = (shapes - shapes.mean(axis=0)).reshape(n_s, -1) * np.repeat(np.sqrt(weights), 3)
    return np.linalg.svd(centred, compute_uv=False)[:n_s - 1] ** 2 / n_s


def test_leave_out_cases_is_all_up_to_the_limit_and_a_sorted_subset_beyond():
    rng = np.random.default_rng(1)
    assert leave_out_cases(50, 50, rng) is None and leave_out_cases(50, None, rng) is None
    cases = leave_out_cases(51, 50, rng)
    assert len(cases) == 50 and len(set(cases.tolist())) == 50
    assert np.all(np.diff(cases) > 0) and cases.min() >= 0 and cases.max() <= 50
    again = leave_out_cases(51, 50, np.random.default_rng(1))
    np.testing.assert_array_equal(cases, again)           # reproducible from the generator


def test_a_subset_estimates_the_exact_generalization_within_its_standard_error():
    rng = np.random.default_rng(7)
    shapes, weights = random_population(rng, 160)
    n_s, k, modes = len(shapes), 30, 3
    space = model_space(shapes, weights)
    exact = generalization(shapes, weights, modes, space)
    assert "squared_subsample_se" not in exact
    estimates, reported = [], []
    for seed in range(120):
        cases = leave_out_cases(n_s, k, np.random.default_rng(seed))
        found = generalization(shapes, weights, modes, space, cases)
        # each left-out case's errors are those of the exact measure (its model: all the others)
        np.testing.assert_allclose(found["squared_per_case"], exact["squared_per_case"][cases],
                                   rtol=1e-10)
        np.testing.assert_allclose(found["distance_per_case"], exact["distance_per_case"][cases],
                                   rtol=1e-10)
        # eq. 21 over the k cases
        np.testing.assert_allclose(found["squared_se"], found["squared_per_case"].std(
            axis=0, ddof=1) / np.sqrt(k - 1), rtol=1e-12)
        estimates.append(found["squared"])
        reported.append(found["squared_subsample_se"])
        assert np.all(found["squared_subsample_se"] < found["squared_se"])
    estimates, reported = np.array(estimates), np.array(reported)
    within = np.abs(estimates - exact["squared"]) <= 2.0 * reported
    assert within.mean() > 0.88, within.mean()
    # the reported error of the subset is its spread over many subsets
    spread = estimates.std(axis=0, ddof=1)
    np.testing.assert_allclose(reported.mean(axis=0), spread, rtol=0.2)
    # and the subsets' mean is the exact mean (unbiased)
    assert np.all(np.abs(estimates.mean(axis=0) - exact["squared"])
                  < 4.0 * spread / np.sqrt(len(estimates)))


def test_the_subsets_own_error_shrinks_to_0_as_it_takes_in_every_case():
    """Drawn without replacement: a subset of half the cases has sqrt(1/2) of the error of k
    cases drawn with replacement, sd / sqrt(k); a 'subset' of every case has none."""
    rng = np.random.default_rng(11)
    shapes, weights = random_population(rng, 24)
    n_s, modes = len(shapes), 3
    space = model_space(shapes, weights)
    half = generalization(shapes, weights, modes, space, leave_out_cases(n_s, n_s // 2, rng))
    for measure in ("squared", "distance"):
        with_replacement = half[measure + "_per_case"].std(axis=0, ddof=1) / np.sqrt(n_s // 2)
        np.testing.assert_allclose(half[measure + "_subsample_se"],
                                   with_replacement * np.sqrt(0.5), rtol=1e-12)
    every = generalization(shapes, weights, modes, space, np.arange(n_s))
    assert np.all(every["squared_subsample_se"] == 0.0)
    assert np.all(every["distance_subsample_se"] == 0.0)


def test_a_subsets_jackknife_leaves_out_each_group_of_its_cases_in_turn():
    """The k-th case of the subset in group k mod groups; each group's value is the mean of the
    subset's errors without it."""
    rng = np.random.default_rng(12)
    shapes, weights = random_population(rng, 30)
    space = model_space(shapes, weights)
    cases = leave_out_cases(len(shapes), 10, rng)
    judged = generalization_jackknife(space, 3, groups=4, cases=cases)
    np.testing.assert_allclose(judged.per_case, generalization(
        shapes, weights, 3, space, cases)["squared_per_case"], rtol=1e-10)
    group = np.arange(10) % 4
    expected = [judged.per_case[group != g].mean(axis=0) for g in range(4)]
    np.testing.assert_allclose(judged.left_out, expected, rtol=1e-12)


def test_evaluate_leaves_out_a_subset_only_beyond_generalization_cases():
    rng = np.random.default_rng(3)
    shapes, triangles, weights, surfaces = radial_population(rng, 13, 6)
    n_s = len(shapes)
    variances = variances_of(shapes, weights)

    def evaluated(limit):
        return evaluate(shapes, weights, variances, 3, 200, np.random.default_rng(5),
                        triangles=triangles, surfaces=surfaces, surface_samples=10,
                        generalization_cases=limit)

    unlimited = evaluated(None)
    assert evaluated(n_s) == unlimited                   # up to the limit: exactly the same
    assert "generalization_cases" not in unlimited
    subset = evaluated(n_s - 1)
    assert subset["generalization_cases"] == n_s - 1
    assert subset["generalization"] != unlimited["generalization"]
    for key in ("generalization_subsample_se", "generalization_mm_subsample_se"):
        assert len(subset[key]) == 3 and all(v > 0 for v in subset[key])
    # the specificity samples are not touched by the choice of the cases
    for key in ("specificity", "specificity_se", "specificity_mm", "specificity_surface_mm",
                "compactness"):
        assert subset[key] == unlimited[key], key
    # the point and the surface generalization leave out the same cases: those drawn from the
    # generator spawned from the evaluation's
    cases = leave_out_cases(n_s, n_s - 1, np.random.default_rng(5).spawn(1)[0])
    exact = generalization(shapes, weights, 3)
    np.testing.assert_allclose(subset["generalization"],
                               exact["squared_per_case"][cases].mean(axis=0), rtol=1e-12)
    # the jackknife (for the paired differences against a baseline) is of the same cases
    judged = evaluate(shapes, weights, variances, 3, 200, np.random.default_rng(5),
                      jackknife=True, generalization_cases=n_s - 1)["jackknife"]
    np.testing.assert_allclose(judged.per_case, exact["squared_per_case"][cases], rtol=1e-12)
    assert judged.left_out.shape == (n_s - 1, 3)
    on_surfaces = surface_generalization(shapes, weights, triangles, surfaces, 3,
                                         SURFACE_GENERALIZATION_POINTS, None, None, cases)
    np.testing.assert_allclose(subset["generalization_surface_mm"], on_surfaces["distance"],
                               rtol=1e-12)


def test_the_build_setting_is_checked_and_has_a_default():
    assert BuildConfig().generalization_cases >= 100
    with pytest.raises(ConfigError, match="generalization_cases"):
        BuildConfig(generalization_cases=1).validate()


def surfaces_case(tmp_path):
    """Five small prepared label maps, their initial correspondence and a configuration that
    measures surface to surface."""
    from mdlshapemodel.correspondence.initial import initial_state
    from mdlshapemodel.prepare.batch import preprocess

    from files import write_label_map
    from synthetic import small_mask

    paths = [str(write_label_map(tmp_path / f"s{k}.nii.gz", small_mask(position)))
             for k, position in enumerate((-0.6, -0.3, 0.0, 0.3, 0.6))]
    config = BuildConfig(points=42, workers=1, cache_dir="", evaluation_modes=2,
                         specificity_samples=100, surface_samples=10)
    prepared, _ = preprocess(paths, config)
    return prepared, initial_state(prepared, config)[0], config


def test_the_true_surfaces_are_moved_to_the_model_frame_one_case_at_a_time(tmp_path):
    import pickle

    from mdlshapemodel.geometry import Pose
    from mdlshapemodel.model.evaluation import ModelFrameSurfaces, evaluate_state
    from mdlshapemodel.parallel import process_pool

    prepared, state, config = surfaces_case(tmp_path)
    eager = [(state.to_model_frame(i, case.surface()[0]), case.surface()[1])
             for i, case in enumerate(prepared)]
    lazy = ModelFrameSurfaces(state, prepared)
    copied = pickle.loads(pickle.dumps(lazy))       # as a pool's process gets it
    assert len(lazy) == len(copied) == len(eager)
    for (v, f), (lv, lf), (cv, cf) in zip(eager, lazy, copied):
        assert np.array_equal(v, lv) and np.array_equal(v, cv)
        assert np.array_equal(f, lf) and np.array_equal(f, cf)
    here = evaluate_state(state, config, prepared)
    assert "generalization_surface_mm" in here
    with process_pool(2) as pool:
        assert evaluate_state(state, config, prepared, pool=pool, background=False) == here
        assert evaluate_state(state, config, prepared, pool=pool).result() == here
    # the surfaces and their copy stay in the frame they were made in as the state moves on
    pose = state.examples[0].pose
    state.examples[0].pose = Pose(pose.scale, pose.rotation, pose.translation + 5.0)
    assert not np.array_equal(state.to_model_frame(0, prepared[0].surface()[0]), eager[0][0])
    assert np.array_equal(lazy[0][0], eager[0][0]) and np.array_equal(copied[0][0], eager[0][0])


def test_an_evaluation_in_the_background_holds_no_copy_of_the_true_surfaces(tmp_path):
    """While a baseline's evaluation waits on the pool (the whole optimisation), the build keeps
    its arguments: the surfaces among them are the prepared cases' own meshes and the poses, not
    the meshes moved to the model frame."""
    import threading
    import tracemalloc
    from concurrent.futures import ThreadPoolExecutor

    from mdlshapemodel.model.evaluation import evaluate_state

    prepared, state, config = surfaces_case(tmp_path)
    meshes_bytes = sum(v.nbytes + f.nbytes for v, f in (case.surface() for case in prepared))
    go = threading.Event()
    with ThreadPoolExecutor(1) as pool:
        pool.submit(go.wait)                        # the evaluation waits behind this
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            task = evaluate_state(state, config, prepared, pool=pool)
            held = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
            go.set()
        assert "generalization_surface_mm" in task.result()
    # the aligned shapes (5 x 42 points) and the poses are far smaller than the meshes
    shapes_bytes = state.aligned_shapes().nbytes
    assert held < shapes_bytes + 0.5 * meshes_bytes, (held, shapes_bytes, meshes_bytes)
