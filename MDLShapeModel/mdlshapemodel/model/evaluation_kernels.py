"""Compiled (numba) loops of the model's evaluation (see :mod:`.evaluation`).

Two kinds of work dominate an evaluation, both repeated for many slightly different inputs:

- exact closest points on a triangle mesh, asked again and again for points or meshes that move
  a little between two questions (a reconstruction with one more mode, the next sample).
  :func:`closest_from` starts each point's search from a guessed triangle (the answer to the
  previous question): its distance bounds the search to the grid cells within it, and each
  triangle there whose bounding box lies farther is passed over without the full point-to-triangle
  test. The answer is the exact minimum over all triangles of the same point-to-triangle distance
  as :func:`~mdlshapemodel.prepare.nearest.query_grid` computes, whatever the guess, so the two
  give the same distances bit for bit;
- the area-weighted point-to-point distance of each specificity sample to its nearest training
  shape, for every number of modes: :func:`sample_distances` builds each sample's points mode by
  mode and measures them against the training shape chosen for that number of modes, in one pass
  over the points, without the arrays of every sample's points.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..prepare.nearest import cell_index, closest_on_triangle


@njit(cache=True, nogil=True)
def triangle_boxes(vertices, faces):
    """The bounding box of each triangle, (m, 6): low x, y, z, then high x, y, z; and the largest
    absolute coordinate of their vertices."""
    boxes = np.empty((faces.shape[0], 6))
    extent = 0.0
    for f in range(faces.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        for d in range(3):
            boxes[f, d] = min(vertices[a, d], vertices[b, d], vertices[c, d])
            boxes[f, 3 + d] = max(vertices[a, d], vertices[b, d], vertices[c, d])
            extent = max(extent, -boxes[f, d], boxes[f, 3 + d])
    return boxes, extent


@njit(cache=True, nogil=True)
def farthest_points(points, size):
    """Indices (size,) of farthest-point samples of ``points`` (n, 3): point 0, then each time
    the point farthest from those chosen (the first of equals), by Euclidean distances computed
    as ``numpy.linalg.norm(points - point, axis=1)`` computes them."""
    n = points.shape[0]
    centres = np.zeros(size, dtype=np.int64)
    distance = np.empty(n)
    for i in range(n):
        x, y, z = points[i, 0] - points[0, 0], points[i, 1] - points[0, 1], points[i, 2] - points[0, 2]
        distance[i] = np.sqrt(x * x + y * y + z * z)
    for h in range(1, size):
        best = 0
        for i in range(1, n):
            if distance[i] > distance[best]:
                best = i
        centres[h] = best
        for i in range(n):
            x = points[i, 0] - points[best, 0]
            y = points[i, 1] - points[best, 1]
            z = points[i, 2] - points[best, 2]
            distance[i] = min(distance[i], np.sqrt(x * x + y * y + z * z))
    return centres


@njit(cache=True, nogil=True, inline="always")
def _triangle_distance2(f, px, py, pz, vertices, faces, q):
    """Squared distance from point p to triangle f (:func:`closest_on_triangle`)."""
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    return closest_on_triangle(px, py, pz, vertices[a, 0], vertices[a, 1], vertices[a, 2],
                                vertices[b, 0], vertices[b, 1], vertices[b, 2],
                                vertices[c, 0], vertices[c, 1], vertices[c, 2], q)


@njit(cache=True, nogil=True)
def closest_from(points, guess, vertices, faces, boxes, origin, cell, shape, start, triangles,
                 extent):
    """Exact squared distance from each point to the mesh, and a triangle at that distance,
    searched from the guessed triangle ``guess[p]`` of each point.

    The grid (``origin``, ``cell``, ``shape``, ``start``, ``triangles``) is that of
    :class:`~mdlshapemodel.prepare.nearest.TriangleGrid` for (``vertices``, ``faces``), whose
    every cell lists each triangle whose bounding box meets it, and ``boxes`` are the triangles'
    bounding boxes (:func:`triangle_boxes`). With r the distance to the guessed triangle, any
    nearer triangle has its nearest point within r of p along each axis, hence in a cell of the
    range searched, which lists that triangle; a triangle whose box lies farther than the nearest
    distance found so far cannot be nearer and is not tested. Both bounds are widened by 1e-9
    times the size of the coordinates (``extent``, the largest absolute vertex coordinate, or
    the point's): far above their rounding, so that no triangle is passed over by rounding. The
    result is the minimum over all triangles of the distances
    :func:`~mdlshapemodel.prepare.nearest.query_grid` computes, for any guess; among triangles
    at exactly that distance, the guess or the first tested is returned.

    Returns (squared distances (k,), faces (k,)).
    """
    k = points.shape[0]
    nx, ny, nz = shape[0], shape[1], shape[2]
    squared = np.empty(k)
    face = np.empty(k, dtype=np.int64)
    tested = np.full(faces.shape[0], -1, dtype=np.int64)     # the last point tested against
    q = np.empty(3)
    for p in range(k):
        px, py, pz = points[p, 0], points[p, 1], points[p, 2]
        tolerance = 1e-9 * (1.0 + max(extent, abs(px), abs(py), abs(pz)))
        best_face = guess[p]
        best = _triangle_distance2(best_face, px, py, pz, vertices, faces, q)
        tested[best_face] = p
        reach = np.sqrt(best) + tolerance
        limit = reach * reach
        i0, i1 = cell_index(px - reach, origin[0], cell, nx), cell_index(px + reach, origin[0], cell, nx)
        j0, j1 = cell_index(py - reach, origin[1], cell, ny), cell_index(py + reach, origin[1], cell, ny)
        k0, k1 = cell_index(pz - reach, origin[2], cell, nz), cell_index(pz + reach, origin[2], cell, nz)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                for kk in range(k0, k1 + 1):
                    index = (i * ny + j) * nz + kk
                    for t in range(start[index], start[index + 1]):
                        f = triangles[t]
                        gx = max(boxes[f, 0] - px, px - boxes[f, 3], 0.0)
                        gy = max(boxes[f, 1] - py, py - boxes[f, 4], 0.0)
                        gz = max(boxes[f, 2] - pz, pz - boxes[f, 5], 0.0)
                        # (a triangle is listed in every cell its box meets: tested once)
                        if gx * gx + gy * gy + gz * gz > limit or tested[f] == p:
                            continue
                        tested[f] = p
                        d = _triangle_distance2(f, px, py, pz, vertices, faces, q)
                        if d < best:
                            best, best_face = d, f
                            reach = np.sqrt(best) + tolerance
                            limit = reach * reach
        squared[p] = best
        face[p] = best_face
    return squared, face


@njit(cache=True, nogil=True)
def sample_distances(scores, to_points, train_points, nearest, kept, weights, out):
    """Area-weighted mean point-to-point distances of model samples to training shapes.

    For sample s and column c, the sample's point displacements are
    sum_{m < kept[c]} scores[s, m] to_points[m] (accumulated in the order of m), and
    ``out[s, c]`` = sum_p weights[p] |displacement_p - train_points[nearest[s, c]]_p|, summed over
    the points in order (as :func:`~mdlshapemodel.correspondence.hotloops.weighted_point_norms`).
    ``kept`` must not decrease along c. Shapes: scores (k, r), to_points (r, 3 n_p), train_points
    (n_s, 3 n_p), nearest (k, c), kept (c,), weights (n_p,), out (k, c).
    """
    n_columns = kept.shape[0]
    n_points = weights.shape[0]
    points = np.empty(3 * n_points)
    for s in range(scores.shape[0]):
        points[:] = 0.0
        used = 0
        for c in range(n_columns):
            while used < kept[c]:
                score = scores[s, used]
                for e in range(3 * n_points):
                    points[e] += score * to_points[used, e]
                used += 1
            train = train_points[nearest[s, c]]
            total = 0.0
            for p in range(n_points):
                x = points[3 * p] - train[3 * p]
                y = points[3 * p + 1] - train[3 * p + 1]
                z = points[3 * p + 2] - train[3 * p + 2]
                total += weights[p] * np.sqrt(x * x + y * y + z * z)
            out[s, c] = total
