"""Template correspondence by coherent point drift (CPD): the baseline without MDL.

A common way to put shapes in correspondence in Python when no MDL optimisation is available is to
take one *template* (the corresponded points of one case) and register it onto every other surface
with the deformable coherent point drift of Myronenko & Song (IEEE TPAMI 32(12), 2010; the
``pycpd`` package): point k of the registered template is then point k of that case. This module
does exactly that, per target surface:

1. **similarity pre-alignment**: both point sets are centred on their centroids and scaled to unit
   RMS radius, then CPD rigid registration with scaling (:class:`pycpd.RigidRegistration`) aligns
   the template to the target;
2. **deformable CPD** (:class:`pycpd.DeformableRegistration`) of the aligned template points
   Y (moving, the M Gaussian centroids) onto the target vertices X (fixed, N data points, at most
   ``max_target_points`` of them, drawn at random with ``seed``), in the target's unit-RMS frame,
   so that ``beta`` and ``alpha`` do not depend on the size or units of the shapes. The EM starts
   from ``sigma2_factor`` times the variance the rigid registration ended with, not from pycpd's
   start (the mean squared distance over all point pairs), see below;
3. the deformed points are mapped back to the target's frame and each is **projected** onto the
   closest point of the target triangle mesh
   (:class:`~mdlshapemodel.prepare.surface.SurfaceDistance`).

pycpd 2.0.0 (the release on PyPI) solves the full M x M system of the deformable M-step (eq. 22 of
the paper) at every iteration and builds its E-step through (M, N, D) difference arrays; it has no
``low_rank`` option (only newer pycpd sources have one; 2.0.0 silently swallows a ``low_rank=True``
keyword in its ``**kwargs``). With M = 2,562 template points that costs 0.3-0.6 s per iteration.
The classes below keep pycpd's EM loop, rigid M-step and variance updates and replace (a) the
E-step by a lean one (squared distances by one matrix product, exponentials in single precision,
no (M, N, D) array) and (b) the deformable M-step by the paper's fast low-rank form (section
5.2): G ~ Q Lambda Q^T with the ``num_eig`` largest eigenpairs (found by a randomised range
finder, Halko et al. 2011), solved with the Woodbury identity in O(M K^2). With exact solves they
reproduce pycpd's own classes (``Testing/test_registration.py``).

Why the defaults (``sigma2_factor``, ``num_eig``, ``beta``) are what they are, with the
measurements behind them: docs/benchmarks.md, "The template + CPD baseline". In short, pycpd's own
start is far too wide for shapes that are already aligned: in the first iterations the flexible
field collapses the template towards its centre and it comes back folded and slid along the
surface; the narrow start recovers large deformations (strong bending) less well, for which
``sigma2_factor`` can be raised.

Run it in a process pool with :func:`cpd_case`. Give each worker one BLAS thread
(``OPENBLAS_NUM_THREADS=1`` / ``OMP_NUM_THREADS=1`` in the environment before the pool starts):
multi-threaded BLAS in several processes at once slows the same registration down several
times.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Executor
from dataclasses import dataclass

import numpy as np
from pycpd import DeformableRegistration, RigidRegistration
from pycpd.emregistration import EMRegistration

from ..config import BuildConfig
from ..errors import ArgumentError, InternalError
from ..parallel import executor_for, map_cases
from ..prepare.case import one_blas_thread
from ..prepare.surface import SurfaceDistance
from ..progress import Progress
from .state import CorrespondenceState, FixedExample

log = logging.getLogger("mdlshapemodel")

#: Template and target points used to estimate the similarity transform (7 parameters).
RIGID_POINTS = 1000
#: Smallest sigma^2 (in units of the squared RMS radius): the single-precision E-step loses
#: accuracy below it (relative error of P about 4e-7 / sigma^2), and sigma = 0.3 % of the radius is
#: far below the CPD fits of real surfaces (hippocampi end at sigma ~ 2 % of the radius).
MIN_SIGMA2 = 1e-5
#: Oversampling and power iterations of the randomised eigendecomposition of G.
_OVERSAMPLING = 20
_POWER_ITERATIONS = 2


@dataclass
class CPDResult:
    """What :func:`cpd_registration` found for one target.

    Attributes
    ----------
    points : ndarray (n_p, 3)
        The correspondence: template point k registered onto the target and projected onto its
        surface.
    deformed : ndarray (n_p, 3)
        The CPD result before projection, T(y_k), in the target's frame.
    fit_distance : ndarray (n_p,)
        Distance of each deformed point to the target surface (the length of its projection).
    triangles : ndarray (n_p,) int
        Index of the target face that holds each projected point.
    scale, rotation, translation : float, ndarray (3, 3), ndarray (3,)
        The similarity pre-alignment: ``scale * rotation @ y + translation`` maps template point y
        into the target's frame (before the deformation).
    sigma : float
        Final standard deviation of the CPD Gaussian mixture, in target units.
    target_indices : ndarray (N,) int
        The target vertices used as the fixed point set (sorted).
    rigid_iterations, iterations : int
        EM iterations of the rigid and of the deformable registration.
    seconds : float
        Wall time of the whole registration.
    """

    points: np.ndarray
    deformed: np.ndarray
    fit_distance: np.ndarray
    triangles: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    sigma: float
    target_indices: np.ndarray
    rigid_iterations: int
    iterations: int
    seconds: float


def initial_sigma2(X: np.ndarray, Y: np.ndarray) -> float:
    """sigma^2 = sum_mn ||x_n - y_m||^2 / (D M N) in closed form (pycpd's ``initialize_sigma2``
    without its (M, N, D) array)."""
    (N, D), M = X.shape, len(Y)
    total = M * np.sum(X * X) + N * np.sum(Y * Y) - 2.0 * X.sum(axis=0) @ Y.sum(axis=0)
    return float(total / (D * M * N))


def gaussian_exponent(Y: np.ndarray, X: np.ndarray, scale: float) -> np.ndarray:
    """(M, N) float32 matrix of -scale ||y_m - x_n||^2 (scale > 0), clipped at 0.

    One single-precision matrix product of the augmented rows [y, ||y||^2, 1] and
    [2 scale x, -scale, -scale ||x||^2]: no (M, N, D) array, no further passes.
    """
    Y = np.asarray(Y, dtype=np.float64)
    X = np.asarray(X, dtype=np.float64)
    left = np.empty((len(Y), Y.shape[1] + 2), dtype=np.float32)
    left[:, :-2] = Y
    left[:, -2] = np.einsum("ij,ij->i", Y, Y)
    left[:, -1] = 1.0
    right = np.empty((len(X), X.shape[1] + 2), dtype=np.float32)
    right[:, :-2] = 2.0 * scale * X
    right[:, -2] = -scale
    right[:, -1] = -scale * np.einsum("ij,ij->i", X, X)
    exponent = left @ right.T
    np.minimum(exponent, 0.0, out=exponent)
    return exponent


def gaussian_kernel(Y: np.ndarray, beta: float, Z: np.ndarray | None = None) -> np.ndarray:
    """G_ij = exp(-||y_i - z_j||^2 / (2 beta^2)) (float64; exponentials in single precision)."""
    G = gaussian_exponent(Y, Y if Z is None else Z, 0.5 / beta ** 2)
    np.exp(G, out=G)
    return G.astype(np.float64)


def low_rank_eigen(G: np.ndarray, num_eig: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The ``num_eig`` largest eigenpairs (Q (M, K), Lambda (K,)) of the symmetric positive
    semi-definite matrix G, by a randomised range finder with power iterations (Halko, Martinsson
    & Tropp, SIAM Review 2011, algorithms 4.4 and 5.3). Costs O(M^2 K) instead of O(M^3)."""
    M = len(G)
    Z = G @ rng.standard_normal((M, min(M, num_eig + _OVERSAMPLING)))
    for _ in range(_POWER_ITERATIONS):
        Z, _ = np.linalg.qr(Z)
        Z = G @ Z
    basis, _ = np.linalg.qr(Z)
    values, vectors = np.linalg.eigh(basis.T @ G @ basis)
    keep = slice(len(values) - num_eig, None)
    return basis @ vectors[:, keep], np.maximum(values[keep], 1e-12)


