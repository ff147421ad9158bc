"""Closest points on a triangle mesh: exact point-to-triangle distances over a uniform grid (numba).

The surface measures of a model (generalization and specificity surface to surface) and the
fidelity of corresponded points ask for millions of closest points per build, nearly all of them
close to the surface. Here the triangles are binned once into a uniform grid of cubic cells (each
triangle in every cell its bounding box meets), and a query visits the cells in growing shells
around its own cell, testing each triangle once, until no unvisited cell can hold anything
nearer than the best found. The answer is exact (the search only stops on a proven bound); the
distance to one triangle is the distance to the nearest point of the triangle, found by the
region of the triangle's plane the projected point falls in (a vertex, an edge or the inside).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: triangles per grid cell aimed at when the grid is built
TRIANGLES_PER_CELL = 2.0
#: and at most this many cells in the mesh's box per triangle (the grid's memory)
MAX_CELLS_PER_TRIANGLE = 8.0


@njit(cache=True, nogil=True, inline="always")
def closest_point_and_region(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz, out):
    """The point of triangle abc nearest to p, into ``out`` (3,); returns its squared distance
    and where it lies: -1 inside the triangle, k = 0, 1, 2 at corner k (a, b, c), 3 + k on the
    edge opposite corner k.

    With ab = b - a, ac = c - a, ap = p - a and d1 = ab.ap, d2 = ac.ap (and the same from b and
    c), the sign of these dot products and of the barycentric numerators tells which vertex, edge
    or the interior holds the nearest point."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    region = -1
    if d1 <= 0.0 and d2 <= 0.0:                       # vertex a
        qx, qy, qz = ax, ay, az
        region = 0
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        vc = d1 * d4 - d3 * d2
        if d3 >= 0.0 and d4 <= d3:                    # vertex b
            qx, qy, qz = bx, by, bz
            region = 1
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:   # edge ab
            t = d1 / (d1 - d3)
            qx, qy, qz = ax + t * abx, ay + t * aby, az + t * abz
            region = 5
        else:
            cpx, cpy, cpz = px - cx, py - cy, pz - cz
            d5 = abx * cpx + aby * cpy + abz * cpz
            d6 = acx * cpx + acy * cpy + acz * cpz
            vb = d5 * d2 - d1 * d6
            va = d3 * d6 - d5 * d4
            if d6 >= 0.0 and d5 <= d6:                # vertex c
                qx, qy, qz = cx, cy, cz
                region = 2
            elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:   # edge ac
                t = d2 / (d2 - d6)
                qx, qy, qz = ax + t * acx, ay + t * acy, az + t * acz
                region = 4
            elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:   # edge bc
                t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                qx, qy, qz = bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz)
                region = 3
            else:                                     # inside: barycentric (u, v, w)
                total = va + vb + vc
                if total <= 0.0:                      # zero area, no edge region met: a
                    qx, qy, qz = ax, ay, az
                    region = 0
                else:
                    v = vb / total
                    w = vc / total
                    qx = ax + abx * v + acx * w
                    qy = ay + aby * v + acy * w
                    qz = az + abz * v + acz * w
    out[0], out[1], out[2] = qx, qy, qz
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz, region


@njit(cache=True, nogil=True, inline="always")
def closest_on_triangle(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz, out):
    """The point of triangle abc nearest to p, into ``out`` (3,); returns its squared distance
    (:func:`closest_point_and_region`)."""
    return closest_point_and_region(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz, out)[0]


@njit(cache=True, nogil=True, inline="always")
def _test_triangle(f, p, points, vertices, faces, q, found, squared, face):
    """Keep triangle f's nearest point to point p if it is nearer than the best so far."""
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    d = closest_on_triangle(points[p, 0], points[p, 1], points[p, 2],
                             vertices[a, 0], vertices[a, 1], vertices[a, 2],
                             vertices[b, 0], vertices[b, 1], vertices[b, 2],
                             vertices[c, 0], vertices[c, 1], vertices[c, 2], q)
    if d < squared[p]:
        squared[p], face[p] = d, f
        found[p, 0], found[p, 1], found[p, 2] = q[0], q[1], q[2]


