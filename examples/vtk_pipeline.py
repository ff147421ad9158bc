"""A shape model as a VTK pipeline: label maps -> closed surfaces -> sphere maps -> model.

    python examples/vtk_pipeline.py [OUTPUT]      (default OUTPUT: example-vtk)

Writes 8 demo label maps as MetaImage files to OUTPUT/labels, builds a model of them with the
VTK pipeline objects, and writes OUTPUT/model.h5 (as `mdlshapemodel build` writes it) and
OUTPUT/plus2sd.vtp (the mean + 2 SD of the first mode).
"""

import sys
from pathlib import Path

import SimpleITK as sitk
import vtk

from mdlshapemodel import BuildConfig
from mdlshapemodel.demo import write_demo_population
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface, SurfaceToSphereMap
from mdlshapemodel.vtkmodel import ShapeModelBuilder, ShapeModelInstance, ShapeModelWriter


def main(output: Path) -> None:
    files = {}                                    # case name -> a .mha label map
    for path in write_demo_population(output / "labels", n_subjects=8, seed=0):
        name = path.name.split(".")[0]
        files[name] = output / "labels" / f"{name}.mha"
        sitk.WriteImage(sitk.ReadImage(str(path)), str(files[name]))

    builder = ShapeModelBuilder()
    builder.SetConfig(BuildConfig(points=162, max_time=20))
    for path in files.values():
        reader = vtk.vtkMetaImageReader()         # any source of a vtkImageData label map
        reader.SetFileName(str(path))
        to_surface = LabelMapToClosedSurface()
        to_surface.SetInputConnection(reader.GetOutputPort())
        to_sphere = SurfaceToSphereMap()
        to_sphere.SetInputConnection(to_surface.GetOutputPort())
        builder.AddInputConnection(to_sphere.GetOutputPort())
    builder.SetCaseNames(list(files))
    builder.Update()
    if builder.GetErrorText():
        sys.exit(f"the build failed: {builder.GetErrorText()}")

    instance = ShapeModelInstance()               # the mean + 2 SD of mode 1
    instance.SetInputConnection(builder.GetOutputPort(0))
    instance.SetWeights([2.0])
    mesh_writer = vtk.vtkXMLPolyDataWriter()
    mesh_writer.SetInputConnection(instance.GetOutputPort())
    mesh_writer.SetFileName(str(output / "plus2sd.vtp"))
    mesh_writer.Write()

    model_writer = ShapeModelWriter()             # the model as `mdlshapemodel build` writes it
    model_writer.SetInputConnection(builder.GetOutputPort(0))
    model_writer.SetFileName(str(output / "model.h5"))
    model_writer.Write()
    corresponded = builder.GetOutput(1)           # a block per case, same points and triangles
    print(f"{corresponded.GetNumberOfBlocks()} corresponded cases of "
          f"{builder.GetOutput(0).GetNumberOfPoints()} points; wrote {output}")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "example-vtk"))