class _LeanExpectation:
    """CPD E-step (eq. 7 of the paper) without pycpd's (M, N, D) difference array.

    P_mn = exp(-||x_n - y_m||^2 / 2 sigma^2) / (sum_k exp(...) + c),
    c = (2 pi sigma^2)^(D/2) w / (1 - w) M / N. The exponentials dominate the run time and are
    several times faster in single precision, so K = exp(...) is float32; P^T 1, P 1 and P X are
    formed from K and the column normalisers by matrix products (float64 results) without
    normalising K itself. ``P`` is only materialised when ``keep_P`` (the rigid M-step reads it).
    """

    keep_P = True

    def expectation(self):
        K = gaussian_exponent(self.TY, self.X, 0.5 / self.sigma2)
        np.exp(K, out=K)
        c = (2.0 * np.pi * self.sigma2) ** (self.D / 2.0) * self.w / (1.0 - self.w) * self.M / self.N
        column = (np.ones(self.M, dtype=np.float32) @ K).astype(np.float64)
        # a target point far (> ~14 sigma) from every centroid gets no weight (pycpd: 0 / eps)
        scale = np.divide(1.0, column + c, out=np.zeros_like(column), where=column + c > 0)
        self.Pt1 = column * scale
        weighted = np.empty((self.N, self.D + 1), dtype=np.float32)
        weighted[:, 0] = scale
        weighted[:, 1:] = self.X * scale[:, None]
        products = (K @ weighted).astype(np.float64)  # [P 1, P X]
        self.P1 = products[:, 0]
        self.PX = products[:, 1:]
        self.Np = float(self.P1.sum())
        if not self.Np > 0:
            raise ArgumentError("CPD lost every correspondence: the point sets are too far apart")
        if self.keep_P:
            K *= scale.astype(np.float32)[None, :]
            self.P = K
        else:
            self.P = None


