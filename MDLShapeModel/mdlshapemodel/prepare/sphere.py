"""Bijective maps of closed genus-0 surfaces onto the unit sphere (docs/method.md section 5).

The map is built in three steps:

1. a spherical conformal map (FLASH, via ``lapy``) where it is fold-free, otherwise a map that is
   fold-free by construction (:func:`.multilevel.multilevel_map`: simplification to a tetrahedron,
   then vertex re-insertion), for strongly elongated or badly shaped surfaces;
2. for the conformal map, the Moebius transformation with the least mean |ln area ratio|
   (:func:`balance_area`, BFGS over the 3-parameter family of Moebius maps modulo rotations, with
   the analytic gradient);
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

from ..errors import SphereMapError
from .spherical import cross_rows, orientation, solid_angles  # noqa: F401 (re-exported)
from .surface import face_areas


@dataclass
class SphereMap:
    """A surface and its bijective map onto the unit sphere."""

    vertices: np.ndarray          # (n, 3) surface points (physical coordinates)
    faces: np.ndarray             # (m, 3) triangles, normals outwards
    sphere: np.ndarray            # (n, 3) unit vectors: the image of each vertex on the sphere
    quality: dict = field(default_factory=dict)


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


def mobius(points: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """A Moebius transformation of the unit sphere, given by a point ``centre`` of the open ball.

    phi_c(x) = (1 - |c|^2) (x - c) / |x - c|^2 - c: a conformal, orientation-preserving bijection
    of the sphere that spreads the points near c apart and crowds those opposite; c = 0 is the
    identity and phi_-c is its inverse. Every Moebius transformation of the sphere is one of these
    followed by a rotation.
    """
    d = points - centre
    return (1.0 - centre @ centre) * d / np.einsum("ij,ij->i", d, d)[:, None] - centre


def balance_objective(v, points, faces, target_log_share, smoothing):
    """Smoothed mean |ln area ratio| after :func:`mobius` with centre v / sqrt(1 + |v|^2).

    Returns the value and its analytic gradient with respect to ``v``.
    """
    scale = np.sqrt(1.0 + v @ v)
    centre = v / scale
    d = points - centre
    dd = np.einsum("ij,ij->i", d, d)
    factor = 1.0 - centre @ centre
    y = factor * d / dd[:, None] - centre
    p0, p1, p2 = y[faces[:, 0]], y[faces[:, 1]], y[faces[:, 2]]
    normal = cross_rows(p1 - p0, p2 - p0)
    twice_area = np.sqrt(np.einsum("ij,ij->i", normal, normal))
    twice_area = np.maximum(twice_area, 1e-300)
    log_ratio = np.log(twice_area) - np.log(twice_area.sum()) - target_log_share
    smooth = np.sqrt(log_ratio * log_ratio + smoothing * smoothing)
    m = len(faces)
    value = float(smooth.mean())
    # d value / d(twice_area_t)
    h = log_ratio / smooth / m
    d_area = h / twice_area - h.sum() / twice_area.sum()
    unit = normal * (d_area / twice_area)[:, None]
    # d|n| / dp0 = (p1 - p2) x n/|n|, and cyclically
    g_y = np.zeros_like(y)
    for k, (q1, q2) in enumerate(((p1, p2), (p2, p0), (p0, p1))):
        contribution = cross_rows(q1 - q2, unit)
        for axis in range(3):
            g_y[:, axis] += np.bincount(faces[:, k], contribution[:, axis], minlength=len(y))
    # chain through y = factor d / dd - c with d = x - c:
    # dy/dc^T g = -2 c (d.g)/dd - factor (g - 2 d (d.g)/dd) / dd - g
    dg = np.einsum("ij,ij->i", d, g_y) / dd
    g_c = (-2.0 * centre * dg.sum() - factor * ((g_y / dd[:, None]).sum(axis=0)
           - 2.0 * (d * (dg / dd)[:, None]).sum(axis=0)) - g_y.sum(axis=0))
    # centre = v / scale: dc/dv = I / scale - v v^T / scale^3 (symmetric)
    g_v = g_c / scale - v * (v @ g_c) / scale ** 3
    return value, g_v


def balance_area(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                 smoothing: float = 0.01) -> np.ndarray:
    """The Moebius transformation of a sphere map with the least mean |ln area ratio|.

    Minimises the mean over triangles of sqrt(ln(r)^2 + smoothing^2), r = chord-triangle area share
    / surface area share, over the 3-parameter family :func:`mobius` (rotations do not change the
    areas), by BFGS with the analytic gradient.
    """
    from scipy.optimize import minimize

    faces = np.asarray(faces, dtype=np.int64)
    surface_area = np.maximum(face_areas(vertices, faces), 1e-300)
    target = np.log(surface_area / surface_area.sum())
    result = minimize(balance_objective, np.zeros(3), jac=True, method="BFGS",
                      args=(sphere, faces, target, smoothing), options={"gtol": 1e-6})
    v = result.x
    return mobius(sphere, v / np.sqrt(1.0 + v @ v))


def _conformal_map(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
    """The spherical conformal map (FLASH, via ``lapy``), Moebius-balanced; None when it breaks
    down or is not fold-free (on badly shaped or strongly elongated surfaces)."""
    import logging

    from lapy import TriaMesh
    from lapy.conformal import spherical_conformal_map

    logging.getLogger("lapy").setLevel(logging.ERROR)
    try:
        with np.errstate(all="ignore"):
            sphere = spherical_conformal_map(TriaMesh(vertices, faces))
            sphere = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    except (ValueError, FloatingPointError, ArithmeticError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(sphere)) or np.any(orientation(sphere, faces) <= 0):
        return None
    try:
        with np.errstate(all="ignore"):
            balanced = balance_area(vertices, faces, sphere)
        balanced = balanced / np.linalg.norm(balanced, axis=1, keepdims=True)
        if np.all(np.isfinite(balanced)) and np.all(orientation(balanced, faces) > 0):
            sphere = balanced
    except (ValueError, FloatingPointError, ArithmeticError, np.linalg.LinAlgError):
        pass
    return sphere


def _initial_map(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Fold-free initial map: the conformal map when it is fold-free (fast: 0.04-0.3 s for
    2,000-5,000 vertices), else the multilevel map, fold-free by construction (about 0.6 ms per
    vertex)."""
    from .multilevel import multilevel_map

    sphere = _conformal_map(vertices, faces)
    return multilevel_map(vertices, faces) if sphere is None else sphere


