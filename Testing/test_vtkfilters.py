"""The VTK filters in real VTK pipelines."""

import dataclasses
import inspect

import numpy as np
import pytest
import SimpleITK as sitk
import vtk
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from mdlshapemodel import BuildConfig
from mdlshapemodel.prepare import prepare_case, surface
from mdlshapemodel.prepare.io import write_polydata
from mdlshapemodel.prepare.sphere import orientation, sphere_map
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface, SurfaceToSphereMap

from synthetic import small_mask, torus


def image_source(mask, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0), direction=None):
    image = vtk.vtkImageData()
    image.SetDimensions(mask.shape[2], mask.shape[1], mask.shape[0])
    image.SetSpacing(*spacing)
    image.SetOrigin(*origin)
    if direction is not None:
        matrix = vtk.vtkMatrix3x3()
        for r in range(3):
            for c in range(3):
                matrix.SetElement(r, c, direction[r][c])
        image.SetDirectionMatrix(matrix)
    image.GetPointData().SetScalars(numpy_to_vtk(mask.astype(np.uint8).ravel(), deep=True))
    producer = vtk.vtkTrivialProducer()
    producer.SetOutput(image)
    return producer


def arrays(polydata):
    return surface.polydata_to_arrays(polydata)


@pytest.fixture
def pipeline():
    """A fresh label map -> surface -> sphere map pipeline, run once; each test gets its own, as
    one changes the filters' parameters."""
    labels = small_mask(0.3).astype(np.uint8) * 2
    source = image_source(labels, spacing=(1.5, 1.0, 1.0), origin=(5.0, -3.0, 2.0))
    to_surface = LabelMapToClosedSurface()
    to_surface.SetInputConnection(source.GetOutputPort())
    to_surface.SetLabels([2])
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputConnection(to_surface.GetOutputPort())
    to_sphere.Update()
    return labels, to_surface, to_sphere, source


def test_outputs_match_the_library_and_are_bijective(pipeline):
    labels, to_surface, to_sphere, _ = pipeline
    vertices, faces = arrays(to_surface.GetOutput())
    expected, expected_faces, _ = surface.mask_to_surface(labels > 0, (1.5, 1.0, 1.0),
                                                          (5.0, -3.0, 2.0))
    np.testing.assert_allclose(vertices, expected)
    assert np.array_equal(faces, expected_faces)
    mapped = to_sphere.GetOutput(0)
    sphere = vtk_to_numpy(mapped.GetPointData().GetArray("SphereCoordinates"))
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.0, atol=1e-12)
    assert np.all(orientation(sphere, arrays(mapped)[1]) > 0)
    assert mapped.GetFieldData().GetArray("FlippedTriangles").GetValue(0) == 0
    assert mapped.GetFieldData().GetArray("MeanAbsLogAreaRatio").GetValue(0) < 0.5
    sphere_points, sphere_faces = arrays(to_sphere.GetOutput(1))
    np.testing.assert_allclose(sphere_points, sphere)
    assert np.array_equal(sphere_faces, arrays(mapped)[1])


def test_filters_reexecute_only_when_a_parameter_changes(pipeline):
    _, to_surface, to_sphere, _ = pipeline
    runs = (to_surface.executions, to_sphere.executions)
    to_sphere.Update()
    to_surface.SetLabels([2])            # same value: not modified
    to_sphere.SetAreaWeight(to_sphere.GetAreaWeight())
    to_sphere.Update()
    assert (to_surface.executions, to_sphere.executions) == runs
    to_sphere.SetMaxIterations(200)      # only the downstream filter changes
    to_sphere.Update()
    assert (to_surface.executions, to_sphere.executions) == (runs[0], runs[1] + 1)
    to_surface.SetSmoothingSigma(1.5)    # upstream change: both run again
    to_sphere.Update()
    assert (to_surface.executions, to_sphere.executions) == (runs[0] + 1, runs[1] + 2)
    assert to_surface.GetSmoothingSigma() == 1.5 and to_sphere.GetMaxIterations() == 200
    to_surface.SetSurfaceMethod("slicer")
    to_surface.SetSmoothingFactor(0.3)
    to_sphere.Update()
    assert (to_surface.executions, to_sphere.executions) == (runs[0] + 2, runs[1] + 3)
    assert to_surface.GetOutput().GetNumberOfPoints() > 0 and to_surface.GetErrorText() == ""


