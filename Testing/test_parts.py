"""Multi-part objects (III-E): parts by labels and by manifest, one pose per case, parts apart."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel import BuildConfig
from mdlshapemodel.config import PartSpec, parse_part
from mdlshapemodel.geometry import align
from mdlshapemodel.correspondence.initial import initial_state
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.warps import SymmetricTheta
from mdlshapemodel.demo import DEMO_PARTS, write_demo_population
from mdlshapemodel.errors import ConfigError, InputError
from mdlshapemodel.model.shape_model import ShapeModel
from mdlshapemodel.prepare import preprocess
from mdlshapemodel.prepare.parts import read_manifest
from common import run_cli
from files import read_polydata
from synthetic import split_into_part_files

PARTS = list(DEMO_PARTS)          # left=1, right=2


def test_part_specs_are_parsed_and_checked():
    assert parse_part("tail=2, 3") == PartSpec("tail", (2, 3))
    assert parse_part("head") == PartSpec("head", ())
    assert BuildConfig(parts=["head=1", "tail=2"]).validate().part_specs()[1].labels == (2,)
    for bad, words in ((["head=1", "head=2"], "names must differ"), (["=1"], "NAME=LABELS"),
                       (["a/b=1"], "NAME=LABELS"), (["a=x"], "integers"),
                       (["a=0"], "positive")):
        with pytest.raises(ConfigError, match=words):
            BuildConfig(parts=bad).validate()


@pytest.fixture(scope="module")
def two_label_maps(tmp_path_factory):
    """Six generated two-label maps (the two-part demo population), and the same split into one
    file per part."""
    folder = tmp_path_factory.mktemp("two_part")
    paths = write_demo_population(folder / "joint", 6, seed=3, parts=True)
    (folder / "split").mkdir()
    table = split_into_part_files(paths, {"left": 1, "right": 2}, folder / "split")
    # the manifest beside the split folder: its paths relative to its own folder
    (folder / "cases.csv").write_text(table.read_text().replace(",subject", ",split/subject"))
    return folder, paths


def test_a_manifest_names_its_cases_parts_and_problems(tmp_path):
    (tmp_path / "a.nii.gz").write_bytes(b"")
    table = tmp_path / "cases.csv"
    table.write_text("case,part,file\n"
                     "s1,head,a.nii.gz\ns1,tail,/abs/b.nii.gz\n"
                     "s2,head,c.nii.gz\n"                       # no tail
                     "s3,head,d.nii.gz\ns3,head,e.nii.gz\ns3,tail,f.nii.gz\n")
    cases = read_manifest(table, BuildConfig())
    assert [c.name for c in cases] == ["s1", "s2", "s3"]
    s1 = cases[0]
    assert [(p.part, p.path) for p in s1.parts] == [("head", str(tmp_path / "a.nii.gz")),
                                                   ("tail", "/abs/b.nii.gz")]
    assert s1.problem == ""
    assert cases[1].problem == "no file for part 'tail' in cases.csv"
    assert cases[2].problem == "two files for part 'head' in cases.csv"
    # --part gives the order and the labels within each part's file
    ordered = read_manifest(table, BuildConfig(parts=["tail=4", "head"]))
    assert [(p.part, p.labels) for p in ordered[0].parts] == [("tail", (4,)), ("head", ())]
    with pytest.raises(ConfigError, match="'tail' is not among the --part parts"):
        read_manifest(table, BuildConfig(parts=["head"]))
    # one part: a one-part object (the outputs' layout of a plain build)
    table.write_text("case,part,file\ns1,,a.nii.gz\ns2,,b.nii.gz\n")
    assert [p.part for c in read_manifest(table, BuildConfig()) for p in c.parts] == ["", ""]
    for text, words in (("case,file\ns1,a\n", "missing: part"), ("case,part,file\n", "no rows"),
                        ("case,part,file\n,head,a\n", "line 2: a row needs a case")):
        table.write_text(text)
        with pytest.raises(InputError, match=words):
            read_manifest(table, BuildConfig())


def test_parts_by_labels_and_by_files_prepare_the_same_surfaces(two_label_maps):
    folder, paths = two_label_maps
    config = BuildConfig(parts=PARTS, points=162, workers=1, cache_dir="")
    by_labels, rejected = preprocess(paths, config)
    assert not rejected
    plain = BuildConfig(points=162, workers=1, cache_dir="")     # the parts are the manifest's
    by_files, rejected = preprocess(read_manifest(folder / "cases.csv", plain), plain)
    assert not rejected
    for a, b in zip(by_labels, by_files):
        assert a.name == b.name and a.part_names == b.part_names == ["left", "right"]
        for pa, pb in zip(a.parts, b.parts):
            assert np.array_equal(pa.map.vertices, pb.map.vertices)
            assert np.array_equal(pa.map.sphere, pb.map.sphere)
        # the two parts are two closed surfaces that touch: neither is the whole object
        left, right = (p.map.vertices for p in a.parts)
        assert left[:, 0].mean() < right[:, 0].mean()
        assert abs(left[:, 0].max() - right[:, 0].min()) < 2.0


def test_a_case_whose_part_fails_is_rejected_whole_with_the_part_named(two_label_maps,
                                                                        tmp_path):
    _, paths = two_label_maps
    image = sitk.ReadImage(str(paths[0]))
    only_left = sitk.Cast(image == 1, sitk.sitkUInt8)       # label 2 is absent
    only_left.CopyInformation(image)
    broken = tmp_path / "no_right.nii.gz"
    sitk.WriteImage(only_left, str(broken))
    config = BuildConfig(parts=PARTS, points=162, workers=1, cache_dir="")
    prepared, rejected = preprocess([broken, paths[1]], config)
    assert [c.name for c in prepared] == [paths[1].name[:-7]]
    assert len(rejected) == 1 and rejected[0].name == "no_right"
    assert rejected[0].reason.startswith("part right: ")


@pytest.fixture(scope="module")
def two_part_state(two_label_maps):
    _, paths = two_label_maps
    config = BuildConfig(parts=PARTS, points=162, workers=1, cache_dir="")
    prepared, _ = preprocess(paths, config)
    return prepared, config


def test_one_pose_moves_every_part_and_parts_keep_their_own_parameterizations(two_part_state):
    prepared, config = two_part_state
    state, _, _, _ = initial_state(prepared, config)
    assert [len(points) for points, _ in state.grids] == [162, 162]
    raw, aligned = state.raw_shapes(), state.aligned_shapes()
    for i in range(state.n_shapes):
        # one similarity maps all the case's points (both parts) onto its aligned points
        pose = align(raw[i], aligned[i], state.weights)
        assert np.abs(pose.apply(raw[i]) - aligned[i]).max() < 1e-9 * np.abs(aligned).max()
    # warping one part's parameterization moves nothing of the other part; re-aligning moves
    # both parts' aligned points by the one new pose of the case
    left, right = state.examples[2].parts
    before = right.positions.copy(), right.points.copy(), aligned[2].copy()
    kernel = SymmetricTheta(left.random_surface_parameter(np.random.default_rng(5)), 0.5, 0.4)
    assert not left.folds(kernel.apply(left.positions))
    left.commit(kernel, *left.propose(kernel))
    state.commit_shape(2)
    state.procrustes()
    assert np.array_equal(right.positions, before[0]) and np.array_equal(right.points, before[1])
    moved = state.aligned_shapes()[2]
    rows = state.part_slices[1]
    assert not np.allclose(moved[rows], before[2][rows])       # the pose changed ...
    pose = align(right.points, moved[rows], state.weights[rows] / state.weights[rows].sum())
    assert np.abs(pose.apply(right.points) - moved[rows]).max() < 1e-9   # ... rigidly
    assert not np.allclose(left.positions, left.grid)          # the left part did move


@pytest.mark.parametrize("strategy", ["fast", "one-at-a-time-pose"])
def test_every_part_is_optimised_and_none_folds(two_part_state, strategy):
    prepared, config = two_part_state
    state, pair, _, _ = initial_state(prepared, config)
    before = [[p.positions.copy() for p in e.parts] for e in state.examples]
    state.objective = pair[1]
    start = state.value()               # the description length and the default prior's energy
    settings = BuildConfig(parts=PARTS, points=162, strategy=strategy, max_sweeps=3, fixed_fraction=0,
                           max_time=60).optimisation_settings()
    final = optimise(state, pair, settings, np.random.default_rng(0), Trace())
    assert final < start
    for example, positions in zip(state.examples, before):
        for part, start_positions in zip(example.parts, positions):
            assert not part.folds(part.positions)
    moved = [[not np.array_equal(p.positions, b) for p, b in zip(e.parts, positions)]
             for e, positions in zip(state.examples, before)]
    assert any(m[0] for m in moved) and any(m[1] for m in moved)


@pytest.mark.slow
def test_cli_builds_a_two_part_model_by_labels_and_by_manifest(two_label_maps, tmp_path):
    folder, paths = two_label_maps
    common = ["--points", "162", "--max-sweeps", "2", "--surface-samples", "0",
              "--specificity-samples", "200", "--workers", "1"]
    by_labels = tmp_path / "labels"
    run = run_cli("build", *paths, "-o", by_labels, "--part", "left=1", "--part", "right=2",
                  *common)
    assert run.returncode == 0, run.stderr
    model = ShapeModel.load(by_labels / "model.h5")
    assert model.part_names == ["left", "right"] and model.part_sizes == [162, 162]
    mean = read_polydata(by_labels / "mean.vtp")
    part = vtk_to_numpy(mean.GetCellData().GetArray("part"))
    assert mean.GetNumberOfPoints() == 324 and sorted(set(part.tolist())) == [0, 1]
    for name in ("left", "right"):
        for sub in ("correspondence", "aligned"):
            files = sorted(p.name for p in (by_labels / sub / name).iterdir())
            assert files == sorted(p.name.replace(".nii.gz", ".vtp") for p in paths)
        one = read_polydata(by_labels / "correspondence" / name / "subject_01.vtp")
        assert one.GetNumberOfPoints() == 162 and one.GetNumberOfPolys() == 320
    # the left part of a case, in its own physical space, is the model's left rows of the case
    index = model.names.index("subject_01")
    aligned_left = vtk_to_numpy(read_polydata(by_labels / "aligned" / "left" /
                                          "subject_01.vtp").GetPoints().GetData())
    assert np.allclose(aligned_left, model.instance(model.scores[index])[:162], atol=1e-6)

    # a manifest with one file per part gives the same model; a missing file is one line
    table = folder / "with_a_missing_file.csv"      # beside the files it names
    table.write_text((folder / "cases.csv").read_text() + "ghost,left,nowhere.nii.gz\n"
                                                         "ghost,right,split/subject_01_right.nii.gz\n")
    by_files = tmp_path / "files"
    run = run_cli("build", "--manifest", table, "-o", by_files, *common)
    assert run.returncode == 0, run.stderr
    assert "nowhere.nii.gz: part left: no such file" in run.stderr
    other = ShapeModel.load(by_files / "model.h5")
    assert other.part_names == ["left", "right"]
    assert np.array_equal(other.mean, model.mean) and np.array_equal(other.modes, model.modes)
    metrics = json.loads((by_files / "metrics.json").read_text())
    assert metrics["n_rejected"] == 1


def test_demo_population_with_parts_has_two_touching_labels(tmp_path):
    paths = write_demo_population(tmp_path, 3, parts=True)
    for path in paths:
        labels = sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
        assert set(np.unique(labels).tolist()) == {0, 1, 2}
        one, two = np.argwhere(labels == 1), np.argwhere(labels == 2)
        assert one[:, 2].max() + 1 == two[:, 2].min()          # they share a face
    assert Path(paths[0]).name == "subject_01.nii.gz"


@pytest.mark.slow
def test_fit_and_compare_take_two_part_models(two_label_maps, tmp_path):
    """A new case is fitted to a two-part model part by part (split by the model's labels, or
    from a manifest of one file per part); compare evaluates two-part models side by side."""
    folder, paths = two_label_maps
    common = ["--points", "162", "--max-sweeps", "2", "--surface-samples", "0",
              "--specificity-samples", "200", "--workers", "1"]
    models = {}
    for strategy in ("fast", "none"):
        models[strategy] = tmp_path / strategy
        run = run_cli("build", *paths[:5], "-o", models[strategy], "--part", "left=1",
                      "--part", "right=2", "--strategy", strategy, *common)
        assert run.returncode == 0, run.stderr
    table = folder / "held_out.csv"
    table.write_text("case,part,file\nby_files,left,split/subject_06_left.nii.gz\n"
                     "by_files,right,split/subject_06_right.nii.gz\n")
    fitted = tmp_path / "fitted"
    run = run_cli("fit", models["fast"], paths[5], "--manifest", table, "-o", fitted,
                  "--max-sweeps", "2")
    assert run.returncode == 0, run.stderr
    summary = json.loads((fitted / "fit.json").read_text())
    assert set(summary) == {"subject_06", "by_files"}
    for name, result in summary.items():
        squared = result["reconstruction_squared_mm2"]
        assert squared[-1] < 0.5 * squared[0], name     # the modes explain the new case
        for part in ("left", "right"):
            for sub in ("correspondence", "reconstruction"):
                one = read_polydata(fitted / sub / part / f"{name}.vtp")
                assert one.GetNumberOfPoints() == 162
    # the same new case, from one label map or from two files: the same fit
    assert np.allclose(summary["subject_06"]["reconstruction_squared_mm2"],
                       summary["by_files"]["reconstruction_squared_mm2"], rtol=1e-9)
    run = run_cli("compare", models["fast"], models["none"], "-o", tmp_path / "cmp",
                  "--samples", "200", "--modes", "3")
    assert run.returncode == 0, run.stderr
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert result["n_cases"] == 5 and result["reference"] == "fast (fast)"
    assert set(result["models"]) == {"fast (fast)", "none (none)"}
    assert set(result["differences"]) == {"none (none)"}
    # each model is compared whole, both parts: its compactness is its own variances' sums
    for strategy, folder in models.items():
        measures = result["models"][f"{strategy} ({strategy})"]
        variances = ShapeModel.load(folder / "model.h5").variances
        np.testing.assert_allclose(measures["compactness"], np.cumsum(variances[:3]), rtol=1e-6)
        for measure in ("generalization", "specificity"):
            assert len(measures[measure]) == 3 and np.all(np.array(measures[measure]) > 0)


def test_a_two_part_model_goes_through_files_and_vtk_whole(tmp_path, rng):
    from mdlshapemodel.correspondence.sampling import sphere_grid
    from mdlshapemodel.vtkmodel import ShapeModelReader, model_to_polydata, polydata_to_model

    grid, triangles = sphere_grid(42)
    shapes = np.concatenate([grid + rng.normal(scale=0.05, size=(6, 42, 3)),
                             2 * grid + 5 + rng.normal(scale=0.05, size=(6, 42, 3))], axis=1)
    model = ShapeModel.from_shapes(shapes, np.full(84, 1 / 84), part_sizes=[42, 42],
                                   part_names=["inner", "outer"],
                                   triangles=np.concatenate([triangles, triangles + 42]))
    assert [m.name for m in model.part_meshes()] == ["inner", "outer"]
    assert np.array_equal(model.part_meshes()[1].triangles, triangles)
    model.save(tmp_path / "model.h5")
    assert ShapeModel.load(tmp_path / "model.h5").part_names == ["inner", "outer"]
    polydata = model_to_polydata(model)
    part = vtk_to_numpy(polydata.GetCellData().GetArray("part"))
    assert part.tolist() == [0] * len(triangles) + [1] * len(triangles)
    assert polydata_to_model(polydata).part_names == ["inner", "outer"]
    reader = ShapeModelReader()
    reader.SetFileName(str(tmp_path / "model.h5"))
    reader.Update()
    assert polydata_to_model(reader.GetOutput()).part_sizes == [42, 42]
