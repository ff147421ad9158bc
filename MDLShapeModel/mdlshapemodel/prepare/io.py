"""Reading and writing files: label maps (SimpleITK), meshes (VTK), tables.

Readers raise :class:`InputError` with a one-line reason; callers add the file name.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import re
import sys
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import MAX_COORDINATE, MAX_LABEL_VALUES, MAX_VOXELS
from ..errors import InputError
from . import integrity

log = logging.getLogger("mdlshapemodel")

IMAGE_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd", ".hdr", ".img", ".img.gz")
MESH_SUFFIXES = (".vtk", ".vtp", ".stl", ".ply", ".obj")
# files that only hold 2-D curves (a .vtk/.vtp polyline or a one-slice image is one too: see
# prepare.curve_io.is_curve_file)
CURVE_SUFFIXES = (".csv", ".txt", ".png")
# left out of a folder's inputs (READMEs, licences): a .txt curve is given by its name
FOLDER_SKIPS = (".txt",)


def suffix_of(path) -> str:
    """The recognised (possibly double) suffix of a file name, lower case, or ''."""
    name = Path(path).name.lower()
    for suffix in IMAGE_SUFFIXES + MESH_SUFFIXES + CURVE_SUFFIXES:
        if name.endswith(suffix):
            return suffix
    return ""


def case_name(path) -> str:
    """The file name without its recognised suffix: the case's name in outputs."""
    name = Path(path).name
    suffix = suffix_of(path)
    return name[: len(name) - len(suffix)] if suffix else Path(path).stem


def case_file(folder, name: str, suffix: str = ".vtp") -> Path:
    """The file of case ``name`` in an output ``folder``: the one place where a case's name
    becomes a path. Path separators and control characters in the name become '_' ('.' and
    '..' too), so the file is always directly in ``folder``: a name from anywhere (a file name,
    a Slicer node, a caller of the API) can neither leave the output folder nor break a line."""
    separators = {"/", "\\"} | ({":"} if os.name == "nt" else set())
    safe = "".join("_" if c in separators or not c.isprintable() else c for c in str(name))
    if safe.strip(".") == "":
        safe = "_" * max(len(safe), 1)
    return Path(folder) / f"{safe}{suffix}"


def is_image(path) -> bool:
    return suffix_of(path) in IMAGE_SUFFIXES


def is_mesh(path) -> bool:
    return suffix_of(path) in MESH_SUFFIXES


def find_inputs(paths) -> list[Path]:
    """Expand folders into their supported files (sorted; not .txt files, which are given by
    name); keep files as given.

    Raises :class:`InputError` for a path that does not exist. (The commands refuse a build's
    output folder first: :func:`mdlshapemodel.folders.find_inputs`.)
    """
    found = []
    for path in map(Path, paths):
        if path.is_dir():
            found.extend(sorted(p for p in path.iterdir() if p.is_file() and suffix_of(p)
                                and suffix_of(p) not in FOLDER_SKIPS))
        elif path.exists():
            found.append(path)
        else:
            raise InputError(f"{path}: no such file or folder")
    return found


@dataclass
class LabelMap:
    """A binary mask and its geometry (SimpleITK conventions: arrays are z, y, x)."""

    mask: np.ndarray
    spacing: tuple
    origin: tuple
    direction: tuple
    labels: tuple = ()        # the non-zero label values of the file

    @property
    def voxel_size(self) -> float:
        """Geometric mean of the spacing (mm)."""
        return float(np.prod(self.spacing) ** (1.0 / 3.0))


def _require_scalar(components: int):
    """A label map has one value per voxel (SimpleITK images and vtkImageData alike)."""
    if components != 1:
        raise InputError(f"expected a scalar label map, got an image of {components} values per "
                         "voxel")


