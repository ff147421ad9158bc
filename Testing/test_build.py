"""build_model() end to end on small synthetic label maps, with bad inputs mixed in."""

import json

import numpy as np
import pytest
import SimpleITK as sitk

from mdlshapemodel import BuildConfig, ShapeModel, build_model
from mdlshapemodel.correspondence.strategies.base import PhasePoint
from mdlshapemodel.folders import read_checkpoint
from mdlshapemodel.kernels import compile_ahead
from mdlshapemodel.prepare.io import read_csv
from mdlshapemodel.errors import BuildError

from files import polydata_triangles, write_label_map
from synthetic import small_mask

# real builds (the command line or build_model): deselected by -m "not slow"
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("labels")
    paths = []
    for k, position in enumerate(np.linspace(-0.6, 0.6, 4)):
        origin = (10.0 * k, -5.0, 3.0)  # each case in its own physical place
        mask = small_mask(float(position))
        if k == 0:  # debris and a cavity, both repaired
            mask[0:2, 0:2, 0:2] = True
            centre = np.array(mask.shape) // 2
            mask[tuple(slice(c - 1, c + 1) for c in centre)] = False
        paths.append(write_label_map(folder / f"case_{k}.nii.gz", mask, origin=origin))
    write_label_map(folder / "empty.nii.gz", np.zeros((10, 10, 10), bool))
    (folder / "notes.nrrd").write_text("this is not an image")
    return folder, paths


@pytest.fixture(scope="module")
def built(population, tmp_path_factory):
    folder, _ = population
    output = tmp_path_factory.mktemp("out")
    # the fast strategy optimises on 42 of the 162 points per part and measures eq. 14 there;
    # without the prior on smooth correspondence, so that the objective convergence.csv traces
    # (the optimised one, the prior included) is eq. 14 of metrics.json
    config = BuildConfig(points=162, coarse_points=42, max_time=4.0, workers=2,
                         specificity_samples=500, evaluation_modes=3, smoothness=0.0)
    return build_model([folder], output, config), output


def test_bad_inputs_are_rejected_and_the_build_goes_on(built):
    result, output = built
    assert result.metrics["n_shapes"] == 4
    rejected = {row["case"]: row["reason"] for row in read_csv(output / "rejected.csv")}
    assert set(rejected) == {"empty", "notes"}
    assert "empty" in rejected["empty"]
    assert "not a readable image" in rejected["notes"]
    log = (output / "build.log").read_text()
    assert "rejected" in log and "notes.nrrd" in log


def test_repairs_are_reported_per_case(built):
    _, output = built
    cases = {row["case"]: row for row in read_csv(output / "cases.csv")}
    assert "dropped 1 small component(s) of 8 voxels" in cases["case_0"]["repair"]
    assert "filled 8 cavity voxels" in cases["case_0"]["repair"]
    assert cases["case_1"]["repair"] == ""
    assert all(float(row["smoothing_sigma"]) >= 1.0 for row in cases.values())


def test_outputs_have_identical_connectivity_and_physical_placement(built, population):
    result, output = built
    _, paths = population
    names = [f"case_{k}" for k in range(4)]
    mean_points, mean_cells = polydata_triangles(output / "mean.vtp")
    assert mean_points.shape == (162, 3)
    for k, name in enumerate(names):
        points, cells = polydata_triangles(output / "correspondence" / f"{name}.vtp")
        aligned, aligned_cells = polydata_triangles(output / "aligned" / f"{name}.vtp")
        assert np.array_equal(cells, mean_cells) and np.array_equal(aligned_cells, mean_cells)
        # correspondence meshes overlay their image: centred near the mask's physical centre
        image = sitk.ReadImage(str(paths[k]))
        mask = sitk.GetArrayFromImage(image) > 0
        centre_index = np.argwhere(mask).mean(axis=0)[::-1]
        centre = np.array(image.TransformContinuousIndexToPhysicalPoint(centre_index.tolist()))
        assert np.linalg.norm(points.mean(axis=0) - centre) < 1.5


