"""Closed 2-D curves: reading, checking, and the arc-length parameterization on the circle.

A curve is an array (n, 2) float64 of ordered points in physical coordinates (mm), the polygon
through them closed by the segment from the last point back to the first. Every reader returns it
*clean*: counter-clockwise (positive signed area), no two consecutive points equal, the closing
point not repeated, at least :data:`MIN_POINTS` points, finite, enclosing an area, and simple
(:func:`check_curve`). Readers raise :class:`~mdlshapemodel.errors.InputError` with a one-line
reason; callers add the file name.

The 2-D counterpart of a sphere map is the arc-length parameterization on the unit circle
(:func:`curve_map`, docs/method.md section 1): t = 2 pi s / L, s the arc length from the curve's
origin, L its length. :func:`align_curve_origins` moves the origins of a population so that
equal parameters start as nearly corresponding points.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import MAX_COORDINATE, MAX_VOXELS
from ..errors import InputError
from . import io

#: the fewest points of a usable curve
MIN_POINTS = 8
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
# Geometry of closed polygons


def signed_area(points: np.ndarray) -> float:
    """Signed area of the closed polygon (shoelace formula): positive when counter-clockwise."""
    x, y = points[:, 0], points[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def segment_lengths(points: np.ndarray) -> np.ndarray:
    """Length of each segment k -> k + 1 of the closed polygon (the last one closes it)."""
    return np.linalg.norm(np.roll(points, -1, axis=0) - points, axis=1)


def segment_vertex_lengths(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Half the summed length of the segments around each vertex: eq. 17 in 2-D.

    Parameters
    ----------
    points : ndarray (n, d)
        Vertex positions (e.g. the mean shape's samples, d = 3 with z = 0).
    segments : ndarray (m, 2)
        Vertex indices of each segment.

    Returns
    -------
    ndarray (n,)
        w_k before normalisation; sums to the polygon's length.
    """
    length = np.linalg.norm(points[segments[:, 1]] - points[segments[:, 0]], axis=-1)
    result = np.zeros(len(points))
    for k in range(2):
        np.add.at(result, segments[:, k], 0.5 * length)
    return result


def _orientation(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Twice the signed area of triangles (a, b, c), rowwise: > 0 when counter-clockwise."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - \
           (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _segments_meet(p1, p2, q1, q2) -> np.ndarray:
    """Whether closed segments p1p2 and q1q2 share a point, rowwise (touching counts)."""
    d1, d2 = _orientation(q1, q2, p1), _orientation(q1, q2, p2)
    d3, d4 = _orientation(p1, p2, q1), _orientation(p1, p2, q2)
    straddle = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    collinear = (d1 == 0) & (d2 == 0)
    # collinear segments meet only when their extents overlap along both axes
    overlap = np.ones(len(p1), dtype=bool)
    for axis in range(2):
        overlap &= (np.maximum(np.minimum(p1[:, axis], p2[:, axis]),
                               np.minimum(q1[:, axis], q2[:, axis]))
                    <= np.minimum(np.maximum(p1[:, axis], p2[:, axis]),
                                  np.maximum(q1[:, axis], q2[:, axis])))
    return np.where(collinear, overlap, straddle)


def find_crossing(points: np.ndarray) -> tuple[int, int, tuple[float, float]] | None:
    """Segments i < j (segment k joins point k to k + 1) where the closed polygon touches or
    crosses itself, and a point where they meet; None when the polygon is simple.

    Segments are binned in a uniform grid of cells about the median segment length (coarser
    when long segments would cover more than 16 n cells); only segments sharing a cell are
    tested, so the cost is about O(n) for evenly spaced points (10^4 points: milliseconds). Two consecutive segments cross when the second folds back onto
    the first (a spike).
    """
    n = len(points)
    start, end = points, np.roll(points, -1, axis=0)
    # spikes: consecutive segments that are collinear and point in opposite directions
    a, b = end - start, np.roll(end - start, -1, axis=0)
    spike = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] == 0) & (np.einsum("ij,ij->i", a, b) < 0)
    if np.any(spike):
        k = int(np.flatnonzero(spike)[0])
        i, j = sorted((k, (k + 1) % n))
        return i, j, (float(end[k, 0]), float(end[k, 1]))
    lower, upper = np.minimum(start, end), np.maximum(start, end)
    cell = max(float(np.median(np.linalg.norm(a, axis=1))), 1e-300)
    origin = lower.min(axis=0)
    while True:
        first = np.floor((lower - origin) / cell).astype(np.int64)
        last = np.floor((upper - origin) / cell).astype(np.int64)
        span = last - first + 1
        counts = span[:, 0] * span[:, 1]
        # a few long segments among many short ones would cover too many cells: coarser cells
        if counts.sum() <= 16 * n:
            break
        cell *= 2.0
    segment = np.repeat(np.arange(n), counts)
    offset = np.arange(len(segment)) - np.repeat(np.cumsum(counts) - counts, counts)
    cx = first[segment, 0] + offset % span[segment, 0]
    cy = first[segment, 1] + offset // span[segment, 0]
    key = cx * (int(last[:, 1].max()) + 2) + cy
    order = np.lexsort((segment, key))
    key, segment = key[order], segment[order]
    for gap in range(1, len(key)):
        same = np.flatnonzero(key[gap:] == key[:-gap])
        if len(same) == 0:
            break
        i, j = segment[same], segment[same + gap]
        apart = (np.abs(i - j) > 1) & (np.abs(i - j) != n - 1)   # neighbours share a vertex
        i, j = i[apart], j[apart]
        meet = _segments_meet(start[i], end[i], start[j], end[j])
        if np.any(meet):
            k = int(np.flatnonzero(meet)[0])
            i, j = int(i[k]), int(j[k])
            return min(i, j), max(i, j), _meeting_point(start[i], end[i], start[j], end[j])
    return None