# Iteration cap of the distortion minimisation. Most hippocampus maps converge in 500-2000
# iterations (0.1-0.2 ms each for 2,000 vertices); a few strongly elongated ones need 4,000-7,000
# and end with a visibly worse distortion when cut off at 3,000.
MAX_ITERATIONS = 10000
# Weight of the area term against the symmetric Dirichlet term of the distortion energy.
AREA_WEIGHT = 4.0


class DistortionEnergy:
    """Symmetric Dirichlet + area energy of the map surface -> sphere.

    For each triangle, with surface areas rescaled to a total of 4 pi (``A``), cotangent weights
    of the rescaled surface, and ``a`` = det[p0, p1, p2] / 2 on the sphere side::

        E = sum dirichlet (1 + (A / a)^2) + area_weight * sum (a + A^2 / a)

    where ``dirichlet`` = 1/2 sum_k cot_k |edge_k|^2 is A times the squared Frobenius norm of the
    linear map surface triangle -> chord triangle. ``a`` is the chord-triangle area weighted by
    its plane's distance from the centre: positive exactly when the triangle keeps its orientation
    and zero when its vertices fall on one great circle, so the energy is a barrier against folds.
    Evaluated in one compiled pass (:func:`.sphere_kernels.distortion_energy`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, area_weight: float):
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
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
        self.area_weight = float(area_weight)
        self._no_gradient = np.empty((0, 3))

    def __call__(self, x: np.ndarray, gradient: bool = True):
        x = np.ascontiguousarray(x, dtype=np.float64)
        grad = np.empty_like(x) if gradient else self._no_gradient
        from .sphere_kernels import distortion_energy

        energy = distortion_energy(x, self.faces, self.cot, self.area, self.area_weight, grad)
        if not np.isfinite(energy):
            return np.inf, None
        return energy, (grad if gradient else None)


def minimise_distortion(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                        area_weight: float = AREA_WEIGHT, max_iterations: int = MAX_ITERATIONS,
                        tolerance: float = 1e-7, memory: int = 10) -> np.ndarray:
    """Lower the distortion of a fold-free sphere map, never flipping a triangle.

    Riemannian L-BFGS with the projection retraction; every trial point is checked for flipped
    triangles (the energy is infinite there), so each accepted iterate is fold-free (compiled:
    :func:`.sphere_kernels.lbfgs`). It stops
    when the energy fell by less than ``tolerance`` (relative) per iteration over the last 20,
    when no step lowers the energy, or after ``max_iterations``.
    """
    from .sphere_kernels import lbfgs

    energy_of = DistortionEnergy(vertices, faces, area_weight)
    x = np.array(sphere, dtype=np.float64, order="C")
    energy, _ = energy_of(x, gradient=False)
    if not np.isfinite(energy):
        raise SphereMapError("the initial sphere map has flipped triangles")
    lbfgs(x, energy_of.faces, energy_of.cot, energy_of.area, energy_of.area_weight,
           int(max_iterations), float(tolerance), int(memory))
    return x


def sphere_map(vertices: np.ndarray, faces: np.ndarray, area_weight: float = AREA_WEIGHT,
               max_iterations: int = MAX_ITERATIONS) -> SphereMap:
    """Bijective, low-distortion map of a closed genus-0 surface onto the unit sphere.

    Parameters
    ----------
    vertices, faces : ndarray
        A closed genus-0 triangle mesh with outward normals.
    area_weight : float
        Weight of the area term against the symmetric Dirichlet (angle and area) term.
    max_iterations : int
        Cap on the iterations of the distortion minimisation (:func:`minimise_distortion`).

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
    from .surface import triangle_vertex_areas

    weights = triangle_vertex_areas(vertices, faces)
    design = np.hstack([np.ones((len(sphere), 1)), sphere])
    weighted = design * weights[:, None]
    coefficients = np.linalg.solve(design.T @ weighted, weighted.T @ vertices)
    return coefficients[0], coefficients[1:].T


