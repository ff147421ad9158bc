"""Bijective maps of closed genus-0 surfaces onto the unit sphere (METHOD.md section 5).

The map is built in three steps:

1. a spherical conformal map (FLASH, via ``lapy``), or the spherical Tutte map when the conformal
   map breaks down on badly shaped or strongly elongated surfaces; both are fold-free;
2. a Moebius transformation that balances the area distortion (``lapy``);
3. a fold-free minimisation of a distortion energy that is infinite for collapsed triangles: the
   symmetric Dirichlet energy (angles and areas) plus an area term ``A (r + 1/r)``, where ``r`` is the
   ratio of sphere area to (normalised) surface area of a triangle. The minimiser is a Riemannian
   L-BFGS on the sphere whose line search never accepts a step that flips a triangle, so the map
   stays bijective at every iterate.

The result is checked: every triangle positively oriented on the sphere and the triangles cover the
sphere exactly once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .errors import SphereMapError
from .surface import face_areas


@dataclass
class SphereMap:
    """A surface and its bijective map onto the unit sphere."""

    vertices: np.ndarray          # (n, 3) surface points (physical coordinates)
    faces: np.ndarray             # (m, 3) triangles, normals outwards
    sphere: np.ndarray            # (n, 3) unit vectors: the image of each vertex on the sphere
    quality: dict = field(default_factory=dict)


def orientation(sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """det[a, b, c] per face: positive when the triangle is counter-clockwise seen from outside."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def solid_angles(sphere: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed solid angle of each spherical triangle (Van Oosterom & Strackee)."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    numerator = np.einsum("ij,ij->i", a, np.cross(b, c))
    denominator = 1.0 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c) \
        + np.einsum("ij,ij->i", c, a)
    return 2.0 * np.arctan2(numerator, denominator)


def distortion(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray) -> np.ndarray:
    """Per-triangle ln(sphere area share / surface area share)."""
    surface_share = face_areas(vertices, faces)
    sphere_share = face_areas(sphere, faces)
    return np.log(np.maximum(sphere_share / sphere_share.sum(), 1e-300)
                  / np.maximum(surface_share / surface_share.sum(), 1e-300))


def check_bijective(sphere: np.ndarray, faces: np.ndarray) -> int:
    """Number of flipped triangles; raise when the triangles do not cover the sphere exactly once."""
    flips = int(np.sum(orientation(sphere, faces) <= 0))
    coverage = float(np.sum(solid_angles(sphere, faces))) / (4 * np.pi)
    if flips == 0 and abs(coverage - 1.0) > 1e-6:
        raise SphereMapError(f"the sphere map covers the sphere {coverage:.4f} times, not once")
    return flips


def map_quality(vertices, faces, sphere, seconds: float = float("nan")) -> dict:
    """Flips and area distortion statistics of a sphere map."""
    log_ratio = np.abs(distortion(vertices, faces, sphere))
    return {"flipped_triangles": int(np.sum(orientation(sphere, faces) <= 0)),
            "mean_abs_log_area_ratio": float(np.mean(log_ratio)),
            "p95_abs_log_area_ratio": float(np.percentile(log_ratio, 95)),
            "max_abs_log_area_ratio": float(np.max(log_ratio)),
            "seconds": float(seconds)}


