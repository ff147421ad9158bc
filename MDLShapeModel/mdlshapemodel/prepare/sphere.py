"""Bijective maps of closed genus-0 surfaces onto the unit sphere (docs/method.md section 5).

The map is built in three steps:

1. a spherical conformal map (FLASH, :func:`.conformal.spherical_conformal_map`) where it is
   fold-free, otherwise a map that is fold-free by construction
   (:func:`.multilevel.multilevel_map`: simplification to a tetrahedron, then vertex
   re-insertion), for strongly elongated or badly shaped surfaces;
2. for the conformal map, the Moebius transformation with the least mean |ln area ratio|
   (:func:`balance_area`, BFGS over the 3-parameter family of Moebius maps modulo rotations, with
   the analytic gradient);
3. a fold-free minimisation of a distortion energy that is infinite for collapsed triangles: the
   symmetric Dirichlet energy (angles and areas) plus an area term ``A (r + 1/r)``, where ``r`` is the
   ratio of sphere area to (normalised) surface area of a triangle. The minimiser is a Riemannian
   L-BFGS on the sphere, preconditioned by the surface's Laplacian, whose line search never
   accepts a step that flips a triangle, so the map stays bijective at every iterate.

The result is checked: every triangle positively oriented on the sphere and the triangles cover the
sphere exactly once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SphereMapError
from ..geometry import best_rotation
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

    Returns the value and its analytic gradient with respect to ``v`` (compiled, one pass per
    stage: :func:`.sphere_kernels.balance_objective`).
    """
    from .sphere_kernels import balance_objective as compiled

    gradient = np.empty(3)
    value = compiled(np.asarray(v, dtype=np.float64), points, faces, target_log_share,
                     float(smoothing), gradient)
    return value, gradient