def test_model_file_scores_and_metrics_agree(built):
    result, output = built
    model = ShapeModel.load(output / "model.h5")
    assert model.names == [f"case_{k}" for k in range(4)]
    rows = read_csv(output / "scores.csv")
    scores = np.array([[float(v) for k, v in row.items() if k != "case"] for row in rows])
    np.testing.assert_allclose(scores, model.scores, rtol=1e-5, atol=1e-8)
    aligned = np.stack([polydata_triangles(output / "aligned" / f"{n}.vtp")[0] for n in model.names])
    np.testing.assert_allclose(model.instance(model.scores[1]), aligned[1], atol=1e-6)
    metrics = json.loads((output / "metrics.json").read_text())
    assert metrics["modes"] == [1, 2, 3]
    for key in ("compactness", "generalization", "specificity"):
        assert len(metrics[key]) == 3 and len(metrics[key + "_se"]) == 3
    np.testing.assert_allclose(metrics["compactness"], np.cumsum(model.variances)[:3])
    assert metrics["objective"]["final"] < metrics["objective"]["initial"]
    assert metrics["objective"]["n_points"] == 42 and metrics["n_points"] == 162
    assert "on the 42 sample points it was optimised on" in (output / "report.html").read_text()
    assert metrics["surface_distance_mm"]["mean"] < 0.5
    convergence = read_csv(output / "convergence.csv")
    assert float(convergence[-1]["objective"]) == pytest.approx(metrics["objective"]["final"])
    assert (output / "report.html").read_text().count("data:image/png;base64") >= 2
    # the checkpoint holds the optimisation's end once it converged (a --resume has nothing left
    # to do), else the last step's point (a --resume carries on), and its trace, the rows of
    # convergence.csv
    checkpoint = read_checkpoint(output / "checkpoint.npz")
    converged = metrics["optimisation"]["converged"]
    assert (checkpoint.point.phase == PhasePoint.DONE) == converged
    rows = [float(row["objective"]) for row in convergence]
    if not converged:   # after the last step, a row may say the initial correspondence is kept
        rows = rows[:len(checkpoint.trace_rows)]
    assert [row.objective for row in checkpoint.trace_rows] == pytest.approx(rows, rel=1e-9)


def test_the_reported_objective_is_the_minimised_one_with_its_parts(population, tmp_path):
    """With the prior on smooth correspondence (the default weight), metrics.json's objective is
    the F the optimisation minimised, the sum of its named parts: the last value convergence.csv
    traces, the model's metadata and the report's."""
    folder, paths = population
    config = BuildConfig(points=162, coarse_points=42, max_time=3.0, workers=1,
                         specificity_samples=200, evaluation_modes=2)
    result = build_model(paths, tmp_path / "out", config)
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    objective = metrics["objective"]
    for when in ("initial", "final"):
        parts = objective["parts"][when]
        assert set(parts) == {"description_length", "prior", "guides"}
        assert parts["prior"] > 0 and parts["guides"] == 0.0
        assert objective[when] == pytest.approx(
            parts["description_length"] + parts["prior"] + parts["guides"], rel=1e-12)
    convergence = read_csv(tmp_path / "out" / "convergence.csv")
    assert float(convergence[-1]["objective"]) == pytest.approx(objective["final"], rel=1e-9)
    assert result.model.metadata["objective"] == objective["final"]
    report = (tmp_path / "out" / "report.html").read_text()
    assert f"smoothness prior {objective['parts']['final']['prior']:.3f}" in report


def test_too_few_usable_cases_is_an_error(population, tmp_path):
    _, paths = population
    with pytest.raises(BuildError, match="at least 3"):
        build_model(paths[:2], tmp_path / "out", BuildConfig(points=42, max_time=0, workers=1))