def principal_axes(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroid and principal axes (columns, descending variance, det +1)."""
    from .surface import triangle_vertex_areas

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


def reference_frames(surfaces: list, reference: int = 0) -> list:
    """For each surface (vertices, faces), the rotation Q that brings it into the frame of the
    reference's: principal axes, with the sign ambiguity resolved by the smallest chamfer
    distance among the four proper choices."""
    ref_vertices, ref_faces = surfaces[reference]
    ref_centre, ref_axes = principal_axes(ref_vertices, ref_faces)
    ref_points = _subsample(ref_vertices - ref_centre)
    flips = [np.diag(d) for d in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1))]
    frames = []
    for vertices, faces in surfaces:
        centre, axes = principal_axes(vertices, faces)
        points = _subsample(vertices - centre)
        candidates = [ref_axes @ flip @ axes.T for flip in flips]
        frames.append(min(candidates, key=lambda q: _chamfer(points @ q.T, ref_points)))
    return frames


def align_parameterizations(maps: list, reference: int = 0, frames: list | None = None
                            ) -> list:
    """Rotate each sphere map so that its parameterization matches the reference's.

    Each shape is first brought into the reference's frame (``frames``, default
    :func:`reference_frames` of the maps' own surfaces; a multi-part object passes the frames of
    its whole surfaces, so that the arrangement of the parts settles what one part's symmetry
    leaves open). In that frame, the rotation P of the parameter sphere that best matches the
    first-order maps, min ||Q M_i P - M_ref||_F over proper rotations, is an orthogonal
    Procrustes problem. The new sphere coordinates are P^T u, so that S_i'(u) = S_i(P u).

    Returns new :class:`SphereMap` objects (the inputs are not modified); each ``quality`` gains
    ``parameter_rotation_degrees``.
    """
    if frames is None:
        frames = reference_frames([(m.vertices, m.faces) for m in maps], reference)
    ref = maps[reference]
    _, ref_first = first_order_map(ref.vertices, ref.faces, ref.sphere)
    aligned = []
    for item, frame in zip(maps, frames):
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