class RigidCPD(_LeanExpectation, RigidRegistration):
    """pycpd's rigid CPD with scaling, the lean E-step and a relative stopping rule.

    pycpd stops when the objective Q changes by less than ``tolerance`` in absolute terms, but Q
    grows with the number of points; here the change is taken relative to |Q|.
    """

    def update_variance(self):
        previous = self.q
        super().update_variance()
        self.sigma2 = max(self.sigma2, MIN_SIGMA2)
        self.diff = abs(self.q - previous) / max(abs(self.q), 1.0)


class LowRankDeformableCPD(_LeanExpectation, DeformableRegistration):
    """pycpd's deformable CPD with the lean E-step and the low-rank M-step of the paper (sec. 5.2).

    Parameters
    ----------
    X, Y : ndarray (N, D), (M, D)
        Fixed and moving points.
    alpha, beta : float
        Regularisation weight (the paper's lambda) and Gaussian kernel width.
    num_eig : int or None
        Rank K of the approximation G ~ Q Lambda Q^T; None or >= M: the exact M x M solve.
    rng : numpy Generator
        For the randomised eigendecomposition.
    **kwargs
        ``sigma2``, ``max_iterations``, ``tolerance``, ``w`` of :class:`pycpd.EMRegistration`.
    """

    keep_P = False

    def __init__(self, X, Y, alpha: float, beta: float, num_eig: int | None,
                 rng: np.random.Generator, **kwargs):
        # pycpd's own constructor builds G through (M, M, D) tiled arrays: set it up here instead
        EMRegistration.__init__(self, X, Y, **kwargs)
        self.alpha = float(alpha)
        self.beta = float(beta)
        self.W = np.zeros((self.M, self.D))
        self.G = gaussian_kernel(self.Y, self.beta)
        self.low_rank = num_eig is not None and num_eig < self.M
        if self.low_rank:
            self.Q, self.S = low_rank_eigen(self.G, int(num_eig), rng)

    def update_transform(self):
        """W from (d(P1) G + alpha sigma^2 I) W = P X - d(P1) Y (eq. 22), exactly or with
        G ~ Q S Q^T and the Woodbury identity:
        W = (F - d(P1) Q (alpha sigma^2 S^-1 + Q^T d(P1) Q)^-1 Q^T F) / (alpha sigma^2)."""
        a = self.alpha * self.sigma2
        F = self.PX - self.P1[:, None] * self.Y
        if self.low_rank:
            dPQ = self.P1[:, None] * self.Q
            inner = self.Q.T @ dPQ
            inner[np.diag_indices_from(inner)] += a / self.S
            self.W = (F - dPQ @ np.linalg.solve(inner, self.Q.T @ F)) / a
        else:
            A = self.P1[:, None] * self.G
            A[np.diag_indices_from(A)] += a
            self.W = np.linalg.solve(A, F)

    def displacement(self) -> np.ndarray:
        """G W, the displacement v(y_m) of every moving point."""
        if self.low_rank:
            return self.Q @ (self.S[:, None] * (self.Q.T @ self.W))
        return self.G @ self.W

    def transform_point_cloud(self, Y=None):
        if Y is None:
            self.TY = self.Y + self.displacement()
            return None
        # any other points: T(z) = z + G(z, Y) W
        return Y + gaussian_kernel(Y, self.beta, self.Y) @ self.W

    def update_variance(self):
        """sigma^2 = (tr(X^T d(P^T 1) X) - 2 tr((P X)^T T) + tr(T^T d(P 1) T)) / (N_P D) (eq. 23),
        using the P X of the E-step, floored at ``MIN_SIGMA2`` (pycpd resets sigma^2 <= 0 to
        tolerance / 10); ``diff`` is the change of sigma^2, as in pycpd."""
        previous = self.sigma2
        self.q = np.inf
        xPx = self.Pt1 @ np.einsum("ij,ij->i", self.X, self.X)
        yPy = self.P1 @ np.einsum("ij,ij->i", self.TY, self.TY)
        trPXY = np.sum(self.TY * self.PX)
        self.sigma2 = max(float((xPx - 2.0 * trPXY + yPy) / (self.Np * self.D)), MIN_SIGMA2)
        self.diff = abs(self.sigma2 - previous)