def remove_small_loops(points: np.ndarray, max_fraction: float = 0.01
                       ) -> tuple[np.ndarray, int]:
    """Cut out the small loops of a closed polygon: where it crosses itself and the shorter of
    the two arcs between the crossing is under ``max_fraction`` of its length, that arc is
    replaced by the crossing point (traced outlines often have sub-pixel twists). Returns the
    polygon and the number of loops cut; raises :class:`InputError` at the first larger crossing.
    """
    cut = 0
    while True:
        found = find_crossing(points)
        if found is None:
            return points, cut
        i, j, (x, y) = found
        if j - i == 1 or (i == 0 and j == len(points) - 1):   # a spike: drop its tip
            points = np.delete(points, j if j - i == 1 else 0, axis=0)
            cut += 1
            continue
        lengths = segment_lengths(points)
        inner = float(lengths[i + 1:j].sum())         # the arc from point i + 1 to point j
        if min(inner, float(lengths.sum()) - inner) > max_fraction * float(lengths.sum()):
            raise InputError(f"the curve crosses itself near ({x:.4g}, {y:.4g})")
        crossing = np.array([[x, y]])
        if inner <= lengths.sum() - inner:
            points = np.concatenate([points[:i + 1], crossing, points[j + 1:]])
        else:
            points = np.concatenate([crossing, points[i + 1:j + 1]])
        points = points[np.any(points != np.roll(points, 1, axis=0), axis=1)]
        cut += 1


def _meeting_point(p1, p2, q1, q2) -> tuple[float, float]:
    """Where segments p1p2 and q1q2 meet (an end point of one when they are parallel)."""
    r, s = p2 - p1, q2 - q1
    denominator = r[0] * s[1] - r[1] * s[0]
    if denominator == 0:
        point = q1 if np.all(np.minimum(p1, p2) <= q1) and np.all(q1 <= np.maximum(p1, p2)) else p1
    else:
        t = ((q1 - p1)[0] * s[1] - (q1 - p1)[1] * s[0]) / denominator
        point = p1 + t * r
    return float(point[0]), float(point[1])