def select_labels(array: np.ndarray, labels=()) -> np.ndarray:
    """The mask of the union of ``labels`` in a label array (all non-zero labels when empty).

    The one rule of label selection, for files (:func:`read_label_map`) and VTK images
    (:func:`label_map_of_image_data`) alike. Labels that are absent are ignored as long as one
    of them is present.

    Raises
    ------
    InputError
        When the array has non-integer values, no non-zero value, or none of ``labels`` (the
        message lists the labels found), or is not a label map by :func:`require_label_map`.

    Examples
    --------
    >>> select_labels(np.array([0, 1, 2, 2]), [2, 3]).tolist()
    [False, False, True, True]
    >>> select_labels(np.array([0, 1, 5]), [7])
    Traceback (most recent call last):
    ...
    mdlshapemodel.errors.InputError: label 7 not present (labels found: 1, 5)
    """
    return selected_labels(array, labels)[0]


def selected_labels(array: np.ndarray, labels=()) -> tuple[np.ndarray, tuple]:
    """:func:`select_labels` and the non-zero label values the array holds (sorted ints), so
    that a build can say which of its labels no case has."""
    array = np.asarray(array)
    if not np.issubdtype(array.dtype, np.integer):
        rounded = np.round(array)
        if not np.allclose(array, rounded):
            raise InputError("the image has non-integer values; expected a label map")
        array = rounded.astype(np.int64)
    present = np.unique(array)
    present = present[present != 0]
    if len(present) == 0:
        raise InputError("the label map is empty (no non-zero voxels)")
    found = tuple(int(v) for v in present)
    if labels:
        if not np.isin(labels, present).any():
            shown = ", ".join(str(v) for v in found[:20])
            raise InputError(f"label {', '.join(str(int(v)) for v in labels)} not present "
                             f"(labels found: {shown})")
        mask = np.isin(array, labels)
    else:
        mask = array != 0
    require_label_map(len(present), mask, labels)
    return mask, found


def require_label_map(values: int, mask: np.ndarray, labels=()):
    """The rule that tells a label map from an intensity image (a CT, an MR) given as one.

    Without ``labels``, an image of more than :data:`~mdlshapemodel.config.MAX_LABEL_VALUES`
    distinct non-zero ``values`` is not a label map. With or without them, an object ``mask``
    that holds every voxel of the image's border (both end slices along every axis longer than
    one voxel) is refused: its surface would be the image's box, as when every voxel of an
    intensity image is non-zero. Raises :class:`InputError` saying which, and suggesting
    ``--label`` when none was given.

    Examples
    --------
    >>> require_label_map(2, np.pad(np.ones((2, 2, 2), bool), 1))   # inside its image: fine
    >>> require_label_map(1, np.ones((3, 4, 5), bool), [1])
    Traceback (most recent call last):
    ...
    mdlshapemodel.errors.InputError: label 1 fills the image out to its border on every side: ...
    """
    suggestion = "give the object's label value(s) with --label"
    if not len(labels) and values > MAX_LABEL_VALUES:
        raise InputError(f"not a label map: {values:,} distinct values (an intensity image's "
                         f"grey values, as of a CT or MR; a label map has at most "
                         f"{MAX_LABEL_VALUES}); {suggestion}")
    if _fills_border(mask):
        if len(labels):
            raise InputError(f"label {', '.join(str(int(v)) for v in labels)} fills the image "
                             "out to its border on every side: its surface would be the image's "
                             "box, not an object's")
        raise InputError("not a label map: its non-zero voxels fill the image out to its border "
                         "on every side, as an intensity image's do, so its surface would be the "
                         f"image's box; {suggestion}")


def _fills_border(mask: np.ndarray) -> bool:
    """Whether ``mask`` holds every voxel of both end slices along every axis longer than one
    voxel (every voxel, when there is no such axis)."""
    axes = [k for k, n in enumerate(mask.shape) if n > 1]
    if not axes:
        return bool(mask.all())
    return all(np.take(mask, end, axis=k).all() for k in axes for end in (0, -1))


_NATIVE_STDERR = threading.Lock()


@contextmanager
def captured_native_stderr():
    """Collect what native code (ITK's MetaImage and NIfTI readers) prints on the process's
    standard error instead of printing it; yields a callable that returns the collected text,
    which is the caller's to use (:func:`itk_reading`: the reason of a rejection, or log lines).

    File descriptor 2 belongs to the whole process: one block at a time (a lock).
    """
    with _NATIVE_STDERR:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (AttributeError, OSError, ValueError):     # no stderr (e.g. a GUI without one)
            yield lambda: ""
            return
        with tempfile.TemporaryFile() as sink:
            def collected() -> str:
                sink.seek(0)
                return sink.read().decode("utf-8", "replace")

            os.dup2(sink.fileno(), 2)
            try:
                yield collected
            finally:
                os.dup2(saved, 2)
                os.close(saved)