def subsample_indices(n: int, max_points: int | None, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``max_points`` of ``n`` items, drawn without replacement with a
    generator seeded by ``seed`` (all of them, in order, when ``n <= max_points`` or
    ``max_points`` is None)."""
    if max_points is None or n <= max_points:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=int(max_points), replace=False))


def closest_points_on_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point of a triangle mesh to each query point: (closest (n, 3), distance (n,),
    index of the face holding it (n,)), by :class:`mdlshapemodel.prepare.surface.SurfaceDistance`."""
    return SurfaceDistance(vertices, faces).closest(points)


def _check_inputs(template_points, target_vertices, target_faces):
    template = np.asarray(template_points, dtype=np.float64)
    vertices = np.asarray(target_vertices, dtype=np.float64)
    faces = np.asarray(target_faces)
    if template.ndim != 2 or template.shape[1] != 3 or len(template) < 4:
        raise ArgumentError(f"template_points must be (n_p >= 4, 3), got shape {template.shape}")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4:
        raise ArgumentError(f"target_vertices must be (v >= 4, 3), got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ArgumentError(f"target_faces must be (f >= 1, 3), got shape {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ArgumentError(f"target_faces must be integers, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ArgumentError("target_faces index vertices that do not exist")
    if not (np.all(np.isfinite(template)) and np.all(np.isfinite(vertices))):
        raise ArgumentError("the points must be finite (no NaN or infinity)")
    return template, vertices, faces.astype(np.int64)


def _normalisation(points: np.ndarray) -> tuple[np.ndarray, float]:
    centre = points.mean(axis=0)
    radius = float(np.sqrt(np.mean(np.sum((points - centre) ** 2, axis=1))))
    if radius <= 0:
        raise ArgumentError("the points all coincide")
    return centre, radius


@one_blas_thread()   # the same arithmetic wherever it runs: see the docstring
def cpd_registration(template_points: np.ndarray, target_vertices: np.ndarray,
                     target_faces: np.ndarray, *, beta: float = 0.3, alpha: float = 2.0,
                     max_iterations: int = 150, tolerance: float = 1e-6,
                     max_target_points: int | None = 3000, num_eig: int | None = 150,
                     sigma2_factor: float | None = 4.0, w: float = 0.0, seed: int = 0
                     ) -> CPDResult:
    """Register template points onto one target surface by CPD; see :func:`cpd_correspondence`
    for the parameters. Returns a :class:`CPDResult` with the correspondence and diagnostics.

    BLAS runs single-threaded, as in preparation, so the result is the same bit for bit in a
    worker process, on a Dask worker and in the build's own process (``--workers 1``: there,
    threaded BLAS gave other last bits)."""
    started = time.perf_counter()
    template, vertices, faces = _check_inputs(template_points, target_vertices, target_faces)
    if not (beta > 0 and alpha > 0 and tolerance > 0 and 0 <= w < 1 and max_iterations >= 1
            and (sigma2_factor is None or sigma2_factor > 0)):
        raise ArgumentError("need beta > 0, alpha > 0, tolerance > 0, 0 <= w < 1, max_iterations >= 1"
                         f" and sigma2_factor > 0 or None (got beta={beta}, alpha={alpha}, "
                         f"tolerance={tolerance}, w={w}, max_iterations={max_iterations}, "
                         f"sigma2_factor={sigma2_factor})")
    if max_target_points is not None and max_target_points < 4:
        raise ArgumentError(f"max_target_points must be at least 4, got {max_target_points}")
    rng = np.random.default_rng(seed)

    # (1) centroids and unit RMS radius, then rigid CPD with scaling on a subset
    target_centre, target_radius = _normalisation(vertices)
    template_centre, template_radius = _normalisation(template)
    X_all = (vertices - target_centre) / target_radius
    Y = (template - template_centre) / template_radius
    rigid_Y = Y[subsample_indices(len(Y), RIGID_POINTS, seed)]
    rigid_X = X_all[subsample_indices(len(X_all), RIGID_POINTS, seed + 1)]
    rigid = RigidCPD(X=rigid_X, Y=rigid_Y, sigma2=initial_sigma2(rigid_X, rigid_Y),
                   max_iterations=100, tolerance=1e-5, w=w)
    rigid.register()
    Y_aligned = rigid.transform_point_cloud(Y=Y)

    # (2) deformable CPD of the aligned template onto (a subset of) the target vertices
    target_indices = subsample_indices(len(vertices), max_target_points, seed)
    X = X_all[target_indices]
    sigma2_start = (initial_sigma2(X, Y_aligned) if sigma2_factor is None
                    else max(sigma2_factor * rigid.sigma2, MIN_SIGMA2))
    deformable = LowRankDeformableCPD(X=X, Y=Y_aligned, alpha=alpha, beta=beta, num_eig=num_eig, rng=rng,
                             sigma2=sigma2_start,
                             max_iterations=int(max_iterations), tolerance=tolerance, w=w)
    deformable.register()

    # (3) back to the target's frame, onto the target surface
    deformed = deformable.TY * target_radius + target_centre
    points, distance, triangles = closest_points_on_surface(vertices, faces, deformed)
    # pycpd's row-vector convention s Y R + t -> column vectors: scale * R^T y + translation
    scale = float(rigid.s) * target_radius / template_radius
    rotation = np.asarray(rigid.R).T.copy()
    translation = (target_centre + target_radius * np.ravel(rigid.t)
                   - scale * rotation @ template_centre)
    return CPDResult(points=points, deformed=deformed, fit_distance=distance, triangles=triangles,
                     scale=scale, rotation=rotation, translation=translation,
                     sigma=float(np.sqrt(deformable.sigma2)) * target_radius,
                     target_indices=target_indices, rigid_iterations=int(rigid.iteration),
                     iterations=int(deformable.iteration),
                     seconds=time.perf_counter() - started)


def cpd_correspondence(template_points: np.ndarray, target_vertices: np.ndarray,
                       target_faces: np.ndarray, *, beta: float = 0.3, alpha: float = 2.0,
                       max_iterations: int = 150, tolerance: float = 1e-6,
                       max_target_points: int | None = 3000, num_eig: int | None = 150,
                       sigma2_factor: float | None = 4.0, w: float = 0.0, seed: int = 0
                       ) -> np.ndarray:
    """Template correspondence on one target surface by coherent point drift.

    The template points y_k (moving) are registered onto the target vertices (fixed): similarity
    pre-alignment (centroids, unit RMS radius, rigid CPD with scaling), deformable CPD, then each
    deformed point T(y_k) is projected onto the closest point of the target mesh. Point k of the
    result corresponds to template point k.

    Parameters
    ----------
    template_points : ndarray (n_p, 3)
        The template's corresponded points (e.g. 2,562 points sampled on one case's surface).
    target_vertices : ndarray (v, 3)
        Vertices of the target: a closed triangle mesh, in the units of the template.
    target_faces : ndarray (f, 3) int
        Its triangles.
    beta : float
        Width of the Gaussian kernel of the displacement field (the paper's beta), in units of
        the target's RMS radius (hippocampi: about 11 mm, so 0.3 is about 3.3 mm).
    alpha : float
        Weight of the smoothness regulariser (the paper's lambda). With the coordinates
        normalised, alpha and beta are scale-free.
    max_iterations : int
        EM iterations of the deformable registration (the rigid one stops at 100).
    tolerance : float
        Stop when sigma^2 changes by less than this between iterations (pycpd's rule), in the
        normalised units: 1e-6 is about 0.3 % of the final sigma^2 on hippocampi (sigma about
        0.19 mm); 1e-5 gives the same fit in 17 instead of 26 iterations, 1e-7 needs 53.
    max_target_points : int or None
        At most this many target vertices (drawn at random with ``seed``, without replacement)
        are the fixed point set; None: all of them. The cost of an iteration is O(n_p N).
    num_eig : int or None
        Rank of the low-rank kernel G ~ Q Lambda Q^T; None: exact M x M solves (about 20 times
        slower per iteration for 2,562 points). The eigenvalues of G fall faster for wider
        kernels: for beta = 0.3 on hippocampi, 90 / 150 eigenpairs hold 99 % / 99.9 % of its
        trace; for beta = 0.2 it takes 190 / 310.
    sigma2_factor : float or None
        The deformable EM starts at sigma^2 = ``sigma2_factor`` times the final sigma^2 of the
        rigid registration (the variance the similarity leaves unexplained). None: pycpd's start,
        the mean squared distance over all point pairs, which folds the hippocampus template
        (see the module docstring). Larger values capture larger deformations at more risk.
    w : float in [0, 1)
        Weight of the uniform outlier component of the mixture (pycpd's w). Closed surfaces of
        one object have no outliers: 0.
    seed : int
        Seeds the target subsampling and the randomised eigendecomposition: equal inputs and
        seed give equal results.

    Returns
    -------
    ndarray (n_p, 3)
        Points on the target surface, point k corresponding to template point k.

    Notes
    -----
    Defaults, measured with ``benchmarks/cpd_baseline.py`` on shared hippocampi (module
    docstring): beta = 0.3 (3.3 mm) fits the hippocampi to 0.065 mm on average (95th percentile
    0.16 mm) before projection in about 2 s per case; beta = 0.2 fits closer (0.043 mm) but needs
    twice the eigenpairs and 1.7 times the time, beta = 0.5 fits worse (0.10 mm). On hippocampi
    with a known smooth deformation (2.5 mm bumps, 10 % stretch) the error to the true
    correspondence was 0.95 mm (beta 0.3), 0.97 (0.2), 0.90 (0.5). num_eig = 150 holds 99.9 % of
    the kernel's trace for beta = 0.3; exact solves fit to 0.038 mm at 6 times the cost.
    ``max_target_points = 3000`` keeps every vertex of the hippocampus surfaces (the fixed set
    should cover the surface about as densely as the template) and bounds the cost on larger
    meshes (the iteration cost is O(n_p N)).
    """
    return cpd_registration(template_points, target_vertices, target_faces, beta=beta,
                            alpha=alpha, max_iterations=max_iterations, tolerance=tolerance,
                            max_target_points=max_target_points, num_eig=num_eig,
                            sigma2_factor=sigma2_factor, w=w, seed=seed).points


def cpd_case(arguments: tuple) -> CPDResult:
    """Process-pool entry point: ``arguments`` is ``(template_points, target_vertices,
    target_faces)`` or ``(template_points, target_vertices, target_faces, options)`` with
    ``options`` a dict of keyword arguments of :func:`cpd_correspondence`. Everything is plain
    numpy arrays and numbers, so it pickles. Returns the :class:`CPDResult` (``.points`` is the
    correspondence)::

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            results = list(pool.map(cpd_case, [(template, v, f, {"seed": 0}) for v, f in targets]))
    """
    template, vertices, faces, *rest = arguments
    options = dict(rest[0]) if rest and rest[0] else {}
    return cpd_registration(template, vertices, faces, **options)


def cpd_state(state: CorrespondenceState, prepared: list, config: BuildConfig,
              executor: Executor | None = None, progress: Progress | None = None
              ) -> tuple[CorrespondenceState, str]:
    """The CPD template correspondence of the same cases (the peer baseline), and its template.

    The template is the case whose initial correspondence is closest to the initial mean (the
    medoid); its points are registered onto every other case's surface by coherent point drift
    (part by part for a multi-part object) and projected onto it (:func:`cpd_correspondence`), on ``executor`` (default: a process
    pool of ``config.workers``). A registration whose worker process dies runs again alone in a
    fresh process (:func:`~mdlshapemodel.parallel.map_cases`); one that kills that one too is a
    bug (:class:`InternalError`, naming the case): its input was prepared already.
    """
    aligned = state.aligned_shapes()
    distances = np.einsum("ikd,k->i", (aligned - aligned.mean(axis=0)) ** 2, state.weights)
    template = int(np.argmin(distances))
    points = state.examples[template].raw_points()
    log.info("CPD baseline: registering the template %s onto %d cases",
             state.examples[template].name, len(prepared) - 1)
    # each part of the template onto the same part of every other case
    tasks = [(i, j) for i in range(len(prepared)) if i != template
             for j in range(len(state.part_slices))]

    def died(index: int, how: str):
        raise InternalError(f"{prepared[tasks[index][0]].name}: {how} while the CPD template was "
                            "registered onto it, also in a process of its own; please report it")

    with executor_for(config.workers, executor) as pool:
        registered = map_cases(cpd_correspondence,
                               [(points[state.part_slices[j]], prepared[i].parts[j].map.vertices,
                                 prepared[i].parts[j].map.faces) for i, j in tasks],
                               pool, progress, "CPD registered", died, config.workers)
    shapes = {template: points}
    for (i, _), part_points in zip(tasks, registered):
        shapes[i] = np.concatenate([shapes[i], part_points]) if i in shapes else part_points
    examples = [FixedExample(case.name, shapes[i]) for i, case in enumerate(prepared)]
    return (CorrespondenceState(examples, state.grids, scaling=config.scaling),
            state.examples[template].name)
