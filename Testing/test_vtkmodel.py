"""The model-building VTK objects (vtkmodel) in real VTK pipelines, against build_model."""

import ast
import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import vtk_to_numpy

from mdlshapemodel import BuildConfig, ShapeModel, build_model
from mdlshapemodel.prepare import surface
from mdlshapemodel.prepare.surface import point_surface_distances
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface, SurfaceToSphereMap
from mdlshapemodel.vtkmodel import (ShapeModelBuilder, ShapeModelInstance, ShapeModelReader,
                                    ShapeModelWriter, model_to_polydata, polydata_to_model)

from files import read_polydata, write_label_map
from synthetic import small_bump_top, small_mask

VTK_GUIDE = Path(__file__).resolve().parents[1] / "docs" / "vtk.md"
NAMES = ["left_0", "left_1", "left_2", "right_3"]
# small and deterministic: fast draws no random numbers and stops on its convergence test long
# before the time limit
CONFIG = BuildConfig(points=162, strategy="fast", max_time=600, baselines=[], workers=1,
                     mirror=["right_*"], specificity_samples=100, evaluation_modes=2,
                     surface_samples=0, cache_dir="")


def write_label_maps(folder: Path, names) -> list:
    """Small bumpy ellipsoids as .mha label maps (each in its own place); the ``right_`` ones
    are left-right mirror images."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (name, position) in enumerate(zip(names, np.linspace(-0.6, 0.6, len(names)))):
        mask = small_mask(float(position)).astype(np.uint8)
        if name.startswith("right_"):
            mask = mask[:, :, ::-1]                     # x -> -x about the image centre
        paths.append(write_label_map(folder / f"{name}.mha", mask, origin=(12.0 * k, -4.0, 2.0)))
    return paths


def sphere_maps(paths) -> list:
    """One reader -> LabelMapToClosedSurface -> SurfaceToSphereMap branch per file; the
    ``right_`` cases mirrored, as build mirrors the files that CONFIG.mirror matches."""
    branches = []
    for path in paths:
        reader = vtk.vtkMetaImageReader()
        reader.SetFileName(str(path))
        to_surface = LabelMapToClosedSurface()
        to_surface.SetInputConnection(reader.GetOutputPort())
        to_sphere = SurfaceToSphereMap()
        to_sphere.SetInputConnection(to_surface.GetOutputPort())
        to_sphere.SetMirrored(path.name.startswith("right_"))
        branches.append((reader, to_surface, to_sphere))
    return branches


def builder_of(branches, config: BuildConfig, names=None) -> ShapeModelBuilder:
    builder = ShapeModelBuilder()
    for _, _, to_sphere in branches:
        builder.AddInputConnection(to_sphere.GetOutputPort())
    builder.SetConfig(config)
    if names is not None:
        builder.SetCaseNames(names)
    return builder


def point_array(polydata, name):
    return vtk_to_numpy(polydata.GetPointData().GetArray(name))


def block_names(blocks) -> list:
    return [blocks.GetMetaData(i).Get(vtk.vtkCompositeDataSet.NAME())
            for i in range(blocks.GetNumberOfBlocks())]


def assert_same_model(a: ShapeModel, b: ShapeModel):
    """Every field of the two models, bit for bit."""
    for key in ("mean", "modes", "variances", "weights", "scores", "triangles", "parameters"):
        assert np.array_equal(getattr(a, key), getattr(b, key)), key
    assert a.names == b.names and a.part_sizes == b.part_sizes and a.metadata == b.metadata


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    return write_label_maps(tmp_path_factory.mktemp("labels"), NAMES)


@pytest.fixture(scope="module")
def pipeline(population):
    branches = sphere_maps(population)
    builder = builder_of(branches, CONFIG, NAMES)
    progress = []
    builder.AddObserver("ProgressEvent", lambda caller, _: progress.append(
        (caller.GetProgress(), caller.GetProgressText() or "")))
    builder.Update()
    return branches, builder, progress


@pytest.fixture(scope="module")
def built(population, tmp_path_factory):
    return build_model(population, tmp_path_factory.mktemp("out"), CONFIG)


@pytest.fixture(scope="module")
def quick(pipeline):
    """A second builder on the same sphere maps that runs in a moment (no optimisation)."""
    branches, _, _ = pipeline
    builder = builder_of(branches, BuildConfig(points=42, strategy="none", baselines=[],
                                               workers=1))
    builder.Update()
    return builder


def test_the_builder_gives_the_model_of_build_model(pipeline, built):
    _, builder, _ = pipeline
    assert builder.GetErrorText() == ""
    output = builder.GetOutput(0)
    model = polydata_to_model(output)
    assert_same_model(model, built.model)
    assert model.names == NAMES and model.n_modes == 3
    assert model.metadata["objective"] == built.final_objective
    field = output.GetFieldData()
    assert field.GetArray("InitialObjective").GetValue(0) == built.initial_objective
    assert built.final_objective < built.initial_objective     # the optimisation did something
    # the modes for a warp by vector: each at one standard deviation
    assert output.GetPointData().GetArray("mode_4") is None
    for k in range(3):
        np.testing.assert_allclose(point_array(output, f"mode_{k + 1}"),
                                   model.modes[k] * np.sqrt(model.variances[k]), rtol=1e-14)
    assert np.array_equal(vtk_to_numpy(field.GetArray("Variances")), built.model.variances)
    assert output.GetNumberOfPolys() == len(built.model.triangles)


def test_corresponded_surfaces_are_named_in_input_order_and_overlay_their_inputs(pipeline, built):
    branches, builder, _ = pipeline
    blocks = builder.GetOutput(1)
    assert isinstance(blocks, vtk.vtkMultiBlockDataSet) and block_names(blocks) == NAMES
    triangles = surface.polydata_to_arrays(builder.GetOutput(0))[1]
    for k, name in enumerate(NAMES):
        points, faces = surface.polydata_to_arrays(blocks.GetBlock(k))
        assert np.array_equal(faces, triangles)
        # as build writes them, and over the surface of the input (the right one reflected
        # back from its mirrored preparation)
        written, _ = surface.polydata_to_arrays(read_polydata(built.output / "correspondence" /
                                                         f"{name}.vtp"))
        np.testing.assert_allclose(points, written, rtol=0, atol=1e-12)
        vertices, input_faces = surface.polydata_to_arrays(branches[k][1].GetOutput())
        assert np.max(point_surface_distances(points, vertices, input_faces)) < 1e-9
    sphere_map = branches[3][2].GetOutput(0)
    assert sphere_map.GetFieldData().GetArray("Mirrored").GetValue(0) == 1
    assert np.mean(surface.polydata_to_arrays(sphere_map)[0][:, 0]) < 0 < np.mean(
        surface.polydata_to_arrays(blocks.GetBlock(3))[0][:, 0])


def test_progress_goes_up_to_the_end_with_the_optimisation_in_the_text(pipeline):
    _, _, progress = pipeline
    fractions = [fraction for fraction, _ in progress]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    assert fractions == sorted(fractions)
    assert any(re.search(r"integrated: .*F = ", text) for _, text in progress)


def test_settings_start_at_the_build_defaults():
    builder, defaults = ShapeModelBuilder(), BuildConfig()
    assert builder.GetConfig() == defaults
    assert builder.GetPoints() == defaults.points and builder.GetStrategy() == defaults.strategy
    assert builder.GetCorrespondence() == defaults.correspondence
    assert builder.GetMaxTime() == defaults.max_time and builder.GetSeed() == defaults.seed
    assert builder.GetMaxSweeps() == defaults.max_sweeps and builder.GetCaseNames() == ()
    builder.SetPoints(642)
    builder.SetMaxTime(30)
    assert builder.GetConfig() == BuildConfig(points=642, max_time=30.0,
                                              target_vertices=defaults.target_vertices)


def test_the_builder_says_why_its_optimisation_stopped(pipeline, quick):
    """Field data ``StoppedBy``: "converged", or the limit that came first; absent when
    nothing was optimised."""
    _, builder, _ = pipeline
    assert builder.GetOutput(0).GetFieldData().GetAbstractArray("StoppedBy").GetValue(0) == \
        "converged"
    assert quick.GetOutput(0).GetFieldData().GetAbstractArray("StoppedBy") is None
    branches, _, _ = pipeline
    hurried = builder_of(branches, BuildConfig(points=42, strategy="fast", max_time=0,
                                               baselines=[], workers=1))
    hurried.Update()
    assert hurried.GetErrorText() == ""
    assert hurried.GetOutput(0).GetFieldData().GetAbstractArray("StoppedBy").GetValue(0) == \
        "time limit"


def test_the_builder_reexecutes_only_when_an_input_or_a_setting_changes(quick, pipeline):
    builder = quick
    runs = builder.executions
    assert builder.GetErrorText() == "" and builder.GetOutput(0).GetNumberOfPoints() == 42
    builder.Update()
    builder.SetPoints(42)                                   # same values: not modified
    builder.SetConfig(builder.GetConfig())
    builder.SetCaseNames([])
    builder.Update()
    assert builder.executions == runs
    instance = ShapeModelInstance()
    instance.SetInputConnection(builder.GetOutputPort(0))
    instance.SetWeights([1.0])
    instance.Update()
    instance.SetWeights((1.0,))                             # same weights: not modified
    instance.Update()
    instance.SetWeights([-1.5, 0.5])                        # the instance runs, not the builder
    instance.Update()
    assert (builder.executions, instance.executions) == (runs, 2)
    builder.SetSeed(7)                                      # a setting: both run again
    instance.Update()
    assert (builder.executions, instance.executions) == (runs + 1, 3)
    assert builder.GetConfig().seed == 7
    builder.SetCaseNames(["a", "b", "c", "d"])
    builder.Update()
    assert builder.executions == runs + 2 and block_names(builder.GetOutput(1)) == list("abcd")


def test_case_names_from_the_inputs_field_data_else_defaults(pipeline):
    branches, _, _ = pipeline
    builder = ShapeModelBuilder()
    builder.SetConfig(BuildConfig(points=42, strategy="none", workers=1))
    for k, (_, _, to_sphere) in enumerate(branches[:3]):
        data = vtk.vtkPolyData()
        data.ShallowCopy(to_sphere.GetOutput(0))
        if k != 1:
            name = vtk.vtkStringArray()
            name.SetName("CaseName")
            name.InsertNextValue(f"named_{k}")
            data.GetFieldData().AddArray(name)
        builder.AddInputData(data)
    builder.Update()
    assert builder.GetErrorText() == ""
    assert block_names(builder.GetOutput(1)) == ["named_0", "case_1", "named_2"]
    assert polydata_to_model(builder.GetOutput(0)).names == ["named_0", "case_1", "named_2"]


def test_an_instance_is_the_mean_plus_weighted_modes(pipeline):
    _, builder, _ = pipeline
    model_output = builder.GetOutput(0)
    instance = ShapeModelInstance()
    instance.SetInputConnection(builder.GetOutputPort(0))
    instance.Update()                                       # no weights: the mean
    mean, triangles = surface.polydata_to_arrays(model_output)
    points, faces = surface.polydata_to_arrays(instance.GetOutput())
    assert np.array_equal(points, mean) and np.array_equal(faces, triangles)
    weights = [2.0, -1.0, 0.5]
    instance.SetWeights(weights)
    assert instance.GetWeights() == (2.0, -1.0, 0.5)
    instance.Update()
    expected = mean + sum(w * point_array(model_output, f"mode_{k + 1}")
                          for k, w in enumerate(weights))
    points, faces = surface.polydata_to_arrays(instance.GetOutput())
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-12)
    assert np.array_equal(faces, triangles)
    assert not np.allclose(points, mean, atol=1e-3)
    instance.SetWeights([1.0, 0.0, 0.0, 1.0])               # the model has 3 modes
    instance.Update()
    assert instance.GetOutput().GetNumberOfPoints() == 0
    assert instance.GetErrorText() == "Weights: 4 weights, but the model has 3 mode(s)"


def test_writer_and_reader_round_trips(pipeline, tmp_path):
    _, builder, _ = pipeline
    path = tmp_path / "model.h5"
    writer = ShapeModelWriter()
    writer.SetInputConnection(builder.GetOutputPort(0))
    writer.SetFileName(path)
    assert writer.Write() == 1 and writer.GetErrorText() == ""
    built = polydata_to_model(builder.GetOutput(0))
    assert_same_model(ShapeModel.load(path), built)
    reader = ShapeModelReader()
    reader.SetFileName(path)
    reader.Update()
    again = tmp_path / "again.h5"
    rewriter = ShapeModelWriter()
    rewriter.SetInputConnection(reader.GetOutputPort())
    rewriter.SetFileName(again)
    assert rewriter.Write() == 1
    second = ShapeModelReader()
    second.SetFileName(again)
    second.Update()
    first_output, second_output = reader.GetOutput(), second.GetOutput()
    assert_same_model(polydata_to_model(second_output), built)
    # every array, bit for bit, and the builder's output but for its InitialObjective and
    # StoppedBy (the build's, not the model's)
    for data in ("GetPointData", "GetFieldData"):
        arrays = [getattr(output, data)() for output in (first_output, second_output,
                                                         builder.GetOutput(0))]
        names = [[a.GetAbstractArray(i).GetName() for i in range(a.GetNumberOfArrays())]
                 for a in arrays]
        assert names[0] == names[1] == [n for n in names[2]
                                        if n not in ("InitialObjective", "StoppedBy")]
        for name in names[0]:
            values = [a.GetAbstractArray(name) for a in arrays]
            if isinstance(values[0], vtk.vtkStringArray):
                texts = [[v.GetValue(i) for i in range(v.GetNumberOfValues())] for v in values]
                assert texts[0] == texts[1] == texts[2], name
            else:
                assert np.array_equal(vtk_to_numpy(values[0]), vtk_to_numpy(values[1])), name
                assert np.array_equal(vtk_to_numpy(values[0]), vtk_to_numpy(values[2])), name
    assert reader.executions == 1
    reader.SetFileName(str(path))                           # the same name: not modified
    reader.Update()
    assert reader.executions == 1


def test_a_model_without_triangles_or_metadata_survives_the_polydata():
    rng = np.random.default_rng(3)
    model = ShapeModel.from_shapes(rng.normal(size=(5, 7, 3)), np.full(7, 1 / 7),
                                   objective=np.float64(2.5), ranges=np.arange(3))
    back = polydata_to_model(model_to_polydata(model))
    assert back.triangles is None and back.parameters is None
    assert back.metadata["objective"] == 2.5
    assert np.array_equal(back.metadata["ranges"], np.arange(3))
    for key in ("mean", "modes", "variances", "weights", "scores"):
        assert np.array_equal(getattr(back, key), getattr(model, key)), key


def test_failures_leave_empty_outputs_and_a_message(pipeline, quick, tmp_path):
    branches, _, _ = pipeline
    two = builder_of(branches[:2], BuildConfig(points=42, strategy="none", workers=1))
    two.Update()
    assert "only 2 usable case(s); at least 3 are needed" in two.GetErrorText()
    assert two.GetOutput(0).GetNumberOfPoints() == 0
    assert two.GetOutput(1).GetNumberOfBlocks() == 0
    # an input that is not sphere-mapped: the surface itself
    unmapped = builder_of(branches[:3], BuildConfig(points=42, strategy="none", workers=1))
    unmapped.AddInputConnection(branches[3][1].GetOutputPort())
    unmapped.SetCaseNames(NAMES)
    unmapped.Update()
    assert unmapped.GetErrorText().startswith("right_3: no point data SphereCoordinates")
    assert unmapped.GetOutput(0).GetNumberOfPoints() == 0
    # a bad setting, and too few case names; a good run afterwards clears the message
    quick.SetPoints(5)
    quick.Update()
    assert quick.GetErrorText() == "points: must be at least 12 (got 5)"
    assert quick.GetOutput(0).GetNumberOfPoints() == 0
    quick.SetPoints(42)
    quick.SetCaseNames(["a", "b"])
    quick.Update()
    assert quick.GetErrorText() == "CaseNames: 2 names for 4 inputs"
    quick.SetCaseNames([])
    quick.Update()
    assert quick.GetErrorText() == "" and quick.GetOutput(0).GetNumberOfPoints() == 42
    # model files
    reader = ShapeModelReader()
    reader.SetFileName(tmp_path / "missing.h5")
    reader.Update()
    assert reader.GetErrorText() == f"{tmp_path / 'missing.h5'}: no such model file"
    assert reader.GetOutput().GetNumberOfPoints() == 0
    (tmp_path / "text.h5").write_text("not a model")
    reader.SetFileName(tmp_path / "text.h5")
    reader.Update()
    assert reader.GetErrorText().startswith(f"{tmp_path / 'text.h5'}: not an HDF5 file")
    writer = ShapeModelWriter()
    writer.SetInputConnection(branches[0][2].GetOutputPort())  # a surface, not a model
    writer.SetFileName(tmp_path / "out.h5")
    assert writer.Write() == 0 and "not a shape model: no field data Variances" in \
        writer.GetErrorText()
    assert not (tmp_path / "out.h5").exists()
    writer.SetInputConnection(quick.GetOutputPort(0))
    writer.SetFileName(tmp_path / "no" / "such" / "folder.h5")
    assert writer.Write() == 0 and "could not be written" in writer.GetErrorText()
    # a model polydata whose arrays do not agree: fewer variances than modes
    damaged = vtk.vtkPolyData()
    damaged.DeepCopy(quick.GetOutput(0))
    variances = damaged.GetFieldData().GetArray("Variances")
    assert variances.GetNumberOfTuples() == 3
    variances.SetNumberOfTuples(2)
    instance = ShapeModelInstance()
    instance.SetInputData(damaged)
    instance.Update()
    assert instance.GetErrorText().startswith("not a shape model: cannot reshape")
    assert instance.GetOutput().GetNumberOfPoints() == 0


def test_abort_execute_cancels_the_optimisation(pipeline):
    branches, _, _ = pipeline
    builder = builder_of(branches, BuildConfig(points=42, max_time=600, baselines=[],
                                               workers=1))
    reports = []

    def abort_at_the_optimisation(caller, _):
        text = caller.GetProgressText() or ""
        if "F = " in text:
            reports.append(text)
            caller.AbortExecuteOn()

    builder.AddObserver("ProgressEvent", abort_at_the_optimisation)
    builder.Update()
    assert len(set(reports)) == 1                            # stopped at the first report
    assert builder.GetErrorText() == "cancelled (AbortExecute): no model"
    assert builder.GetOutput(0).GetNumberOfPoints() == 0
    builder.RemoveAllObservers()
    builder.AbortExecuteOff()
    builder.Update()                                         # runs again, to the end
    assert builder.executions == 2 and builder.GetErrorText() == ""
    assert builder.GetOutput(0).GetNumberOfPoints() == 42


def test_the_vtk_guides_example_runs(tmp_path, monkeypatch):
    section = VTK_GUIDE.read_text()
    code = next(block for block in re.findall(r"```python\n(.*?)```", section, re.S)
                if "ShapeModelBuilder" in block)
    files = re.search(r"files = (\{.*?\})", code, re.S).group(1)
    write_label_maps(tmp_path / "labels", list(ast.literal_eval(files)))  # the files it reads
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(code, str(VTK_GUIDE), "exec"), namespace)
    builder, model_reader = namespace["builder"], namespace["model_reader"]
    assert builder.GetErrorText() == ""
    assert block_names(namespace["corresponded"]) == ["case_1", "case_2", "case_3", "case_4"]
    assert namespace["instance"].GetOutput().GetNumberOfPoints() == 642
    model = ShapeModel.load(tmp_path / "model.h5")
    assert_same_model(model, polydata_to_model(namespace["mean"]))
    assert_same_model(polydata_to_model(model_reader.GetOutput()), model)


def test_a_guided_builder_gives_the_model_of_the_guided_build(population, pipeline, tmp_path):
    """Landmarks (the config's folder) guide the builder as they guide build_model, with the
    smoothness prior: the same model bit for bit, its landmarks in the model polydata."""
    marks = tmp_path / "marks"
    marks.mkdir()
    for k, (name, position) in enumerate(zip(NAMES, np.linspace(-0.6, 0.6, len(NAMES)))):
        top = small_bump_top(float(position))
        if name.startswith("right_"):
            top[0] = small_mask(0.0).shape[2] - 1 - top[0]
        point = top + (12.0 * k, -4.0, 2.0)
        (marks / f"{name}.csv").write_text("label,x,y,z\ntop,{},{},{}\n".format(*point))
    config = dataclasses.replace(CONFIG, landmarks=str(marks), smoothness=0.01)
    branches, _, _ = pipeline
    builder = builder_of(branches, config, NAMES)
    builder.Update()
    assert builder.GetErrorText() in ("", None)
    model = polydata_to_model(builder.GetOutput(0))
    reference = build_model(population, tmp_path / "out", config)
    assert_same_model(model, reference.model)
    assert model.landmarks == reference.model.landmarks and list(model.landmarks) == ["top"]
    unguided = polydata_to_model(pipeline[1].GetOutput(0))
    assert not unguided.landmarks and not np.array_equal(unguided.mean, model.mean)