def printable(text) -> str:
    """``text`` on one line, control characters (newlines, terminal escapes) written as escapes:
    file names and reasons as they go into a log line."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in str(text))


def _printed(native: str) -> tuple[list, list]:
    """(errors, warnings) in what a reader printed: ITK's warnings are blocks 'WARNING: In
    file, line n' + 'Class (0x...): message'; MetaIO and nifticlib print their errors as plain
    lines, and go on."""
    errors, warnings, warning = [], [], False
    for line in native.splitlines():
        if line.startswith("WARNING"):
            warning = True
        elif line.strip():
            if warning:
                warnings.append(re.sub(r"^\w+ \(0x[0-9a-fA-F]+\): ", "", line.strip()))
            else:
                errors.append(line.strip())
            warning = False
    return errors, warnings


def _itk_reason(text: str, native: str, path) -> str:
    """The informative part of a SimpleITK error (and of what its reader printed)."""
    if "Unable to determine ImageIO reader" in text:
        return "unknown format or corrupt file"
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    teem = [line.split(": ", 1)[1] for line in lines if line.startswith("[nrrd]") and ": " in line]
    if teem:
        reason = teem[-1]                       # NRRD: the innermost of teem's messages
    else:
        reason = next((line for line in lines if "Exception thrown" not in line
                       and not line.startswith("Reason:")), "unknown error")
        reason = re.sub(r"^(ITK |itk::|sitk::)?ERROR: (\w+\(0x[0-9a-fA-F]+\): )?", "", reason)
    printed, _ = _printed(native)
    if printed and reason.startswith(("File cannot be read", "unknown error")):
        reason = printed[0]                     # MetaIO prints why; its exception says little
    return reason.replace(str(path), "the file")[:200]


@contextmanager
def itk_reading(path):
    """SimpleITK's errors while reading ``path``, and the errors its reader printed and went on
    from (MetaIO's 'Uncompress failed' returns an image), -> one InputError; the warnings ITK
    printed -> one log line each, naming the file."""
    with captured_native_stderr() as native:
        try:
            yield
            errors, warnings = _printed(native())
            if errors:
                raise RuntimeError("")
        except RuntimeError as error:
            reason = _itk_reason(str(error), native(), path)
            raise InputError(f"not a readable image ({reason})") from None
    for warning in dict.fromkeys(warnings):
        log.warning("%s: %s", printable(path), printable(warning.replace(str(path), "the file")))


def _bits(pixel: str) -> int:
    """Bits per voxel of a SimpleITK pixel type name ('8-bit unsigned integer', 'vector of
    32-bit float', 'complex of 64-bit float')."""
    found = re.search(r"(\d+)-bit", pixel)
    return (int(found.group(1)) if found else 64) * (2 if "complex" in pixel else 1)


def check_image_header(size, spacing, origin, direction, components: int, pixel: str) -> int:
    """What a label-map header says, checked before any voxel is read: three dimensions (or a
    fourth of size 1), one value per voxel, at most :data:`~mdlshapemodel.config.MAX_VOXELS`
    voxels, finite positive spacing, a finite origin, a direction that is a rotation (to 1%),
    corners within :data:`~mdlshapemodel.config.MAX_COORDINATE`. Returns the bytes of the
    voxels. ``pixel`` is SimpleITK's name of the pixel type."""
    shape = " x ".join(str(n) for n in size)
    if len(size) == 2:
        raise InputError(f"a 2-D image ({shape}); this build needs 3-D label maps")
    if len(size) != 3 and not (len(size) == 4 and size[3] == 1):
        raise InputError(f"a {len(size)}-D image ({shape}); this build needs 3-D label maps")
    _require_scalar(components)
    voxels = math.prod(size)
    nbytes = voxels * components * _bits(pixel) // 8
    if voxels > MAX_VOXELS:
        raise InputError(f"the header claims {shape} = {voxels:,} voxels ({nbytes / 1e9:,.1f} GB "
                         f"of {pixel}); a label map may have at most {MAX_VOXELS:,} voxels "
                         "(MAX_VOXELS: memory)")
    values = ", ".join(f"{v:g}" for v in spacing)
    if not all(math.isfinite(v) for v in spacing):
        raise InputError(f"the header's spacing ({values}) is not a number")
    if not all(v > 0 for v in spacing):
        raise InputError(f"the header's spacing ({values}) is zero or negative")
    if not all(math.isfinite(v) for v in tuple(origin) + tuple(direction)):
        raise InputError("the header's origin or direction is not a number")
    axes = np.clip(np.reshape(direction, (len(size), len(size))), -2, 2)   # no overflow
    if np.abs(axes.T @ axes - np.eye(len(size))).max() > 0.01:      # ITK hangs on 1e308 in it
        values = ", ".join(f"{v:.3g}" for v in direction)
        raise InputError(f"the header's direction ({values}) is not a rotation (its axes are "
                         "not orthonormal)")
    extent = max(abs(o) + s * n for o, s, n in zip(origin, spacing, size))
    if extent > MAX_COORDINATE:
        raise InputError(f"the image reaches {extent:.3g} mm from the origin, beyond "
                         f"{MAX_COORDINATE:.0e} (MAX_COORDINATE)")
    return nbytes


def read_label_map(path, labels=()) -> LabelMap:
    """The union of ``labels`` (all non-zero labels when empty) of a label-map image file
    (:func:`select_labels`).

    The header is read and checked first (:func:`check_image_header`), then the file's data
    against it (:func:`.integrity.check_image_data`: complete, intact compressed streams), and only
    then the voxels."""
    import SimpleITK as sitk

    if not Path(path).is_file():
        raise InputError("no such file")
    integrity.check_image_text_header(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    with itk_reading(path):        # what the reader prints about a file it rejects is dropped
        try:
            reader.ReadImageInformation()
        except RuntimeError:
            integrity.check_gzip(path)  # a damaged .nii.gz: say so, not 'unknown format'
            raise
        nbytes = check_image_header(
            reader.GetSize(), reader.GetSpacing(), reader.GetOrigin(), reader.GetDirection(),
            reader.GetNumberOfComponents(), sitk.GetPixelIDValueAsString(reader.GetPixelID()))
        integrity.check_image_data(path, nbytes)
        image = reader.Execute()
    if image.GetDimension() == 4:                  # a 4-D image of one volume
        image = image[:, :, :, 0]
    if image.GetDimension() != 3:
        raise InputError(f"expected a 3-D label map, got a {image.GetDimension()}-D image")
    _require_scalar(image.GetNumberOfComponentsPerPixel())
    mask, found = selected_labels(sitk.GetArrayViewFromImage(image), labels)
    return LabelMap(np.ascontiguousarray(mask), image.GetSpacing(), image.GetOrigin(),
                    image.GetDirection(), found)


def image_values(image) -> np.ndarray:
    """The scalars of a vtkImageData as a (z, y, x) numpy view, checked against its extent.

    A vtkImageData carries its size twice: in its extent and in the length of its scalars. A
    pipeline that asks a source for another extent than it can give, or a hand-made image, can
    leave the two apart; viewing the scalars in the extent's shape would then read past them
    (or index garbage), so a mismatch is an :class:`InputError` naming both sizes.

    Examples
    --------
    >>> import vtk
    >>> image = vtk.vtkImageData()
    >>> image.SetDimensions(4, 3, 2)
    >>> image.AllocateScalars(vtk.VTK_UNSIGNED_CHAR, 1)
    >>> image_values(image).shape
    (2, 3, 4)
    """
    from vtk.util.numpy_support import vtk_to_numpy

    scalars = image.GetPointData().GetScalars() if image is not None else None
    if scalars is None or scalars.GetNumberOfTuples() == 0:
        raise InputError("the input image has no scalars")
    nx, ny, nz = image.GetDimensions()
    if min(nx, ny, nz) <= 0:
        raise InputError(f"the input image's extent {tuple(image.GetExtent())} is empty")
    _require_scalar(scalars.GetNumberOfComponents())
    if scalars.GetNumberOfTuples() != nx * ny * nz:
        raise InputError(f"the input image's scalars hold {scalars.GetNumberOfTuples()} values "
                         f"but its extent {tuple(image.GetExtent())} says {nx} x {ny} x {nz} = "
                         f"{nx * ny * nz}")
    return vtk_to_numpy(scalars).reshape(nz, ny, nx)


def point_values(dataset, name: str, components: int) -> np.ndarray | None:
    """A point-data array of a VTK data set as an (n_points, components) numpy view, or None
    when the data set has no array of that name.

    The array must have one tuple per point of ``dataset`` and ``components`` components: an
    array of another size (VTK lets one be added) would have compiled loops that index it by
    point read past its end, so it is an :class:`InputError` naming the array and both sizes.
    """
    from vtk.util.numpy_support import vtk_to_numpy

    array = dataset.GetPointData().GetArray(name) if dataset is not None else None
    if array is None:
        return None
    tuples, width = array.GetNumberOfTuples(), array.GetNumberOfComponents()
    if tuples != dataset.GetNumberOfPoints() or width != components:
        raise InputError(f"point data {name} holds {tuples} x {width} values; the data set has "
                         f"{dataset.GetNumberOfPoints()} points x {components} components")
    return vtk_to_numpy(array).reshape(tuples, components)


def label_map_of_image_data(image, labels=()) -> LabelMap:
    """The union of ``labels`` (all non-zero labels when empty) of a label map held in a
    vtkImageData, with the same rules and messages as :func:`read_label_map`; the geometry is
    the image's origin, spacing and direction matrix. The scalars are checked against the
    extent first (:func:`image_values`)."""
    mask, found = selected_labels(image_values(image), labels)
    matrix = image.GetDirectionMatrix()
    direction = tuple(matrix.GetElement(r, c) for r in range(3) for c in range(3))
    return LabelMap(np.ascontiguousarray(mask), tuple(image.GetSpacing()),
                    tuple(image.GetOrigin()), direction, found)


def _reader_for(path):
    import vtk

    # PLY files are read by .ply.read_ply: VTK's reader crashes on damaged ones
    readers = {".vtk": vtk.vtkPolyDataReader, ".vtp": vtk.vtkXMLPolyDataReader,
               ".stl": vtk.vtkSTLReader, ".obj": vtk.vtkOBJReader}
    suffix = suffix_of(path)
    if suffix not in readers:
        raise InputError(f"unsupported mesh format {suffix or Path(path).suffix!r}")
    return readers[suffix]()


@contextmanager
def captured_vtk_messages():
    """Collect VTK's error and warning text instead of printing it; yields a callable that
    returns the collected text (a str: VTK gives bytes when a damaged file put invalid UTF-8
    into a message)."""
    import vtk

    window = vtk.vtkStringOutputWindow()
    previous_window = vtk.vtkOutputWindow.GetInstance()
    previous_verbosity = vtk.vtkLogger.GetCurrentVerbosityCutoff()
    vtk.vtkOutputWindow.SetInstance(window)
    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    try:
        yield lambda: _text(window.GetOutput())
    finally:
        vtk.vtkOutputWindow.SetInstance(previous_window)
        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.ConvertToVerbosity(previous_verbosity))


def _text(value) -> str:
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value or "")


def read_polydata(path):
    """A vtkPolyData from any supported mesh file (quietly: errors become InputError)."""
    return _read_polydata(path)[0]


def vtk_errors(text: str) -> list:
    """The messages of the errors (not the warnings) in text collected by
    :func:`captured_vtk_messages`."""
    reasons, in_error = [], False
    for line in text.splitlines():
        if line.startswith(("ERROR:", "Warning:", "Generic Warning:")):
            in_error = line.startswith("ERROR:")
        elif in_error and line.strip():
            reasons.append(re.sub(r"^\w+ \(0x[0-9a-fA-F]+\): ", "", line.strip()))
            in_error = False
    return reasons


def _read_polydata(path):
    """(vtkPolyData, the texts in which the file may say its coordinate system); a reader's
    error, a header that claims too much (:func:`.integrity.check_mesh_counts`) or an empty mesh
    is an InputError."""
    if not Path(path).is_file():
        raise InputError("no such file")
    if suffix_of(path) == ".ply":
        return _read_ply(path)
    reader = _reader_for(path)
    integrity.check_mesh_file(path)
    reader.SetFileName(str(path))
    with captured_vtk_messages() as messages:
        reader.Update()
        errors = vtk_errors(messages())
    polydata = reader.GetOutput()
    if errors:
        reason = printable(errors[0].replace(str(path), "the file"))[:120]
        raise InputError(f"not a readable mesh ({reason})")
    if polydata is None or polydata.GetNumberOfPoints() == 0:
        raise InputError("not a readable mesh or the mesh is empty")
    array = polydata.GetFieldData().GetAbstractArray(SPACE)
    notes = [array.GetValue(0)] if array is not None and array.GetNumberOfValues() else []
    notes += [getattr(reader, getter)() for getter in ("GetHeader", "GetComment")
              if hasattr(reader, getter)]
    return polydata, [_text(note) for note in notes]


def _read_ply(path):
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray

    from .ply import read_ply

    mesh = read_ply(path)
    if len(mesh.vertices) == 0:
        raise InputError("not a readable mesh or the mesh is empty")
    polydata = vtk.vtkPolyData()
    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(mesh.vertices, deep=True))
    polydata.SetPoints(points)
    polygons = vtk.vtkCellArray()
    polygons.SetData(numpy_to_vtkIdTypeArray(mesh.offsets, deep=True),
                     numpy_to_vtkIdTypeArray(mesh.connectivity, deep=True))
    polydata.SetPolys(polygons)
    return polydata, mesh.comments


