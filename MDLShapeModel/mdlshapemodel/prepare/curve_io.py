"""Reading closed 2-D curves: point tables, polylines and one-slice label images.

Every reader returns the curve as :mod:`.curve` defines it, an array (n, 2) float64 of ordered
points in physical coordinates (mm); :func:`read_curve` makes it clean
(:func:`.curve.check_curve`). Readers raise :class:`~mdlshapemodel.errors.InputError` with a
one-line reason; callers add the file name. :func:`is_curve_file` tells a curve file from a
surface's or a volume's by its extension and a cheap look at its header.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..config import MAX_VOXELS
from ..errors import InputError
from . import io
from .curve import MIN_POINTS, check_curve, segment_lengths

#: table files (x y per row)
TABLE_SUFFIXES = (".csv", ".txt")
#: polydata files that hold a curve when they have lines and no polygons
POLYLINE_SUFFIXES = (".vtk", ".vtp")
#: image files that hold a curve's region when they have one slice
CURVE_IMAGE_SUFFIXES = (".png", ".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")
#: a table curve whose closing segment is longer than this many times the median segment (and
#: twice the longest other one) is taken to be open
OPEN_GAP = 5.0
#: the Gaussian blur (pixels) of a label image's region before its outline is taken
IMAGE_SMOOTHING_SIGMA = 0.7


# ------------------------------------------------------------------------------------------------
# Chaining line segments into closed loops


def chain_loops(points: np.ndarray, segments: np.ndarray, tolerance: float = 0.0) -> list:
    """The closed loops formed by line segments, as arrays of point coordinates.

    Points with equal coordinates are merged first (several line cells sharing end points). A
    loop follows the direction of its first segment in ``segments``. A chain whose two ends lie
    within ``tolerance`` of each other is closed.

    Raises
    ------
    InputError
        When the lines branch (a point on more than two segments) or a chain is open.
    """
    points = np.asarray(points, dtype=np.float64)
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    segments = inverse.ravel()[np.asarray(segments, dtype=np.int64)].reshape(-1, 2)
    segments = segments[segments[:, 0] != segments[:, 1]]
    if len(segments) == 0:
        raise InputError("the file has no line segments")
    # the same segment twice (in either direction) once
    _, first = np.unique(np.sort(segments, axis=1), axis=0, return_index=True)
    segments = segments[np.sort(first)]
    degree = np.bincount(segments.ravel(), minlength=len(unique))
    if degree.max() > 2:
        x, y = unique[int(np.argmax(degree > 2))][:2]
        raise InputError(f"the lines branch at ({x:.4g}, {y:.4g}); a curve is one closed chain")
    neighbours = np.full((len(unique), 2), -1, dtype=np.int64)
    filled = np.zeros(len(unique), dtype=np.int64)
    for a, b in segments:
        neighbours[a, filled[a]] = b
        filled[a] += 1
        neighbours[b, filled[b]] = a
        filled[b] += 1
    ends = np.flatnonzero(degree == 1)
    if len(ends) > 2:
        raise InputError(f"the lines form {len(ends) // 2} open pieces; a curve is one closed "
                         "chain")
    if len(ends):
        gap = float(np.linalg.norm(unique[ends[0]] - unique[ends[1]]))
        if len(ends) == 2 and gap <= tolerance:
            a, b = ends
            neighbours[a, 1], neighbours[b, 1] = b, a
        else:
            raise InputError(f"the curve is open: its ends are {gap:.4g} mm apart")
    visited = np.zeros(len(unique), dtype=bool)
    loops = []
    for a, b in segments:
        if visited[a]:
            continue
        loop, previous, current = [a], a, b
        visited[a] = True
        while current != a:
            loop.append(current)
            visited[current] = True
            following = neighbours[current, 0]
            if following == previous:
                following = neighbours[current, 1]
            previous, current = current, following
        loops.append(unique[np.array(loop)])
    return loops


def _one_loop(loops: list) -> np.ndarray:
    if len(loops) != 1:
        raise InputError(f"{len(loops)} separate curves; a 2-D curve file must hold one closed "
                         "curve")
    return loops[0]


def _planar_xy(points: np.ndarray) -> np.ndarray:
    """x, y of 3-D points whose z is constant (to rounding of the coordinates)."""
    points = np.asarray(points, dtype=np.float64)
    if points.shape[1] == 3:
        z = points[:, 2]
        spread = float(np.ptp(z)) if np.all(np.isfinite(z)) else np.inf
        scale = max(float(np.ptp(points[:, :2], axis=0).max()), float(np.abs(z).max()), 1.0)
        if spread > 1e-9 * scale:
            raise InputError(f"the curve is not planar: z varies by {spread:.4g} mm (a 2-D curve "
                             "has constant z)")
    return points[:, :2]


# ------------------------------------------------------------------------------------------------
# Readers


def read_curve_table(path) -> np.ndarray:
    """Points x y per row of a .csv/.txt file (comma, semicolon, space or tab separated).

    An optional first line of non-numbers (a header) and lines starting with ``#`` are skipped;
    a third column z is allowed when constant. The curve is closed by joining the last point to
    the first. A last row repeating the first says so explicitly; without it a closing gap longer
    than :data:`OPEN_GAP` times the median segment and twice the longest other segment means the
    curve is open. Returns the raw points (n, 2); see :func:`read_curve` for the clean curve.
    """
    rows, width = [], None
    with open(path, encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = [f for f in re.split(r"[,;\s]+", text) if f]
            try:
                values = [float(f) for f in fields]
            except ValueError:
                if not rows and width is None:
                    width = 0           # the header line
                    continue
                raise InputError(f"line {number} is not numbers: {text[:60]!r}") from None
            if len(values) not in (2, 3):
                raise InputError(f"line {number} has {len(values)} values; expected x y "
                                 "(or x y z)")
            if rows and len(values) != len(rows[0]):
                raise InputError(f"line {number} has {len(values)} values, line 1 of the data "
                                 f"{len(rows[0])}")
            rows.append(values)
    if not rows:
        raise InputError("the file holds no points")
    points = _planar_xy(np.array(rows, dtype=np.float64))
    if len(points) > 2 and np.all(points[-1] == points[0]):
        return points[:-1]
    lengths = segment_lengths(points)
    if len(points) >= MIN_POINTS and np.all(np.isfinite(lengths)):
        gap, others = lengths[-1], lengths[:-1]
        if gap > OPEN_GAP * np.median(others) and gap > 2.0 * others.max():
            raise InputError(f"the curve is open: its ends are {gap:.4g} mm apart")
    return points


def read_curve_polydata(path) -> np.ndarray:
    """The one closed polyline of a .vtk/.vtp polydata with constant z, as points (n, 2).

    The line cells may be one polyline (closed when its last point id is its first, or its first
    and last points coincide) or several forming one closed chain, in any order and direction.
    """
    from vtk.util.numpy_support import vtk_to_numpy

    from .io import read_polydata

    polydata = read_polydata(path)
    if polydata.GetNumberOfPolys() or polydata.GetNumberOfStrips():
        raise InputError("the mesh has polygons; a 2-D curve file holds a closed polyline")
    lines = polydata.GetLines()
    if lines is None or lines.GetNumberOfCells() == 0:
        raise InputError("the file has no lines; a 2-D curve file holds a closed polyline")
    points = _planar_xy(vtk_to_numpy(polydata.GetPoints().GetData()))
    if not np.all(np.isfinite(points)):
        raise InputError("the curve has non-finite (NaN or infinite) coordinates")
    offsets = vtk_to_numpy(lines.GetOffsetsArray()).astype(np.int64)
    ids = vtk_to_numpy(lines.GetConnectivityArray()).astype(np.int64)
    # consecutive ids within each cell are segments
    pairs = np.stack([ids[:-1], ids[1:]], axis=1)
    within = np.ones(len(pairs), dtype=bool)
    within[offsets[1:-1] - 1] = False
    size = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    return _one_loop(chain_loops(points, pairs[within], tolerance=1e-9 * max(size, 1e-300)))


def _image_geometry(size, spacing, origin, direction) -> tuple[int, np.ndarray]:
    """For an image with one slice: the singleton axis (None for a 2-D image) and the 3 x 3 (or
    2 x 2) matrix index -> physical (direction times spacing)."""
    dimension = len(size)
    matrix = np.reshape(direction, (dimension, dimension)) * np.asarray(spacing)[None, :]
    if dimension == 2:
        return None, matrix
    singleton = [k for k in range(dimension) if size[k] == 1]
    if dimension != 3 or len(singleton) != 1:
        shape = " x ".join(str(n) for n in size)
        raise InputError(f"a {dimension}-D image ({shape}); a 2-D label image has one slice")
    return singleton[0], matrix


def read_label_region(path, labels=()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mask (ny, nx) of the labelled region of a 2-D or one-slice label image, the matrix
    (3, 2) or (2, 2) from pixel index (i along x, j along y) to physical offset, and the physical
    origin. The mask is one region, holes filled."""
    import SimpleITK as sitk
    from scipy import ndimage

    from . import integrity
    from .io import itk_reading, select_labels

    if not Path(path).is_file():
        raise InputError("no such file")
    integrity.check_image_text_header(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    # SimpleITK's errors and what its reader printed -> one InputError, as for 3-D label maps
    with itk_reading(path):
        reader.ReadImageInformation()
        size = reader.GetSize()
        singleton, matrix = _image_geometry(size, reader.GetSpacing(), reader.GetOrigin(),
                                            reader.GetDirection())
        if int(np.prod(size)) > MAX_VOXELS:
            raise InputError(f"the header claims {int(np.prod(size)):,} pixels; at most "
                             f"{MAX_VOXELS:,} (MAX_VOXELS: memory)")
        if not np.all(np.isfinite(matrix)) or not np.all(np.isfinite(reader.GetOrigin())):
            raise InputError("the header's spacing, origin or direction is not a number")
        pixel = sitk.GetPixelIDValueAsString(reader.GetPixelID())
        bits = int(re.search(r"(\d+)-bit", pixel).group(1)) if "bit" in pixel else 64
        integrity.check_image_data(
            path, int(np.prod(size)) * reader.GetNumberOfComponents() * bits // 8)
        image = reader.Execute()
    array = _grey(sitk.GetArrayFromImage(image), image.GetNumberOfComponentsPerPixel())
    origin = np.asarray(image.GetOrigin(), dtype=np.float64)
    if singleton is not None:
        # numpy axes are (z, y, x): drop the singleton one; keep the in-plane index axes
        array = array.reshape([n for k, n in enumerate(reversed(size))
                               if len(size) - 1 - k != singleton])
        matrix = np.delete(matrix, singleton, axis=1)
    mask = select_labels(array, labels)
    regions, count = ndimage.label(mask, structure=np.ones((3, 3)))
    if count > 1:
        sizes = np.sort(np.bincount(regions.ravel())[1:])[::-1]
        listed = ", ".join(str(int(s)) for s in sizes[:5]) + (", ..." if count > 5 else "")
        raise InputError(f"{count} separate regions ({listed} pixels); a 2-D label image must "
                         "hold one region")
    return ndimage.binary_fill_holes(mask), matrix, origin


def pixel_size(path) -> float | None:
    """The side (mm) of a square of a label image's pixel area (the geometric mean of its two
    in-plane spacings), or None for a curve file that is not an image. Reads the header only."""
    if io.suffix_of(path) not in CURVE_IMAGE_SUFFIXES:
        return None
    import SimpleITK as sitk

    from .io import itk_reading

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    with itk_reading(path):
        reader.ReadImageInformation()
    singleton, matrix = _image_geometry(reader.GetSize(), reader.GetSpacing(),
                                        reader.GetOrigin(), reader.GetDirection())
    if singleton is not None:
        matrix = np.delete(matrix, singleton, axis=1)
    columns = np.linalg.norm(matrix, axis=0)
    return float(np.sqrt(np.prod(columns[:2])))


def _grey(array: np.ndarray, components: int) -> np.ndarray:
    """One value per pixel: a grey picture saved in colour (equal red, green and blue; an alpha
    channel ignored) gives its first channel; other colour pictures are rejected."""
    if components == 1:
        return array
    colours = array[..., :min(components, 3)]
    if np.any(colours != colours[..., :1]):
        raise InputError(f"a colour image ({components} values per pixel); a 2-D label image "
                         "has one value per pixel")
    return array[..., 0]


def _in_plane(physical: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """2-D coordinates of physical points in an axis-aligned plane: (x, y) for an axial slice,
    (y, z) for a sagittal one, (z, x) for a coronal one (right-handed about the axis)."""
    axis = int(np.argmax(np.abs(normal)))
    if abs(normal[axis]) < (1.0 - 1e-6) * np.linalg.norm(normal):
        raise InputError("an oblique slice; a 2-D label image must lie in an axial, coronal or "
                         "sagittal plane")
    keep = [(axis + 1) % 3, (axis + 2) % 3]
    return physical[:, keep]


def region_outline(mask: np.ndarray, sigma: float = IMAGE_SMOOTHING_SIGMA,
                   smoothing_steps: int = 10) -> np.ndarray:
    """The sub-pixel outline of a 2-D mask (ny, nx) in pixel index coordinates (i along x).

    The mask is blurred (Gaussian, ``sigma`` pixels) and contoured at 0.5 (VTK's flying edges in
    2-D); the longest loop is kept (a blur may split off a speck) and smoothed lightly by
    ``smoothing_steps`` Taubin steps (lambda 0.5, mu -0.53), which keep its size.
    """
    import vtk
    from scipy import ndimage
    from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

    pad = int(np.ceil(3 * sigma)) + 2
    field = ndimage.gaussian_filter(np.pad(mask.astype(np.float64), pad), sigma, mode="constant")
    image = vtk.vtkImageData()
    image.SetDimensions(field.shape[1], field.shape[0], 1)
    image.GetPointData().SetScalars(numpy_to_vtk(field.ravel(), deep=True))
    contour = vtk.vtkFlyingEdges2D()
    contour.SetInputData(image)
    contour.SetValue(0, 0.5)
    contour.Update()
    output = contour.GetOutput()
    if output.GetNumberOfCells() == 0:
        raise InputError("the region is too small to outline")
    points = vtk_to_numpy(output.GetPoints().GetData())[:, :2] - pad
    ids = vtk_to_numpy(output.GetLines().GetConnectivityArray()).astype(np.int64)
    loops = chain_loops(points, ids.reshape(-1, 2))
    outline = max(loops, key=lambda loop: float(segment_lengths(loop).sum()))
    for _ in range(smoothing_steps):
        for factor in (0.5, -0.53):
            neighbours = 0.5 * (np.roll(outline, 1, axis=0) + np.roll(outline, -1, axis=0))
            outline = outline + factor * (neighbours - outline)
    return outline


def read_curve_image(path, labels=(), sigma: float = IMAGE_SMOOTHING_SIGMA) -> np.ndarray:
    """The outline (n, 2), in physical coordinates, of the one labelled region of a 2-D label
    image (.png) or a one-slice volume (.nii/.nii.gz/.nrrd/.mha): :func:`read_label_region`,
    then :func:`region_outline`. The labels are ``labels`` (all non-zero ones when empty)."""
    mask, matrix, origin = read_label_region(path, labels)
    outline = region_outline(mask, sigma)
    physical = origin[None, :] + outline @ matrix.T
    if len(origin) == 3:
        normal = np.cross(matrix[:, 0], matrix[:, 1])
        physical = _in_plane(physical, normal)
    return physical


def read_curve(path, labels=(), notes: list | None = None) -> np.ndarray:
    """A clean closed 2-D curve (n, 2) from a curve file (:func:`.curve.check_curve`).

    Parameters
    ----------
    path : str or Path
        .csv/.txt (x y per row), .vtk/.vtp (one closed polyline, constant z), or a label image
        with one slice (.png, .nii, .nii.gz, .nrrd, .mha): the outline of its labelled region.
    labels : sequence of int
        For label images: the labels of the region (all non-zero labels when empty).
    notes : list, optional
        Receives a line for each repair made (:func:`.curve.check_curve`).

    Raises
    ------
    InputError
        One line naming the problem (the caller adds the file name).
    """
    suffix = io.suffix_of(path)
    if not Path(path).is_file():
        raise InputError("no such file")
    if suffix in TABLE_SUFFIXES:
        points = read_curve_table(path)
    elif suffix in POLYLINE_SUFFIXES:
        points = read_curve_polydata(path)
    elif suffix in CURVE_IMAGE_SUFFIXES:
        points = read_curve_image(path, labels)
    else:
        raise InputError(f"not a 2-D curve file (unknown type {Path(path).suffix!r})")
    return check_curve(points, notes=notes)


def is_curve_file(path) -> bool:
    """Whether a file holds a 2-D curve, by its extension and a cheap look at its header.

    .csv and .txt always; .vtk/.vtp when the polydata has lines and no polygons (the legacy
    file's section keywords, the XML file's piece counts); images when they have two dimensions
    or one of their three is of size 1 (the header only). False for missing or unreadable files.
    """
    suffix = io.suffix_of(path)
    try:
        if suffix in TABLE_SUFFIXES:
            return True
        if suffix == ".vtp":
            with open(path, "rb") as handle:
                head = handle.read(1 << 16)
            counts = {name: int(value) for name, value in
                      re.findall(rb'NumberOf(Lines|Polys|Strips)="(\d+)"', head)}
            return counts.get(b"Lines", 0) > 0 and not counts.get(b"Polys", 0) \
                and not counts.get(b"Strips", 0)
        if suffix == ".vtk":
            import mmap

            with open(path, "rb") as handle, \
                    mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                return (data.find(b"\nLINES ") >= 0 and data.find(b"\nPOLYGONS ") < 0
                        and data.find(b"\nTRIANGLE_STRIPS ") < 0)
        if suffix in CURVE_IMAGE_SUFFIXES:
            import SimpleITK as sitk

            from . import integrity
            from .io import captured_native_stderr

            # a header SimpleITK would choke on (an NDims of -1 hangs its reader) is no curve's:
            # the 3-D reader rejects it with its reason
            integrity.check_image_text_header(path)
            reader = sitk.ImageFileReader()
            reader.SetFileName(str(path))
            with captured_native_stderr():
                reader.ReadImageInformation()
            size = reader.GetSize()
            return len(size) == 2 or (len(size) == 3 and sorted(size)[0] == 1
                                      and sorted(size)[1] > 1)
    except (OSError, ValueError, RuntimeError, InputError):
        return False
    return False