@njit(cache=True, nogil=True)
def closest_on_triangles(points, vertices, faces, candidates):
    """Brute force: for each point, the nearest point over the triangles ``candidates`` (all
    faces when it is every index); returns (closest (k, 3), squared distance (k,), face (k,))."""
    k = points.shape[0]
    found = np.empty((k, 3))
    squared = np.full(k, np.inf)
    face = np.full(k, -1, dtype=np.int64)
    q = np.empty(3)
    for i in range(k):
        for f in candidates:
            _test_triangle(f, i, points, vertices, faces, q, found, squared, face)
    return found, squared, face


@njit(cache=True, nogil=True, inline="always")
def cell_index(value, origin, cell, size):
    """The index along one axis of the cell holding ``value``, clamped to the grid."""
    return min(max(int(np.floor((value - origin) / cell)), 0), size - 1)


@njit(cache=True, nogil=True)
def build_grid(vertices, faces, origin, cell, shape):
    """CSR arrays (start, triangles) of the cells of a grid of ``shape`` (3,) cubic cells of size
    ``cell`` from ``origin``: cell (i, j, k) lists every triangle whose bounding box meets it."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    counts = np.zeros(nx * ny * nz + 1, dtype=np.int64)
    low = np.empty((faces.shape[0], 3), dtype=np.int64)
    high = np.empty((faces.shape[0], 3), dtype=np.int64)
    for f in range(faces.shape[0]):
        for d in range(3):
            lo = min(vertices[faces[f, 0], d], vertices[faces[f, 1], d], vertices[faces[f, 2], d])
            hi = max(vertices[faces[f, 0], d], vertices[faces[f, 1], d], vertices[faces[f, 2], d])
            low[f, d] = cell_index(lo, origin[d], cell, shape[d])
            high[f, d] = cell_index(hi, origin[d], cell, shape[d])
        for i in range(low[f, 0], high[f, 0] + 1):
            for j in range(low[f, 1], high[f, 1] + 1):
                for k in range(low[f, 2], high[f, 2] + 1):
                    counts[(i * ny + j) * nz + k + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    triangles = np.empty(start[-1], dtype=np.int64)
    for f in range(faces.shape[0]):
        for i in range(low[f, 0], high[f, 0] + 1):
            for j in range(low[f, 1], high[f, 1] + 1):
                for k in range(low[f, 2], high[f, 2] + 1):
                    index = (i * ny + j) * nz + k
                    triangles[fill[index]] = f
                    fill[index] += 1
    return start, triangles


@njit(cache=True, nogil=True, inline="always")
def _visit_cell(i, j, kk, p, points, vertices, faces, origin, cell, shape, start, triangles,
                stamp, q, found, squared, face):
    """Test the triangles of grid cell (i, j, kk) not yet tested for point p, unless the cell
    lies farther from p than the nearest point found; keep the nearest."""
    px, py, pz = points[p, 0], points[p, 1], points[p, 2]
    gap = 0.0
    for axis, value, c in ((0, px, i), (1, py, j), (2, pz, kk)):
        low = origin[axis] + c * cell
        d = max(low - value, value - (low + cell), 0.0)
        gap += d * d
    if gap >= squared[p]:
        return
    index = (i * shape[1] + j) * shape[2] + kk
    for t in range(start[index], start[index + 1]):
        f = triangles[t]
        if stamp[f] == p:
            continue
        stamp[f] = p
        _test_triangle(f, p, points, vertices, faces, q, found, squared, face)


@njit(cache=True, nogil=True, inline="always")
def _part_distance2(point, origin, cell, shape, axis, first, stop):
    """Squared distance from ``point`` to the part of the grid's box whose cells along ``axis``
    have indices first..stop-1 (all cells along the other axes)."""
    total = 0.0
    for d in range(3):
        low = origin[d] + (first if d == axis else 0) * cell
        high = origin[d] + (stop if d == axis else shape[d]) * cell
        gap = max(low - point[d], point[d] - high, 0.0)
        total += gap * gap
    return total


@njit(cache=True, nogil=True)
def query_grid(points, vertices, faces, origin, cell, shape, start, triangles):
    """The exact nearest point of the mesh to each point, searching the grid of
    :func:`build_grid` in shells of cells around the point's cell (clamped to the grid) until the
    region visited provably holds the nearest triangle; cells farther than the nearest point so
    far are not searched. Returns (closest (k, 3), squared distance (k,), face (k,)); among
    triangles at exactly the same distance, the first tested is kept. The search suits points
    near the mesh (within a few cells of its bounding box): from far outside it, it visits most
    cells."""
    k = points.shape[0]
    nx, ny, nz = shape[0], shape[1], shape[2]
    found = np.zeros((k, 3))
    squared = np.full(k, np.inf)
    face = np.full(k, -1, dtype=np.int64)
    stamp = np.full(faces.shape[0], -1, dtype=np.int64)
    q = np.empty(3)
    for p in range(k):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        ci = cell_index(px, origin[0], cell, nx)
        cj = cell_index(py, origin[1], cell, ny)
        ck = cell_index(pz, origin[2], cell, nz)
        ring = 0
        while True:
            i0, i1 = max(ci - ring, 0), min(ci + ring, nx - 1)
            j0, j1 = max(cj - ring, 0), min(cj + ring, ny - 1)
            k0, k1 = max(ck - ring, 0), min(ck + ring, nz - 1)
            # the shell: the cells at Chebyshev distance ``ring`` from (ci, cj, ck)
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    # on a side of the shell every kk, inside it only its top and bottom
                    # (ring > 0 there)
                    side = abs(i - ci) == ring or abs(j - cj) == ring
                    first, last = (k0, k1) if side else (ck - ring, ck + ring)
                    for kk in range(first, last + 1, 1 if side else 2 * ring):
                        if k0 <= kk <= k1:
                            _visit_cell(i, j, kk, p, points, vertices, faces, origin, cell,
                                        shape, start, triangles, stamp, q, found, squared, face)
            # every unvisited cell lies in the part of the grid beyond one side of the visited
            # box: the nearest such part bounds the distance of anything not yet tested
            bound = np.inf
            for axis, low, high, size in ((0, i0, i1, nx), (1, j0, j1, ny), (2, k0, k1, nz)):
                if low > 0:         # the grid below index ``low`` along ``axis``
                    bound = min(bound, _part_distance2(points[p], origin, cell, shape, axis,
                                                       0, low))
                if high < size - 1:
                    bound = min(bound, _part_distance2(points[p], origin, cell, shape, axis,
                                                       high + 1, size))
            if bound == np.inf or squared[p] <= bound:
                break
            ring += 1
    return found, squared, face


class TriangleGrid:
    """The triangles of a mesh binned in a uniform grid, for exact closest-point queries.

    Parameters
    ----------
    vertices : ndarray (n, 3)
    faces : ndarray (m, 3)
        Triangles, m >= 1.

    Examples
    --------
    >>> import numpy as np
    >>> vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> grid = TriangleGrid(vertices, np.array([[0, 1, 2]]))
    >>> points, squared, faces = grid.closest(np.array([[0.2, 0.2, 3.0], [2.0, 0, 0]]))
    >>> np.sqrt(squared).round(6).tolist(), faces.tolist()
    ([3.0, 1.0], [0, 0])
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.move(vertices)

    def move(self, vertices: np.ndarray):
        """New vertex positions (same triangles): the grid is built again."""
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        low, high = self.vertices.min(axis=0), self.vertices.max(axis=0)
        extent = np.maximum(high - low, 1e-9 * max(float(np.max(high - low)), 1.0))
        # cubic cells, about TRIANGLES_PER_CELL triangles per occupied cell: a surface of m
        # triangles meets about (m / TRIANGLES_PER_CELL) cells, which scale as the area
        area = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[0] * extent[2])
        cell = float(np.sqrt(area * TRIANGLES_PER_CELL / max(len(self.faces), 1)))
        cell = max(cell, float(np.max(extent)) / 256.0)
        # at most MAX_CELLS_PER_TRIANGLE cells per triangle in the box (a thin or sparse mesh)
        cells = float(np.prod(np.ceil(extent / cell)))
        limit = MAX_CELLS_PER_TRIANGLE * len(self.faces) + 64.0
        if cells > limit:
            cell *= (cells / limit) ** (1.0 / 3.0)
        self.cell = cell
        self.origin = low.astype(np.float64)
        self.shape = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
        self.start, self.triangles = build_grid(self.vertices, self.faces, self.origin, cell,
                                                self.shape)

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest mesh points (k, 3), squared distances (k,) and their faces (k,)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        return query_grid(points, self.vertices, self.faces, self.origin, self.cell, self.shape,
                          self.start, self.triangles)