def test_strict_turns_rejections_into_failure(population, tmp_path):
    folder, _ = population
    with pytest.raises(BuildError, match="strict"):
        build_model([folder], tmp_path / "out",
                    BuildConfig(points=42, max_time=0, workers=1, strict=True))


def test_cancelled_optimisation_still_writes_the_model(population, tmp_path):
    from mdlshapemodel import Cancelled

    folder, paths = population
    calls = []

    def progress(fraction, message):
        if fraction is None:  # optimisation messages
            calls.append(message)
            if len(calls) == 3:
                raise Cancelled()

    config = BuildConfig(points=42, max_time=600, workers=1, specificity_samples=100,
                         evaluation_modes=2)
    result = build_model(paths, tmp_path / "out", config, progress=progress)
    assert result.interrupted and len(calls) == 3
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["interrupted"] is True
    assert ShapeModel.load(tmp_path / "out" / "model.h5").scores.shape[0] == 4


def test_a_progress_callback_returning_false_cancels_like_raising(population, tmp_path):
    _, paths = population
    calls = []

    def progress(fraction, message):
        if fraction is None:
            calls.append(message)
            return len(calls) < 2       # False at the second optimisation report: stop

    config = BuildConfig(points=42, max_time=600, workers=1, specificity_samples=100,
                         evaluation_modes=2, cache_dir="")
    result = build_model(paths, tmp_path / "out", config, progress=progress)
    assert result.interrupted and len(calls) == 2


