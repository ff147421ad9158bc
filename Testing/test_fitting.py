"""Fitting new cases to a built model: correspondence, scores, reconstruction."""

import json
from dataclasses import replace

import numpy as np
import pytest

from mdlshapemodel import BuildConfig, build_model
from mdlshapemodel.errors import InputError
from mdlshapemodel.model.evaluation import generalization
from mdlshapemodel.correspondence.smoothness import bending_matrix
from mdlshapemodel.fit import fit_cases
from mdlshapemodel.folders import BuildFolder
from mdlshapemodel.model.fitting import build_config_of, fit_case
from mdlshapemodel.prepare.io import read_csv
from mdlshapemodel.prepare import prepare_case
from mdlshapemodel.prepare.surface import point_surface_distances

from files import write_label_map
from synthetic import small_mask

# real builds (the command line or build_model): deselected by -m "not slow"
pytestmark = pytest.mark.slow

POSITIONS = np.linspace(-0.6, 0.6, 7)
HELD_BACK = 3


def write_case(folder, k, position, origin=(0.0, 0.0, 0.0)):
    return write_label_map(folder / f"case_{k}.nii.gz", small_mask(float(position)),
                           origin=origin)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """A model of all 7 cases and one of the 6 others, with the held-back case's file."""
    folder = tmp_path_factory.mktemp("labels")
    paths = [write_case(folder, k, p, origin=(7.0 * k, 0.0, -3.0)) for k, p in enumerate(POSITIONS)]
    config = BuildConfig(points=162, max_time=600, max_sweeps=2, workers=1,
                         specificity_samples=200, evaluation_modes=3, surface_samples=0)
    full = build_model(paths, tmp_path_factory.mktemp("full"), config)
    others = [p for k, p in enumerate(paths) if k != HELD_BACK]
    partial = build_model(others, tmp_path_factory.mktemp("partial"), config)
    return full, partial, paths[HELD_BACK]


@pytest.fixture(scope="module")
def fitted(models):
    _, partial, path = models
    model = BuildFolder(partial.output).model()
    return model, fit_case(model, path, max_time=600, max_sweeps=3)


def test_reconstruction_error_falls_with_every_mode(fitted):
    model, result = fitted
    assert result.scores.shape == (model.n_modes,)
    assert result.squared_error.shape == (model.n_modes + 1,)
    assert np.all(np.diff(result.squared_error) <= 1e-12)
    assert result.squared_error[-1] < 0.5 * result.squared_error[0]
    # the projection is the weighted least-squares fit: the residual is orthogonal to the modes
    residual = result.aligned - model.instance(result.scores)
    inner = np.einsum("mkd,kd->m", model.modes, residual * model.weights[:, None])
    np.testing.assert_allclose(inner, 0.0, atol=1e-9 * np.abs(result.scores).max())


def test_fitted_points_lie_on_the_case_and_overlay_it(fitted, models):
    model, result = fitted
    _, _, path = models
    case = prepare_case(str(path), BuildConfig())
    distances = point_surface_distances(result.corresponded, case.map.vertices,
                                  case.map.faces)
    assert distances.max() < 0.2       # sampled on the case's own surface (mesh vs its vertices)
    reconstruction = result.reconstruction(model)
    assert np.linalg.norm(reconstruction.mean(axis=0) - case.map.vertices.mean(axis=0)) < 1.0
    # the model frame and the case's frame are related by the stored pose
    np.testing.assert_allclose(result.to_model.apply(result.corresponded), result.aligned,
                               atol=1e-9)


def test_optimising_the_new_case_lowers_the_objective(fitted):
    _, result = fitted
    assert result.objective["final"] < result.objective["initial"]
    assert result.objective["evaluations"] > 0
    assert result.objective["strategy"] == "fast"           # the model's own build strategy


