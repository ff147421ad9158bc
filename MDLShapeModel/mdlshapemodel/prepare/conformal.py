"""The spherical conformal map of a closed genus-0 triangle mesh, the first try of
:func:`~.sphere.sphere_map`: the harmonic map onto the plane and the inverse stereographic
projection (Angenent et al., IEEE TMI 18(8), 1999), with the rescaling of FLASH (Choi, Lam and
Lui, SIAM J. Imaging Sci. 8(1), 2015).

1. The cotangent Laplace equation on the surface, with the three corners of one well-shaped
   triangle (the "big triangle", the most regular one) pinned to a triangle of its own shape:
   the whole surface but that triangle lands inside it, conformally up to discretisation error.
2. The plane is rescaled so that the big triangle (at the north pole after step 3) and the
   triangle nearest the origin (the south pole) come out of a similar size.
3. The inverse stereographic projection puts it on the unit sphere.

FLASH then corrects the map near the south pole, where the triangles are smallest and the
discretisation error largest, by a quasi-conformal map (the linear Beltrami solver). Here the map
is only the start of the distortion minimisation, which moves the south pole's triangles far
more than the correction would, so it is left out (it costs a second factorisation; the
uncorrected map is as often fold-free: docs/benchmarks.md, "Preparing the inputs").

The linear system is symmetric positive definite and factored by SuperLU with a minimum-degree
ordering and diagonal pivots (deterministic). A map that cannot be computed in double precision
(triangles of the plane that degenerate, as on strongly elongated surfaces) is None:
:func:`~.sphere.sphere_map` then takes the multilevel map.
"""

from __future__ import annotations

import numpy as np