def _initial_map(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Fold-free initial map: conformal when it works, Tutte otherwise; Moebius-balanced."""
    import logging

    from lapy import TriaMesh
    from lapy.conformal import (mobius_area_correction_spherical, spherical_conformal_map,
                                spherical_tutte_map)

    logging.getLogger("lapy").setLevel(logging.ERROR)
    mesh = TriaMesh(vertices, faces)
    candidates = []
    try:
        candidates.append(spherical_conformal_map(mesh))
    except (ValueError, FloatingPointError, ArithmeticError, np.linalg.LinAlgError):
        pass
    candidates.append(spherical_tutte_map(mesh, bigtri=int(np.argmax(face_areas(vertices, faces)))))
    for sphere in candidates:
        sphere = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
        if not np.all(np.isfinite(sphere)) or np.any(orientation(sphere, faces) <= 0):
            continue
        try:
            with np.errstate(all="ignore"):
                balanced, _ = mobius_area_correction_spherical(mesh, sphere)
            balanced = balanced / np.linalg.norm(balanced, axis=1, keepdims=True)
            if np.all(np.isfinite(balanced)) and np.all(orientation(balanced, faces) > 0):
                sphere = balanced
        except (ValueError, FloatingPointError, ArithmeticError, np.linalg.LinAlgError):
            pass
        return sphere
    raise SphereMapError("neither the conformal nor the Tutte map is fold-free on this surface")


class _DistortionEnergy:
    """Symmetric Dirichlet + area energy of the map surface -> sphere."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, area_weight: float):
        self.faces = faces
        self.n = len(vertices)
        areas = face_areas(vertices, faces)
        self.area = areas * (4 * np.pi / areas.sum())
        scale = np.sqrt(4 * np.pi / areas.sum())
        v = vertices * scale
        cot = np.empty((len(faces), 3))
        for k in range(3):  # cotangent of the angle at corner k, opposite edge (k+1, k+2)
            p, q, r = v[faces[:, k]], v[faces[:, (k + 1) % 3]], v[faces[:, (k + 2) % 3]]
            u, w = q - p, r - p
            cot[:, k] = np.einsum("ij,ij->i", u, w) / np.maximum(
                np.linalg.norm(np.cross(u, w), axis=1), 1e-300)
        self.cot = cot
        self.area_weight = area_weight

    def __call__(self, x: np.ndarray, gradient: bool = True):
        f = self.faces
        p = [x[f[:, k]] for k in range(3)]
        edges = [p[(k + 2) % 3] - p[(k + 1) % 3] for k in range(3)]  # edge opposite corner k
        # Half the determinant [p0, p1, p2]: the chord-triangle area weighted by its plane's distance
        # from the centre. It is positive exactly when the triangle keeps its orientation and vanishes
        # when its vertices fall on one great circle, so the energy below is a barrier against folds.
        a = 0.5 * np.einsum("ij,ij->i", p[0], np.cross(p[1], p[2]))
        if np.any(a <= 0):
            return np.inf, None
        dirichlet = 0.5 * sum(self.cot[:, k] * np.einsum("ij,ij->i", edges[k], edges[k])
                              for k in range(3))
        A = self.area
        inverse_ratio2 = (A / a) ** 2
        energy = np.sum(dirichlet * (1 + inverse_ratio2)) + self.area_weight * np.sum(a + A * A / a)
        if not gradient:
            return energy, None
        coefficient_d = 1 + inverse_ratio2
        coefficient_a = self.area_weight * (1 - inverse_ratio2) - 2 * dirichlet * inverse_ratio2 / a
        grad = np.zeros_like(x)
        for k in range(3):
            i, j, m = k, (k + 1) % 3, (k + 2) % 3
            # d(dirichlet)/dp_i: edges (i,j) opposite corner m and (i,m) opposite corner j
            d_dirichlet = (self.cot[:, m, None] * (p[i] - p[j]) + self.cot[:, j, None] * (p[i] - p[m]))
            d_area = 0.5 * np.cross(p[j], p[m])
            contribution = coefficient_d[:, None] * d_dirichlet + coefficient_a[:, None] * d_area
            np.add.at(grad, f[:, i], contribution)
        return energy, grad


def _tangent(x: np.ndarray, v: np.ndarray) -> np.ndarray:
    return v - np.einsum("ij,ij->i", x, v)[:, None] * x


def _line_search(energy_of, x, energy, direction, slope, max_halvings: int = 30):
    """Backtracking (Armijo) along ``direction`` with retraction; None when no step is accepted."""
    step = 1.0
    for _ in range(max_halvings):
        trial = x + step * direction
        trial /= np.linalg.norm(trial, axis=1, keepdims=True)
        trial_energy, _ = energy_of(trial, gradient=False)
        if np.isfinite(trial_energy) and trial_energy <= energy + 1e-4 * step * slope:
            return trial
        step *= 0.5
    return None


def minimise_distortion(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                        area_weight: float = 4.0, max_iterations: int = 3000,
                        tolerance: float = 1e-7, memory: int = 10) -> np.ndarray:
    """Lower the distortion of a fold-free sphere map, never flipping a triangle.

    Riemannian L-BFGS with the projection retraction; every trial point is checked for flipped
    triangles (the energy is infinite there), so each accepted iterate is fold-free.
    """
    energy_of = _DistortionEnergy(vertices, faces, area_weight)
    x = sphere.copy()
    energy, grad = energy_of(x)
    if not np.isfinite(energy):
        raise SphereMapError("the initial sphere map has flipped triangles")
    grad = _tangent(x, grad)
    s_list, y_list = [], []
    history = [energy]
    for _ in range(max_iterations):
        q = grad.ravel().copy()
        alphas = []
        for s, y in zip(reversed(s_list), reversed(y_list)):
            rho = 1.0 / np.dot(y, s)
            alpha = rho * np.dot(s, q)
            alphas.append((rho, alpha))
            q -= alpha * y
        if s_list:
            q *= np.dot(s_list[-1], y_list[-1]) / np.dot(y_list[-1], y_list[-1])
        else:
            q *= 1e-3 / max(np.abs(q).max(), 1e-300)
        for (s, y), (rho, alpha) in zip(zip(s_list, y_list), reversed(alphas)):
            beta = rho * np.dot(y, q)
            q += (alpha - beta) * s
        direction = -_tangent(x, q.reshape(x.shape))
        slope = float(np.sum(direction * grad))
        if slope >= 0:
            direction, slope = -grad, -float(np.sum(grad * grad))
            s_list.clear()
            y_list.clear()
        trial = _line_search(energy_of, x, energy, direction, slope)
        if trial is None and s_list:  # quasi-Newton step failed: restart from steepest descent
            s_list.clear()
            y_list.clear()
            direction = -grad * (1e-3 / max(np.abs(grad).max(), 1e-300))
            trial = _line_search(energy_of, x, energy, direction, float(np.sum(direction * grad)))
        if trial is None:
            break
        trial_energy, trial_grad = energy_of(trial)
        trial_grad = _tangent(trial, trial_grad)
        s_vec = (trial - x).ravel()
        y_vec = (trial_grad - _tangent(trial, grad)).ravel()
        if np.dot(s_vec, y_vec) > 1e-12:
            s_list.append(s_vec)
            y_list.append(y_vec)
            if len(s_list) > memory:
                s_list.pop(0)
                y_list.pop(0)
        x, energy, grad = trial, trial_energy, trial_grad
        history.append(energy)
        if len(history) > 20 and history[-21] - energy < tolerance * abs(energy) * 20:
            break
    return x


def sphere_map(vertices: np.ndarray, faces: np.ndarray, area_weight: float = 4.0,
               max_iterations: int = 3000) -> SphereMap:
    """Bijective, low-distortion map of a closed genus-0 surface onto the unit sphere.

    Parameters
    ----------
    vertices, faces : ndarray
        A closed genus-0 triangle mesh with outward normals.
    area_weight : float
        Weight of the area term against the symmetric Dirichlet (angle and area) term.

    Returns
    -------
    SphereMap
        With ``quality``: flipped triangles (always 0), mean, 95th percentile and maximum of
        |ln(sphere area / surface area)| per triangle, and seconds.

    Raises
    ------
    SphereMapError
        When no fold-free map can be found.
    """
    start = time.perf_counter()
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    sphere = _initial_map(vertices, faces)
    sphere = minimise_distortion(vertices, faces, sphere, area_weight=area_weight,
                                 max_iterations=max_iterations)
    flips = check_bijective(sphere, faces)
    if flips:
        raise SphereMapError(f"the sphere map has {flips} flipped triangles")
    quality = map_quality(vertices, faces, sphere, time.perf_counter() - start)
    return SphereMap(vertices, faces, sphere, quality)


def first_order_map(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted least-squares fit x(u) ~ c + M u over the surface (first-degree harmonics).

    Returns the centre c (3,) and the 3x3 matrix M; M maps directions of the parameter sphere to
    directions of the shape (the first-order ellipsoid of SPHARM).
    """
    from .sampling import triangle_vertex_areas

    weights = triangle_vertex_areas(vertices, faces)
    design = np.hstack([np.ones((len(sphere), 1)), sphere])
    weighted = design * weights[:, None]
    coefficients = np.linalg.solve(design.T @ weighted, weighted.T @ vertices)
    return coefficients[0], coefficients[1:].T


def principal_axes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroid and principal axes (columns, descending variance, det +1)."""
    from .sampling import triangle_vertex_areas

    weights = triangle_vertex_areas(vertices, faces)
    weights = weights / weights.sum()
    centre = weights @ vertices
    centred = vertices - centre
    _, axes = np.linalg.eigh((centred * weights[:, None]).T @ centred)
    axes = axes[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    return centre, axes


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return float(np.mean(cKDTree(b).query(a)[0]) + np.mean(cKDTree(a).query(b)[0]))


def _subsample(points: np.ndarray, count: int = 600) -> np.ndarray:
    step = max(1, len(points) // count)
    return points[::step]


def align_parameterizations(maps: list, reference: int = 0) -> list:
    """Rotate each sphere map so that its parameterization matches the reference's.

    Each shape is first brought into the reference's frame (principal axes, with the sign
    ambiguity resolved by the smallest chamfer distance among the four proper choices). In that
    frame, the rotation P of the parameter sphere that best matches the first-order maps,
    min ||Q M_i P - M_ref||_F over proper rotations, is an orthogonal Procrustes problem. The new
    sphere coordinates are P^T u, so that S_i'(u) = S_i(P u).

    Returns new :class:`SphereMap` objects (the inputs are not modified); each ``quality`` gains
    ``parameter_rotation_degrees``.
    """
    ref = maps[reference]
    ref_centre, ref_axes = principal_axes(ref.vertices, ref.faces)
    _, ref_first = first_order_map(ref.vertices, ref.faces, ref.sphere)
    ref_points = _subsample(ref.vertices - ref_centre)
    flips = [np.diag(d) for d in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1))]
    aligned = []
    for item in maps:
        centre, axes = principal_axes(item.vertices, item.faces)
        points = _subsample(item.vertices - centre)
        candidates = [ref_axes @ flip @ axes.T for flip in flips]
        frame = min(candidates, key=lambda q: _chamfer(points @ q.T, ref_points))
        _, first = first_order_map(item.vertices, item.faces, item.sphere)
        u, _, vt = np.linalg.svd((frame @ first).T @ ref_first)
        d = np.ones(3)
        d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
        rotation = (u * d) @ vt
        quality = dict(item.quality)
        angle = np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1)))
        quality["parameter_rotation_degrees"] = float(angle)
        aligned.append(SphereMap(item.vertices, item.faces, item.sphere @ rotation, quality))
    return aligned
