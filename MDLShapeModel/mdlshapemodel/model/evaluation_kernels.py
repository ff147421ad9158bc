"""Compiled (numba) loops of the model's evaluation (see :mod:`.evaluation`).

Three kinds of work dominate an evaluation, each repeated for many slightly different inputs:

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
  over the points, without the arrays of every sample's points;
- the leading roots of the secular equation of each leave-one-out model
  (:func:`~.space.leave_one_out`), for every case and, in the generalization's jackknife, every
  group left out: :func:`secular_roots` bisects them as numpy would, with numpy's order of
  summation (:func:`pairwise_sum`), so the roots are the same bit for bit.
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


@njit(cache=True, nogil=True, inline="always")
def _block_sum(values, start, n):
    """The sum of ``values[start:start + n]`` (n at most 128) as numpy sums a block: fewer than
    eight values in order, else on eight accumulators and the rest in order."""
    if n < 8:
        total = -0.0
        for i in range(start, start + n):
            total += values[i]
        return total
    r0, r1, r2, r3 = values[start], values[start + 1], values[start + 2], values[start + 3]
    r4, r5, r6, r7 = values[start + 4], values[start + 5], values[start + 6], values[start + 7]
    i = 8
    while i < n - n % 8:
        r0 += values[start + i]
        r1 += values[start + i + 1]
        r2 += values[start + i + 2]
        r3 += values[start + i + 3]
        r4 += values[start + i + 4]
        r5 += values[start + i + 5]
        r6 += values[start + i + 6]
        r7 += values[start + i + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        total += values[start + i]
        i += 1
    return total


@njit(cache=True, nogil=True)
def pairwise_sum(values):
    """The sum of a contiguous 1-D array in the order of numpy's pairwise summation: runs of at
    most 128 values summed as :func:`_block_sum`, a longer run as the sum of its two halves (the
    first a multiple of eight long), so that it equals ``numpy.sum(values)`` bit for bit. The
    halving is walked with an explicit stack (depth at most 64)."""
    n = values.shape[0]
    if n <= 128:
        return _block_sum(values, 0, n)
    starts = np.empty(64, dtype=np.int64)
    sizes = np.empty(64, dtype=np.int64)
    stage = np.zeros(64, dtype=np.int64)     # 0: not split, 1: left half pending, 2: right
    left = np.empty(64)
    top = 0
    starts[0], sizes[0], stage[0] = 0, n, 0
    value = 0.0
    done = False                             # value holds the sum of the run above top
    while True:
        if done:
            if top < 0:
                return value
            if stage[top] == 1:
                left[top] = value
                stage[top] = 2
                half = sizes[top] // 2
                half -= half % 8
                top += 1
                starts[top], sizes[top], stage[top] = starts[top - 1] + half, sizes[top - 1] - half, 0
                done = False
            else:
                value = left[top] + value
                top -= 1
            continue
        size = sizes[top]
        if size <= 128:
            value = _block_sum(values, starts[top], size)
            top -= 1
            done = True
        else:
            half = size // 2
            half -= half % 8
            stage[top] = 1
            top += 1
            starts[top], sizes[top], stage[top] = starts[top - 1], half, 0


@njit(cache=True, nogil=True)
def secular_roots(d, v, rho, count):
    """The ``count`` largest roots of the secular equation 1 - rho sum_j v_j^2 / (d_j - x) = 0
    for d descending: root k in (d[k+1], d[k]), found by bisection until the midpoint of its
    bracket is one of its ends (at most 200 halvings).

    Each step evaluates the secular function as
    ``1.0 - rho * numpy.sum(v * v / (d - x))`` does (:func:`pairwise_sum`), so the roots are
    those of the same bisection written with numpy, bit for bit; a root's bracket no longer
    changes once its midpoint is one of its ends, so each root stops on its own.
    """
    r = d.shape[0]
    squares = v * v
    terms = np.empty(r)
    roots = np.empty(count)
    for k in range(count):
        low, high = d[k + 1], d[k]
        for _ in range(200):
            middle = 0.5 * (low + high)
            if middle <= low or middle >= high:
                break
            for j in range(r):
                terms[j] = squares[j] / (d[j] - middle)
            # the secular function falls from +inf to -inf across the bracket
            if 1.0 - rho * pairwise_sum(terms) > 0.0:
                low = middle
            else:
                high = middle
        roots[k] = 0.5 * (low + high)
    return roots