def cotangents(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The cotangent of the angle at each corner of each triangle, (m, 3)."""
    cot = np.empty((len(faces), 3))
    for k in range(3):  # the angle at corner k, opposite edge (k+1, k+2)
        p = vertices[faces[:, k]]
        u = vertices[faces[:, (k + 1) % 3]] - p
        w = vertices[faces[:, (k + 2) % 3]] - p
        cross = np.stack([u[:, 1] * w[:, 2] - u[:, 2] * w[:, 1],
                          u[:, 2] * w[:, 0] - u[:, 0] * w[:, 2],
                          u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0]], axis=1)
        cot[:, k] = np.einsum("ij,ij->i", u, w) / np.maximum(
            np.sqrt(np.einsum("ij,ij->i", cross, cross)), 1e-300)
    return cot


def cotangent_laplacian(faces: np.ndarray, cot: np.ndarray, n: int):
    """The cotangent Laplacian L (n x n, scipy.sparse CSC, indices sorted): -(cot a + cot b) / 2
    for an edge with opposite angles a and b, the row sums on the diagonal (positive
    semi-definite, every vertex's diagonal entry present). Both the harmonic map and the
    preconditioner of the distortion minimisation are made from it."""
    from scipy import sparse

    rows, cols, values = [], [], []
    for k in range(3):  # the edge opposite corner k, weighted by half its cotangent
        i, j = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        w = 0.5 * cot[:, k]
        rows += [i, j, i, j]
        cols += [j, i, i, j]
        values += [-w, -w, w, w]
    laplacian = sparse.csc_matrix((np.concatenate(values),
                                   (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    laplacian.sort_indices()
    return laplacian


def diagonal_positions(matrix) -> np.ndarray:
    """Where each column's diagonal entry is in ``matrix.data`` (a CSC matrix that has them
    all)."""
    column = np.repeat(np.arange(matrix.shape[1]), np.diff(matrix.indptr))
    return np.flatnonzero(matrix.indices == column)


def _harmonic_solve(laplacian, fixed: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The solution of L x = 0 on the free vertices with x = ``target`` on the ``fixed`` ones
    (the fixed rows and columns of L replaced by the identity, their known values moved to the
    right-hand side: a symmetric positive definite system); None when it cannot be factored."""
    from scipy.sparse.linalg import splu

    n = laplacian.shape[0]
    known = np.zeros((n, target.shape[1]))
    known[fixed] = target
    rhs = -(laplacian @ known)
    rhs[fixed] = target
    is_fixed = np.zeros(n, dtype=bool)
    is_fixed[fixed] = True
    column = np.repeat(np.arange(n), np.diff(laplacian.indptr))
    system = laplacian.copy()
    system.data[is_fixed[laplacian.indices] | is_fixed[column]] = 0.0
    system.data[diagonal_positions(laplacian)[fixed]] = 1.0
    try:
        lu = splu(system, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError:                 # exactly singular
        return None
    return lu.solve(rhs)


def _big_triangle(vertices: np.ndarray, faces: np.ndarray) -> int:
    """The most regular triangle: the largest 4 sqrt(3) area / (sum of squared edges)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    doubled = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    squares = (np.einsum("ij,ij->i", b - a, b - a) + np.einsum("ij,ij->i", c - b, c - b)
               + np.einsum("ij,ij->i", a - c, a - c))
    return int(np.argmax(2.0 * np.sqrt(3.0) * doubled / np.maximum(squares, 1e-300)))


def _inverse_stereographic(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The point of the unit sphere that projects from the north pole to (x, y)."""
    r2 = x * x + y * y
    return np.stack([2.0 * x, 2.0 * y, r2 - 1.0], axis=1) / (1.0 + r2)[:, None]


def spherical_conformal_map(vertices: np.ndarray, faces: np.ndarray,
                            cot: np.ndarray | None = None, laplacian=None) -> np.ndarray | None:
    """The spherical conformal map of a closed genus-0 mesh (see the module's docstring).

    Parameters
    ----------
    vertices : ndarray (n, 3)
    faces : ndarray (m, 3)
        A closed genus-0 triangle mesh with outward normals.
    cot : ndarray (m, 3), optional
        The cotangents of its angles (:func:`cotangents`), when known already.
    laplacian : scipy.sparse matrix, optional
        Its :func:`cotangent_laplacian`, when known already.

    Returns
    -------
    ndarray (n, 3) or None
        Points of the unit sphere, one per vertex (not checked for folds), or None when the map
        could not be computed in double precision.

    Examples
    --------
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> from mdlshapemodel.prepare.sphere import check_bijective
    >>> points, triangles = icosphere(3)
    >>> sphere = spherical_conformal_map(points * [1.5, 1.0, 1.0], triangles)
    >>> check_bijective(sphere, triangles)   # flipped triangles
    0
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    if cot is None:
        cot = cotangents(vertices, faces)
    big = _big_triangle(vertices, faces)
    p0, p1, p2 = faces[big]
    # the big triangle's own shape, its first edge from (0, 0) to (1, 0)
    a, b = vertices[p1] - vertices[p0], vertices[p2] - vertices[p0]
    length_a = float(np.linalg.norm(a))
    if not length_a > 0:
        return None
    x2 = float(np.dot(a, b)) / length_a ** 2
    y2 = float(np.linalg.norm(np.cross(a, b))) / length_a ** 2
    if not y2 > 0:
        return None
    if laplacian is None:
        laplacian = cotangent_laplacian(faces, cot, n)
    with np.errstate(all="ignore"):
        solution = _harmonic_solve(laplacian, faces[big],
                                   np.array([[0.0, 0.0], [1.0, 0.0], [x2, y2]]))
        if solution is None or not np.all(np.isfinite(solution)):
            return None
        z = solution[:, 0] + 1j * solution[:, 1]
        z = z - z.mean()
        # rescale: the big triangle and the one nearest the origin (in the south pole's chart,
        # where |w_a - w_b| = |z_a - z_b| / (|z_a| |z_b|)) of about one size
        r = np.abs(z)
        order = np.argsort(r[faces].sum(axis=1), kind="stable")
        inner = int(order[1] if order[0] == big else order[0])
        i0, i1, i2 = faces[inner]
        if not (r[i0] > 0 and r[i1] > 0 and r[i2] > 0):
            return None
        north = (abs(z[p0] - z[p1]) + abs(z[p1] - z[p2]) + abs(z[p2] - z[p0])) / 3.0
        south = (abs(z[i0] - z[i1]) / (r[i0] * r[i1]) + abs(z[i1] - z[i2]) / (r[i1] * r[i2])
                 + abs(z[i2] - z[i0]) / (r[i2] * r[i0])) / 3.0
        z = z * np.sqrt(north * south) / north
        result = _inverse_stereographic(z.real, z.imag)
    if not np.all(np.isfinite(result)):
        return None
    return result
