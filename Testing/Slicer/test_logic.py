"""The module's Logic against a real MRML scene (slicer-core), headless, as scripts and other
modules use it; see harness.py for what stands in for the Slicer application."""

import dataclasses
import json
import time

import numpy as np
import pytest
import slicer
import vtk
from vtk.util.numpy_support import vtk_to_numpy

import harness
import MDLShapeModel as module
from MDLShapeModelLib import dependencies
from mdlshapemodel import BuildConfig, ShapeModel
from mdlshapemodel.config import SMOOTHNESS, SURFACE_POINTS, AnalysisConfig
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.folders import FitFolder, mesh_points
from mdlshapemodel.progress import OBJECTIVE
from mdlshapemodel.prepare import io, preprocess
from mdlshapemodel.prepare.surface import (arrays_to_polydata, mask_to_surface,
                                           point_surface_distances)
import files
from common import run_cli, run_python
from synthetic import small_bump_top, small_mask

# small and quick: 162 points, a short evaluation
QUICK = dict(points=162, baselines=[], max_time=120, evaluation_modes=2, specificity_samples=100,
             workers=1)
LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


def points_of(node) -> np.ndarray:
    return vtk_to_numpy(node.GetPolyData().GetPoints().GetData()).astype(np.float64)


def write_label_map(path, mask, label=1, origin=(5.0, -3.0, 2.0), spacing=(1.2, 1.0, 1.0)):
    """Label maps placed off the origin with anisotropic voxels (files.write_label_map)."""
    return files.write_label_map(path, mask, label, spacing=spacing, origin=origin)


def load_label_map_node(path):
    """A label-map volume node read by Slicer's volume storage node (as 'Add data' does)."""
    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", path.name.split(".")[0])
    storage = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLVolumeArchetypeStorageNode")
    storage.SetFileName(str(path))
    assert storage.ReadData(node)
    return node


def load_model_node(path, name):
    """A model node read by Slicer's model storage node (as 'Add data' does; it honours the
    file's coordinate system)."""
    node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelNode", name)
    storage = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelStorageNode")
    storage.SetFileName(str(path))
    assert storage.ReadData(node)
    node.SetAndObserveStorageNodeID(storage.GetID())
    return node


def closed_surface_ras(segmentation_node) -> tuple:
    """Slicer's own closed surface of all segments (RAS): vertices, triangles."""
    segmentation_node.CreateClosedSurfaceRepresentation()
    append = vtk.vtkAppendPolyData()
    segmentation = segmentation_node.GetSegmentation()
    for k in range(segmentation.GetNumberOfSegments()):
        polydata = vtk.vtkPolyData()
        segmentation_node.GetClosedSurfaceRepresentation(segmentation.GetNthSegmentID(k), polydata)
        append.AddInputData(polydata)
    append.Update()
    return io.mesh_arrays(append.GetOutput())


@pytest.fixture(scope="module")
def generated_files(tmp_path_factory):
    """Five small bumpy ellipsoid label maps (label 1) with a non-trivial geometry."""
    folder = tmp_path_factory.mktemp("generated")
    return [write_label_map(folder / f"case_{k}.nii.gz", small_mask(float(p), 1.0 + 0.03 * k))
            for k, p in enumerate(np.linspace(-0.6, 0.6, 5))]