def test_direction_matrix_is_honoured():
    mask = small_mask(0.3)
    flip = [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    plain, flipped = LabelMapToClosedSurface(), LabelMapToClosedSurface()
    sources = image_source(mask), image_source(mask, direction=flip)  # keep the producers alive
    plain.SetInputConnection(sources[0].GetOutputPort())
    flipped.SetInputConnection(sources[1].GetOutputPort())
    plain.Update()
    flipped.Update()
    a, _ = arrays(plain.GetOutput())
    b, _ = arrays(flipped.GetOutput())
    np.testing.assert_allclose(b, a * np.array([-1.0, -1.0, 1.0]), atol=1e-9)


READ_THROUGH_THE_FILTER = """
import sys
import vtk
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface

reader = getattr(vtk, sys.argv[1])()
reader.SetFileName(sys.argv[2])
to_surface = LabelMapToClosedSurface()
to_surface.SetInputConnection(reader.GetOutputPort())
to_surface.Update()
print(to_surface.GetOutput().GetNumberOfPoints())
print(to_surface.GetErrorText())
"""


def test_a_file_its_reader_could_not_read_is_named_as_such(tmp_path):
    from common import run_python

    good = tmp_path / "good.nii"
    sitk.WriteImage(sitk.GetImageFromArray(small_mask(0.0).astype(np.uint8)), str(good))
    (tmp_path / "damaged.mha").write_text("not a MetaImage header\n")
    (tmp_path / "cut.nii").write_bytes(good.read_bytes()[:len(good.read_bytes()) // 3])
    for reader, name, reason in (("vtkMetaImageReader", "missing.mha", "missing, or not"),
                                 ("vtkMetaImageReader", "damaged.mha", "missing, or not"),
                                 ("vtkNIFTIImageReader", "cut.nii", "PrematureEndOfFile")):
        result = run_python(READ_THROUGH_THE_FILTER, reader, tmp_path / name)
        points, message = result.stdout.splitlines()
        assert points == "0"
        assert message.startswith(f"{tmp_path / name}: the input could not be read ({reader}: "
                                  f"{reason}"), message
        assert "too thin" not in message
    read = run_python(READ_THROUGH_THE_FILTER, "vtkNIFTIImageReader", good)
    assert int(read.stdout.splitlines()[0]) > 0 and read.stdout.splitlines()[1:] in ([], [""])


def test_failures_leave_an_empty_output_and_a_message():
    missing = LabelMapToClosedSurface()
    source = image_source(small_mask(0.0))
    missing.SetInputConnection(source.GetOutputPort())
    missing.SetLabels([7])
    missing.Update()
    assert missing.GetOutput().GetNumberOfPoints() == 0
    assert "label 7 not present" in missing.GetErrorText()
    points, faces = torus()
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputData(surface.arrays_to_polydata(points, faces))
    to_sphere.Update()
    assert to_sphere.GetOutput(0).GetNumberOfPoints() == 0
    assert "genus 1" in to_sphere.GetErrorText()


def field_value(polydata, name):
    array = polydata.GetFieldData().GetAbstractArray(name)
    return array.GetValue(0) if isinstance(array, vtk.vtkStringArray) else array.GetTuple1(0)


def assert_same_preparation(to_sphere, case):
    """The filter's outputs are bit for bit the prepared case of build."""
    assert to_sphere.GetErrorText() == "" and not hasattr(case, "reason"), case
    vertices, faces = arrays(to_sphere.GetOutput(0))
    sphere = vtk_to_numpy(to_sphere.GetOutput(0).GetPointData().GetArray("SphereCoordinates"))
    assert np.array_equal(vertices, case.map.vertices)
    assert np.array_equal(faces, case.map.faces)
    assert np.array_equal(sphere, case.map.sphere)
    assert np.array_equal(arrays(to_sphere.GetOutput(1))[0], case.map.sphere)
    assert field_value(to_sphere.GetOutput(0), "VoxelSize") == case.voxel_size
    assert field_value(to_sphere.GetOutput(0), "Repair") == case.repair
    assert field_value(to_sphere.GetOutput(0), "Mirrored") == case.mirrored


def messy_mesh(vertices, faces):
    """The mesh as a file might hold it: the first 40 triangles as a soup of their own (duplicate
    points), every 7th triangle turned over, and two degenerate triangles."""
    vertices, faces = vertices.copy(), faces.copy()
    soup = faces[:40].copy()
    faces[:40] = len(vertices) + np.arange(120).reshape(40, 3)
    vertices = np.concatenate([vertices, vertices[soup.ravel()]])
    faces[::7] = faces[::7][:, [0, 2, 1]]
    degenerate = np.array([[faces[100, 0], faces[100, 0], faces[100, 1]],
                           [faces[200, 0], faces[200, 1], faces[200, 1]]])
    return vertices, np.concatenate([faces, degenerate])


def test_surface_to_sphere_map_prepares_a_mesh_file_as_build_does(tmp_path, bump_surface):
    vertices, faces = messy_mesh(*bump_surface)
    path = tmp_path / "case_r.vtk"
    write_polydata(path, vertices, faces)
    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(path))
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputConnection(reader.GetOutputPort())
    progress = []
    to_sphere.AddObserver("ProgressEvent", lambda caller, _: progress.append(caller.GetProgress()))
    to_sphere.Update()
    case = prepare_case(path, BuildConfig())
    assert_same_preparation(to_sphere, case)
    assert progress[0] == 0.0 and progress[-1] == 1.0
    # the cleaning happened: duplicates merged, orientation repaired, remeshed
    assert "made the orientation of" in case.repair
    assert len(case.map.vertices) != len(bump_surface[0])
    assert np.mean(case.map.vertices[:, 0]) > 0
    # mirrored (build: the file name matches a mirror pattern) and decimated
    to_sphere.MirroredOn()
    to_sphere.SetTargetVertices(500)
    to_sphere.Update()
    mirrored = prepare_case(path, BuildConfig(mirror=["*_r.*"], target_vertices=500))
    assert mirrored.mirrored and to_sphere.GetMirrored()
    assert_same_preparation(to_sphere, mirrored)
    assert np.mean(mirrored.map.vertices[:, 0]) < 0
    assert len(mirrored.map.vertices) < len(case.map.vertices)
    assert to_sphere.executions == 2


def test_label_map_pipeline_prepares_a_label_map_file_as_build_does(tmp_path):
    labels = small_mask(0.3).astype(np.uint8) * 2
    image = sitk.GetImageFromArray(labels)
    image.SetSpacing((1.5, 1.0, 1.0))
    image.SetOrigin((5.0, -3.0, 2.0))
    path = tmp_path / "labels.mha"
    sitk.WriteImage(image, str(path))
    reader = vtk.vtkMetaImageReader()
    reader.SetFileName(str(path))
    to_surface = LabelMapToClosedSurface()
    to_surface.SetInputConnection(reader.GetOutputPort())
    to_surface.SetLabels([2, 9])         # 9 is absent: fine, as in build, while 2 is present
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputConnection(to_surface.GetOutputPort())
    to_sphere.Update()
    case = prepare_case(path, BuildConfig(labels=[2, 9]))
    assert_same_preparation(to_sphere, case)
    assert field_value(to_surface.GetOutput(), "SmoothingSigma") == case.smoothing_sigma
    assert case.voxel_size == pytest.approx(1.5 ** (1 / 3))


def test_filters_start_at_the_build_defaults():
    defaults = BuildConfig()
    to_surface, to_sphere = LabelMapToClosedSurface(), SurfaceToSphereMap()
    assert to_surface.GetLabels() == tuple(defaults.labels)
    assert to_surface.GetSurfaceMethod() == defaults.surface_method
    assert to_surface.GetSmoothingFactor() == defaults.smoothing_factor
    assert to_surface.GetDecimation() == defaults.decimation
    assert to_surface.GetSmoothingSigma() == defaults.smoothing_sigma
    assert to_surface.GetMaxSmoothingSigma() == defaults.max_smoothing_sigma
    assert to_surface.GetEdgeLength() == defaults.edge_length
    assert to_surface.GetTargetVertices() == defaults.target_vertices
    assert to_sphere.GetTargetVertices() == defaults.target_vertices
    assert to_sphere.GetVoxelSize() == defaults.voxel_size
    assert not to_sphere.GetMirrored() and not defaults.mirror
    assert to_surface.GetConfig() == defaults and to_sphere.GetConfig() == defaults
    mapping = inspect.signature(sphere_map).parameters
    assert to_sphere.GetAreaWeight() == mapping["area_weight"].default
    assert to_sphere.GetMaxIterations() == mapping["max_iterations"].default
    contouring = inspect.signature(surface.mask_to_surface).parameters
    # max_smoothing_sigma and target_vertices: None in both, the rules of config
    declared = {f.name: f.default for f in dataclasses.fields(BuildConfig)}
    for name in ("max_smoothing_sigma", "target_vertices"):
        assert contouring[name].default is declared[name] is None, name
    for name, field in (("smoothing_sigma", "smoothing_sigma"), ("edge_length", "edge_length"),
                        ("method", "surface_method"), ("smoothing_factor", "smoothing_factor"),
                        ("decimation", "decimation")):
        assert contouring[name].default == getattr(defaults, field), name


def test_a_missing_label_gives_the_message_of_build(tmp_path):
    path = tmp_path / "other_label.mha"
    sitk.WriteImage(sitk.GetImageFromArray(small_mask(0.0).astype(np.uint8) * 5), str(path))
    reader = vtk.vtkMetaImageReader()
    reader.SetFileName(str(path))
    to_surface = LabelMapToClosedSurface()
    to_surface.SetInputConnection(reader.GetOutputPort())
    to_surface.SetLabels([1, 3])
    to_surface.Update()
    rejection = prepare_case(path, BuildConfig(labels=[1, 3]))
    assert to_surface.GetErrorText() == rejection.reason
    assert rejection.reason == "label 1, 3 not present (labels found: 5)"
    assert to_surface.GetOutput().GetNumberOfPoints() == 0
