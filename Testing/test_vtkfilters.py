"""The VTK filters in real VTK pipelines."""

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from mdlshapemodel.prepare import surface
from mdlshapemodel.prepare.sphere import orientation
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface, SurfaceToSphereMap

from synthetic import small_mask
from test_bad_inputs import torus


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


@pytest.fixture(scope="module")
def pipeline():
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