def test_importing_the_module_loads_none_of_the_librarys_heavy_dependencies():
    code = ("import sys; sys.path.insert(0, %r); import harness; harness.install(); "
            "import MDLShapeModel; print(sorted(m for m in ('numba', 'h5py', 'scipy', "
            "'pycpd', 'matplotlib', 'SimpleITK') if m in sys.modules))"
            % str(harness.HERE))
    done = run_python(code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_the_parameter_node_holds_the_build_configs_defaults_and_fills_it(scene):
    parameters = module.MDLShapeModelLogic().getParameterNode()
    # (the panel builds surfaces: its points default is the surfaces', BuildConfig's is None,
    # per kind of input; the prior's weight is BuildConfig's rule, None, while defaultSmoothness)
    defaults = BuildConfig(points=SURFACE_POINTS)
    assert module.buildConfigOf(parameters) == defaults
    assert parameters.smoothness == SMOOTHNESS
    parameters.labels = "1, 2"
    parameters.points = 642
    parameters.strategy = "one-at-a-time"
    parameters.baselines = "none cpd"
    parameters.defaultSmoothness = False
    parameters.smoothness = 0.02
    assert module.buildConfigOf(parameters) == BuildConfig(
        labels=[1, 2], points=642, strategy="one-at-a-time", baselines=["none", "cpd"],
        smoothness=0.02)
    with pytest.raises(ValueError):
        parameters.strategy = "fastest"          # the choices are BuildConfig's
    parameters.labels = "1, a"
    with pytest.raises(ConfigError, match="labels must be integers"):
        module.buildConfigOf(parameters)


def test_check_landmarks_beside_the_point_lists_joins_a_build_given_them(scene):
    parameters = module.MDLShapeModelLogic().getParameterNode()
    config = module.buildConfigOf(parameters)
    assert module.landmarkConfigOf(config, parameters, landmarks=False) == config
    parameters.check_landmarks = True
    assert module.buildConfigOf(parameters) == config         # not without the point lists
    assert module.landmarkConfigOf(config, parameters, landmarks=True).check_landmarks
    with pytest.raises(ValueError, match="Check landmarks: check the cases' landmark point"):
        module.landmarkConfigOf(config, parameters, landmarks=False)


def test_the_parameter_node_survives_saving_and_reloading_the_scene(scene, tmp_path):
    explorer = scene.AddNewNodeByClass("vtkMRMLModelNode", "explorer")
    inputs = [scene.AddNewNodeByClass(kind, name) for kind, name in (
        ("vtkMRMLSegmentationNode", "left"), ("vtkMRMLLabelMapVolumeNode", "right"),
        ("vtkMRMLModelNode", "third"))]
    marks = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "left_landmarks")
    parameters = module.MDLShapeModelLogic().getParameterNode()
    parameters.points = 642
    parameters.max_time = 90.5
    parameters.strict = True
    parameters.labels = "1, 2"
    parameters.strategy = "one-at-a-time"
    parameters.defaultSmoothness = False
    parameters.smoothness = 0.02
    parameters.check_landmarks = True
    parameters.segments = "Left hippocampus, head"
    parameters.outputDirectory = tmp_path / "out"
    parameters.explorerModel = explorer
    parameters.inputNodes = inputs
    parameters.landmarkNodes = [marks]
    parameters.analysisPermutations = 999
    parameters.analysisGroup = "diagnosis"
    parameters.analysisCovariates = "age, volume"
    parameters.analysisTfce = True
    parameters.analysisFolds = 4
    parameters.analysisRepeats = 3
    parameters.analysisClassificationPermutations = 0
    scene.SetURL(str(tmp_path / "scene.mrml"))
    assert scene.Commit()
    reloaded = harness.new_scene()
    reloaded.SetURL(str(tmp_path / "scene.mrml"))
    assert reloaded.Connect()
    again = module.MDLShapeModelLogic().getParameterNode()
    assert again.parameterNode.GetID() is not None and again.points == 642
    assert again.max_time == 90.5 and again.strict is True
    assert module.segmentNames(again.segments) == ["Left hippocampus", "head"]
    assert again.outputDirectory == tmp_path / "out"
    assert again.explorerModel is not None and again.explorerModel.GetName() == "explorer"
    # the input selections and the landmark point lists are saved with the scene, in order
    assert [node.GetName() for node in again.inputNodes] == ["left", "right", "third"]
    assert [node.GetClassName() for node in again.inputNodes] == [
        "vtkMRMLSegmentationNode", "vtkMRMLLabelMapVolumeNode", "vtkMRMLModelNode"]
    assert [node.GetName() for node in again.landmarkNodes] == ["left_landmarks"]
    assert module.buildConfigOf(again) == BuildConfig(
        labels=[1, 2], points=642, max_time=90.5, strict=True, strategy="one-at-a-time",
        smoothness=0.02)
    assert again.check_landmarks is True and again.analysisPermutations == 999
    assert again.analysisColorBy == module.EFFECT_SCALARS[0]
    # the analysis's settings, the classifier's among them, are the AnalysisConfig run
    assert module.analysisConfigOf(again) == AnalysisConfig(
        group="diagnosis", covariates=["age", "volume"], permutations=999, tfce=True, folds=4,
        repeats=3, classification_permutations=0)
    # fewer nodes written over more leave no stale entry behind
    again.inputNodes = [again.inputNodes[2]]
    assert [node.GetName() for node in again.inputNodes] == ["third"]