# Mesh files say in which coordinate system their points are as 3D Slicer writes and reads it:
# a field-data string array SPACE (.vtp), or "SPACE=LPS" / "SPACE=RAS" in the header (.vtk, .stl)
# or a comment (.ply, .obj). The library's physical space is LPS, like the images SimpleITK reads;
# a mesh that says RAS is turned into LPS (x and y negated) when read.
SPACE = "SPACE"
COORDINATE_SYSTEM = "LPS"


def coordinate_system_of(notes) -> str | None:
    """"LPS" or "RAS" when one of a mesh file's ``notes`` (its SPACE field data, header or
    comments) says which, else None."""
    for text in notes:
        text = text.upper()
        for system in ("LPS", "RAS"):
            if text == system or f"{SPACE}={system}" in text.replace(" ", ""):
                return system
    return None


def read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3) of a mesh file (:func:`mesh_arrays`), in LPS: a
    file that says its points are RAS (:func:`coordinate_system_of`) is turned into LPS."""
    polydata, notes = _read_polydata(path)
    vertices, faces = mesh_arrays(polydata)
    if coordinate_system_of(notes) == "RAS":
        vertices = vertices * np.array([-1.0, -1.0, 1.0])
    return vertices, faces


def mesh_arrays(polydata) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3) of a vtkPolyData; polygons are triangulated, vertex
    and line cells ignored. Raises :class:`InputError` when there is no triangle."""
    import vtk

    from .surface import polydata_to_arrays

    if polydata is None or polydata.GetNumberOfPoints() == 0:
        raise InputError("the mesh is empty")
    require_valid_cells(polydata)
    triangulate = vtk.vtkTriangleFilter()
    triangulate.SetInputData(polydata)
    triangulate.PassVertsOff()
    triangulate.PassLinesOff()
    triangulate.Update()
    vertices, faces = polydata_to_arrays(triangulate.GetOutput())
    if len(faces) == 0:
        raise InputError("the mesh has no triangles")
    return vertices, faces


