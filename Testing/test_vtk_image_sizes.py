"""VTK data of differing sizes through the faces: every image-consuming filter asks its source for
the whole image, and every VTK array is checked against the size its data set says before the
library views it.

The pipelines run in a subprocess: a pipeline that wrote out of bounds would abort the process,
and that must fail the test, not end the test run.
"""

from __future__ import annotations

import re
import subprocess
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
import SimpleITK as sitk
import vtk
from vtk.util.numpy_support import numpy_to_vtk

from mdlshapemodel import BuildConfig, ShapeModel
from mdlshapemodel.errors import InputError
from mdlshapemodel.prepare import io, prepare_case
from mdlshapemodel.vtkmodel import ShapeModelReader, model_to_polydata, polydata_to_model

from common import hippocampi, needs_hippocampi, run_cli, run_python
from synthetic import small_mask

VTK_GUIDE = Path(__file__).resolve().parents[1] / "docs" / "vtk.md"


def run_pipeline(code: str, folder: Path, *arguments) -> subprocess.CompletedProcess:
    """Run ``code`` in ``folder`` in a fresh interpreter; fails the test when the process does
    not exit 0 (an abort in native code included)."""
    result = run_python(code, *arguments, cwd=folder)
    assert result.returncode == 0, (result.returncode, result.stderr[-3000:])
    return result


def guide_pipeline() -> str:
    """docs/vtk.md's label-map-to-model VTK example, as written there."""
    section = VTK_GUIDE.read_text()
    return next(block for block in re.findall(r"```python\n(.*?)```", section, re.S)
                if "ShapeModelBuilder" in block)


# The guide's reader replaced by VTK's NIfTI reader and the file's orientation: the reader
# leaves it in the q-form matrix (from the image's coordinates, spacing applied, to RAS), and
# vtkImageChangeInformation puts it into the image in LPS, the space of the library's reader.
NIFTI_READER = textwrap.indent(textwrap.dedent("""\
    nifti = vtk.vtkNIFTIImageReader()
    nifti.SetFileName(path)
    nifti.UpdateInformation()
    q = nifti.GetQFormMatrix() or nifti.GetSFormMatrix()
    lps = [[q.GetElement(r, c) * (-1 if r < 2 else 1) for c in range(4)] for r in range(3)]
    reader = vtk.vtkImageChangeInformation()
    reader.SetInputConnection(nifti.GetOutputPort())
    reader.SetOutputOrigin(lps[0][3], lps[1][3], lps[2][3])
    reader.SetOutputDirection([lps[r][c] for r in range(3) for c in range(3)])
"""), "    ")


def no_vtk_errors(stderr: str):
    lines = [line for line in stderr.splitlines() if "ERR" in line or "rror" in line]
    assert not lines, lines[:5]


@pytest.mark.slow
@needs_hippocampi
@pytest.mark.parametrize("reader", ["mha", "nifti"])
def test_the_vtk_guides_pipeline_on_ten_hippocampi_builds_the_model_of_the_cli(reader, tmp_path):
    files = hippocampi(10)
    names = [path.name.split(".")[0] for path in files]
    if reader == "mha":     # the same images as MetaImage files, which vtkMetaImageReader reads
        inputs = []
        for name, path in zip(names, files):
            inputs.append(tmp_path / f"{name}.mha")
            sitk.WriteImage(sitk.ReadImage(str(path)), str(inputs[-1]))
    else:
        inputs = files
    code = guide_pipeline()
    listed = re.search(r"files = \{.*?\}", code, re.S).group(0)
    code = code.replace(listed, "files = " + repr({n: str(p) for n, p in zip(names, inputs)}))
    # a budget the optimisation never reaches, so that both builds stop on convergence alone
    assert "max_time=120" in code
    code = code.replace("max_time=120", "max_time=3000")
    if reader == "nifti":
        pattern = r"    reader = vtk\.vtkMetaImageReader\(\).*\n    reader\.SetFileName\(path\)\n"
        assert re.search(pattern, code)
        code = re.sub(pattern, lambda _: NIFTI_READER, code)
    result = run_pipeline(code, tmp_path)
    assert result.stdout.strip().endswith("built")
    no_vtk_errors(result.stderr)

    points = re.search(r"BuildConfig\(points=(\d+)", code).group(1)
    built = run_cli("build", *files, "-o", tmp_path / "cli", "--points", points, "--max-time",
                    "3000", "--baselines", "", "--evaluation-modes", "2",
                    "--specificity-samples", "100", "--surface-samples", "0", "--no-cache", "-q")
    assert built.returncode == 0, built.stderr
    piped, built = ShapeModel.load(tmp_path / "model.h5"), ShapeModel.load(tmp_path / "cli" /
                                                                           "model.h5")
    assert piped.names == built.names == names
    for key in ("mean", "modes", "variances", "weights", "scores", "triangles", "parameters"):
        assert np.array_equal(getattr(piped, key), getattr(built, key)), key
    assert piped.metadata["objective"] == built.metadata["objective"]