def test_fit_with_another_strategy(fitted, models):
    """The paper's strategy 4 on the same case: it moves the case's samples by theta kernels
    and also lowers the objective from the same start."""
    _, _, path = models
    model, by_default = fitted
    result = fit_case(model, path, max_time=600, max_sweeps=2, strategy="one-at-a-time-pose")
    assert result.objective["strategy"] == "one-at-a-time-pose"
    assert result.objective["initial"] == pytest.approx(by_default.objective["initial"])
    assert result.objective["final"] < result.objective["initial"]
    assert not np.allclose(result.corresponded, by_default.corresponded)


def test_the_models_smoothness_prior_holds_for_the_new_case(models, fitted):
    """A model's prior on smooth correspondence (its config's ``smoothness``) is part of the
    new case's objective: with a heavy one, the fitted case differs from the mean by a
    displacement that bends less than without it; the objective reported is eq. 14 alone, from
    the same start."""
    _, _, path = models
    model, plain = fitted
    smooth = fit_case(model, path, replace(build_config_of(model), smoothness=1.0),
                      max_time=600, max_sweeps=3)
    bending = bending_matrix(model.mean)

    def energy(result):
        displacement = result.aligned - model.mean
        return float(np.trace(displacement.T @ bending @ displacement))

    # without the prior the two fits are the same, bit for bit
    assert energy(smooth) < 0.98 * energy(plain), (energy(smooth), energy(plain))
    assert smooth.objective["initial"] == pytest.approx(plain.objective["initial"])


def test_held_back_error_is_close_to_its_leave_one_out_error(models, fitted):
    full, _, _ = models
    model, result = fitted
    # the held-back case's leave-one-out error in the model of all seven, M = 1..3
    index = full.model.names.index(f"case_{HELD_BACK}")
    shapes = full.model.instance(full.model.scores)
    per_case = generalization(shapes, full.model.weights, 3)["squared_per_case"][index]
    fitted_errors = result.squared_error[1:4]
    # its error with M modes in the model of all seven, which was built with it
    scores = full.model.scores[index]
    in_sample = np.array([
        np.sum(full.model.weights[:, None]
               * (shapes[index] - full.model.instance(np.where(np.arange(scores.size) < m,
                                                               scores, 0.0))) ** 2)
        for m in (1, 2, 3)])
    # the fit also optimises the case's correspondence, so it may beat the leave-one-out error,
    # but not by more than half, and not the model that was built with the case
    assert np.all(fitted_errors < 2.0 * per_case)
    assert np.all(fitted_errors > in_sample), (fitted_errors, in_sample, per_case)


def test_fit_cases_writes_outputs_and_rejects_bad_inputs(models, tmp_path):
    _, partial, path = models
    bad = tmp_path / "bad.nii.gz"
    write_label_map(bad, np.zeros((8, 8, 8)))
    out = tmp_path / "fit"
    results, rejected = fit_cases(partial.output, [path, bad], out, max_time=600, max_sweeps=1)
    assert [r.name for r in results] == [f"case_{HELD_BACK}"]
    assert [r[0] for r in rejected] == ["bad"] and "empty" in rejected[0][2]
    summary = json.loads((out / "fit.json").read_text())
    entry = summary[f"case_{HELD_BACK}"]
    assert len(entry["reconstruction_squared_mm2"]) == results[0].squared_error.size
    # the case's distance from the mean in the model it was fitted to, and its scores there
    model = BuildFolder(partial.output).model()
    assert entry["mahalanobis"] == pytest.approx(
        np.sqrt(np.sum(results[0].scores ** 2 / model.variances)), rel=1e-12)
    rows = read_csv(out / "scores.csv")
    assert rows[0]["case"] == f"case_{HELD_BACK}"
    np.testing.assert_allclose([float(v) for k, v in rows[0].items() if k != "case"],
                               results[0].scores, rtol=1e-5, atol=1e-8)
    assert (out / "correspondence" / f"case_{HELD_BACK}.vtp").is_file()
    assert (out / "reconstruction" / f"case_{HELD_BACK}.vtp").is_file()
    assert read_csv(out / "rejected.csv")[0]["case"] == "bad"


def test_missing_model_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="no such model file"):
        BuildFolder(tmp_path / "nothing").model()
