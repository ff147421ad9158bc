"""Compiled inner loops (numba): point location and barycentric evaluation on the sphere, the
displacement fields, and weighted point distances.

The optimisers evaluate S_i(phi(u_k)) for thousands of sample points per example and objective
evaluation; in numpy each step gathers per-point 3 x 3 matrices and corner values into temporary
arrays. These loops do the same arithmetic point by point without temporaries. They are compiled
on first use and cached on disk (``cache=True``), so later processes load them in milliseconds.

Each function here computes a documented formula that the tests check against plain numpy:
the walk against the barycentric coordinates it reports, ``interpolate`` against an einsum,
``jacobian_transpose`` against ``SphereLocator.jacobian``, ``field_apply`` against
``FieldBasis.displacement``, ``field_gradient`` against finite differences and
``weighted_point_norms`` through the generalization distances.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def walk(inverse, neighbours, points, hint, steps, tolerance, face, coords, found):
    """From face ``hint[k]`` walk towards ``points[k]`` across the edge opposite the most negative
    central-projection coordinate (M^-1 u), at most ``steps`` faces; for the points reached, fills
    ``face``, ``coords`` (barycentric: clamped at 0 and normalised to sum 1) and ``found``."""
    for k in range(points.shape[0]):
        current = hint[k]
        x, y, z = points[k, 0], points[k, 1], points[k, 2]
        found[k] = False
        for _ in range(steps):
            m = inverse[current]
            l0 = m[0, 0] * x + m[0, 1] * y + m[0, 2] * z
            l1 = m[1, 0] * x + m[1, 1] * y + m[1, 2] * z
            l2 = m[2, 0] * x + m[2, 1] * y + m[2, 2] * z
            worst, value = 0, l0
            if l1 < value:
                worst, value = 1, l1
            if l2 < value:
                worst, value = 2, l2
            if value >= tolerance:
                l0, l1, l2 = max(l0, 0.0), max(l1, 0.0), max(l2, 0.0)
                total = l0 + l1 + l2
                face[k] = current
                coords[k, 0], coords[k, 1], coords[k, 2] = l0 / total, l1 / total, l2 / total
                found[k] = True
                break
            following = neighbours[current, worst]
            if following < 0:
                break
            current = following


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


@njit(cache=True, nogil=True)
def jacobian_transpose(inverse, faces, values, face, points, gradient):
    """(dS/du)^T g per point: M^-T (I - 1 b^T) V g / s, with lambda = M^-1 u, s = 1^T lambda,
    b = lambda / s and V the face's corner values (see ``SphereLocator.jacobian``)."""
    n = face.shape[0]
    result = np.empty((n, 3))
    corner = np.empty(3)
    raw = np.empty(3)
    for k in range(n):
        f = face[k]
        m = inverse[f]
        total = 0.0
        for i in range(3):
            raw[i] = m[i, 0] * points[k, 0] + m[i, 1] * points[k, 1] + m[i, 2] * points[k, 2]
            total += raw[i]
        projected = 0.0
        for i in range(3):
            v = faces[f, i]
            corner[i] = (values[v, 0] * gradient[k, 0] + values[v, 1] * gradient[k, 1]
                         + values[v, 2] * gradient[k, 2])
            projected += raw[i] * corner[i]
        projected /= total
        for i in range(3):
            corner[i] -= projected
        for j in range(3):
            result[k, j] = (m[0, j] * corner[0] + m[1, j] * corner[1]
                            + m[2, j] * corner[2]) / total
    return result


@njit(cache=True, nogil=True)
def field_apply(indptr, indices, data, points, coefficients):
    """phi(u_k) = m / |m| with m = u + (I - u u^T) W c, for the sparse bump matrix W (CSR arrays);
    returns phi (n, 3) and |m| (n,)."""
    n = points.shape[0]
    phi = np.empty((n, 3))
    norms = np.empty(n)
    raw = np.empty(3)
    for k in range(n):
        raw[0] = raw[1] = raw[2] = 0.0
        for t in range(indptr[k], indptr[k + 1]):
            j, w = indices[t], data[t]
            raw[0] += w * coefficients[j, 0]
            raw[1] += w * coefficients[j, 1]
            raw[2] += w * coefficients[j, 2]
        ux, uy, uz = points[k, 0], points[k, 1], points[k, 2]
        normal = raw[0] * ux + raw[1] * uy + raw[2] * uz
        mx = ux + raw[0] - normal * ux
        my = uy + raw[1] - normal * uy
        mz = uz + raw[2] - normal * uz
        norm = np.sqrt(mx * mx + my * my + mz * mz)
        norms[k] = norm
        phi[k, 0], phi[k, 1], phi[k, 2] = mx / norm, my / norm, mz / norm
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
