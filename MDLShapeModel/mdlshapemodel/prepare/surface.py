"""Closed surfaces: label map -> triangle mesh, cleaning and topology checks.

A surface is a pair of arrays ``(vertices, faces)``: ``vertices`` is (n, 3) float64 in physical
coordinates (mm), ``faces`` is (m, 3) int64, counter-clockwise seen from outside (normals point out).
Everything downstream requires one closed, manifold, genus-0 component (Euler characteristic 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from ..config import (MAX_COORDINATE, SURFACE_METHODS, SURFACE_POINTS, BuildConfig,
                      max_smoothing_for, target_vertices_for)
from ..errors import ArgumentError, SurfaceError
from .nearest import TriangleGrid


@dataclass
class Topology:
    """Topological summary of a triangle mesh."""

    n_vertices: int
    n_faces: int
    n_edges: int
    n_components: int
    n_boundary_edges: int
    n_nonmanifold_edges: int
    consistently_oriented: bool

    @property
    def euler_characteristic(self) -> int:
        return self.n_vertices - self.n_edges + self.n_faces

    @property
    def is_closed_manifold(self) -> bool:
        return self.n_boundary_edges == 0 and self.n_nonmanifold_edges == 0

    @property
    def is_sphere_like(self) -> bool:
        """One closed, manifold, orientable component with Euler characteristic 2 (genus 0)."""
        return (self.is_closed_manifold and self.n_components == 1 and self.consistently_oriented
                and self.euler_characteristic == 2)

    def describe(self) -> str:
        """A one-line reason why the mesh is not sphere-like (empty if it is)."""
        problems = []
        if self.n_faces == 0:
            return "the surface is empty"
        if self.n_components != 1:
            problems.append(f"{self.n_components} disconnected components")
        if self.n_boundary_edges:
            problems.append(f"{self.n_boundary_edges} boundary edges (holes)")
        if self.n_nonmanifold_edges:
            problems.append(f"{self.n_nonmanifold_edges} non-manifold edges")
        if not problems and not self.consistently_oriented:
            problems.append("inconsistently oriented faces")
        if not problems and self.euler_characteristic != 2:
            genus = (2 - self.euler_characteristic) // 2
            problems.append(f"Euler characteristic {self.euler_characteristic} (genus {genus}), "
                            "not a sphere")
        return "; ".join(problems)


def edges_of(faces: np.ndarray) -> np.ndarray:
    """The directed edges (3m, 2) of the faces, in face order."""
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def topology(vertices: np.ndarray, faces: np.ndarray) -> Topology:
    """Count components, boundary and non-manifold edges, and check orientation."""
    faces = np.asarray(faces, dtype=np.int64)
    n_vertices = len(vertices)
    if len(faces) == 0:
        return Topology(n_vertices, 0, 0, 0, 0, 0, True)
    directed = edges_of(faces)
    # one integer key per undirected edge: a 1-D unique is several times faster than rows
    size = max(n_vertices, int(faces.max()) + 1)
    keys = np.minimum(directed[:, 0], directed[:, 1]) * size + np.maximum(directed[:, 0],
                                                                           directed[:, 1])
    unique_keys, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    unique = np.stack(np.divmod(unique_keys, size), axis=1)
    used = np.unique(faces)
    graph = sparse.coo_matrix((np.ones(len(unique)), (unique[:, 0], unique[:, 1])),
                              shape=(n_vertices, n_vertices))
    n_labels, labels = csgraph.connected_components(graph, directed=False)
    n_components = len(np.unique(labels[used]))
    # Each interior edge must be traversed once in each direction by its two faces.
    forward = directed[:, 0] < directed[:, 1]
    per_edge_forward = np.bincount(inverse, weights=forward, minlength=len(unique))
    two = counts == 2
    oriented = bool(np.all(per_edge_forward[two] == 1))
    return Topology(n_vertices=len(used), n_faces=len(faces), n_edges=len(unique),
                    n_components=n_components, n_boundary_edges=int(np.sum(counts == 1)),
                    n_nonmanifold_edges=int(np.sum(counts > 2)), consistently_oriented=oriented)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed mesh; positive when the normals point outwards."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return float(np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6.0)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of every triangle."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def triangle_vertex_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """One third of the summed area of the triangles around each vertex (eq. 17)."""
    a, b, c = (points[..., triangles[:, k], :] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    result = np.zeros(points.shape[:-1])
    for k in range(3):
        np.add.at(result.T, triangles[:, k], area.T / 3.0)
    return result


def largest_component(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keep the connected component with most faces; drop unused vertices."""
    if len(faces) == 0:
        return vertices[:0], faces
    edges = edges_of(faces)
    graph = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])),
                              shape=(len(vertices), len(vertices)))
    _, labels = csgraph.connected_components(graph, directed=False)
    face_labels = labels[faces[:, 0]]
    keep = face_labels == np.bincount(face_labels).argmax()
    return compact(vertices, faces[keep])


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses and renumber the faces."""
    used, new_faces = np.unique(faces, return_inverse=True)
    return vertices[used], new_faces.reshape(faces.shape).astype(np.int64)


def drop_degenerate_faces(vertices: np.ndarray, faces: np.ndarray,
                          relative_area: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Remove faces with a repeated vertex or (near-)zero area, then unused vertices."""
    faces = np.asarray(faces, dtype=np.int64)
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[distinct]
    if len(faces) == 0:
        return vertices[:0], faces
    areas = face_areas(vertices, faces)
    faces = faces[areas > relative_area * max(np.median(areas), 1e-300)]
    return compact(vertices, faces)


