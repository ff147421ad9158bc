"""Compiled inner loops (numba): point location and barycentric evaluation on the sphere, the
displacement fields and their chain rule, poses, and weighted point distances.

The optimisers evaluate S_i(phi(u_k)) for thousands of sample points per example and objective
evaluation; in numpy each step gathers per-point 3 x 3 matrices and corner values into temporary
arrays. These loops do the same arithmetic point by point without temporaries. They are compiled
on first use and cached on disk (``cache=True``), so later processes load them in milliseconds.

Each function here computes a documented formula that the tests check against plain numpy:
the walk against the barycentric coordinates it reports, ``interpolate`` against an einsum,
``field_apply`` against ``FieldBasis.displacement``, ``field_gradient`` against finite
differences, ``bump_matrix`` against the Wendland function of all distances, ``field_sample``
against ``field_apply`` + ``SphereLocator.locate`` / ``interpolate`` / ``jacobian``,
``field_sample_gradient`` against ``FieldBasis.coefficient_gradient`` of the chained gradient,
``field_map`` against ``field_apply`` of ``bump_matrix`` (bit for bit), ``apply_poses`` against
``Pose.apply``, ``negated_distances`` through ``bending_matrix`` (bit for bit) and
``weighted_point_norms`` through the generalization distances.

The fast strategy's evaluation is ``field_sample`` per part, ``apply_poses``, the objective, then
``field_sample_gradient`` per part: every per-point step of the chain rule in two passes.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _face_inverse(sphere, faces, f, m):
    """M^-1 = [a b c]^-1 of face ``f`` (corners a, b, c on the sphere) into ``m`` (3, 3): the rows
    b x c, c x a, a x b over det = a . (b x c).

    Operation by operation the arithmetic of these matrices in numpy, so they are the same bit
    for bit: each component of a cross product as ``np.cross`` forms it, and the determinant's
    three products summed in the order ``np.einsum("ij,ij->i", a, b x c)`` sums them (first and
    last, then the middle one), which the tests check against numpy."""
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    ax, ay, az = sphere[a, 0], sphere[a, 1], sphere[a, 2]
    bx, by, bz = sphere[b, 0], sphere[b, 1], sphere[b, 2]
    cx, cy, cz = sphere[c, 0], sphere[c, 1], sphere[c, 2]
    m[0, 0], m[0, 1], m[0, 2] = by * cz - bz * cy, bz * cx - bx * cz, bx * cy - by * cx
    m[1, 0], m[1, 1], m[1, 2] = cy * az - cz * ay, cz * ax - cx * az, cx * ay - cy * ax
    m[2, 0], m[2, 1], m[2, 2] = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    det = (ax * m[0, 0] + az * m[0, 2]) + ay * m[0, 1]
    for i in range(3):
        for j in range(3):
            m[i, j] = m[i, j] / det


@njit(cache=True, nogil=True)
def face_inverses(sphere, faces, face):
    """M^-1 of each face in ``face`` (n,): (n, 3, 3), as ``_face_inverse``."""
    result = np.empty((face.shape[0], 3, 3))
    for k in range(face.shape[0]):
        _face_inverse(sphere, faces, face[k], result[k])
    return result


@njit(cache=True, nogil=True, inline="always")
def _walk_point(sphere, faces, neighbours, x, y, z, start, steps, tolerance, lam, m):
    """From face ``start`` walk towards the point (x, y, z) across the edge opposite the most
    negative central-projection coordinate (M^-1 u), at most ``steps`` faces. Returns the face
    reached and whether the point lies in it (all coordinates >= ``tolerance``); ``lam`` holds
    that face's coordinates M^-1 u and ``m`` its M^-1 (``_face_inverse``: computed per step
    rather than stored per face, 72 bytes a face less for every part a build holds)."""
    current = start
    for _ in range(steps):
        _face_inverse(sphere, faces, current, m)
        for i in range(3):
            lam[i] = m[i, 0] * x + m[i, 1] * y + m[i, 2] * z
        worst = 0
        if lam[1] < lam[worst]:
            worst = 1
        if lam[2] < lam[worst]:
            worst = 2
        if lam[worst] >= tolerance:
            return current, True
        following = neighbours[current, worst]
        if following < 0:
            break
        current = following
    return current, False


@njit(cache=True, nogil=True)
def walk(sphere, faces, neighbours, points, hint, steps, tolerance, face, coords, found):
    """``_walk_point`` from face ``hint[k]`` to each ``points[k]``; for the points reached, fills
    ``face``, ``coords`` (barycentric: clamped at 0 and normalised to sum 1) and ``found``."""
    lam = np.empty(3)
    m = np.empty((3, 3))
    for k in range(points.shape[0]):
        current, found[k] = _walk_point(sphere, faces, neighbours, points[k, 0], points[k, 1],
                                        points[k, 2], hint[k], steps, tolerance, lam, m)
        if found[k]:
            l0, l1, l2 = max(lam[0], 0.0), max(lam[1], 0.0), max(lam[2], 0.0)
            total = l0 + l1 + l2
            face[k] = current
            coords[k, 0], coords[k, 1], coords[k, 2] = l0 / total, l1 / total, l2 / total


@njit(cache=True, nogil=True)
def interpolate(values, faces, face, coords):
    """sum_j coords[k, j] * values[faces[face[k], j]] for per-vertex values (v, d)."""
    n, d = face.shape[0], values.shape[1]
    result = np.empty((n, d))
    for k in range(n):
        a, b, c = faces[face[k], 0], faces[face[k], 1], faces[face[k], 2]
        wa, wb, wc = coords[k, 0], coords[k, 1], coords[k, 2]
        for e in range(d):
            result[k, e] = wa * values[a, e] + wb * values[b, e] + wc * values[c, e]
    return result


@njit(cache=True, nogil=True, inline="always")
def _field_point(indptr, indices, data, points, coefficients, k, phi, norms):
    """phi[k] and norms[k] of ``field_apply``."""
    r0 = r1 = r2 = 0.0
    for t in range(indptr[k], indptr[k + 1]):
        j, w = indices[t], data[t]
        r0 += w * coefficients[j, 0]
        r1 += w * coefficients[j, 1]
        r2 += w * coefficients[j, 2]
    _project_point(points[k, 0], points[k, 1], points[k, 2], r0, r1, r2, k, phi, norms)


@njit(cache=True, nogil=True, inline="always")
def _project_point(ux, uy, uz, r0, r1, r2, k, phi, norms):
    """phi[k] = m / |m| and norms[k] = |m| for m = u + (I - u u^T) r, r = (W c)_k."""
    normal = r0 * ux + r1 * uy + r2 * uz
    mx = ux + r0 - normal * ux
    my = uy + r1 - normal * uy
    mz = uz + r2 - normal * uz
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    norms[k] = norm
    phi[k, 0], phi[k, 1], phi[k, 2] = mx / norm, my / norm, mz / norm


@njit(cache=True, nogil=True)
def field_apply(indptr, indices, data, points, coefficients):
    """phi(u_k) = m / |m| with m = u + (I - u u^T) W c, for the sparse bump matrix W (CSR arrays);
    returns phi (n, 3) and |m| (n,)."""
    n = points.shape[0]
    phi = np.empty((n, 3))
    norms = np.empty(n)
    for k in range(n):
        _field_point(indptr, indices, data, points, coefficients, k, phi, norms)
    return phi, norms


@njit(cache=True, nogil=True)
def field_gradient(indptr, indices, data, points, phi, norms, position_gradient, n_centres):
    """dF/dc (n_c, 3) from dF/dphi(u_k): W^T (I - u u^T) (I - phi phi^T) g / |m|."""
    result = np.zeros((n_centres, 3))
    for k in range(points.shape[0]):
        gx, gy, gz = position_gradient[k, 0], position_gradient[k, 1], position_gradient[k, 2]
        along = gx * phi[k, 0] + gy * phi[k, 1] + gz * phi[k, 2]
        gx = (gx - along * phi[k, 0]) / norms[k]
        gy = (gy - along * phi[k, 1]) / norms[k]
        gz = (gz - along * phi[k, 2]) / norms[k]
        ux, uy, uz = points[k, 0], points[k, 1], points[k, 2]
        normal = gx * ux + gy * uy + gz * uz
        gx, gy, gz = gx - normal * ux, gy - normal * uy, gz - normal * uz
        for t in range(indptr[k], indptr[k + 1]):
            j, w = indices[t], data[t]
            result[j, 0] += w * gx
            result[j, 1] += w * gy
            result[j, 2] += w * gz
    return result


@njit(cache=True, nogil=True)
def weighted_point_norms(displacements, weights):
    """sum_p weights[p] |d_p| for each row of point displacements (k, 3 n_p) -> (k,)."""
    k = displacements.shape[0]
    result = np.zeros(k)
    for i in range(k):
        total = 0.0
        for p in range(weights.shape[0]):
            x = displacements[i, 3 * p]
            y = displacements[i, 3 * p + 1]
            z = displacements[i, 3 * p + 2]
            total += weights[p] * np.sqrt(x * x + y * y + z * z)
        result[i] = total
    return result


@njit(cache=True, nogil=True)
def negated_distances(points, out):
    """out[j, k] = -|p_j - p_k| for points (n, 3) into ``out`` (n, n), the squares summed x, y,
    then z: the bits of ``-np.linalg.norm(points[:, None] - points[None], axis=2)`` without its
    (n, n, 3) temporaries."""
    n = points.shape[0]
    for j in range(n):
        x, y, z = points[j, 0], points[j, 1], points[j, 2]
        for k in range(n):
            dx, dy, dz = x - points[k, 0], y - points[k, 1], z - points[k, 2]
            out[j, k] = -np.sqrt(dx * dx + dy * dy + dz * dz)


#: :func:`bump_matrix` tests every centre up to this many, and those of nearby cells beyond
BINNED_CENTRES = 200


@njit(cache=True, nogil=True)
def _length2_excess(vectors):
    """max(0, the largest |v|^2 - 1) of the rows of ``vectors``."""
    excess = 0.0
    for k in range(vectors.shape[0]):
        length2 = vectors[k, 0] ** 2 + vectors[k, 1] ** 2 + vectors[k, 2] ** 2
        excess = max(excess, length2 - 1.0)
    return excess


@njit(cache=True, nogil=True)
def _bump_candidates(px, py, pz, low, cell, shape, start, order, reach, bounds, found):
    """The centres binned (``start``, ``order``) in the cells of a box of side ``reach`` around
    (px, py, pz) into ``found`` (in the cells' order); returns how many. ``bounds`` (3, 2):
    room for the box's cell range."""
    count = 0
    for axis, value in enumerate((px, py, pz)):
        for side, shifted in enumerate((value - reach, value + reach)):
            index = int(np.floor((shifted - low[axis]) / cell))
            bounds[axis, side] = min(max(index, 0), shape[axis] - 1)
    for i in range(bounds[0, 0], bounds[0, 1] + 1):
        for j in range(bounds[1, 0], bounds[1, 1] + 1):
            for k in range(bounds[2, 0], bounds[2, 1] + 1):
                box = (i * shape[1] + j) * shape[2] + k
                for t in range(start[box], start[box + 1]):
                    found[count] = order[t]
                    count += 1
    return count


#: What :func:`_row_bumps` needs to find the bumps at a point (:func:`_bump_search`): the
#: dot-product threshold, the cells' side ``reach``, their ``low`` corner and ``shape``, the
#: centres binned (``start``, ``order``), ``binned`` (whether to search the cells; else every
#: centre is tested, in order) and work arrays ``bounds``, ``found``, ``columns`` and ``values``
#: (room for a row of every centre)
BumpSearch = namedtuple("BumpSearch", ["threshold", "reach", "low", "shape", "start", "order",
                                       "binned", "bounds", "found", "columns", "values"])


@njit(cache=True, nogil=True)
def _bump_search(points, centres, radius):
    """The :data:`BumpSearch` of ``centres`` (support radius ``radius``) for ``points``."""
    m = centres.shape[0]
    threshold = 1.0 - 0.5 * radius * radius
    excess = max(_length2_excess(points), _length2_excess(centres))
    reach = np.sqrt(radius * radius + 2.0 * excess + 1e-12) + 1e-9
    low = np.empty(3)
    shape = np.ones(3, dtype=np.int64)
    for axis in range(3):
        if m:
            low[axis] = centres[:, axis].min()
            shape[axis] = int((centres[:, axis].max() - low[axis]) / reach) + 1
        else:
            low[axis] = 0.0
    cells = shape[0] * shape[1] * shape[2]
    home = np.empty(m, dtype=np.int64)
    start = np.zeros(cells + 1, dtype=np.int64)
    index = np.empty(3, dtype=np.int64)
    for j in range(m):
        for axis in range(3):
            cell_index = int(np.floor((centres[j, axis] - low[axis]) / reach))
            index[axis] = min(max(cell_index, 0), shape[axis] - 1)
        home[j] = (index[0] * shape[1] + index[1]) * shape[2] + index[2]
        start[home[j] + 1] += 1
    start = np.cumsum(start)
    order = np.empty(m, dtype=np.int64)
    filled = start[:-1].copy()
    for j in range(m):
        order[filled[home[j]]] = j
        filled[home[j]] += 1
    binned = m > BINNED_CENTRES and cells > 1
    return BumpSearch(threshold, reach, low, shape, start, order, binned,
                      np.empty((3, 2), dtype=np.int64), np.arange(m),
                      np.empty(m, dtype=np.int64), np.empty(m))


@njit(cache=True, nogil=True, inline="always")
def _row_bumps(x, y, z, centres, radius, search):
    """The bumps at the point (x, y, z): their centres' indices into ``search.columns`` and
    values g(|u - P_j| / r) into ``search.values`` (a :data:`BumpSearch`), in increasing order
    of index; returns how many. A centre counts where u.P passes the threshold
    (|u - P|^2 = 2 - 2 u.P < r^2)."""
    threshold, found = search.threshold, search.found
    columns, values = search.columns, search.values
    candidates = centres.shape[0] if not search.binned else _bump_candidates(
        x, y, z, search.low, search.reach, search.shape, search.start, search.order, search.reach,
        search.bounds, found)
    count = 0
    for c in range(candidates):
        j = found[c]
        if x * centres[j, 0] + y * centres[j, 1] + z * centres[j, 2] > threshold:
            dx, dy, dz = x - centres[j, 0], y - centres[j, 1], z - centres[j, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz) / radius
            value = (1.0 - d) ** 4 * (4.0 * d + 1.0) if d < 1.0 else 0.0
            # into the row in increasing order of column (an insertion: a few dozen; the cells
            # give them out of order, every centre in turn gives them in order)
            at = count
            while at > 0 and columns[at - 1] > j:
                columns[at], values[at] = columns[at - 1], values[at - 1]
                at -= 1
            columns[at], values[at] = j, value
            count += 1
    return count


@njit(cache=True, nogil=True)
def bump_matrix(points, centres, radius):
    """The CSR arrays (indptr, indices, data) of the (n, n_c) matrix of Wendland bumps
    g(|u_k - P_j| / r) at unit vectors u_k, centres P_j (unit), support radius r (chord): every
    pair within r, columns in increasing order, with the test |u - P|^2 = 2 - 2 u.P < r^2 on the
    dot product.

    Beyond :data:`BINNED_CENTRES` centres, they are binned in cubic cells of side ``reach`` and
    each point tests those of the cells within ``reach`` along each axis, its row then put in
    increasing order of column (fewer centres: every one, in order): the same pairs and
    arithmetic as a test of every centre. A pair that passes has |u - P|^2 < |u|^2 + |P|^2 - 2 +
    r^2 (up to the dot product's rounding), so ``reach`` is r widened by the vectors' largest
    departure from unit length and a margin far above that rounding. One pass over the points:
    the arrays grow as the rows come, and the filled part of them is returned (no copy).
    """
    n = points.shape[0]
    search = _bump_search(points, centres, radius)
    columns, values = search.columns, search.values
    indptr = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(max(16 * n, 16), dtype=np.int64)
    data = np.empty(indices.shape[0])
    t = 0
    for k in range(n):
        count = _row_bumps(points[k, 0], points[k, 1], points[k, 2], centres, radius, search)
        if t + count > indices.shape[0]:
            room = max(2 * indices.shape[0], t + count)
            more, wider = np.empty(room, dtype=np.int64), np.empty(room)
            for c in range(t):   # a loop: a slice assignment compiles far more
                more[c], wider[c] = indices[c], data[c]
            indices, data = more, wider
        for c in range(count):
            indices[t], data[t] = columns[c], values[c]
            t += 1
        indptr[k + 1] = t
    return indptr, indices[:t], data[:t]


@njit(cache=True, nogil=True)
def field_map(points, centres, radius, coefficients):
    """``field_apply`` of the bumps of ``bump_matrix(points, centres, radius)`` without the
    matrix: each point's bumps are found (:func:`_row_bumps`) and summed in the same order, so
    phi (n, 3) and |m| (n,) are those of ``field_apply`` bit for bit. For a map applied once
    (a round's field replayed on another grid), where the matrix would be made for one use."""
    n = points.shape[0]
    phi = np.empty((n, 3))
    norms = np.empty(n)
    search = _bump_search(points, centres, radius)
    columns, values = search.columns, search.values
    for k in range(n):
        x, y, z = points[k, 0], points[k, 1], points[k, 2]
        count = _row_bumps(x, y, z, centres, radius, search)
        r0 = r1 = r2 = 0.0
        for t in range(count):
            j, w = columns[t], values[t]
            r0 += w * coefficients[j, 0]
            r1 += w * coefficients[j, 1]
            r2 += w * coefficients[j, 2]
        _project_point(x, y, z, r0, r1, r2, k, phi, norms)
    return phi, norms


@njit(cache=True, nogil=True)
def field_sample(indptr, indices, data, points, coefficients, sphere, neighbours, faces,
                 values, hint, steps, phi, norms, face, sampled, jac, found):
    """One pass per point of what a gradient step needs: the field map phi(u_k) and |m| (as
    ``field_apply``), the face containing phi(u_k) by a walk from ``hint[k]`` (as ``walk``), the
    surface point S(phi(u_k)) (as ``interpolate``) and dS/du there, jac[k, d, e] = dS_d/du_e
    (as ``SphereLocator.jacobian``), into the given arrays. ``found[k]`` is False where the walk
    did not reach the point within ``steps`` faces (then only phi and norms are set)."""
    lam = np.empty(3)
    m = np.empty((3, 3))
    for k in range(points.shape[0]):
        _field_point(indptr, indices, data, points, coefficients, k, phi, norms)
        current, reached = _walk_point(sphere, faces, neighbours, phi[k, 0], phi[k, 1],
                                       phi[k, 2], hint[k], steps, -1e-12, lam, m)
        found[k] = reached
        if not reached:
            continue
        face[k] = current
        total = lam[0] + lam[1] + lam[2]
        clamped = max(lam[0], 0.0) + max(lam[1], 0.0) + max(lam[2], 0.0)
        for d in range(3):
            sampled[k, d] = 0.0
            for e in range(3):
                jac[k, d, e] = 0.0
        for i in range(3):
            v = faces[current, i]
            weight = max(lam[i], 0.0) / clamped
            b = lam[i] / total
            for d in range(3):
                sampled[k, d] += weight * values[v, d]
            # dS/du = V^T (I - b 1^T) M^-1 / s: corner i contributes V_i (M^-1[i] - b_i colsum)
            for e in range(3):
                row = (m[i, e] - b * (m[0, e] + m[1, e] + m[2, e])) / total
                for d in range(3):
                    jac[k, d, e] += values[v, d] * row


@njit(cache=True, nogil=True)
def field_sample_gradient(indptr, indices, data, points, phi, norms, jac, scale, rotation,
                          shape_gradient, n_centres):
    """dF/dc (n_c, 3) of one part's field from dF/dX of its posed points X = scale R S(phi) + t:
    per point dF/dS = scale R^T g, dF/dphi = (dS/du)^T dF/dS (``jac`` of ``field_sample``),
    then the chain rule of ``field_gradient``."""
    du = np.empty((points.shape[0], 3))
    for k in range(points.shape[0]):
        g0, g1, g2 = shape_gradient[k, 0], shape_gradient[k, 1], shape_gradient[k, 2]
        s0 = scale * (rotation[0, 0] * g0 + rotation[1, 0] * g1 + rotation[2, 0] * g2)
        s1 = scale * (rotation[0, 1] * g0 + rotation[1, 1] * g1 + rotation[2, 1] * g2)
        s2 = scale * (rotation[0, 2] * g0 + rotation[1, 2] * g1 + rotation[2, 2] * g2)
        for e in range(3):
            du[k, e] = jac[k, 0, e] * s0 + jac[k, 1, e] * s1 + jac[k, 2, e] * s2
    return field_gradient(indptr, indices, data, points, phi, norms, du, n_centres)


@njit(cache=True, nogil=True)
def apply_poses(points, scale, rotation, translation):
    """scale[a] R[a] x + t[a] for every point x of every shape a: (n_a, n, 3) -> (n_a, n, 3)."""
    result = np.empty(points.shape)
    for a in range(points.shape[0]):
        r = rotation[a] * scale[a]
        t0, t1, t2 = translation[a, 0], translation[a, 1], translation[a, 2]
        for k in range(points.shape[1]):
            x, y, z = points[a, k, 0], points[a, k, 1], points[a, k, 2]
            result[a, k, 0] = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t0
            result[a, k, 1] = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t1
            result[a, k, 2] = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t2
    return result
