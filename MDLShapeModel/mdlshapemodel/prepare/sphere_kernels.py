"""Compiled (numba) kernels of the sphere map's distortion minimisation (see :mod:`.sphere`).

Kept apart from :mod:`.sphere` so that importing the package does not import numba; the first
call in a process loads the compiled code from numba's cache (compiled once per installation).
"""

from __future__ import annotations

import numba
import numpy as np

from ..errors import ArgumentError


def no_factor() -> tuple:
    """The ``factor`` argument of :func:`lbfgs` for no preconditioner."""
    return (np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
            np.zeros(0), np.zeros(0, dtype=np.int64))


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
def balance_objective(v, points, faces, target_log_share, smoothing, gradient):
    """Smoothed mean |ln area ratio| of the triangles after the Moebius transformation with
    centre c = v / sqrt(1 + |v|^2) (see :func:`.sphere.balance_objective`); its gradient with
    respect to ``v`` into ``gradient`` (3,).

    Each point x goes to y = (1 - |c|^2) (x - c) / |x - c|^2 - c. The ratio of a triangle is
    its share of the chord triangles' total area over ``exp(target_log_share)``; the gradient
    runs back through the areas (d|n| / dp0 = (p1 - p2) x n / |n|, cyclically) and y.
    """
    n = points.shape[0]
    m = faces.shape[0]
    scale = np.sqrt(1.0 + v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    c0, c1, c2 = v[0] / scale, v[1] / scale, v[2] / scale
    factor = 1.0 - (c0 * c0 + c1 * c1 + c2 * c2)
    y = np.empty((n, 3))
    dd = np.empty(n)
    for i in range(n):
        d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
        dd[i] = d0 * d0 + d1 * d1 + d2 * d2
        y[i, 0] = factor * d0 / dd[i] - c0
        y[i, 1] = factor * d1 / dd[i] - c1
        y[i, 2] = factor * d2 / dd[i] - c2
    normal = np.empty((m, 3))
    twice_area = np.empty(m)
    total = 0.0
    for t in range(m):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        ux, uy, uz = y[i1, 0] - y[i0, 0], y[i1, 1] - y[i0, 1], y[i1, 2] - y[i0, 2]
        wx, wy, wz = y[i2, 0] - y[i0, 0], y[i2, 1] - y[i0, 1], y[i2, 2] - y[i0, 2]
        nx, ny, nz = uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx
        normal[t, 0], normal[t, 1], normal[t, 2] = nx, ny, nz
        twice_area[t] = max(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        total += twice_area[t]
    log_total = np.log(total)
    value = 0.0
    h = np.empty(m)
    h_sum = 0.0
    for t in range(m):
        log_ratio = np.log(twice_area[t]) - log_total - target_log_share[t]
        smooth = np.sqrt(log_ratio * log_ratio + smoothing * smoothing)
        value += smooth
        h[t] = log_ratio / smooth / m
        h_sum += h[t]
    g_y = np.zeros((n, 3))
    for t in range(m):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        d_area = h[t] / twice_area[t] - h_sum / total
        ux = normal[t, 0] * d_area / twice_area[t]
        uy = normal[t, 1] * d_area / twice_area[t]
        uz = normal[t, 2] * d_area / twice_area[t]
        for corner, j1, j2 in ((i0, i1, i2), (i1, i2, i0), (i2, i0, i1)):
            ex, ey, ez = y[j1, 0] - y[j2, 0], y[j1, 1] - y[j2, 1], y[j1, 2] - y[j2, 2]
            g_y[corner, 0] += ey * uz - ez * uy
            g_y[corner, 1] += ez * ux - ex * uz
            g_y[corner, 2] += ex * uy - ey * ux
    # through y = factor d / dd - c, d = x - c:
    # dy/dc^T g = -2 c (d.g)/dd - factor (g - 2 d (d.g)/dd) / dd - g
    dg_sum = 0.0
    s0 = s1 = s2 = 0.0       # sum g / dd
    r0 = r1 = r2 = 0.0       # sum d (d.g) / dd^2
    t0 = t1 = t2 = 0.0       # sum g
    for i in range(n):
        d0, d1, d2 = points[i, 0] - c0, points[i, 1] - c1, points[i, 2] - c2
        dg = (d0 * g_y[i, 0] + d1 * g_y[i, 1] + d2 * g_y[i, 2]) / dd[i]
        dg_sum += dg
        s0 += g_y[i, 0] / dd[i]
        s1 += g_y[i, 1] / dd[i]
        s2 += g_y[i, 2] / dd[i]
        r0 += d0 * (dg / dd[i])
        r1 += d1 * (dg / dd[i])
        r2 += d2 * (dg / dd[i])
        t0 += g_y[i, 0]
        t1 += g_y[i, 1]
        t2 += g_y[i, 2]
    g0 = -2.0 * c0 * dg_sum - factor * (s0 - 2.0 * r0) - t0
    g1 = -2.0 * c1 * dg_sum - factor * (s1 - 2.0 * r1) - t1
    g2 = -2.0 * c2 * dg_sum - factor * (s2 - 2.0 * r2) - t2
    # c = v / scale: dc/dv = I / scale - v v^T / scale^3 (symmetric)
    vg = v[0] * g0 + v[1] * g1 + v[2] * g2
    cube = scale * scale * scale
    gradient[0] = g0 / scale - v[0] * vg / cube
    gradient[1] = g1 / scale - v[1] * vg / cube
    gradient[2] = g2 / scale - v[2] * vg / cube
    return value / m


@numba.njit(cache=True)
def _copy3(out, out_column, v, v_column):
    """out[:, out_column:out_column + 3] = v[:, v_column:v_column + 3], element by element: a
    slice assignment between arrays would make numba compile its shape-mismatch message (string
    formatting), more code than the kernels that copy."""
    for i in range(out.shape[0]):
        out[i, out_column] = v[i, v_column]
        out[i, out_column + 1] = v[i, v_column + 1]
        out[i, out_column + 2] = v[i, v_column + 2]


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
    """Sum of a * b over two (n, 3) arrays, without temporaries (one running sum per column, so
    that the three chains of additions overlap)."""
    total_x = 0.0
    total_y = 0.0
    total_z = 0.0
    for i in range(a.shape[0]):
        total_x += a[i, 0] * b[i, 0]
        total_y += a[i, 1] * b[i, 1]
        total_z += a[i, 2] * b[i, 2]
    return total_x + total_y + total_z


@numba.njit(cache=True)
def _add_scaled(out, factor, v):
    """out += factor * v for (n, 3) arrays."""
    for i in range(out.shape[0]):
        out[i, 0] += factor * v[i, 0]
        out[i, 1] += factor * v[i, 1]
        out[i, 2] += factor * v[i, 2]


@numba.njit(cache=True)
def _largest_magnitude(v):
    """max |v_ij| of an (n, 3) array."""
    largest = 0.0
    for i in range(v.shape[0]):
        for k in range(3):
            largest = max(largest, abs(v[i, k]))
    return largest


@numba.njit(cache=True)
def solve_factor(lower_start, lower_row, lower_value, pivot, permutation, b, work):
    """b <- A^-1 b for the six columns of ``b`` (n, 6): two vector fields at once, which costs
    less than two solves (the factor is read once). A = P^T L D L^T P.

    ``L`` is unit lower triangular, given by its entries below the diagonal in compressed
    columns (``lower_start``, ``lower_row``, ``lower_value``), ``D`` = diag(``pivot``), and P
    the permutation with (P b)[permutation[i]] = b[i]. ``work`` is a scratch array like ``b``.
    The six columns are written out: a loop over them runs at half the speed.
    """
    n = b.shape[0]
    if b.shape[1] != 6 or work.shape[0] != n or work.shape[1] != 6:
        raise ArgumentError("solve_factor solves (n, 6) arrays")
    for i in range(n):
        p = permutation[i]
        for c in range(6):
            work[p, c] = b[i, c]
    for j in range(n):                     # L y = P b, by columns of L
        w0, w1, w2 = work[j, 0], work[j, 1], work[j, 2]
        w3, w4, w5 = work[j, 3], work[j, 4], work[j, 5]
        for k in range(lower_start[j], lower_start[j + 1]):
            i = lower_row[k]
            value = lower_value[k]
            work[i, 0] -= value * w0
            work[i, 1] -= value * w1
            work[i, 2] -= value * w2
            work[i, 3] -= value * w3
            work[i, 4] -= value * w4
            work[i, 5] -= value * w5
    for j in range(n):
        inverse = 1.0 / pivot[j]
        for c in range(6):
            work[j, c] *= inverse
    for j in range(n - 1, -1, -1):         # L^T z = D^-1 y: column j of L is row j of L^T
        s0, s1, s2 = work[j, 0], work[j, 1], work[j, 2]
        s3, s4, s5 = work[j, 3], work[j, 4], work[j, 5]
        for k in range(lower_start[j], lower_start[j + 1]):
            i = lower_row[k]
            value = lower_value[k]
            s0 -= value * work[i, 0]
            s1 -= value * work[i, 1]
            s2 -= value * work[i, 2]
            s3 -= value * work[i, 3]
            s4 -= value * work[i, 4]
            s5 -= value * work[i, 5]
        work[j, 0] = s0
        work[j, 1] = s1
        work[j, 2] = s2
        work[j, 3] = s3
        work[j, 4] = s4
        work[j, 5] = s5
    for i in range(n):
        p = permutation[i]
        for c in range(6):
            b[i, c] = work[p, c]


@numba.njit(cache=True)
def _line_search(faces, cot, area, area_weight, x, energy, direction, slope, trial, trial_raw,
                 max_halvings=30):
    """Backtracking (Armijo) along ``direction`` with retraction into ``trial``; the energy's
    gradient at the accepted trial point is left in ``trial_raw`` (computed with each trial
    energy: the first step is usually taken).

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
        trial_energy = distortion_energy(trial, faces, cot, area, area_weight, trial_raw)
        if np.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * step * slope:
            return trial_energy
        step *= 0.5
    return np.inf


@numba.njit(cache=True)
def _steepest(x, grad, factor, direction, joint, joint_work):
    """A small first step: minus the (preconditioned, when ``factor`` has pivots) gradient,
    scaled so that no coordinate moves by more than 1e-3; returns its slope. ``joint`` and
    ``joint_work`` are (n, 6) scratch arrays."""
    _copy3(direction, 0, grad, 0)
    if factor[3].shape[0] > 0:
        _copy3(joint, 0, grad, 0)
        joint[:, 3:] = 0.0
        solve_factor(factor[0], factor[1], factor[2], factor[3], factor[4], joint, joint_work)
        _copy3(direction, 0, joint, 0)
        _tangent(x, direction, direction)
    direction *= -1e-3 / max(_largest_magnitude(direction), 1e-300)
    return _dot(direction, grad)


@numba.njit(cache=True)
def lbfgs(x, faces, cot, area, area_weight, max_iterations, tolerance, memory, factor,
          window):
    """Riemannian L-BFGS of :func:`distortion_energy` from the fold-free ``x`` (modified in place).

    ``factor`` is a preconditioner (the arguments of :func:`solve_factor` after the matrix, a
    Laplacian of the surface: see :func:`.sphere.laplacian_factor`), or arrays of length 0 for
    none. With it, the inverse Hessian the two-loop recursion starts from is gamma A^-1 (gamma
    from the newest pair: s.y / y.A^-1 y, solved with the step's own system) instead of the
    scaled identity: smooth, far-reaching
    moves, which the energy's slow global modes need. When a quasi-Newton step fails, the
    memory is dropped and a small steepest-descent step is tried, preconditioned first, then
    plain; when that fails too, or the energy fell by less than ``tolerance`` (relative) per
    iteration over the last ``window``, or after ``max_iterations``, it stops.

    Returns the number of iterations done.
    """
    n = x.shape[0]
    preconditioned = factor[3].shape[0] > 0
    plain = (factor[0][:0], factor[1][:0], factor[2][:0], factor[3][:0], factor[4][:0])
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
    gamma = 1.0
    q = np.empty((n, 3))
    direction = np.empty((n, 3))
    joint = np.empty((n, 6))             # [q, newest y], solved together
    joint_work = np.empty((n, 6))
    solved_y = np.empty((n, 3))          # A^-1 y of the newest pair, from the joint solve
    trial = np.empty((n, 3))
    trial_grad = np.empty((n, 3))
    history = np.empty(max_iterations + 1)
    history[0] = energy
    iterations = 0
    while iterations < max_iterations:
        if stored:
            # two-loop recursion: q = H grad
            _copy3(q, 0, grad, 0)
            for k in range(stored):
                slot = (newest - k) % memory
                alpha[slot] = rho[slot] * _dot(pairs_s[slot], q)
                _add_scaled(q, -alpha[slot], pairs_y[slot])
            if preconditioned:
                _copy3(joint, 0, q, 0)
                _copy3(joint, 3, pairs_y[newest], 0)
                solve_factor(factor[0], factor[1], factor[2], factor[3], factor[4], joint,
                             joint_work)
                _copy3(q, 0, joint, 0)
                _tangent(x, q, q)
                _copy3(solved_y, 0, joint, 3)
                gamma = 1.0 / (rho[newest] * _dot(pairs_y[newest], solved_y))
            q *= gamma
            for k in range(stored - 1, -1, -1):
                slot = (newest - k) % memory
                beta = rho[slot] * _dot(pairs_y[slot], q)
                _add_scaled(q, alpha[slot] - beta, pairs_s[slot])
            _tangent(x, q, direction)
            direction *= -1.0
            slope = _dot(direction, grad)
            if slope >= 0:
                stored = 0
        if not stored:
            slope = _steepest(x, grad, factor, direction, joint, joint_work)
        trial_energy = _line_search(faces, cot, area, area_weight, x, energy, direction, slope,
                                    trial, raw)
        if not np.isfinite(trial_energy) and stored:
            # the quasi-Newton step failed: restart from a small steepest-descent step
            stored = 0
            slope = _steepest(x, grad, factor, direction, joint, joint_work)
            trial_energy = _line_search(faces, cot, area, area_weight, x, energy, direction,
                                        slope, trial, raw)
        if not np.isfinite(trial_energy) and preconditioned:
            slope = _steepest(x, grad, plain, direction, joint, joint_work)
            trial_energy = _line_search(faces, cot, area, area_weight, x, energy, direction,
                                        slope, trial, raw)
        if not np.isfinite(trial_energy):
            break
        _tangent(trial, raw, trial_grad)
        # s = trial - x, y = trial_grad - (grad transported to the tangent plane at trial)
        slot = (newest + 1) % memory
        y = pairs_y[slot]
        _tangent(trial, grad, y)
        y *= -1.0
        _add_scaled(y, 1.0, trial_grad)
        _copy3(pairs_s[slot], 0, trial, 0)
        _add_scaled(pairs_s[slot], -1.0, x)
        curvature = _dot(pairs_s[slot], y)
        if curvature > 1e-12:
            rho[slot] = 1.0 / curvature
            gamma = curvature / _dot(y, y)   # the preconditioned scale is found with the solve
            newest = slot
            stored = min(stored + 1, memory)
        _copy3(x, 0, trial, 0)
        _copy3(grad, 0, trial_grad, 0)
        energy = trial_energy
        iterations += 1
        history[iterations] = energy
        if iterations >= window and (history[iterations - window] - energy
                                     < tolerance * abs(energy) * window):
            break
    return iterations