def balance_area(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                 smoothing: float = 0.01) -> np.ndarray:
    """The Moebius transformation of a sphere map with the least mean |ln area ratio|.

    Minimises the mean over triangles of sqrt(ln(r)^2 + smoothing^2), r = chord-triangle area share
    / surface area share, over the 3-parameter family :func:`mobius` (rotations do not change the
    areas), by BFGS with the analytic gradient (:func:`bfgs`).
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    surface_area = np.maximum(face_areas(vertices, faces), 1e-300)
    target = np.log(surface_area / surface_area.sum())
    points = np.ascontiguousarray(sphere, dtype=np.float64)
    v = bfgs(lambda v: balance_objective(v, points, faces, target, smoothing), np.zeros(3))
    return mobius(sphere, v / np.sqrt(1.0 + v @ v))


def bfgs(function, x: np.ndarray, gtol: float = 1e-6, max_iterations: int = 200) -> np.ndarray:
    """The minimiser of a smooth function of a few variables, ``function(x)`` -> (value,
    gradient), from ``x``: BFGS on the inverse Hessian, the first one scaled by the first step
    (Nocedal and Wright, eq. 6.20), with Armijo backtracking; until the largest gradient
    component is below ``gtol``, no step lowers the value, or after ``max_iterations``.

    (SciPy's ``minimize`` does the same with a Wolfe line search; importing ``scipy.optimize``
    for three variables costs a worker process more than the minimisation itself.)
    """
    x = np.array(x, dtype=np.float64)
    value, gradient = function(x)
    inverse = np.eye(len(x))
    scaled = False
    for _ in range(max_iterations):
        if not np.max(np.abs(gradient)) > gtol:
            break
        direction = -inverse @ gradient
        slope = float(direction @ gradient)
        if not slope < 0:                       # not a descent direction: start afresh
            inverse, scaled = np.eye(len(x)), False
            direction, slope = -gradient, -float(gradient @ gradient)
        step = 1.0
        for _ in range(60):
            trial = x + step * direction
            trial_value, trial_gradient = function(trial)
            if np.isfinite(trial_value) and trial_value <= value + 1e-4 * step * slope:
                break
            step *= 0.5
        else:
            break
        s, y = trial - x, trial_gradient - gradient
        curvature = float(s @ y)
        if curvature > 1e-12 * float(np.sqrt((s @ s) * (y @ y))):
            if not scaled:
                inverse, scaled = np.eye(len(x)) * (curvature / float(y @ y)), True
            rho = 1.0 / curvature
            left = np.eye(len(x)) - rho * np.outer(s, y)
            inverse = left @ inverse @ left.T + rho * np.outer(s, s)
        x, value, gradient = trial, trial_value, trial_gradient
    return x


def _conformal_map(vertices: np.ndarray, faces: np.ndarray, cot: np.ndarray | None = None,
                   laplacian=None) -> np.ndarray | None:
    """The spherical conformal map (FLASH, :mod:`.conformal`), Moebius-balanced; None when it
    breaks down or is not fold-free (on badly shaped or strongly elongated surfaces)."""
    from .conformal import spherical_conformal_map

    sphere = spherical_conformal_map(vertices, faces, cot, laplacian)
    if sphere is None:
        return None
    with np.errstate(all="ignore"):
        sphere = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
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


def _initial_map(vertices: np.ndarray, faces: np.ndarray, cot: np.ndarray | None = None,
                 laplacian=None) -> np.ndarray:
    """Fold-free initial map: the conformal map when it is fold-free (about 8 microseconds per
    vertex), else the multilevel map, fold-free by construction (about 50 microseconds per
    vertex, most of it spreading each level's map)."""
    from .multilevel import multilevel_map

    sphere = _conformal_map(vertices, faces, cot, laplacian)
    return multilevel_map(vertices, faces) if sphere is None else sphere


# Iteration cap of the distortion minimisation, a bound that converged maps stay far below: the
# preconditioned minimisation converges in 40-140 iterations on the 100 shared hippocampi (about
# 0.5 ms each for 2,000 vertices) and 140-230 on 0.5 mm femurs (5,000 vertices).
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

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, area_weight: float,
                 cot: np.ndarray | None = None):
        from .conformal import cotangents

        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.n = len(vertices)
        areas = face_areas(vertices, faces)
        self.area = areas * (4 * np.pi / areas.sum())
        # the cotangents do not change with the scale
        self.cot = np.ascontiguousarray(cotangents(vertices, self.faces) if cot is None else cot)
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


# Weight of the mass matrix against the cotangent Laplacian in the preconditioner of the
# distortion minimisation (both of the surface rescaled to the sphere's area, 4 pi): it keeps the
# matrix definite and sets the scale, in wavelengths, below which the preconditioner stops
# smoothing the gradient. Between 0.05 and 0.5 the iteration counts on hippocampi and femurs
# differ little; 0.15 was the lowest.
PRECONDITIONER_MASS = 0.15


