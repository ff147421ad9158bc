"""Mesh files say their coordinate system where 3D Slicer looks for it, and meshes that say RAS
are read into the library's LPS space. (Testing/Slicer/ checks the same files with Slicer's own
model storage node.)"""

import numpy as np
import pytest
import vtk
from vtk.util.numpy_support import numpy_to_vtk

from mdlshapemodel.config import field_items, parse_items
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.prepare import io
from mdlshapemodel.prepare.surface import arrays_to_polydata

from files import read_polydata

VERTICES = np.array([[1.0, 2.0, 3.0], [4.0, 2.0, 3.0], [1.0, 6.0, 3.0], [1.0, 2.0, 9.0]])
FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


@pytest.mark.parametrize("suffix", [".vtp", ".vtk", ".stl", ".ply"])
def test_written_meshes_say_lps_and_read_back_unchanged(tmp_path, suffix):
    path = tmp_path / f"mesh{suffix}"
    io.write_polydata(path, VERTICES, FACES)
    if suffix == ".vtp":                       # a field-data string array, as Slicer writes it
        assert read_polydata(path).GetFieldData().GetAbstractArray("SPACE").GetValue(0) == "LPS"
    else:                                      # "SPACE=LPS" in the header or a comment
        assert b"SPACE=LPS" in path.read_bytes()[:1000]
    vertices, faces = io.read_mesh(path)
    order = np.lexsort(vertices.T)             # STL files do not keep the point order
    np.testing.assert_allclose(vertices[order], VERTICES[np.lexsort(VERTICES.T)], atol=1e-6)
    assert len(faces) == 4


def test_a_vtp_that_says_ras_is_read_into_lps(tmp_path):
    polydata = arrays_to_polydata(VERTICES, FACES)
    space = vtk.vtkStringArray()
    space.SetName("SPACE")
    space.InsertNextValue("RAS")
    polydata.GetFieldData().AddArray(space)
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(tmp_path / "ras.vtp"))
    writer.SetInputData(polydata)
    writer.Write()
    vertices, _ = io.read_mesh(tmp_path / "ras.vtp")
    np.testing.assert_allclose(vertices, VERTICES * [-1, -1, 1])


def test_a_legacy_vtk_file_with_a_ras_header_is_read_into_lps(tmp_path):
    writer = vtk.vtkPolyDataWriter()
    writer.SetFileName(str(tmp_path / "ras.vtk"))
    writer.SetHeader("3D Slicer output. SPACE=RAS")
    writer.SetInputData(arrays_to_polydata(VERTICES, FACES))
    writer.Write()
    np.testing.assert_allclose(io.read_mesh(tmp_path / "ras.vtk")[0], VERTICES * [-1, -1, 1])


def test_a_mesh_that_says_nothing_is_taken_as_lps(tmp_path):
    polydata = arrays_to_polydata(VERTICES, FACES)
    polydata.GetPointData().AddArray(numpy_to_vtk(np.zeros(4)))
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(tmp_path / "plain.vtp"))
    writer.SetInputData(polydata)
    writer.Write()
    np.testing.assert_allclose(io.read_mesh(tmp_path / "plain.vtp")[0], VERTICES)


def test_list_settings_parse_from_text_with_the_fields_rules():
    assert field_items("labels", "1, 2 3") == [1, 2, 3]
    assert field_items("baselines", "none,cpd") == ["none", "cpd"]
    assert parse_items("") == []
    with pytest.raises(ConfigError, match="unknown warp kind 'twirl'; choose from symmetric"):
        field_items("warps", "twirl")
    with pytest.raises(ConfigError, match="labels must be integers"):
        field_items("labels", "1, a")
    with pytest.raises(ConfigError, match="no warp kind given"):
        field_items("warps", " ")