def require_valid_cells(polydata):
    """Every cell's points are points of the mesh, its offsets fit its point list, and every
    polygon has three at least (a damaged file may say otherwise; VTK's filters would read
    outside the arrays: a legacy .vtk whose last offset was 9600 for 960 indices crashed
    vtkTriangleFilter)."""
    from vtk.util.numpy_support import vtk_to_numpy

    points = polydata.GetNumberOfPoints()
    for cells in (polydata.GetPolys(), polydata.GetStrips(), polydata.GetLines(),
                  polydata.GetVerts()):
        if cells is None or cells.GetNumberOfCells() == 0:
            continue
        offsets = vtk_to_numpy(cells.GetOffsetsArray())
        indices = vtk_to_numpy(cells.GetConnectivityArray())
        if offsets[0] != 0 or offsets[-1] != indices.size or np.any(np.diff(offsets) < 0):
            raise InputError(f"the cells' offsets (0 to {offsets[-1]}) do not fit their "
                             f"{indices.size} point indices")
        if indices.size and (indices.min() < 0 or indices.max() >= points):
            bad = indices[(indices < 0) | (indices >= points)][0]
            raise InputError(f"a cell refers to point {bad}; the mesh has {points} points")
    polygons = polydata.GetPolys()
    if polygons is not None and polygons.GetNumberOfCells():
        sizes = np.diff(vtk_to_numpy(polygons.GetOffsetsArray()))
        if sizes.min() < 3:
            raise InputError(f"a polygon of only {sizes.min()} point(s)")


