"""Compiled (numba) kernels of the sphere map's distortion minimisation (see :mod:`.sphere`).

Kept apart from :mod:`.sphere` so that importing the package does not import numba; the first
call in a process loads the compiled code from numba's cache (compiled once per installation).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def distortion_energy(x, faces, cot, area, area_weight, grad):
    """Energy of the sphere points ``x``; fills ``grad`` (n, 3) when it has rows (else skips it).

    One pass over the faces, energy and gradient together; infinite (gradient untouched) as soon
    as a triangle is flipped or degenerate.
    """
    with_gradient = grad.shape[0] > 0
    if with_gradient:
        grad[:] = 0.0
    energy_dirichlet = 0.0
    energy_area = 0.0
    for t in range(faces.shape[0]):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        p0x, p0y, p0z = x[i0, 0], x[i0, 1], x[i0, 2]
        p1x, p1y, p1z = x[i1, 0], x[i1, 1], x[i1, 2]
        p2x, p2y, p2z = x[i2, 0], x[i2, 1], x[i2, 2]
        # p1 x p2, p2 x p0, p0 x p1: twice the gradient of the area term at p0, p1, p2
        c0x = p1y * p2z - p1z * p2y
        c0y = p1z * p2x - p1x * p2z
        c0z = p1x * p2y - p1y * p2x
        a = 0.5 * (p0x * c0x + p0y * c0y + p0z * c0z)
        if not a > 0.0:
            return np.inf
        # edges opposite corner 0, 1, 2
        e0x, e0y, e0z = p2x - p1x, p2y - p1y, p2z - p1z
        e1x, e1y, e1z = p0x - p2x, p0y - p2y, p0z - p2z
        e2x, e2y, e2z = p1x - p0x, p1y - p0y, p1z - p0z
        k0, k1, k2 = cot[t, 0], cot[t, 1], cot[t, 2]
        dirichlet = 0.5 * (k0 * (e0x * e0x + e0y * e0y + e0z * e0z)
                           + k1 * (e1x * e1x + e1y * e1y + e1z * e1z)
                           + k2 * (e2x * e2x + e2y * e2y + e2z * e2z))
        big_a = area[t]
        inverse_ratio = big_a / a
        inverse_ratio2 = inverse_ratio * inverse_ratio
        energy_dirichlet += dirichlet * (1.0 + inverse_ratio2)
        energy_area += a + big_a * inverse_ratio
        if with_gradient:
            cd = 1.0 + inverse_ratio2
            ca = 0.5 * (area_weight * (1.0 - inverse_ratio2) - 2.0 * dirichlet * inverse_ratio2 / a)
            # d(dirichlet)/dp0 = k2 (p0 - p1) + k1 (p0 - p2) = k1 e1 - k2 e2, and cyclically
            grad[i0, 0] += cd * (k1 * e1x - k2 * e2x) + ca * c0x
            grad[i0, 1] += cd * (k1 * e1y - k2 * e2y) + ca * c0y
            grad[i0, 2] += cd * (k1 * e1z - k2 * e2z) + ca * c0z
            grad[i1, 0] += cd * (k2 * e2x - k0 * e0x) + ca * (p2y * p0z - p2z * p0y)
            grad[i1, 1] += cd * (k2 * e2y - k0 * e0y) + ca * (p2z * p0x - p2x * p0z)
            grad[i1, 2] += cd * (k2 * e2z - k0 * e0z) + ca * (p2x * p0y - p2y * p0x)
            grad[i2, 0] += cd * (k0 * e0x - k1 * e1x) + ca * (p0y * p1z - p0z * p1y)
            grad[i2, 1] += cd * (k0 * e0y - k1 * e1y) + ca * (p0z * p1x - p0x * p1z)
            grad[i2, 2] += cd * (k0 * e0z - k1 * e1z) + ca * (p0x * p1y - p0y * p1x)
    return energy_dirichlet + area_weight * energy_area


@numba.njit(cache=True)
def _tangent(x, v, out):
    """out = v minus its component along x, row by row (out may be v)."""
    for i in range(x.shape[0]):
        d = x[i, 0] * v[i, 0] + x[i, 1] * v[i, 1] + x[i, 2] * v[i, 2]
        out[i, 0] = v[i, 0] - d * x[i, 0]
        out[i, 1] = v[i, 1] - d * x[i, 1]
        out[i, 2] = v[i, 2] - d * x[i, 2]


@numba.njit(cache=True)
def _dot(a, b):
    """Sum of a * b over two (n, 3) arrays, without temporaries."""
    total = 0.0
    for i in range(a.shape[0]):
        total += a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]
    return total


@numba.njit(cache=True)
def _add_scaled(out, factor, v):
    """out += factor * v for (n, 3) arrays."""
    for i in range(out.shape[0]):
        out[i, 0] += factor * v[i, 0]
        out[i, 1] += factor * v[i, 1]
        out[i, 2] += factor * v[i, 2]


@numba.njit(cache=True)
def _line_search(faces, cot, area, area_weight, x, energy, direction, slope, trial, no_gradient,
                 max_halvings=30):
    """Backtracking (Armijo) along ``direction`` with retraction into ``trial``.

    Returns the accepted trial energy, or infinity when no step is accepted.
    """
    step = 1.0
    for _ in range(max_halvings):
        for i in range(x.shape[0]):
            tx = x[i, 0] + step * direction[i, 0]
            ty = x[i, 1] + step * direction[i, 1]
            tz = x[i, 2] + step * direction[i, 2]
            norm = np.sqrt(tx * tx + ty * ty + tz * tz)
            trial[i, 0] = tx / norm
            trial[i, 1] = ty / norm
            trial[i, 2] = tz / norm
        trial_energy = distortion_energy(trial, faces, cot, area, area_weight, no_gradient)
        if np.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * step * slope:
            return trial_energy
        step *= 0.5
    return np.inf


@numba.njit(cache=True)
def lbfgs(x, faces, cot, area, area_weight, max_iterations, tolerance, memory):
    """Riemannian L-BFGS of :func:`distortion_energy` from the fold-free ``x`` (modified in place).

    Returns the number of iterations done.
    """
    n = x.shape[0]
    no_gradient = np.empty((0, 3))
    raw = np.empty((n, 3))
    grad = np.empty((n, 3))
    energy = distortion_energy(x, faces, cot, area, area_weight, raw)
    _tangent(x, raw, grad)
    pairs_s = np.empty((memory, n, 3))   # ring buffer of the last ``memory`` (s, y) pairs
    pairs_y = np.empty((memory, n, 3))
    rho = np.empty(memory)
    alpha = np.empty(memory)
    stored = 0
    newest = -1
    q = np.empty((n, 3))
    direction = np.empty((n, 3))
    trial = np.empty((n, 3))
    trial_grad = np.empty((n, 3))
    history = np.empty(max_iterations + 1)
    history[0] = energy
    iterations = 0
    while iterations < max_iterations:
        # two-loop recursion: q = H grad
        q[:] = grad
        for k in range(stored):
            slot = (newest - k) % memory
            alpha[slot] = rho[slot] * _dot(pairs_s[slot], q)
            _add_scaled(q, -alpha[slot], pairs_y[slot])
        if stored:
            q *= (_dot(pairs_s[newest], pairs_y[newest])
                  / _dot(pairs_y[newest], pairs_y[newest]))
        else:
            q *= 1e-3 / max(np.abs(q).max(), 1e-300)
        for k in range(stored - 1, -1, -1):
            slot = (newest - k) % memory
            beta = rho[slot] * _dot(pairs_y[slot], q)
            _add_scaled(q, alpha[slot] - beta, pairs_s[slot])
        _tangent(x, q, direction)
        direction *= -1.0
        slope = _dot(direction, grad)
        if slope >= 0:
            direction[:] = -grad
            slope = -_dot(grad, grad)
            stored = 0
        trial_energy = _line_search(faces, cot, area, area_weight, x, energy, direction, slope,
                                    trial, no_gradient)
        if not np.isfinite(trial_energy) and stored:
            # the quasi-Newton step failed: restart from (scaled) steepest descent
            stored = 0
            direction[:] = grad * (-1e-3 / max(np.abs(grad).max(), 1e-300))
            trial_energy = _line_search(faces, cot, area, area_weight, x, energy, direction,
                                        _dot(direction, grad), trial, no_gradient)
        if not np.isfinite(trial_energy):
            break
        trial_energy = distortion_energy(trial, faces, cot, area, area_weight, raw)
        _tangent(trial, raw, trial_grad)
        # s = trial - x, y = trial_grad - (grad transported to the tangent plane at trial)
        slot = (newest + 1) % memory
        y = pairs_y[slot]
        _tangent(trial, grad, y)
        y *= -1.0
        _add_scaled(y, 1.0, trial_grad)
        pairs_s[slot] = trial
        _add_scaled(pairs_s[slot], -1.0, x)
        curvature = _dot(pairs_s[slot], y)
        if curvature > 1e-12:
            rho[slot] = 1.0 / curvature
            newest = slot
            stored = min(stored + 1, memory)
        x[:] = trial
        grad[:] = trial_grad
        energy = trial_energy
        iterations += 1
        history[iterations] = energy
        if iterations >= 20 and history[iterations - 20] - energy < tolerance * abs(energy) * 20:
            break
    return iterations
