"""Writing the tests' label maps and reading the meshes and tables a build writes, in one place (SimpleITK
and VTK's own readers and writers: nothing of the library's, which the tests check)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_label_map(path, mask, label: int = 1, spacing=None, origin=None) -> Path:
    """``mask`` (z, y, x) written by SimpleITK as a uint8 label map, its values times ``label``
    (a boolean mask: ``label`` inside, 0 outside), with the given spacing and origin (x, y, z;
    default SimpleITK's 1 mm and 0); the format follows the suffix. Returns the path."""
    import SimpleITK as sitk

    image = sitk.GetImageFromArray(np.asarray(mask).astype(np.uint8) * np.uint8(label))
    if spacing is not None:
        image.SetSpacing(tuple(map(float, spacing)))
    if origin is not None:
        image.SetOrigin(tuple(map(float, origin)))
    sitk.WriteImage(image, str(path))
    return Path(path)


def triangle_polydata(vertices, faces):
    """A vtkPolyData of triangles from arrays (n, 3) and (m, 3)."""
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64)))
    cells = vtk.vtkCellArray()
    faces = np.asarray(faces, dtype=np.int64)
    cells.SetData(numpy_to_vtkIdTypeArray(np.arange(0, faces.size + 1, 3, dtype=np.int64), deep=True),
                  numpy_to_vtkIdTypeArray(faces.ravel(), deep=True))
    polydata = vtk.vtkPolyData()
    polydata.SetPoints(points)
    polydata.SetPolys(cells)
    return polydata


def read_polydata(path):
    """A .vtp file read by VTK's XML reader: its vtkPolyData."""
    import vtk

    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader.GetOutput()


def polydata_triangles(path) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3), triangles (m, 3)) of a .vtp file of triangles."""
    from vtk.util.numpy_support import vtk_to_numpy

    polydata = read_polydata(path)
    return (vtk_to_numpy(polydata.GetPoints().GetData()).copy(),
            vtk_to_numpy(polydata.GetPolys().GetConnectivityArray()).reshape(-1, 3).copy())


def read_csv_rows(path) -> list:
    """The rows of a CSV file with a header, as dicts (the standard library's reader)."""
    import csv

    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))