def check_curve(points, max_loop: float = 0.01, notes: list | None = None) -> np.ndarray:
    """A clean closed curve from ordered points, or :class:`InputError` saying why not.

    Consecutive equal points and a closing point equal to the first are dropped; the order is
    reversed if needed to make the curve counter-clockwise (the first point kept first); loops
    shorter than ``max_loop`` of the length are cut out (:func:`remove_small_loops`) and, when
    ``notes`` is a list, said there (a repair note for the case's record).

    Raises
    ------
    InputError
        Non-finite or out-of-range coordinates, fewer than :data:`MIN_POINTS` points, zero length
        or area, or a curve that crosses or touches itself beyond a small loop (the message names
        a point where).

    Examples
    --------
    >>> check_curve([(0, 0), (0, 1), (1, 1), (1, 0)])
    Traceback (most recent call last):
    ...
    mdlshapemodel.errors.InputError: the curve has 4 points; a curve needs at least 8
    """
    points = np.array(points, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(points)):
        raise InputError("the curve has non-finite (NaN or infinite) coordinates")
    largest = float(np.abs(points).max()) if points.size else 0.0
    if largest > MAX_COORDINATE:
        raise InputError(f"the curve has a coordinate of {largest:.3g} mm, beyond "
                         f"{MAX_COORDINATE:.0e} (MAX_COORDINATE)")
    keep = np.ones(len(points), dtype=bool)
    keep[1:] = np.any(points[1:] != points[:-1], axis=1)
    points = points[keep]
    if len(points) > 1 and np.all(points[-1] == points[0]):
        points = points[:-1]
    if len(points) < MIN_POINTS:
        raise InputError(f"the curve has {len(points)} points; a curve needs at least "
                         f"{MIN_POINTS}")
    length = float(segment_lengths(points).sum())
    area = signed_area(points)
    if not length > 0:
        raise InputError("the curve has zero length")
    if abs(area) <= 1e-12 * length * length:
        raise InputError("the curve encloses no area (its points are collinear)")
    if area < 0:
        points = np.concatenate([points[:1], points[:0:-1]])
    points, cut = remove_small_loops(points, max_loop)
    if cut and notes is not None:
        notes.append(f"{cut} small loop{'s' if cut > 1 else ''} cut where the curve crossed "
                     "itself")
    if len(points) < MIN_POINTS:
        raise InputError(f"the curve has {len(points)} points; a curve needs at least "
                         f"{MIN_POINTS}")
    return points


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
    from .io import _itk_reading, select_labels

    if not Path(path).is_file():
        raise InputError("no such file")
    integrity.check_image_text_header(path)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    # SimpleITK's errors and what its reader printed -> one InputError, as for 3-D label maps
    with _itk_reading(path):
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

    from .io import _itk_reading

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    with _itk_reading(path):
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
    """A clean closed 2-D curve (n, 2) from a curve file (:func:`check_curve`).

    Parameters
    ----------
    path : str or Path
        .csv/.txt (x y per row), .vtk/.vtp (one closed polyline, constant z), or a label image
        with one slice (.png, .nii, .nii.gz, .nrrd, .mha): the outline of its labelled region.
    labels : sequence of int
        For label images: the labels of the region (all non-zero labels when empty).
    notes : list, optional
        Receives a line for each repair made (:func:`check_curve`).

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


# ------------------------------------------------------------------------------------------------
# The arc-length parameterization on the circle


@dataclass
class CurveMap:
    """A closed curve and its arc-length parameterization on the unit circle.

    Attributes
    ----------
    points : ndarray (n, 2)
        The clean curve (counter-clockwise), points[0] its origin.
    parameter : ndarray (n,)
        t_k = 2 pi s_k / L in [0, 2 pi), s_k the arc length from points[0]; t[0] = 0.
    length : float
        L, the curve's length.
    """

    points: np.ndarray
    parameter: np.ndarray
    length: float


def curve_map(points) -> CurveMap:
    """The arc-length parameterization of a clean closed curve (section III-A in 2-D).

    S(t) is the point at arc length L t / (2 pi) from the origin points[0], linear between the
    points; a homeomorphism of the circle onto the curve, with |dS/dt| = L / (2 pi).
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    lengths = segment_lengths(points)
    length = float(lengths.sum())
    parameter = np.concatenate([[0.0], np.cumsum(lengths[:-1])]) * (2.0 * np.pi / length)
    return CurveMap(points, parameter, length)


def resample_curve(points, count: int, start: float = 0.0) -> np.ndarray:
    """``count`` points equally spaced in arc length along a closed curve, the first at the
    fraction ``start`` of its length from points[0] (e.g. to take a corresponded population out
    of correspondence)."""
    mapped = curve_map(points)
    targets = (2.0 * np.pi * (start + np.arange(count) / count)) % (2.0 * np.pi)
    return point_at(mapped, targets)


def point_at(mapped: CurveMap, parameters: np.ndarray) -> np.ndarray:
    """S(t) (m, 2) at parameters t (any real numbers: taken modulo 2 pi)."""
    t = np.mod(np.asarray(parameters, dtype=np.float64), 2.0 * np.pi)
    knots = np.append(mapped.parameter, 2.0 * np.pi)
    closed = np.vstack([mapped.points, mapped.points[:1]])
    return np.stack([np.interp(t, knots, closed[:, d]) for d in range(2)], axis=1)


def shift_origin(mapped: CurveMap, shift: float) -> CurveMap:
    """The same curve with its origin moved to parameter ``shift``: a point inserted there
    (unless one is there already) and the points rolled so that it comes first."""
    shift = float(np.mod(shift, 2.0 * np.pi))
    index = int(np.searchsorted(mapped.parameter, shift, side="right"))
    if mapped.parameter[index - 1] == shift:
        points = np.roll(mapped.points, -(index - 1), axis=0)
    else:
        origin = point_at(mapped, np.array([shift]))
        points = np.vstack([origin, mapped.points[index:], mapped.points[:index]])
    return curve_map(points)