def file_digest(path) -> str:
    """SHA-256 of a file's bytes (hex), read in blocks."""
    import hashlib

    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


PARTIAL = ".partial"   # in the name of a file being written (written_whole)


@contextmanager
def written_whole(path):
    """Yield a temporary name beside ``path`` to write to; when the block ends without an error,
    rename it into place (``os.replace``: atomic on one file system), else remove it. So a file
    is whole or absent under its final name, even if the process is killed while writing.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> target = pathlib.Path(tempfile.mkdtemp()) / "table.txt"
    >>> with written_whole(target) as temporary:
    ...     _ = temporary.write_text("whole")
    >>> target.read_text()
    'whole'
    """
    path = Path(path)
    # hidden, marked partial, and ending as the file does (some writers add their suffix)
    temporary = path.with_name(f".{path.stem}.{os.getpid()}{PARTIAL}{path.suffix}")
    try:
        yield temporary
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def earlier_outputs(output, names) -> list[Path]:
    """The entries of ``names`` (a command's files and folders) that ``output`` holds: what an
    earlier run of the command left there; empty when there are none."""
    output = Path(output)
    return [output / name for name in names if (output / name).exists()]


def refuse_earlier(output, earlier: list, overwrite: bool, what: str, also: str = "",
                   error: type = InputError) -> None:
    """The one rule of every command's output folder: a folder that holds an earlier run's
    outputs (``earlier``, :func:`earlier_outputs`) is refused unless ``overwrite``, before any
    work, with the names found; ``what`` names the run ("build", "fit", ...) and ``also`` adds
    another way out (", --resume to carry it on"); ``error`` is the exception raised. An output
    that exists but is not a folder is refused in any case."""
    output = Path(output)
    if output.exists() and not output.is_dir():
        raise InputError(f"{output}: exists and is not a folder")
    if earlier and not overwrite:
        raise error(f"{output} holds an earlier {what} "
                         f"({', '.join(Path(p).name for p in earlier)}): give --overwrite to "
                         f"replace it{also}, or another output folder")


