"""Draws MDLShapeModel/Resources/Icons/MDLShapeModel.png (128 x 128): a shape model's mean surface coloured by
the displacement of its first mode. Run with the mean.vtp and model.h5 of any build:

    python MDLShapeModel/Resources/Icons/make_icon.py BUILD_FOLDER \
        MDLShapeModel/Resources/Icons/MDLShapeModel.png
"""

import sys

import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk

from mdlshapemodel import ShapeModel
from mdlshapemodel.prepare.surface import arrays_to_polydata
from mdlshapemodel.report.rendering import offscreen_window_class


def main(folder: str, destination: str, size: int = 128):
    model = ShapeModel.load(f"{folder}/model.h5")
    polydata = arrays_to_polydata(model.mean, model.triangles)
    displacement = np.linalg.norm(model.modes[0], axis=1)
    polydata.GetPointData().SetScalars(numpy_to_vtk(displacement, deep=True))
    normals = vtk.vtkPolyDataNormals()
    normals.SetInputData(polydata)
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputConnection(normals.GetOutputPort())
    mapper.SetScalarRange(displacement.min(), displacement.max())
    lookup = vtk.vtkLookupTable()
    lookup.SetHueRange(0.6, 0.0)
    lookup.Build()
    mapper.SetLookupTable(lookup)
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    renderer = vtk.vtkRenderer()
    renderer.AddActor(actor)
    renderer.SetBackground(1.0, 1.0, 1.0)
    renderer.SetBackgroundAlpha(0.0)
    window = offscreen_window_class()()
    window.SetOffScreenRendering(1)
    window.SetAlphaBitPlanes(1)
    window.AddRenderer(renderer)
    window.SetSize(size, size)
    axes = np.linalg.svd(model.mean - model.mean.mean(axis=0), full_matrices=False)[2]
    camera = renderer.GetActiveCamera()
    camera.SetFocalPoint(*model.mean.mean(axis=0))
    camera.SetPosition(*(model.mean.mean(axis=0) + 100 * axes[2]))
    camera.SetViewUp(*axes[0])
    renderer.ResetCamera()
    camera.Zoom(1.35)
    window.Render()
    capture = vtk.vtkWindowToImageFilter()
    capture.SetInput(window)
    capture.SetInputBufferTypeToRGBA()
    capture.Update()
    writer = vtk.vtkPNGWriter()
    writer.SetFileName(destination)
    writer.SetInputConnection(capture.GetOutputPort())
    writer.Write()


if __name__ == "__main__":
    main(*sys.argv[1:3])