def test_a_callers_executor_serves_the_build_and_gives_the_same_model(population, tmp_path):
    """Any concurrent.futures.Executor plugs in (here a spawn process pool the test owns): the
    same model as a build in one process, and the executor is left running for its owner."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    _, paths = population
    config = BuildConfig(points=42, max_time=600, workers=1, specificity_samples=200,
                         evaluation_modes=2, cache_dir="", baselines=["none", "cpd"])
    alone = build_model(paths, tmp_path / "alone", config)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as executor:
        shared = build_model(paths, tmp_path / "shared", config, executor=executor)
        assert executor.submit(abs, -3).result() == 3      # not shut down by the build
    assert shared.final_objective == alone.final_objective
    assert np.array_equal(shared.model.mean, alone.model.mean)
    for key in ("generalization", "specificity", "generalization_surface_mm"):
        assert shared.metrics[key] == alone.metrics[key]
    assert shared.metrics["baselines"] == alone.metrics["baselines"]


def test_preprocessing_cache_is_reused_only_for_identical_files_and_settings(population, tmp_path,
                                                                            monkeypatch):
    from mdlshapemodel.prepare import preprocess

    _, paths = population
    cache = tmp_path / "cache"
    config = BuildConfig(workers=1, cache_dir=str(cache))
    first, _ = preprocess(paths[:2], config)
    assert len(list(cache.glob("*.npz"))) == 2
    stamps = {f: f.stat().st_mtime_ns for f in cache.glob("*.npz")}
    again, _ = preprocess(paths[:2], config)
    assert {f: f.stat().st_mtime_ns for f in cache.glob("*.npz")} == stamps  # nothing rewritten
    for a, b in zip(first, again):
        assert a.name == b.name and a.record() == b.record() and a.map.quality == b.map.quality
        assert np.array_equal(a.map.sphere, b.map.sphere)
        assert np.array_equal(a.map.faces, b.map.faces)
    # another setting that changes the surface: new entries
    preprocess(paths[:1], BuildConfig(workers=1, cache_dir=str(cache), smoothing_sigma=1.5))
    assert len(list(cache.glob("*.npz"))) == 3
    # a new preprocessing algorithm does not reuse the old entries
    from mdlshapemodel.prepare import cache as preprocessing_cache

    key = preprocessing_cache.cache_key(paths[0], config)
    monkeypatch.setattr(preprocessing_cache, "PREPROCESSING_VERSION", preprocessing_cache.PREPROCESSING_VERSION + 1)
    assert preprocessing_cache.cache_key(paths[0], config) != key
    monkeypatch.undo()
    assert preprocessing_cache.cache_key(paths[0], config) == key
    # a damaged entry is recomputed, not trusted
    damaged = sorted(stamps)[0]
    damaged.write_bytes(b"not an npz file")
    recomputed, _ = preprocess(paths[:2], config)
    assert [r.name for r in recomputed] == [r.name for r in first]
    assert np.load(damaged)["sphere"].shape[1] == 3
    # default place from the environment; switched off, nothing is stored there
    default = tmp_path / "default"
    monkeypatch.setenv("MDLSHAPEMODEL_CACHE", str(default))
    preprocess(paths[:1], BuildConfig(workers=1, cache_dir=""))
    assert not default.exists()
    preprocess(paths[:1], BuildConfig(workers=1))
    assert len(list(default.glob("*.npz"))) == 1


def test_mirrored_inputs_are_modelled_with_their_other_side(tmp_path):
    """A right-side copy of a left shape, mirrored on input, joins the model as that shape and
    its corresponded mesh is written back on the right side, over its input."""
    from mdlshapemodel.prepare import surface
    from mdlshapemodel.prepare.io import write_polydata
    from mdlshapemodel.prepare.surface import point_surface_distances

    folder = tmp_path / "meshes"
    folder.mkdir()
    shapes = []
    for k, position in enumerate((-0.5, 0.0, 0.5)):
        vertices, faces, _ = surface.mask_to_surface(small_mask(position), edge_length=1.5)
        write_polydata(folder / f"left_{k}.vtp", vertices, faces)
        shapes.append((vertices, faces))
    right = shapes[0][0] * np.array([-1.0, 1.0, 1.0]) + np.array([40.0, 0.0, 0.0])
    write_polydata(folder / "right_0.vtp", right, shapes[0][1][:, [0, 2, 1]])
    output = tmp_path / "out"
    # right_0 is left_0 once more (mirrored back, the same shape): allowed here
    result = build_model([folder], output, BuildConfig(points=162, max_time=0, workers=1,
                                                        mirror=["right_*"], voxel_size=1.0,
                                                        specificity_samples=100,
                                                        evaluation_modes=2,
                                                        allow_duplicates=True))
    cases = {row["case"]: row for row in read_csv(output / "cases.csv")}
    assert cases["right_0"]["mirrored"] == "True" and cases["left_0"]["mirrored"] == "False"
    points, triangles = polydata_triangles(output / "correspondence" / "right_0.vtp")
    assert np.max(point_surface_distances(right, points, triangles)) < 1.0
    aligned = {n: polydata_triangles(output / "aligned" / f"{n}.vtp")[0] for n in ("left_0", "right_0")}
    assert np.mean(np.linalg.norm(aligned["left_0"] - aligned["right_0"], axis=1)) < 0.5
    assert result.metrics["n_shapes"] == 4


def test_one_decomposition_of_the_shapes_per_correspondence(population, tmp_path, monkeypatch):
    """The model and its evaluation share one SVD of the n_s x 3 n_p aligned shapes, and the
    baseline's evaluation (the initial correspondence), which needs no model, makes one more:
    two in a build with one baseline, where each model and model space made its own."""
    _, paths = population
    points = 42
    decomposed = []
    svd = np.linalg.svd

    def counted(a, *args, **kwargs):
        if np.ndim(a) == 2 and np.shape(a) == (len(paths), 3 * points):
            decomposed.append(np.shape(a))
        return svd(a, *args, **kwargs)

    compile_ahead(build_model, second_process=False)     # its own tiny build: not counted
    monkeypatch.setattr(np.linalg, "svd", counted)
    result = build_model(paths, tmp_path / "out",
                         BuildConfig(points=points, max_time=0, workers=1, baselines=["none"],
                                     specificity_samples=100, evaluation_modes=2))
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert "none" in metrics["baselines"] and result.model.n_modes == len(paths) - 1
    assert len(decomposed) == 2