# Four label maps of different extents, spacings and origins (and one rotated), each the same
# small ellipsoid padded differently, built by one builder so that the pipeline passes requests
# between the branches. The rotation is symmetric: vtkMetaImageReader reads a MetaImage's
# TransformMatrix transposed against ITK (and so SimpleITK and build), so only a symmetric
# direction matrix means the same to both readers.
GEOMETRIES = [((0, 0, 0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), None),
              ((3, 0, 5), (1.2, 0.9, 1.1), (40.0, -7.5, 3.0), None),
              ((0, 6, 2), (0.8, 1.0, 1.3), (-25.0, 12.0, -9.0), None),
              ((4, 2, 0), (1.0, 1.1, 0.9), (5.0, 5.0, 5.0), (0, 1, 0, 1, 0, 0, 0, 0, -1))]

BRANCHES = """
import sys
import numpy as np
import vtk
from mdlshapemodel import BuildConfig
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface, SurfaceToSphereMap
from mdlshapemodel.vtkmodel import ShapeModelBuilder

builder = ShapeModelBuilder()
builder.SetConfig(BuildConfig(points=42, strategy="none", baselines=[]))
branches = []
for path in sys.argv[1:]:
    reader = vtk.vtkMetaImageReader()
    reader.SetFileName(path)
    to_surface = LabelMapToClosedSurface()
    to_surface.SetInputConnection(reader.GetOutputPort())
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputConnection(to_surface.GetOutputPort())
    builder.AddInputConnection(to_sphere.GetOutputPort())
    branches.append((reader, to_surface, to_sphere))
builder.Update()
print(builder.GetErrorText() or "built")
from vtk.util.numpy_support import vtk_to_numpy
arrays = {}
for k, (_, _, to_sphere) in enumerate(branches):
    output = to_sphere.GetOutput()
    arrays[f"points_{k}"] = vtk_to_numpy(output.GetPoints().GetData())
    arrays[f"sphere_{k}"] = vtk_to_numpy(output.GetPointData().GetArray("SphereCoordinates"))
np.savez("branches.npz", **arrays)
"""


def test_branches_of_different_extents_spacings_and_origins_are_each_prepared_as_build_does(
        tmp_path):
    paths = []
    for k, (pad, spacing, origin, direction) in enumerate(GEOMETRIES):
        mask = np.pad(small_mask(0.2 * k - 0.3).astype(np.uint8), [(p, 1) for p in pad])
        image = sitk.GetImageFromArray(mask)
        image.SetSpacing(spacing)
        image.SetOrigin(origin)
        if direction is not None:
            image.SetDirection(direction)
        paths.append(tmp_path / f"case_{k}.mha")
        sitk.WriteImage(image, str(paths[-1]))
    assert len({sitk.ReadImage(str(p)).GetSize() for p in paths}) == len(paths)
    result = run_pipeline(BRANCHES, tmp_path, *paths)
    assert result.stdout.strip() == "built"
    no_vtk_errors(result.stderr)
    arrays = np.load(tmp_path / "branches.npz")
    for k, path in enumerate(paths):
        mapped = prepare_case(path, BuildConfig()).parts[0].map
        assert np.array_equal(arrays[f"points_{k}"], mapped.vertices), path.name
        assert np.array_equal(arrays[f"sphere_{k}"], mapped.sphere), path.name


SHORT_SCALARS = """
import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk
from mdlshapemodel.vtkfilters import LabelMapToClosedSurface

image = vtk.vtkImageData()
image.SetDimensions(30, 30, 30)
image.GetPointData().SetScalars(numpy_to_vtk(np.ones(20 * 30 * 30, np.uint8), deep=True))
to_surface = LabelMapToClosedSurface()
to_surface.SetInputData(image)
to_surface.Update()
print(to_surface.GetErrorText())
print(to_surface.GetOutput().GetNumberOfPoints())
"""


def test_an_image_whose_scalars_are_shorter_than_its_extent_is_refused_in_one_line(tmp_path):
    result = run_pipeline(SHORT_SCALARS, tmp_path)
    message, points = result.stdout.strip().splitlines()
    assert message == ("the input image's scalars hold 18000 values but its extent "
                       "(0, 29, 0, 29, 0, 29) says 30 x 30 x 30 = 27000")
    assert points == "0"


