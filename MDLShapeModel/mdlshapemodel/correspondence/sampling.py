"""Sampling grids on the sphere and evaluation of S_i(u) on a spherical triangulation.

A surface with a bijective sphere map is a triangulation of the unit sphere whose vertices carry
surface points. The value S(u) at a parameter point u is found by *point location* (which spherical
triangle contains u) and barycentric interpolation of the surface points. We use the central
projection: u lies in the cone of triangle (a, b, c) exactly when ``[a b c]^-1 u >= 0``; the
normalised solution is the barycentric coordinate. Because the map is fold-free, the cones of the
triangles partition space, so every u is found in exactly one triangle (up to shared edges).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..errors import ArgumentError
from . import hotloops


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Icosahedron subdivided ``subdivisions`` times: 10 * 4**k + 2 unit vectors and their triangles.

    Faces are counter-clockwise seen from outside.
    """
    t = (1.0 + np.sqrt(5.0)) / 2.0
    vertices = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
                (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    points = np.array(vertices, dtype=np.float64)
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    triangles = np.array(faces, dtype=np.int64)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]],
                                        triangles[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        midpoints = points[unique[:, 0]] + points[unique[:, 1]]
        midpoints /= np.linalg.norm(midpoints, axis=1, keepdims=True)
        m = len(triangles)
        mid = inverse.reshape(3, m).T + len(points)  # midpoint of edges (0,1), (1,2), (2,0)
        a, b, c = triangles.T
        ab, bc, ca = mid.T
        triangles = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                                    np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
        points = np.concatenate([points, midpoints])
    return points, triangles


def fibonacci_sphere(n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """``n_points`` nearly uniform unit vectors (Fibonacci lattice) and their Delaunay triangles."""
    k = np.arange(n_points) + 0.5
    z = 1.0 - 2.0 * k / n_points
    radius = np.sqrt(1.0 - z * z)
    angle = np.pi * (1.0 + np.sqrt(5.0)) * k
    points = np.stack([radius * np.cos(angle), radius * np.sin(angle), z], axis=1)
    triangles = ConvexHull(points).simplices.astype(np.int64)
    return points, orient_triangles(points, triangles)


def orient_triangles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Reorder each triangle of a star-shaped triangulation to be counter-clockwise from outside."""
    a, b, c = (points[triangles[:, k]] for k in range(3))
    flipped = np.einsum("ij,ij->i", a, np.cross(b, c)) < 0
    triangles = triangles.copy()
    triangles[flipped] = triangles[flipped][:, [0, 2, 1]]
    return triangles


def sphere_grid(n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The sampling grid {u_k}: an icosphere when ``n_points`` is 10 * 4**k + 2, else Fibonacci."""
    if n_points < 12:
        raise ArgumentError(f"at least 12 sample points are needed, got {n_points}")
    k = np.log((n_points - 2) / 10.0) / np.log(4.0)
    if (n_points - 2) % 10 == 0 and abs(k - round(k)) < 1e-9:
        return icosphere(int(round(k)))
    return fibonacci_sphere(n_points)


def farthest_points(points: np.ndarray, count: int, first: int = 0) -> np.ndarray:
    """Indices of ``count`` of ``points`` (n, d) spread evenly over them: the first ``first``
    points, then again and again the point farthest from all those taken (greedy farthest-point
    sampling; ties go to the lowest index, so the order is reproducible).

    Examples
    --------
    >>> line = np.array([[0.0], [1.0], [2.0], [3.0], [10.0]])
    >>> farthest_points(line, 3, first=1).tolist()
    [0, 4, 3]
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if not 0 <= first <= count <= n:
        raise ArgumentError(f"cannot take {count} of {n} points starting with {first}")
    chosen = np.empty(count, dtype=np.int64)
    chosen[:first] = np.arange(first)
    columns = [np.ascontiguousarray(points[:, j]) for j in range(points.shape[1])]

    def squared_distances(index):
        total = np.zeros(n)
        for column in columns:        # column by column: contiguous, several times faster
            total += (column - column[index]) ** 2
        return total

    if first:
        nearest = cKDTree(points[:first]).query(points)[0] ** 2
    else:
        chosen[0] = 0
        nearest = squared_distances(0)
        first = 1
    for k in range(first, count):
        index = int(np.argmax(nearest))
        chosen[k] = index
        np.minimum(nearest, squared_distances(index), out=nearest)
    return chosen


def spherical_triangles(points: np.ndarray) -> np.ndarray:
    """The Delaunay triangulation of unit vectors (their convex hull), counter-clockwise from
    outside; every point is a vertex of it."""
    triangles = ConvexHull(points).simplices.astype(np.int64)
    if len(np.unique(triangles)) != len(points):
        raise ArgumentError("points on the sphere that are not vertices of their hull (repeated?)")
    return orient_triangles(points, triangles)


#: The largest index an ``int16`` table holds (:func:`index_dtype`)
INT16_INDEX_LIMIT = int(np.iinfo(np.int16).max)


def index_dtype(count: int) -> type:
    """The integer type of index tables over ``count`` items (vertices or faces): ``int16`` where
    every index and the padding -1 fit (``count`` <= 32,767), else ``int32``.

    A build holds a surface's triangles and its locator's tables for every case through the
    optimisation; narrow indices halve them. Arithmetic on the indices must be done in a wider
    type (numba's kernels widen to ``intp``; numpy does not: index with them, do not multiply).

    Examples
    --------
    >>> index_dtype(5000).__name__, index_dtype(40000).__name__
    ('int16', 'int32')
    """
    if count > np.iinfo(np.int32).max:
        raise ArgumentError(f"index_dtype: {count} items exceed 32-bit indices")
    return np.int16 if count <= INT16_INDEX_LIMIT else np.int32


#: Points located at once among the faces around their nearest vertices (SphereLocator.locate)
LOCATE_BLOCK = 8192


class SphereLocator:
    """Point location on a fold-free spherical triangulation.

    Parameters
    ----------
    sphere : ndarray (n, 3)
        Unit vectors: the sphere map of the surface vertices.
    faces : ndarray (m, 3)
        Triangles, counter-clockwise seen from outside, none flipped.

    Notes
    -----
    A build keeps one locator per case and part through the optimisation, so it holds no table
    per face beyond the triangles: M^-1 = [a b c]^-1 of a face, which gives the central-projection
    coordinates M^-1 u, is computed where a point is located (``hotloops.face_inverses``, the
    same arithmetic as numpy's for the same matrices bit for bit) rather than stored (72 bytes a
    face). The triangles and the two index tables (the faces around each vertex, the face across
    each edge) are in the narrowest of ``int16`` and ``int32`` that holds their indices
    (:func:`index_dtype`): a quarter or half the bytes of ``int64`` for the same values, so the
    faces and samples located are the same.
    """

    def __init__(self, sphere: np.ndarray, faces: np.ndarray):
        self.sphere = np.asarray(sphere, dtype=np.float64)
        faces = np.asarray(faces)
        # one index type for the three tables (one compiled variant of each kernel a surface size)
        index = index_dtype(max(len(self.sphere), len(faces)))
        self.faces = np.asarray(faces, dtype=index)
        self.tree = cKDTree(self.sphere)
        self.vertex_faces = vertex_face_table(self.faces, len(self.sphere)).astype(index)
        self.neighbours = face_neighbours(self.faces).astype(index)

    def inverses(self, faces: np.ndarray) -> np.ndarray:
        """M^-1 = [a b c]^-1 of each face in ``faces`` (any shape): (..., 3, 3)."""
        faces = np.asarray(faces)
        flat = np.ascontiguousarray(faces.ravel(), dtype=np.int64)
        return hotloops.face_inverses(self.sphere, self.faces, flat).reshape(faces.shape + (3, 3))

    def coordinates(self, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
        """The central-projection coordinates M^-1 u of ``points`` in ``faces`` (broadcast)."""
        return np.einsum("...ij,...j->...i", self.inverses(faces), points)

    def locate(self, points: np.ndarray, hint: np.ndarray | None = None,
               neighbours: int = 4, walk_steps: int = 6) -> tuple[np.ndarray, np.ndarray]:
        """Triangle index (in the tables' index type, :func:`index_dtype`) and barycentric
        coordinates of each point.

        ``hint`` (one face index per point, e.g. the previous location) starts a short walk over
        neighbouring triangles, which makes relocating slightly moved points cheap; points not found
        that way are located among the triangles around their nearest vertices.
        """
        points = np.asarray(points, dtype=np.float64)
        n = len(points)
        # the faces in the tables' index type: a part keeps them as its next walk's hints
        face = np.full(n, -1, dtype=self.faces.dtype)
        coords = np.zeros((n, 3))
        todo = np.arange(n)
        if hint is not None:
            # walk from the hint towards the point: cross the edge opposite the most negative
            # barycentric coordinate, a few steps at most
            found = np.zeros(n, dtype=np.bool_)
            hotloops.walk(self.sphere, self.faces, self.neighbours, points,
                          np.asarray(hint, dtype=self.faces.dtype), walk_steps, -1e-12, face,
                          coords, found)
            todo = np.flatnonzero(~found)
        k = min(neighbours, len(self.sphere))
        # the points not found by walking, a block at a time: each point's candidate faces
        # (about 40) have a 3 x 3 inverse each, 3 KB a point
        for start in range(0, len(todo), LOCATE_BLOCK):
            self._locate_near(points, todo[start:start + LOCATE_BLOCK], k, face, coords)
        return face, coords

    def _locate_near(self, points, todo, k, face, coords):
        """Locate ``points[todo]`` among the faces around their ``k`` nearest vertices, in place."""
        _, nearest = self.tree.query(points[todo], k=k)
        nearest = np.asarray(nearest).reshape(len(todo), k)
        candidates = self.vertex_faces[nearest].reshape(len(todo), -1)
        valid = candidates >= 0
        safe = np.where(valid, candidates, 0)
        lam = self.coordinates(safe, points[todo][:, None, :])
        score = np.where(valid, lam.min(axis=2), -np.inf)
        best = np.argmax(score, axis=1)
        rows = np.arange(len(todo))
        face[todo] = safe[rows, best]
        coords[todo] = _clamped(lam[rows, best])
        missed = todo[score[rows, best] < -1e-9]
        for index in missed:  # rare: fall back to all faces
            lam_all = self.coordinates(np.arange(len(self.faces)), points[index][None, :])
            best_face = int(np.argmax(lam_all.min(axis=1)))
            face[index], coords[index] = best_face, _clamped(lam_all[best_face])
        return face, coords

    def interpolate(self, values: np.ndarray, face: np.ndarray, coords: np.ndarray) -> np.ndarray:
        """Barycentric interpolation of per-vertex ``values`` at located points."""
        if values.ndim == 2:
            return hotloops.interpolate(values, self.faces, face, coords)
        return np.einsum("ij,ij...->i...", coords, values[self.faces[face]])

    def jacobian(self, values: np.ndarray, face: np.ndarray, points: np.ndarray) -> np.ndarray:
        """dS/du at located points: (n, d, 3) for per-vertex ``values`` (v, d).

        Inside face j with corners M = [a b c], the central-projection barycentrics are
        b = lambda / s with lambda = M^-1 u and s = 1^T lambda, so
        dS/du = V^T (I - b 1^T) M^-1 / s (V the corner values, 3 x d). Radial motions of u do not
        change b, so only the tangential part of a displacement of u matters.
        """
        inverse = self.inverses(face)                                 # (n, 3, 3)
        raw = np.einsum("nij,nj->ni", inverse, points)
        total = raw.sum(axis=1)
        coords = raw / total[:, None]
        projector = np.eye(3)[None] - coords[:, :, None]               # (I - b 1^T)
        db = np.einsum("nij,njk->nik", projector, inverse) / total[:, None, None]
        return np.einsum("njd,njk->ndk", values[self.faces[face]], db)

    def evaluate(self, values: np.ndarray, points: np.ndarray, hint: np.ndarray | None = None):
        """S(u): per-vertex ``values`` at parameter points; returns (values, faces)."""
        face, coords = self.locate(points, hint)
        return self.interpolate(values, face, coords), face


def _clamped(lam: np.ndarray) -> np.ndarray:
    """Barycentric coordinates from central-projection ones (last axis): negative rounding
    clamped to 0, normalised to sum 1 (as the compiled walk does)."""
    lam = np.maximum(lam, 0.0)
    return lam / lam.sum(axis=-1, keepdims=True)


def grid_order(sphere: np.ndarray, faces: np.ndarray, grid: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """A renumbering of a sphere-mapped mesh in the order a sampling grid visits it: faces sorted
    by the grid point nearest to their centroid on the sphere, vertices by first use in those
    faces. Returns (vertex order, renumbered faces): ``sphere[order]`` with the new faces is the
    same triangulation.

    Locating and interpolating the grid points in grid order then reads the mesh arrays nearly
    front to back instead of at random, which the memory system serves much faster once the
    meshes of a population no longer fit in the caches.
    """
    centroids = sphere[faces].sum(axis=1)
    _, nearest = cKDTree(grid).query(centroids)
    faces = faces[np.argsort(nearest, kind="stable")]
    first = np.full(len(sphere), len(faces) * 3)
    flat = faces.ravel()
    np.minimum.at(first, flat, np.arange(len(flat)))
    order = np.argsort(first, kind="stable")
    renumber = np.empty(len(sphere), dtype=np.int64)
    renumber[order] = np.arange(len(sphere))
    return order, renumber[faces]


def vertex_face_table(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(n_vertices, max degree): the faces around each vertex, padded with -1."""
    counts = np.bincount(faces.ravel(), minlength=n_vertices)
    order = np.argsort(faces.ravel(), kind="stable")
    table = np.full((n_vertices, max(int(counts.max(initial=0)), 1)), -1, dtype=np.int64)
    slot = np.arange(faces.size) - np.repeat(np.cumsum(counts) - counts, counts)
    table[np.repeat(np.arange(n_vertices), counts), slot] = order // 3
    return table


def face_neighbours(faces: np.ndarray) -> np.ndarray:
    """(m, 3): the face across the edge opposite corner j of each face (-1 on a boundary)."""
    m = len(faces)
    opposite = np.concatenate([faces[:, [1, 2]], faces[:, [2, 0]], faces[:, [0, 1]]])
    owner = np.tile(np.arange(m), 3)
    corner = np.repeat(np.arange(3), m)
    key = np.sort(opposite, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, owner, corner = key[order], owner[order], corner[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    result = np.full((m, 3), -1, dtype=np.int64)
    first = np.flatnonzero(same)
    result[owner[first], corner[first]] = owner[first + 1]
    result[owner[first + 1], corner[first + 1]] = owner[first]
    return result