def orient_outwards(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces reordered so that the enclosed volume is positive (normals out)."""
    if signed_volume(vertices, faces) < 0:
        return faces[:, [0, 2, 1]].copy()
    return faces


def make_orientation_consistent(vertices: np.ndarray, faces: np.ndarray
                                ) -> tuple[np.ndarray, int]:
    """Reorder faces so that neighbours agree in orientation (breadth-first over shared edges).

    Returns the faces and how many were flipped. A non-orientable mesh keeps some disagreement,
    which :func:`topology` still reports.
    """
    faces = np.asarray(faces, dtype=np.int64).copy()
    m = len(faces)
    if m == 0:
        return faces, 0
    directed = edges_of(faces)
    key = np.sort(directed, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    pairs = np.flatnonzero(np.all(key[order][1:] == key[order][:-1], axis=1))
    first, second = order[pairs] % m, order[pairs + 1] % m
    # neighbours agree when they traverse their shared edge in opposite directions
    same_direction = np.all(directed[order[pairs]] == directed[order[pairs + 1]], axis=1)
    relation = sparse.coo_matrix((same_direction.astype(float) + 1.0, (first, second)),
                                 shape=(m, m)).tocsr()
    relation = relation + relation.T  # 1: consistent, 2: one of the two must flip
    flip = np.zeros(m, dtype=bool)
    seen = np.zeros(m, dtype=bool)
    for root in range(m):
        if seen[root]:
            continue
        seen[root] = True
        queue = [root]
        while queue:
            face = queue.pop()
            start, stop = relation.indptr[face], relation.indptr[face + 1]
            for neighbour, kind in zip(relation.indices[start:stop], relation.data[start:stop]):
                if not seen[neighbour]:
                    seen[neighbour] = True
                    flip[neighbour] = flip[face] ^ (kind == 2)
                    queue.append(neighbour)
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces, int(flip.sum())


def require_coordinates(vertices: np.ndarray, what: str = "surface"):
    """Raise :class:`SurfaceError` unless every coordinate is finite and within
    :data:`~mdlshapemodel.config.MAX_COORDINATE` mm."""
    if not np.all(np.isfinite(vertices)):
        raise SurfaceError(f"the {what} has non-finite (NaN or infinite) coordinates")
    largest = float(np.abs(vertices).max()) if vertices.size else 0.0
    if largest > MAX_COORDINATE:
        raise SurfaceError(f"the {what} has a coordinate of {largest:.3g} mm, beyond "
                           f"{MAX_COORDINATE:.0e} (MAX_COORDINATE)")


def require_sphere_like(vertices: np.ndarray, faces: np.ndarray) -> Topology:
    """Raise :class:`SurfaceError` unless the mesh is one closed genus-0 component."""
    require_coordinates(vertices)
    topo = topology(vertices, faces)
    if not topo.is_sphere_like:
        raise SurfaceError(topo.describe())
    return topo


def polydata_to_arrays(polydata) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) and triangles (m, 3) of a vtkPolyData whose polygons are triangles."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if polydata.GetNumberOfPoints() == 0 or polydata.GetNumberOfPolys() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    vertices = vtk_to_numpy(polydata.GetPoints().GetData()).astype(np.float64)
    polys = polydata.GetPolys()
    offsets = vtk_to_numpy(polys.GetOffsetsArray())
    connectivity = vtk_to_numpy(polys.GetConnectivityArray())
    if not np.all(np.diff(offsets) == 3):
        raise SurfaceError("the surface has polygons that are not triangles")
    return vertices, connectivity.reshape(-1, 3).astype(np.int64)




def _contour(field: np.ndarray, stride: int = 1):
    """Flying-edges isosurface at 0.5 of a (z, y, x) array sampled on every ``stride``-th voxel
    (:func:`blurred`), in voxel-index coordinates."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    field = np.ascontiguousarray(field)
    image = vtkImageData()
    image.SetDimensions(field.shape[2], field.shape[1], field.shape[0])
    image.SetSpacing(stride, stride, stride)
    image.GetPointData().SetScalars(numpy_to_vtk(field.ravel(), deep=True))
    contour = vtkFlyingEdges3D()
    contour.SetInputData(image)
    contour.SetValue(0, 0.5)
    contour.ComputeNormalsOff()
    contour.ComputeGradientsOff()
    contour.Update()
    return contour.GetOutput()


def slicer_smoothing(polydata, smoothing_factor: float, decimation: float = 0.0):
    """3D Slicer's closed-surface post-processing: optional decimation (topology preserved), then
    windowed-sinc smoothing with pass band 10^(-4 s) and 20 + 40 s iterations (s: smoothing factor,
    Slicer's default 0.5)."""
    from vtkmodules.vtkFiltersCore import vtkDecimatePro, vtkWindowedSincPolyDataFilter

    if decimation > 0:
        decimator = vtkDecimatePro()
        decimator.SetInputData(polydata)
        decimator.SplittingOff()
        decimator.PreserveTopologyOn()
        decimator.SetMaximumError(1)
        decimator.SetTargetReduction(decimation)
        decimator.Update()
        polydata = decimator.GetOutput()
    if smoothing_factor <= 0:
        return polydata
    smoother = vtkWindowedSincPolyDataFilter()
    smoother.SetInputData(polydata)
    smoother.SetNumberOfIterations(int(20 + 40 * smoothing_factor))
    smoother.SetPassBand(10.0 ** (-4.0 * smoothing_factor))
    smoother.BoundarySmoothingOff()
    smoother.FeatureEdgeSmoothingOff()
    smoother.NonManifoldSmoothingOn()
    smoother.NormalizeCoordinatesOn()
    smoother.Update()
    return smoother.GetOutput()


def blurred(field: np.ndarray, sigma: float, step: int = 1) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter(field, sigma)[::step, ::step, ::step]`` (``field`` itself
    when ``sigma`` is 0), bit for bit, without the work for the voxels left out: the filter is
    separable, applied along axis 0, 1, 2 in turn, and each pass needs only the lines of the
    previous one that the sampling keeps (on every second voxel, 7/12 of the arithmetic)."""
    if sigma <= 0:
        return field[::step, ::step, ::step]
    if step == 1:
        return ndimage.gaussian_filter(field, sigma)
    for axis in range(field.ndim):
        field = ndimage.gaussian_filter1d(field, sigma, axis=axis)
        field = field[(slice(None),) * axis + (slice(None, None, step),)]
    return field


# A blurred mask whose surface will be remeshed with edges of at least this many voxels is
# contoured on every second voxel first: a 0.5 mm femur's contour has 36,500 vertices instead of
# 146,000 (about 0.05 voxel from the full one on average, 0.2 at most), which saves most of the
# remeshing's work.
COARSE_CONTOUR_EDGE = 4.0


def contour_stride(mask: np.ndarray, edge_length: float, target_vertices: int) -> int:
    """2 when the remeshed surface of ``mask`` will have edges of at least
    :data:`COARSE_CONTOUR_EDGE` voxels, else 1. The area is estimated from the voxel faces between
    inside and outside (on average 3/2 times a smooth surface's area)."""
    faces = sum(int(np.count_nonzero(np.diff(mask, axis=k))) for k in range(3))
    area = faces / 1.5
    edge = max(edge_length, float(np.sqrt(2.0 * area / (np.sqrt(3.0) * target_vertices))))
    return 2 if edge >= COARSE_CONTOUR_EDGE else 1


def mask_to_surface(mask: np.ndarray, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                    direction=None, smoothing_sigma: float = BuildConfig.smoothing_sigma,
                    max_smoothing_sigma: float | None = BuildConfig.max_smoothing_sigma,
                    edge_length: float = BuildConfig.edge_length,
                    target_vertices: int | None = BuildConfig.target_vertices,
                    method: str = BuildConfig.surface_method,
                    smoothing_factor: float = BuildConfig.smoothing_factor,
                    decimation: float = BuildConfig.decimation
                    ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Closed genus-0 surface of a binary mask, in physical coordinates.

    ``method="gaussian"``: the mask is blurred with a Gaussian of ``smoothing_sigma`` voxels and
    contoured at 0.5 with VTK's flying edges. ``method="slicer"``: 3D Slicer's closed-surface
    conversion: the binary mask is contoured directly, then (optionally decimated and) smoothed
    with a windowed-sinc filter (:func:`slicer_smoothing`). Both work in voxel space and keep the
    largest component. Diagonal voxel contacts make handles in raw masks, so when the surface is
    not genus 0 the mask is blurred (more): from ``smoothing_sigma`` (gaussian) or 1 voxel
    (slicer) in steps of 0.5 voxel up to ``max_smoothing_sigma`` (None: the rule of
    :func:`~mdlshapemodel.config.max_smoothing_for`); ``info["smoothing_sigma"]`` says
    which blur was needed (0: none). The surface is then remeshed isotropically (contouring
    leaves slivers that spoil sphere maps) with edges of ``edge_length`` voxels, or longer ones
    giving about ``target_vertices`` vertices on big objects (:func:`resample`; a blurred mask
    whose edges will be that long is contoured on every second voxel, :func:`contour_stride`),
    and transformed to physical coordinates. The defaults are those of
    :class:`~mdlshapemodel.config.BuildConfig` (None: its rules).

    Parameters
    ----------
    mask : ndarray of bool, shape (nz, ny, nx)
        As returned by ``SimpleITK.GetArrayFromImage`` (x fastest).
    spacing, origin : sequence of 3 floats
        Voxel size and position of voxel (0, 0, 0), x first (SimpleITK convention).
    direction : sequence of 9 floats, optional
        Row-major direction cosine matrix (SimpleITK ``GetDirection``); identity by default.

    Returns
    -------
    vertices, faces, info
    """
    if max_smoothing_sigma is None:
        max_smoothing_sigma = max_smoothing_for(smoothing_sigma)
    if target_vertices is None:
        target_vertices = target_vertices_for(SURFACE_POINTS)
    if method not in SURFACE_METHODS:
        raise SurfaceError(f"unknown surface method {method!r} (use {', '.join(SURFACE_METHODS)})")
    mask = np.asarray(mask) > 0
    if not mask.any():
        raise SurfaceError("the selected label is empty (no voxels)")
    pad = int(np.ceil(3 * max_smoothing_sigma)) + 2
    padded = np.pad(mask, pad).astype(np.float32)
    ladder = [float(smoothing_sigma) if method == "gaussian" else 0.0]
    while ladder[-1] + 0.5 <= max_smoothing_sigma + 1e-9:
        ladder.append(max(ladder[-1] + 0.5, 1.0))
    reasons = []
    stride = contour_stride(mask, edge_length, target_vertices) if method == "gaussian" else 1

    def extract(field, step):
        """The largest component of the contour, and what is wrong with it ('' if nothing)."""
        polydata = _contour(field, step)
        if method == "slicer":
            polydata = slicer_smoothing(polydata, smoothing_factor, decimation)
        vertices, faces = polydata_to_arrays(polydata)
        if len(faces) == 0:
            return vertices, faces, "no surface (the mask is too thin)"
        vertices, faces = merge_close_vertices(vertices, faces)
        vertices, faces = drop_degenerate_faces(vertices, faces)
        vertices, faces = largest_component(vertices, faces)
        topo = topology(vertices, faces)
        return vertices, faces, "" if topo.is_sphere_like else topo.describe()

    for sigma in ladder:
        # the coarser grid only on a blurred mask; on every voxel when it is not genus 0 there
        for step in dict.fromkeys((stride if sigma >= 1 else 1, 1)):
            vertices, faces, problem = extract(blurred(padded, sigma, step), step)
            if not problem:
                break
        if not problem:
            break
        reasons.append(f"blur {sigma:g}: {problem}")
    else:
        raise SurfaceError(f"no genus-0 surface up to a blur of {max_smoothing_sigma:g} voxels ("
                           + "; ".join(reasons[-2:]) + ")")
    vertices, faces = resample(vertices, faces, target_vertices, edge_length)
    # voxel index (x, y, z) -> physical point
    index = vertices - pad
    matrix = np.eye(3) if direction is None else np.asarray(direction, dtype=float).reshape(3, 3)
    physical = np.asarray(origin, float) + (index * np.asarray(spacing, float)) @ matrix.T
    faces = orient_outwards(physical, faces)
    # the topology is that of the contour checked above (resample keeps it)
    require_coordinates(physical)
    return physical, faces, {"smoothing_sigma": float(sigma), "surface_method": method,
                             "n_vertices": len(physical), "n_faces": len(faces)}


def merge_close_vertices(vertices: np.ndarray, faces: np.ndarray,
                         tolerance: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than ``tolerance`` times the bounding-box diagonal (STL soup)."""
    from scipy.spatial import cKDTree

    if len(vertices) == 0:
        return vertices, faces
    scale = float(np.linalg.norm(np.ptp(vertices, axis=0))) or 1.0
    pairs = cKDTree(vertices).query_pairs(tolerance * scale, output_type="ndarray")
    if len(pairs) == 0:
        return vertices, faces
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                              shape=(len(vertices), len(vertices)))
    _, labels = csgraph.connected_components(graph, directed=False)
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    return vertices[first], inverse.ravel()[faces]


def decimate(vertices: np.ndarray, faces: np.ndarray, target_vertices: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation to about ``target_vertices`` vertices, keeping the topology."""
    from vtkmodules.vtkFiltersCore import vtkQuadricDecimation

    polydata = arrays_to_polydata(vertices, faces)
    decimator = vtkQuadricDecimation()
    decimator.SetInputData(polydata)
    decimator.SetTargetReduction(max(0.0, 1.0 - target_vertices / len(vertices)))
    decimator.VolumePreservationOn()
    decimator.Update()
    new_vertices, new_faces = polydata_to_arrays(decimator.GetOutput())
    new_vertices, new_faces = drop_degenerate_faces(new_vertices, new_faces)
    if topology(new_vertices, new_faces).is_sphere_like:
        return new_vertices, new_faces
    return vertices, faces


def mesh_to_mask(vertices: np.ndarray, faces: np.ndarray, spacing: float, margin: int = 4
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Label map of the inside of a closed mesh, on a grid of ``spacing`` (same units) aligned to
    multiples of it, with ``margin`` empty voxels around the mesh (VTK's polygon stencil).

    Returns the mask (uint8, indexed z, y, x like ``SimpleITK.GetArrayFromImage``) and the
    position of voxel (0, 0, 0), x first.
    """
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonCore import VTK_UNSIGNED_CHAR
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkImagingStencil import vtkImageStencil, vtkPolyDataToImageStencil

    origin = np.floor(vertices.min(axis=0) / spacing) * spacing - margin * spacing
    size = np.ceil((vertices.max(axis=0) - origin) / spacing).astype(int) + margin + 1
    image = vtkImageData()
    image.SetOrigin(*origin)
    image.SetSpacing(spacing, spacing, spacing)
    image.SetDimensions(*size)
    image.AllocateScalars(VTK_UNSIGNED_CHAR, 1)
    image.GetPointData().GetScalars().Fill(1)
    stencil = vtkPolyDataToImageStencil()
    stencil.SetInputData(arrays_to_polydata(vertices, faces))
    stencil.SetOutputOrigin(*origin)
    stencil.SetOutputSpacing(spacing, spacing, spacing)
    stencil.SetOutputWholeExtent(image.GetExtent())
    cut = vtkImageStencil()
    cut.SetInputData(image)
    cut.SetStencilConnection(stencil.GetOutputPort())
    cut.ReverseStencilOff()
    cut.SetBackgroundValue(0)
    cut.Update()
    mask = vtk_to_numpy(cut.GetOutput().GetPointData().GetScalars()).reshape(size[::-1])
    return mask.astype(np.uint8), origin


def arrays_to_polydata(vertices: np.ndarray, faces: np.ndarray | None = None,
                       lines: np.ndarray | None = None):
    """A vtkPolyData with the given points and triangles (or line segments). ``faces`` of two
    columns are segments (the connectivity of a model of 2-D curves): they become lines."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

    if faces is not None and np.shape(faces)[1:] == (2,):
        faces, lines = None, faces

    polydata = vtkPolyData()
    points = vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64), deep=True))
    polydata.SetPoints(points)
    for cells, setter in ((faces, polydata.SetPolys), (lines, polydata.SetLines)):
        if cells is None or len(cells) == 0:
            continue
        cells = np.asarray(cells, dtype=np.int64)
        array = vtkCellArray()
        offsets = np.arange(0, cells.size + 1, cells.shape[1], dtype=np.int64)
        array.SetData(numpy_to_vtkIdTypeArray(offsets, deep=True),
                      numpy_to_vtkIdTypeArray(cells.ravel(), deep=True))
        setter(array)
    return polydata


def edge_length_for(vertices: np.ndarray, faces: np.ndarray, target_vertices: int) -> float:
    """Edge length of an equilateral triangulation of the surface with ``target_vertices``
    vertices: a closed genus-0 mesh of n vertices has 2n - 4 triangles, so its area is about
    2n (sqrt(3) / 4) h^2."""
    area = float(face_areas(vertices, faces).sum())
    return float(np.sqrt(2.0 * area / (np.sqrt(3.0) * target_vertices)))


def resample(vertices: np.ndarray, faces: np.ndarray, target_vertices: int, edge_length: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing with edges of ``edge_length`` or, when that would give more than
    ``target_vertices`` vertices, of the length giving about that many (:func:`edge_length_for`).

    If remeshing fails (the result would not be genus 0), a surface above the target is
    decimated to it instead.
    """
    edge = max(float(edge_length), edge_length_for(vertices, faces, target_vertices))
    remeshed, remeshed_faces = remesh(vertices, faces, edge)
    if remeshed is vertices and len(vertices) > target_vertices:
        return decimate(vertices, faces, target_vertices)
    return remeshed, remeshed_faces


def remesh(vertices: np.ndarray, faces: np.ndarray, edge_length: float, iterations: int = 5
           ) -> tuple[np.ndarray, np.ndarray]:
    """Isotropic remeshing to edges of about ``edge_length``; keeps the input when the result is
    not sphere-like.

    Botsch and Kobbelt's remesher (split long edges, collapse short ones, flip towards valence 6,
    tangential relaxation, projection onto the input surface), compiled in
    :func:`.remesh.remesh_isotropic`. Its output depends only on its input arrays (index-ordered
    loops, no random numbers), so the same surface is remeshed bit for bit alike in any process
    or environment. A fine surface (a 0.5 mm femur's contour) is remeshed as it is: decimating it
    first with VTK would cost more than the remeshing saves (docs/benchmarks.md, "Preparing the
    inputs").
    """
    from .remesh import remesh_isotropic

    result = remesh_isotropic(vertices, faces, edge_length, iterations)
    if result is None:
        return vertices, faces
    new_vertices, new_faces = drop_degenerate_faces(*result)
    if topology(new_vertices, new_faces).is_sphere_like:
        return new_vertices, new_faces
    return vertices, faces


class SurfaceDistance:
    """Exact unsigned distances from points to one triangle mesh, with its search grid built once.

    The distance of a point is that to the closest point of the triangles (not to the nearest
    vertex). The triangles are binned in a uniform grid at construction
    (:class:`~mdlshapemodel.prepare.nearest.TriangleGrid`, under a millisecond for 5,000
    triangles); a query point near the mesh then costs a few microseconds, so build one object
    per mesh and reuse it; :meth:`move` re-uses it for a mesh of the same connectivity.

    Parameters
    ----------
    vertices : ndarray (n, 3)
        Mesh vertices.
    faces : ndarray (m, 3)
        Triangles (vertex indices), m >= 1.

    Examples
    --------
    ::

        distance = SurfaceDistance(vertices, faces)
        d = distance(points)                       # (k,) distances of points (k, 3)
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        faces = np.asarray(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ArgumentError(f"need at least one triangle, got faces of shape {faces.shape}")
        self._n_vertices = len(vertices)
        self._grid = TriangleGrid(vertices, faces)

    def move(self, vertices: np.ndarray):
        """Give the mesh new vertex positions (same faces) and rebuild the grid."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        if vertices.shape != (self._n_vertices, 3):
            raise ArgumentError(f"need {self._n_vertices} vertices, got an array of {vertices.shape}")
        self._grid.move(vertices)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Distances (k,) from ``points`` (k, 3) to the mesh."""
        return self.closest(points)[1]

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest mesh points (k, 3), distances (k,) and the faces holding them (k,)."""
        found, squared, faces = self._grid.closest(points)
        return found, np.sqrt(squared), faces


def point_surface_distances(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                            ) -> np.ndarray:
    """Exact distance from each of ``points`` (k, 3) to the mesh (vertices, faces), (k,).

    One-off convenience around :class:`SurfaceDistance`; reuse that class for many queries.
    """
    return SurfaceDistance(vertices, faces)(points)


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """The mask with its cavities filled: the background components (6-connected) that do not
    touch the border of the array become foreground. The result of
    ``scipy.ndimage.binary_fill_holes``, by one labelling of the background instead of its
    repeated dilations (a fifth of the time on a 0.5 mm femur's 10 million voxels)."""
    background, count = ndimage.label(~mask)
    if count == 0:
        return mask.copy()
    outside = np.zeros(count + 1, dtype=bool)
    for axis in range(mask.ndim):
        for end in (0, -1):
            outside[np.take(background, end, axis=axis)] = True
    outside[0] = False                                  # the foreground's label
    return (~outside[background] & (background > 0)) | mask


def mask_components(mask: np.ndarray, min_fraction: float = 0.1) -> tuple[np.ndarray, str]:
    """Fill cavities and keep the largest 26-connected component.

    Raises :class:`SurfaceError` when another component has at least ``min_fraction`` of the
    largest one's voxels (two objects, not one object with debris). Returns the mask and a note.
    """
    labels, count = ndimage.label(mask, structure=np.ones((3, 3, 3)))
    notes = []
    if count > 1:
        sizes = np.bincount(labels.ravel())[1:]
        order = np.argsort(sizes)[::-1]
        if sizes[order[1]] >= min_fraction * sizes[order[0]]:
            raise SurfaceError(f"{count} disjoint objects in the mask (voxels: "
                               f"{', '.join(str(int(s)) for s in sizes[order[:4]])}); expected one")
        mask = labels == order[0] + 1
        notes.append(f"dropped {count - 1} small component(s) of {int(sizes[order[1:]].sum())} voxels")
    filled = fill_holes(mask)
    cavities = int(filled.sum() - mask.sum())
    if cavities:
        notes.append(f"filled {cavities} cavity voxels")
    return filled, "; ".join(notes)


# the reflection of ``BuildConfig.mirror``: x -> -x (left <-> right in RAS/LPS), its own inverse
MIRROR = np.array([-1.0, 1.0, 1.0])


def mirror_points(points: np.ndarray) -> np.ndarray:
    """Points (n, 3) reflected x -> -x (:data:`MIRROR`): a mirrored case's, or its corresponded
    points taken back to its input's side."""
    return points * MIRROR


def mirror(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reflect x -> -x (left <-> right in RAS/LPS) keeping the normals outwards."""
    mirrored = vertices.copy()
    mirrored[:, 0] *= -1.0
    return mirrored, faces[:, [0, 2, 1]].copy()


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, target_vertices: int
               ) -> tuple[np.ndarray, np.ndarray, float, str]:
    """Merge duplicate points, drop degenerate faces, make the orientation consistent, check the
    topology and remesh at the mean edge length, or coarser to about ``target_vertices``
    vertices (:func:`resample`).

    Returns vertices, faces, the mean edge length of the input (the default voxel size of a
    mesh input: its resolution) and a repair note ('' when nothing was repaired).
    """
    require_coordinates(vertices, "mesh")
    vertices, faces = merge_close_vertices(vertices, faces)
    vertices, faces = drop_degenerate_faces(vertices, faces)
    topo = topology(vertices, faces)
    note = ""
    if topo.is_closed_manifold and topo.n_components == 1 and not topo.consistently_oriented:
        faces, flipped = make_orientation_consistent(vertices, faces)
        note = f"made the orientation of {flipped} faces consistent"
    require_sphere_like(vertices, faces)
    faces = orient_outwards(vertices, faces)
    edges = edges_of(faces)
    mean_edge = float(np.mean(np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)))
    vertices, faces = resample(vertices, faces, target_vertices, mean_edge)
    require_sphere_like(vertices, faces)
    return vertices, faces, mean_edge, note