def laplacian_factor(faces: np.ndarray, cot: np.ndarray, area: np.ndarray,
                     mass_weight: float = PRECONDITIONER_MASS, laplacian=None) -> tuple:
    """The preconditioner of the distortion minimisation: A = L + ``mass_weight`` M, factored.

    L is the cotangent Laplacian (weights ``cot``, one row per triangle, the cotangent at each
    corner; :func:`.conformal.cotangent_laplacian`, or ``laplacian`` when made already) and M the
    lumped mass matrix (a third of each triangle's ``area`` to each corner). A is symmetric
    positive definite; SuperLU (minimum-degree ordering on A + A^T, diagonal pivots) factors it
    as P^T L D L^T P, deterministically. Returns the arguments of
    :func:`.sphere_kernels.solve_factor` before ``b``, or :func:`.sphere_kernels.no_factor`
    when the factor is not of that form (never seen).
    """
    from scipy.sparse.linalg import splu

    from .conformal import cotangent_laplacian, diagonal_positions
    from .sphere_kernels import no_factor

    n = int(faces.max()) + 1
    if laplacian is None:
        laplacian = cotangent_laplacian(faces, cot, n)
    matrix = laplacian.copy()
    mass = np.bincount(faces.ravel(), np.repeat(area / 3.0, 3), minlength=n)
    matrix.data[diagonal_positions(matrix)] += mass_weight * mass
    try:
        lu = splu(matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                  options={"SymmetricMode": True})
    except RuntimeError:            # exactly singular: not of a closed mesh with positive areas
        return no_factor()
    pivot = lu.U.diagonal()
    if not (np.array_equal(lu.perm_r, lu.perm_c) and np.all(pivot > 0)
            and np.all(np.isfinite(pivot))):
        return no_factor()
    # L's entries below its (unit) diagonal, column by column; their order within a column
    # does not matter to the solve
    lower = lu.L.tocsc()
    column = np.repeat(np.arange(n), np.diff(lower.indptr))
    below = lower.indices > column
    start = np.concatenate([[0], np.cumsum(np.bincount(column[below], minlength=n))])
    return (start.astype(np.int64), lower.indices[below].astype(np.int64),
            np.ascontiguousarray(lower.data[below], dtype=np.float64),
            np.ascontiguousarray(pivot), lu.perm_r.astype(np.int64))


def minimise_distortion(vertices: np.ndarray, faces: np.ndarray, sphere: np.ndarray,
                        area_weight: float = AREA_WEIGHT, max_iterations: int = MAX_ITERATIONS,
                        tolerance: float = 1e-7, memory: int = 5, window: int = 10,
                        cot: np.ndarray | None = None, laplacian=None) -> np.ndarray:
    """Lower the distortion of a fold-free sphere map, never flipping a triangle.

    Riemannian L-BFGS with the projection retraction, preconditioned by the surface's Laplacian
    (:func:`laplacian_factor`); every trial point is checked for flipped triangles (the energy
    is infinite there), so each accepted iterate is fold-free (compiled:
    :func:`.sphere_kernels.lbfgs`). It stops when the energy fell by less than ``tolerance``
    (relative) per iteration over the last ``window``, when no step lowers the energy, or after
    ``max_iterations``. ``cot``, ``laplacian``: the cotangents of the surface's angles and its
    cotangent Laplacian, when known already.
    """
    from .sphere_kernels import lbfgs

    energy_of = DistortionEnergy(vertices, faces, area_weight, cot)
    x = np.array(sphere, dtype=np.float64, order="C")
    energy, _ = energy_of(x, gradient=False)
    if not np.isfinite(energy):
        raise SphereMapError("the initial sphere map has flipped triangles")
    factor = laplacian_factor(energy_of.faces, energy_of.cot, energy_of.area,
                              laplacian=laplacian)
    lbfgs(x, energy_of.faces, energy_of.cot, energy_of.area, energy_of.area_weight,
          int(max_iterations), float(tolerance), int(memory), factor, int(window))
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
    from .conformal import cotangent_laplacian, cotangents

    cot = cotangents(vertices, faces)
    laplacian = cotangent_laplacian(faces, cot, len(vertices))
    sphere = _initial_map(vertices, faces, cot, laplacian)
    sphere = minimise_distortion(vertices, faces, sphere, area_weight=area_weight,
                                 max_iterations=max_iterations, cot=cot, laplacian=laplacian)
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


