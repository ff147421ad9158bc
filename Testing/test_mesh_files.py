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


@pytest.mark.parametrize("suffix", [".vtp", ".vtk", ".stl", ".ply"])
def test_writing_a_mesh_loads_vtks_io_modules_not_the_whole_of_vtk(tmp_path, suffix):
    """A process that writes meshes (a build's, with its files) keeps only the IO modules of VTK
    resident, not its rendering and the rest (``import vtk``)."""
    import subprocess
    import sys

    script = ("import sys\n"
              "import numpy as np\n"
              "from mdlshapemodel.prepare import io\n"
              f"io.write_polydata({str(tmp_path / ('mesh' + suffix))!r}, np.array({VERTICES.tolist()}),"
              f" np.array({FACES.tolist()}))\n"
              "print(sorted(m for m in ('vtk', 'vtkmodules.vtkRenderingCore') if m in sys.modules))\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
    assert (tmp_path / f"mesh{suffix}").stat().st_size > 0


def test_a_written_vtp_is_compressed_at_zlibs_fastest_level_and_reads_back_bit_for_bit(tmp_path):
    """A build writes two .vtp files per case: each array's zlib blocks say the fastest level
    (FLEVEL 0 in the stream header, RFC 1950) and decompress to the values written."""
    import base64
    import re
    import struct
    import zlib

    from vtk.util.numpy_support import vtk_to_numpy

    rng = np.random.default_rng(1)
    vertices = rng.normal(size=(500, 3)) * 20.0
    faces = rng.integers(0, 500, size=(900, 3))
    normal = rng.normal(size=500)
    path = tmp_path / "mesh.vtp"
    io.write_polydata(path, vertices, faces, point_data={"normal": normal})
    data = path.read_bytes()
    encoded = data[data.index(b"_", data.index(b"<AppendedData")) + 1:
                   data.index(b"</AppendedData>")].strip()
    offsets = [int(o) for o in re.findall(rb'format="appended"[^>]*offset="(\d+)"', data)]
    compressed = 0
    for offset in offsets:
        blocks = struct.unpack("<I", base64.b64decode(encoded[offset:offset + 8])[:4])[0]
        if blocks == 0:                   # an empty array (the mesh has no lines, say)
            continue
        compressed += 1
        header_chars = 4 * -(-4 * (3 + blocks) // 3)
        header = base64.b64decode(encoded[offset:offset + header_chars])
        first_size = struct.unpack("<4I", header[:16])[3]
        # the header and the blocks are base64-encoded separately (VTK's appended layout)
        block = base64.b64decode(encoded[offset + header_chars:
                                         offset + header_chars + 4 * -(-first_size // 3)])
        assert block[0] & 0x0F == 8 and (block[1] >> 6) == 0, block[:2].hex()
        zlib.decompress(block)
    assert compressed >= 4                # the field string, points, triangles, the normal
    read = read_polydata(path)
    np.testing.assert_array_equal(vtk_to_numpy(read.GetPoints().GetData()), vertices)
    np.testing.assert_array_equal(vtk_to_numpy(read.GetPointData().GetArray("normal")), normal)