def test_image_values_are_the_scalars_in_z_y_x_order():
    image = vtk.vtkImageData()
    image.SetExtent(2, 5, 0, 2, 1, 2)
    values = np.arange(4 * 3 * 2, dtype=np.int16)
    image.GetPointData().SetScalars(numpy_to_vtk(values, deep=True))
    array = io.image_values(image)
    assert array.shape == (2, 3, 4)
    assert array[1, 2, 3] == values[-1] and array[0, 1, 0] == 4
    image.GetPointData().SetScalars(numpy_to_vtk(values[:-1], deep=True))
    with pytest.raises(InputError, match="hold 23 values but its extent"):
        io.image_values(image)


SHORT_SPHERE = """
import numpy as np
import vtk
from vtk.util.numpy_support import numpy_to_vtk
from mdlshapemodel import BuildConfig
from mdlshapemodel.demo import bump_ellipsoid_mask
from mdlshapemodel.vtkfilters import SurfaceToSphereMap
from mdlshapemodel.vtkmodel import ShapeModelBuilder
from mdlshapemodel.prepare.surface import arrays_to_polydata, mask_to_surface

builder = ShapeModelBuilder()
builder.SetConfig(BuildConfig(points=42, strategy="none", baselines=[]))
for k in range(3):
    vertices, faces, _ = mask_to_surface(bump_ellipsoid_mask(shape=(18, 20, 28),
                                         semi_axes=(10.0, 6.0, 5.0), bump_position=0.3 * k))
    to_sphere = SurfaceToSphereMap()
    to_sphere.SetInputData(arrays_to_polydata(vertices, faces))
    to_sphere.SetVoxelSize(1.0)
    to_sphere.Update()
    mapped = vtk.vtkPolyData()
    mapped.DeepCopy(to_sphere.GetOutput())
    if k == 1:      # the case's sphere map loses its last tenth of points
        sphere = mapped.GetPointData().GetArray("SphereCoordinates")
        sphere.SetNumberOfTuples(int(0.9 * sphere.GetNumberOfTuples()))
    builder.AddInputData(mapped)
builder.SetCaseNames(["a", "b", "c"])
builder.Update()
print(builder.GetErrorText())
"""


def test_a_sphere_map_shorter_than_its_surface_is_refused_by_the_builder(tmp_path):
    message = run_pipeline(SHORT_SPHERE, tmp_path).stdout.strip()
    assert re.fullmatch(r"b: point data SphereCoordinates holds \d+ x 3 values; the data set "
                        r"has \d+ points x 3 components", message), message


def damaged_copy(source: Path, target: Path, name: str, change) -> Path:
    target.write_bytes(source.read_bytes())
    with h5py.File(target, "r+") as f:
        group = f["mdlshapemodel"]
        value = change(group[name][()])
        del group[name]
        group.create_dataset(name, data=value)
    return target


@pytest.fixture
def model_file(tmp_path):
    from synthetic import small_maps

    maps = small_maps(4)
    n = min(len(m.vertices) for m in maps)
    shapes = np.stack([m.vertices[:n] for m in maps])
    triangles = np.array([[0, 1, 2], [1, 2, 3]])
    model = ShapeModel.from_shapes(shapes, np.full(n, 1 / n), triangles=triangles)
    model.save(tmp_path / "model.h5")
    return tmp_path / "model.h5"


@pytest.mark.parametrize("name, change, reason", [
    ("triangles", lambda t: t + 10 ** 6, "triangles index points outside"),
    ("weights", lambda w: w[:-1], "weights has shape"),
    ("scores", lambda s: s[:, :1], "scores has shape"),
    ("modes", lambda m: m[:, :-2], "modes has shape")])
def test_a_model_file_whose_arrays_do_not_fit_is_refused_by_every_reader(model_file, name, change,
                                                                         reason):
    damaged = damaged_copy(model_file, model_file.with_name(f"{name}.h5"), name, change)
    with pytest.raises(InputError, match=f"{damaged}: damaged or incomplete model file "
                                         f"\\({reason}"):
        ShapeModel.load(damaged)
    reader = ShapeModelReader()
    reader.SetFileName(str(damaged))
    reader.Update()
    assert reason in reader.GetErrorText()
    assert reader.GetOutput().GetNumberOfPoints() == 0


def test_a_model_polydata_whose_arrays_do_not_fit_its_points_is_refused(model_file):
    polydata = model_to_polydata(ShapeModel.load(model_file))
    weights = polydata.GetPointData().GetArray("AreaWeights")
    weights.SetNumberOfTuples(weights.GetNumberOfTuples() - 3)
    with pytest.raises(InputError, match="not a shape model: weights has shape"):
        polydata_to_model(polydata)