def _subsample(points: np.ndarray, count: int = 600) -> np.ndarray:
    step = max(1, len(points) // count)
    return points[::step]


#: the candidate frames of a surface: its principal axes with the first axis either way, each
#: turned about the first axis in this many equal steps
FRAME_TWISTS = 12
#: the candidates at the smallest chamfer distances that iterative closest points refines
FRAME_REFINED = 2
#: iterations of the closest-point refinement of a candidate frame
FRAME_ICP_ITERATIONS = 10


class _Chamfer:
    """The chamfer distance between centred point sets ``points`` @ Q^T and ``reference`` for
    rotations Q, with each set's search tree built once; :meth:`refine` is iterative closest
    points (about the origin, no translation or scale) from Q to a local minimum of the
    distance of the rotated points from the reference."""

    def __init__(self, points: np.ndarray, reference: np.ndarray):
        from scipy.spatial import cKDTree

        self.points, self.reference = points, reference
        self.trees = cKDTree(points), cKDTree(reference)

    def __call__(self, rotation: np.ndarray) -> float:
        there = self.trees[1].query(self.points @ rotation.T)[0]
        back = self.trees[0].query(self.reference @ rotation)[0]
        return float(np.mean(there) + np.mean(back))

    def refine(self, rotation: np.ndarray, iterations: int = FRAME_ICP_ITERATIONS) -> np.ndarray:
        for _ in range(iterations):
            closest = self.reference[self.trees[1].query(self.points @ rotation.T)[1]]
            rotation = best_rotation(self.points.T @ closest)[0].T
        return rotation


def frame_turns() -> list:
    """The rotations T, in principal-axes coordinates, of the candidate frames
    ``ref_axes @ T @ axes.T`` of :func:`reference_frames`: the first axis kept or reversed
    (diag(1, 1, 1), diag(-1, -1, 1)), each turned about the first axis in :data:`FRAME_TWISTS`
    equal steps; 2 :data:`FRAME_TWISTS` distinct rotations.

    These are all the proper sign choices of the axes, each once: the other two,
    diag(1, -1, -1) and diag(-1, 1, -1), are the first two turned half a turn about the first
    axis, so a list of all four sign choices, each turned in steps that include the half
    turn, would hold every rotation twice.
    """
    flips = (np.eye(3), np.diag([-1.0, -1.0, 1.0]))
    angles = 2.0 * np.pi * np.arange(FRAME_TWISTS) / FRAME_TWISTS
    twists = [np.array([[1.0, 0.0, 0.0], [0.0, np.cos(t), -np.sin(t)], [0.0, np.sin(t), np.cos(t)]])
              for t in angles]
    return [twist @ flip for flip in flips for twist in twists]


def reference_frames(surfaces: list, reference: int = 0) -> list:
    """For each surface (vertices, faces), the rotation Q that brings it into the frame of the
    reference's (sizes scaled to one RMS radius, so that size does not decide): among its
    principal axes with the first axis either way, each turned about the first axis in
    :data:`FRAME_TWISTS` steps (:func:`frame_turns`; two axes of nearly equal spread, as a long
    bone's cross-section has, leave the turn open), the :data:`FRAME_REFINED` at the smallest
    chamfer distance are refined by iterative closest points and the closest of them is taken."""
    ref_vertices, ref_faces = surfaces[reference]
    ref_centre, ref_axes = principal_axes(ref_vertices, ref_faces)
    ref_points = _scaled(_subsample(ref_vertices - ref_centre))
    turns = frame_turns()
    frames = []
    for vertices, faces in surfaces:
        centre, axes = principal_axes(vertices, faces)
        points = _scaled(_subsample(vertices - centre))
        chamfer = _Chamfer(points, ref_points)
        candidates = [ref_axes @ turn @ axes.T for turn in turns]
        # the candidates ranked on a quarter of the points
        coarse = _Chamfer(points[::4], ref_points[::4])
        distances = [coarse(q) for q in candidates]
        refined = [chamfer.refine(candidates[k])
                   for k in np.argsort(distances, kind="stable")[:FRAME_REFINED]]
        frames.append(min(refined, key=chamfer))
    return frames


def _scaled(points: np.ndarray) -> np.ndarray:
    """Centred points scaled to unit RMS radius."""
    return points / np.sqrt(np.mean(np.sum(points * points, axis=1)))


#: how strongly landmarks steer the alignment of the parameterizations, against the first-order
#: maps: each matrix is scaled to unit norm, the landmarks' by this factor, so that landmarks
#: decide wherever they pin the rotation (two or more) and the first-order maps break ties
LANDMARK_ALIGNMENT_WEIGHT = 10.0
#: rounds of (rotations given the landmarks' shared places, shared places given the rotations)
LANDMARK_ALIGNMENT_ROUNDS = 5


def align_parameterizations(maps: list, reference: int = 0, frames: list | None = None,
                            landmarks: list | None = None) -> list:
    """Rotate each sphere map so that its parameterization matches the reference's.

    Each shape is first brought into the reference's frame (``frames``, default
    :func:`reference_frames` of the maps' own surfaces; a multi-part object passes the frames of
    its whole surfaces, so that the arrangement of the parts settles what one part's symmetry
    leaves open). In that frame, the rotation P of the parameter sphere that best matches the
    first-order maps, min ||Q M_i P - M_ref||_F over proper rotations, is an orthogonal
    Procrustes problem. The new sphere coordinates are P^T u, so that S_i'(u) = S_i(P u).

    ``landmarks``, one (k, 3) array per map: the sphere images of the same k landmarks on every
    map (a row of NaN where a case lacks one). The rotations then also bring every landmark to
    one shared place g_l on the sphere: max <A_i, P> + c sum_l <s_il g_l^T, P> over rotations
    (A_i the first-order maps' cross-covariance, both terms scaled as
    :data:`LANDMARK_ALIGNMENT_WEIGHT` says), alternating with g_l = the normalised mean of the
    rotated s_il, starting from the rotations without landmarks.

    Returns new :class:`SphereMap` objects (the inputs are not modified); each ``quality`` gains
    ``parameter_rotation_degrees``.
    """
    if frames is None:
        frames = reference_frames([(m.vertices, m.faces) for m in maps], reference)
    ref = maps[reference]
    _, ref_first = first_order_map(ref.vertices, ref.faces, ref.sphere)
    crosses = []
    for item, frame in zip(maps, frames):
        _, first = first_order_map(item.vertices, item.faces, item.sphere)
        crosses.append((frame @ first).T @ ref_first)
    rotations = [best_rotation(cross)[0] for cross in crosses]
    if landmarks is not None and len(landmarks) and np.size(landmarks[0]):
        images = [np.asarray(points, dtype=np.float64) for points in landmarks]
        for _ in range(LANDMARK_ALIGNMENT_ROUNDS):
            places = shared_places(images, rotations)
            rotations = []
            for cross, points in zip(crosses, images):
                known = np.all(np.isfinite(points), axis=1) & np.all(np.isfinite(places), axis=1)
                cross = cross / max(np.linalg.norm(cross), 1e-300)
                if known.any():
                    pull = points[known].T @ places[known]
                    cross = cross + LANDMARK_ALIGNMENT_WEIGHT * pull / known.sum()
                rotations.append(best_rotation(cross)[0])
    aligned = []
    for item, rotation in zip(maps, rotations):
        quality = dict(item.quality)
        angle = np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1)))
        quality["parameter_rotation_degrees"] = float(angle)
        aligned.append(SphereMap(item.vertices, item.faces, item.sphere @ rotation, quality))
    return aligned


def shared_places(images: list, rotations: list) -> np.ndarray:
    """(k, 3): each landmark's shared place on the sphere, the normalised mean of its images
    (rows of ``images``, NaN where absent) rotated as the maps are (u -> u P); NaN where no map
    has the landmark."""
    rotated = np.stack([points @ rotation for points, rotation in zip(images, rotations)])
    known = np.all(np.isfinite(rotated), axis=2)
    total = np.where(known[..., None], rotated, 0.0).sum(axis=0)
    norms = np.linalg.norm(total, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((norms > 0) & known.any(axis=0)[:, None], total / norms, np.nan)