@contextmanager
def written_folder(output, names):
    """Yield a new empty folder beside ``output`` to write a command's outputs into; when the
    block ends without an error they take the place of an earlier run's (the entries of
    ``names`` in ``output`` are removed, then the new ones moved in; a new ``output`` is the
    folder itself, renamed). On an error or an interruption the new folder is removed and
    ``output`` left as it was: a command's outputs are whole or absent, and never mixed with an
    earlier run's."""
    import shutil

    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    # hidden and marked partial, made as mkdir makes folders (mkdtemp's would be private)
    staging = output.parent / f".{output.name}.{os.getpid()}.{os.urandom(4).hex()}{PARTIAL}"
    staging.mkdir()
    try:
        yield staging
        if not output.exists():
            os.replace(staging, output)
            return
        for path in earlier_outputs(output, names):
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
        for path in staging.iterdir():
            os.replace(path, output / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def rejection_lines(rejections, shown: int = 3) -> list[str]:
    """One line per distinct reason of ``rejections`` ((file, reason) pairs), in the order
    first met: ``FILE: REASON`` for a reason of one file, else ``N inputs: REASON (FILE, FILE,
    FILE and K more)`` with the first ``shown`` files. File names and reasons are
    :func:`printable`."""
    by_reason = {}
    for path, reason in rejections:
        by_reason.setdefault(printable(reason), []).append(printable(path))
    lines = []
    for reason, paths in by_reason.items():
        if len(paths) == 1:
            lines.append(f"{paths[0]}: {reason}")
            continue
        more = f" and {len(paths) - shown} more" if len(paths) > shown else ""
        lines.append(f"{len(paths)} inputs: {reason} ({', '.join(paths[:shown])}{more})")
    return lines


def write_text(path, text: str):
    """Write a text file whole or not at all (:func:`written_whole`)."""
    with written_whole(path) as temporary:
        temporary.write_text(text)


def write_polydata(path, vertices: np.ndarray, faces: np.ndarray | None = None,
                   point_data: dict | None = None, lines: np.ndarray | None = None,
                   cell_data: dict | None = None):
    """Write points with triangles (or lines) and optional point and cell arrays (integer
    arrays stay integer) to .vtp/.vtk/.stl/.ply, saying that the points are LPS
    (:data:`COORDINATE_SYSTEM`) where 3D Slicer looks for it; whole or not at all
    (:func:`written_whole`)."""
    # VTK's IO modules alone, not the whole of ``vtk`` (rendering and the rest: about 90 MB
    # more resident in a process that only writes meshes, as a build's does with its files)
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkStringArray
    from vtkmodules.vtkIOGeometry import vtkSTLWriter
    from vtkmodules.vtkIOLegacy import vtkPolyDataWriter
    from vtkmodules.vtkIOPLY import vtkPLYWriter
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    from .surface import arrays_to_polydata

    polydata = arrays_to_polydata(vertices, faces, lines)
    for name, values in (point_data or {}).items():
        array = numpy_to_vtk(np.ascontiguousarray(values, dtype=np.float64), deep=True)
        array.SetName(name)
        polydata.GetPointData().AddArray(array)
    for name, values in (cell_data or {}).items():
        values = np.asarray(values)
        array = numpy_to_vtk(np.ascontiguousarray(
            values, dtype=np.int32 if values.dtype.kind in "iu" else np.float64), deep=True)
        array.SetName(name)
        polydata.GetCellData().AddArray(array)
    suffix = suffix_of(path)
    writers = {".vtp": vtkXMLPolyDataWriter, ".vtk": vtkPolyDataWriter,
               ".stl": vtkSTLWriter, ".ply": vtkPLYWriter}
    if suffix not in writers:
        raise InputError(f"{path}: cannot write meshes of type {suffix!r}")
    writer = writers[suffix]()
    # say the coordinate system as 3D Slicer reads it (see coordinate_system_of)
    if suffix == ".vtp":
        # zlib's fastest level: a build writes two meshes per case, and at VTK's default level
        # (5) compressing them costs about three times as long for files a few percent smaller
        writer.GetCompressor().SetCompressionLevel(1)
        space = vtkStringArray()
        space.SetName(SPACE)
        space.InsertNextValue(COORDINATE_SYSTEM)
        polydata.GetFieldData().AddArray(space)
    elif suffix == ".ply":
        writer.AddComment(f"{SPACE}={COORDINATE_SYSTEM}")
    else:
        writer.SetHeader(f"MDLShapeModel output. {SPACE}={COORDINATE_SYSTEM}")
    writer.SetInputData(polydata)
    with written_whole(path) as temporary:
        writer.SetFileName(str(temporary))
        if not writer.Write():
            raise InputError(f"{path}: could not be written")


def write_csv(path, header, rows):
    """Write a CSV table with a header row (whole or not at all: :func:`written_whole`)."""
    with written_whole(path) as temporary, open(temporary, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))