def _correlation_shift(reference: np.ndarray, samples: np.ndarray) -> float:
    """The cyclic shift (in samples, fractional) of ``samples`` that best matches ``reference``
    after a similarity transform: both are complex, centred, equally spaced in arc length; the
    best rotation and scale for shift m give residual |r|^2 - |c_m|^2 / |x|^2 with
    c_m = sum_k conj(x_{k+m}) r_k, a cyclic cross-correlation (FFT)."""
    count = len(reference)
    c = np.fft.ifft(np.fft.fft(reference) * np.conj(np.fft.fft(samples)))
    # c[m] = sum_k r_k conj(x_{k-m}): the shift that rolls x onto r is -m
    power = np.abs(c)
    m = int(np.argmax(power))
    left, centre, right = power[(m - 1) % count], power[m], power[(m + 1) % count]
    curvature = left - 2.0 * centre + right
    fraction = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
    return m + fraction


def align_curve_origins(maps: list, samples: int = 512, rounds: int = 2) -> list:
    """Move each curve's origin so that equal arc-length parameters start in correspondence.

    Each curve is sampled at ``samples`` points equally spaced in arc length; the origin shift
    that best matches the reference after the best rotation and scale (a proper similarity:
    curves are all counter-clockwise, so no reflection is needed) is found for all shifts at once
    by a cross-correlation (:func:`_correlation_shift`), refined to a fraction of a sample. The
    reference is the first curve, then (``rounds`` > 1) the mean of the aligned samples.

    Why not leave the origins to the optimiser: a curve's origin error is a rigid rotation of
    its parameter circle, which costs the optimiser many kernel steps to undo (every kernel
    fixes two points of the circle) and can trap it in a local minimum half a shape away; the
    correlation finds the globally best shift in O(n log n). Principal axes (the sphere's
    first-order alignment) are ambiguous for near-round or symmetric shapes; the correlation
    uses the whole outline.

    Returns new :class:`CurveMap` objects (the inputs are unchanged).
    """
    sampled = []
    for mapped in maps:
        z = point_at(mapped, 2.0 * np.pi * np.arange(samples) / samples)
        z = z[:, 0] + 1j * z[:, 1]
        sampled.append(z - z.mean())
    shifts = np.zeros(len(maps))
    reference = sampled[0]
    for _ in range(rounds):
        aligned = []
        for k, z in enumerate(sampled):
            shifts[k] = _correlation_shift(reference, z)
            rolled = _roll_fraction(z, shifts[k])
            # the best similarity onto the reference: rolled * <rolled, reference> / |rolled|^2
            aligned.append(rolled * (np.vdot(rolled, reference) / np.vdot(rolled, rolled)))
        reference = np.mean(aligned, axis=0)
    return [shift_origin(mapped, -2.0 * np.pi * shift / samples)
            for mapped, shift in zip(maps, shifts)]


def _roll_fraction(z: np.ndarray, shift: float) -> np.ndarray:
    """z rolled by a fractional number of samples (linear interpolation): result[k] = z[k - shift]."""
    count = len(z)
    position = (np.arange(count) - shift) % count
    low = np.floor(position).astype(np.int64)
    fraction = position - low
    return (1.0 - fraction) * z[low % count] + fraction * z[(low + 1) % count]


def point_curve_distances(points: np.ndarray, curve_points: np.ndarray, segments: np.ndarray,
                          chunk: int = 4096) -> np.ndarray:
    """Distance from each point (n, 2 or 3) to the nearest of the segments (m, 2) joining
    ``curve_points``: the 2-D counterpart of :func:`.surface.point_surface_distances`."""
    points = np.asarray(points, dtype=np.float64)
    a = np.asarray(curve_points, dtype=np.float64)[segments[:, 0]]
    edge = np.asarray(curve_points, dtype=np.float64)[segments[:, 1]] - a
    squared = np.maximum(np.einsum("md,md->m", edge, edge), 1e-300)
    result = np.empty(len(points))
    for start in range(0, len(points), chunk):
        offset = points[start:start + chunk, None, :] - a[None]
        t = np.clip(np.einsum("nmd,md->nm", offset, edge) / squared, 0.0, 1.0)
        nearest = offset - t[..., None] * edge[None]
        result[start:start + chunk] = np.sqrt(np.einsum("nmd,nmd->nm", nearest, nearest)
                                              .min(axis=1))
    return result