def test_segmentation_nodes_build_the_same_model_as_the_command_line_and_overlay(
        scene, hippocampus_files, tmp_path):
    config = BuildConfig(labels=[1, 2], **QUICK)
    logic = harness.segmentations_logic()
    nodes = [logic.LoadSegmentationFromFile(str(f), True, f.name.split(".")[0])
             for f in hippocampus_files]
    result = module.MDLShapeModelLogic().buildModel(nodes, tmp_path / "slicer", config)
    cli = run_cli("build", *hippocampus_files, "-o", tmp_path / "cli", "--label", "1,2",
                  "--points", "162", "--baselines", "", "--max-time", "120",
                  "--evaluation-modes", "2", "--specificity-samples", "100", "--workers", "1",
                  "-q")
    assert cli.returncode == 0, cli.stderr
    ours, theirs = (ShapeModel.load(tmp_path / name / "model.h5") for name in ("slicer", "cli"))
    assert ours.names == theirs.names == [f.name.split(".")[0] for f in hippocampus_files]
    np.testing.assert_array_equal(ours.mean, theirs.mean)
    np.testing.assert_array_equal(ours.variances, theirs.variances)
    np.testing.assert_array_equal(ours.modes, theirs.modes)
    assert result.rejected == [] and len(result.correspondenceModelNodes) == 4
    for node, segmentation in zip(result.correspondenceModelNodes, nodes):
        ras = points_of(node)
        assert len(ras) == 162
        # the CLI's file, LPS, is the same points
        lps, _ = io.read_mesh(tmp_path / "cli" / "correspondence" / f"{node.GetName()}.vtp")
        np.testing.assert_allclose(ras * LPS_TO_RAS, lps, atol=1e-5)
        # and they lie on the surface Slicer itself makes from the segmentation
        vertices, triangles = closed_surface_ras(segmentation)
        assert point_surface_distances(ras, vertices, triangles).mean() < 0.5
        assert point_surface_distances(ras * LPS_TO_RAS, vertices, triangles).mean() > 5.0


@pytest.fixture(scope="module")
def mixed_build(generated_files, tmp_path_factory):
    """A build from two label-map volume nodes, a model node, a segmentation node and a file
    path, with an empty segmentation and an unreadable file among them."""
    harness.new_scene()
    folder = tmp_path_factory.mktemp("mixed")
    volumes = [load_label_map_node(path) for path in generated_files[:2]]
    vertices, faces, _ = mask_to_surface(small_mask(0.1), (1.2, 1.0, 1.0), (5.0, -3.0, 2.0))
    io.write_polydata(folder / "surface.vtp", vertices, faces)
    model = load_model_node(folder / "surface.vtp", "model_case")
    segmentation = harness.segmentations_logic().LoadSegmentationFromFile(
        str(generated_files[2]), True, "segmentation_case")
    empty = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLSegmentationNode", "empty")
    broken = folder / "broken.nii.gz"
    broken.write_bytes(b"not an image")
    inputs = [volumes[0], model, empty, segmentation, broken, volumes[1], generated_files[3]]
    result = module.MDLShapeModelLogic().buildModel(inputs, folder / "out", BuildConfig(**QUICK))
    return result, inputs, broken


def test_every_kind_of_input_goes_in_and_bad_ones_are_rejected_with_their_reason(mixed_build):
    result, inputs, broken = mixed_build
    assert result.caseNames == ["case_0", "model_case", "segmentation_case", "case_1", "case_3"]
    assert [n.GetName() for n in result.correspondenceModelNodes] == result.caseNames
    assert {points_of(n).shape for n in result.correspondenceModelNodes} == {(162, 3)}
    reasons = dict(result.rejected)
    assert reasons["empty"] == "the segmentation has no segments"
    # the unreadable file: the library's own reason, as a build of that file alone gives it
    _, alone = preprocess([broken], BuildConfig(workers=1, cache_dir=""))
    assert [r.reason for r in alone] == [reasons["broken"]]
    assert len(result.rejected) == 2
    # every node sits in the result's subject-hierarchy folder
    hierarchy = slicer.vtkMRMLSubjectHierarchyNode.GetSubjectHierarchyNode(slicer.mrmlScene)
    for node in [result.meanModelNode, result.explorerModelNode, result.metricsTableNode,
                 result.scoresTableNode, *result.correspondenceModelNodes]:
        assert hierarchy.GetItemParent(hierarchy.GetItemByDataNode(node)) == result.folderItemID


def test_the_model_case_overlays_the_model_it_came_from(mixed_build):
    result, inputs, _ = mixed_build
    model = inputs[1]
    corresponded = result.correspondenceModelNodes[1]
    vertices, triangles = io.mesh_arrays(model.GetPolyData())
    assert point_surface_distances(points_of(corresponded), vertices, triangles).mean() < 0.5


def test_a_missing_segment_rejects_that_case_by_name(scene, generated_files, tmp_path):
    segmentation = harness.segmentations_logic().LoadSegmentationFromFile(
        str(generated_files[0]), True, "named")
    exported = module.MDLShapeModelLogic().exportInputs([segmentation], tmp_path, None,
                                                         ["Left hippocampus"])
    assert exported.paths == []
    segment = segmentation.GetSegmentation().GetNthSegment(0).GetName()
    assert exported.rejected == [("named", f"no segment named 'Left hippocampus' (it has {segment})")]


def test_nodes_whose_arrays_do_not_fit_their_size_are_rejected_before_they_are_written(
        scene, generated_files, tmp_path):
    short = load_label_map_node(generated_files[0])
    scalars = short.GetImageData().GetPointData().GetScalars()
    total = scalars.GetNumberOfTuples()
    scalars.SetNumberOfTuples(total // 2)          # the extent still says the whole image
    extent = short.GetImageData().GetExtent()
    vertices, triangles, _ = mask_to_surface(small_mask(0.1))
    dangling = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelNode", "dangling")
    polydata = arrays_to_polydata(vertices, triangles)
    polydata.GetPolys().GetConnectivityArray().SetValue(5, len(vertices) + 7)
    dangling.SetAndObservePolyData(polydata)
    good = load_label_map_node(generated_files[1])
    exported = module.MDLShapeModelLogic().exportInputs([short, dangling, good], tmp_path)
    assert [path.name for path in exported.paths] == [f"{good.GetName()}.nrrd"]
    nx, ny, nz = (extent[1] + 1, extent[3] + 1, extent[5] + 1)
    assert dict(exported.rejected) == {
        short.GetName(): f"the input image's scalars hold {total // 2} values but its extent "
                         f"{tuple(extent)} says {nx} x {ny} x {nz} = {total}",
        "dangling": f"a cell refers to point {len(vertices) + 7}; the mesh has {len(vertices)} "
                    "points"}
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{good.GetName()}.nrrd"]


def test_load_model_and_mode_weights_move_the_explorer_by_the_modes(mixed_build):
    result, *_ = mixed_build
    loaded = module.MDLShapeModelLogic().loadModel(result.modelFile)
    model = ShapeModel.load(result.modelFile)
    assert loaded.correspondenceModelNodes == []
    np.testing.assert_allclose(points_of(loaded.meanModelNode), model.mean * LPS_TO_RAS)
    assert loaded.metricsTableNode.GetNumberOfRows() == 2          # evaluation_modes
    assert loaded.scoresTableNode.GetNumberOfRows() == 5           # cases
    weights = [1.5, -0.5]
    module.MDLShapeModelLogic().setModeWeights(loaded.explorerModelNode, weights)
    expected = model.instance(np.array(weights) * np.sqrt(model.variances[:2]))
    np.testing.assert_allclose(points_of(loaded.explorerModelNode), expected * LPS_TO_RAS,
                               atol=1e-9)
    shown = vtk_to_numpy(loaded.explorerModelNode.GetPolyData().GetPointData()
                         .GetArray("Displacement"))
    np.testing.assert_allclose(shown, np.linalg.norm(expected - model.mean, axis=1), atol=1e-9)
    module.MDLShapeModelLogic().setModeWeights(loaded.explorerModelNode, [0.0])
    np.testing.assert_allclose(points_of(loaded.explorerModelNode), model.mean * LPS_TO_RAS,
                               atol=1e-9)
    with pytest.raises(ValueError, match="modes"):
        module.MDLShapeModelLogic().setModeWeights(loaded.explorerModelNode,
                                                   [0.0] * (model.n_modes + 1))


def test_a_background_build_reports_progress_and_cancel_keeps_the_state_reached(
        scene, generated_files, tmp_path):
    volumes = [load_label_map_node(path) for path in generated_files]
    config = BuildConfig(**{**QUICK, "points": 642, "max_time": 600})
    job = module.MDLShapeModelLogic().startBuild(volumes, tmp_path, config)
    seen, started, cancelled = [], time.monotonic(), False
    while not job.done and time.monotonic() - started < 300:
        seen += job.poll()
        if not cancelled and any(report.kind == OBJECTIVE for report in seen):
            job.cancel()         # once the optimisation runs
            cancelled = True
        time.sleep(0.05)
    assert job.wait(300)
    seen += job.poll()
    messages = [report.message for report in seen]
    # each case reported prepared, in turn, before the optimisation's first report
    prepared = [k for k, message in enumerate(messages) if message.startswith("prepared")]
    # (each but the last with the estimate of the time left)
    assert [messages[k].split(" (about ")[0] for k in prepared] == [
        f"prepared {k}/5" for k in range(1, 6)]
    assert all(" left)" in messages[k] for k in prepared[:-1])
    assert prepared[-1] < next(k for k, report in enumerate(seen) if report.kind == OBJECTIVE)
    result = job.finish()
    assert result.interrupted
    assert json.loads((tmp_path / "metrics.json").read_text())["interrupted"] is True
    assert len(result.correspondenceModelNodes) == 5


def test_slicer_reads_the_librarys_meshes_as_lps_and_the_library_reads_slicers(scene, tmp_path):
    vertices, faces, _ = mask_to_surface(small_mask(0.0), (1.0, 1.0, 1.0), (10.0, 20.0, 30.0))
    io.write_polydata(tmp_path / "ours.vtp", vertices, faces)
    node = scene.AddNewNodeByClass("vtkMRMLModelNode")
    storage = scene.AddNewNodeByClass("vtkMRMLModelStorageNode")
    storage.SetCoordinateSystem(slicer.vtkMRMLStorageNode.CoordinateSystemRAS)  # what it assumes
    storage.SetFileName(str(tmp_path / "ours.vtp"))
    assert storage.ReadData(node)
    assert storage.GetCoordinateSystem() == slicer.vtkMRMLStorageNode.CoordinateSystemLPS
    np.testing.assert_allclose(points_of(node), vertices * LPS_TO_RAS, atol=1e-5)
    for system, suffix in ((slicer.vtkMRMLStorageNode.CoordinateSystemRAS, ".vtk"),
                           (slicer.vtkMRMLStorageNode.CoordinateSystemLPS, ".vtp")):
        writer = scene.AddNewNodeByClass("vtkMRMLModelStorageNode")
        writer.SetCoordinateSystem(system)
        writer.SetFileName(str(tmp_path / f"slicers{suffix}"))
        assert writer.WriteData(node)
        read, _ = io.read_mesh(tmp_path / f"slicers{suffix}")
        np.testing.assert_allclose(read, vertices, atol=1e-5)


def test_resources_are_found_in_the_modules_resources_folder():
    folder = harness.MODULE_DIRECTORY / "Resources"
    assert module.resourcePath("UI/MDLShapeModel.ui") == folder / "UI" / "MDLShapeModel.ui"
    assert dependencies.requirements() and not any(
        r.split(">")[0].lower() in ("vtk", "simpleitk") for r in dependencies.requirements())
    with pytest.raises(FileNotFoundError, match="nothing.txt"):
        module.resourcePath("nothing.txt")


def test_the_modules_own_test_runs_here_too(scene):
    test = module.MDLShapeModelTest()
    test.runTest()


def test_a_new_segmentation_is_fitted_to_a_loaded_model(mixed_build, generated_files, tmp_path):
    result, *_ = mixed_build
    segmentation = harness.segmentations_logic().LoadSegmentationFromFile(
        str(generated_files[4]), True, "new_case")
    fitted, reconstruction, summary = module.MDLShapeModelLogic().fitSegmentation(
        segmentation, result.modelFile, tmp_path, maxTime=20)
    assert fitted.GetName() == "new_case fitted"
    assert points_of(fitted).shape == points_of(reconstruction).shape == (162, 3)
    # the fit's files (the library's, LPS) overlay the segmentation as nodes (RAS)
    fit = FitFolder(tmp_path)
    np.testing.assert_allclose(points_of(fitted),
                               mesh_points(fit.case_mesh("", "new_case")) * LPS_TO_RAS,
                               atol=1e-5)
    np.testing.assert_allclose(
        points_of(reconstruction),
        mesh_points(fit.case_mesh("", "new_case", reconstruction=True)) * LPS_TO_RAS, atol=1e-5)
    assert summary == fit.summary()["new_case"] and summary["reconstruction_distance_mm"]
    vertices, triangles = closed_surface_ras(segmentation)
    assert point_surface_distances(points_of(fitted), vertices, triangles).mean() < 0.5


def test_missing_requirements_are_the_ones_not_installed():
    assert dependencies.missingRequirements() == []    # this virtualenv has the library's packages
    wanted = ["numpy>=1.0", "numpy>=999", "no-such-package-mdl>=1"]
    assert dependencies.missingRequirements(wanted) == ["numpy>=999", "no-such-package-mdl>=1"]


def test_a_two_part_object_is_built_from_label_map_nodes_and_loaded_part_by_part(tmp_path):
    """Label-map volume nodes of a two-label population, the parts set in the parameter node:
    the Logic builds the two-part model and loads one correspondence node per case and part."""
    from mdlshapemodel.demo import DEMO_PARTS, write_demo_population

    harness.new_scene()
    paths = write_demo_population(tmp_path / "labels", 4, parts=True)
    volumes = [load_label_map_node(path) for path in paths]
    parameters = module.MDLShapeModelLogic().getParameterNode()
    parameters.parts = "; ".join(DEMO_PARTS)
    config = module.buildConfigOf(parameters)
    assert config.parts == list(DEMO_PARTS)
    config = dataclasses.replace(config, **QUICK)
    result = module.MDLShapeModelLogic().buildModel(volumes, tmp_path / "out", config)
    assert result.partNames == ["left", "right"] and not result.rejected
    names = [node.GetName() for node in result.correspondenceModelNodes]
    assert names == [f"{case} {part}" for case in result.caseNames for part in ("left", "right")]
    for node in result.correspondenceModelNodes:
        assert node.GetPolyData().GetNumberOfPoints() == 162
    # the explorer holds the whole object: both parts' points
    assert result.explorerModelNode.GetPolyData().GetNumberOfPoints() == 324


def test_markups_nodes_guide_a_build_of_label_map_nodes(generated_files, tmp_path):
    """A markups node per input (points in RAS, as Slicer holds them) is written beside the
    inputs and guides the build: its landmarks.csv holds every case's corresponded landmark near
    the one placed, and the model records the labels; the build checks them when asked."""
    harness.new_scene()
    volumes = [load_label_map_node(path) for path in generated_files[:4]]
    markups = []
    for k, position in enumerate(np.linspace(-0.6, 0.6, 5)[:4]):
        top = small_bump_top(float(position)) * (1.2, 1.0, 1.0) + (5.0, -3.0, 2.0)   # LPS
        node = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", f"marks_{k}")
        node.AddControlPoint(list(top * LPS_TO_RAS), "top")
        markups.append(node)
    markups[3] = None                           # a case without landmarks
    result = module.MDLShapeModelLogic().buildModel(
        volumes, tmp_path / "out", BuildConfig(**QUICK, check_landmarks=True), landmarks=markups)
    assert result.rejected == []
    # checked: the correspondence made again without the one label measures it
    check = json.loads((tmp_path / "out" / "metrics.json").read_text())["landmark_check"]
    assert check["folds"] == [["top"]] and check["per_label"]["top"]["cases"] == 3
    assert sorted(p.name for p in (tmp_path / "out" / "inputs" / "landmarks").iterdir()) == [
        f"case_{k}.mrk.json" for k in range(3)]
    rows = files.read_csv_rows(tmp_path / "out" / "landmarks.csv")
    assert [(row["case"], row["label"]) for row in rows] == [(f"case_{k}", "top")
                                                            for k in range(4)]
    distances = [float(row["distance_mm"]) for row in rows[:3]]
    assert rows[3]["distance_mm"] == "" and max(distances) < 2.0
    assert list(ShapeModel.load(tmp_path / "out" / "model.h5").landmarks) == ["top"]
    # loaded as a point list per case, in RAS, at the corresponded points
    assert [node.GetName() for node in result.landmarkNodes] == [f"case_{k} landmarks"
                                                                 for k in range(4)]
    for node, row in zip(result.landmarkNodes, rows):
        assert node.GetNthControlPointLabel(0) == "top"
        placed = np.array(node.GetNthControlPointPosition(0))
        np.testing.assert_allclose(placed * LPS_TO_RAS, [float(row[c]) for c in "xyz"],
                                   atol=1e-5)


def test_point_lists_are_matched_to_the_inputs_they_are_named_after(scene, tmp_path):
    volume = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLLabelMapVolumeNode", "case_0")
    other = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLModelNode", "case_1")
    path = tmp_path / "case_9.nii.gz"
    first = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "case_0_landmarks")
    ninth = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "case_9")
    logic = module.MDLShapeModelLogic()
    assert logic.landmarksOf([volume, other, path], [ninth, first]) == [first, None, ninth]
    stray = slicer.mrmlScene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode", "F")
    with pytest.raises(ValueError, match="'F': no input is named"):
        logic.landmarksOf([volume, other, path], [first, stray])
