"""The training shapes in model space, and the leave-one-out models in it (IV-B).

The n_s training shapes span an (n_s - 1)-dimensional affine space: a :class:`ModelSpace` holds
their principal scores there and the map back to point displacements. Every measure of a model's
quality (:mod:`.evaluation`, :mod:`.surface_measures`) is computed from one :func:`model_space`:
the leave-one-out models (:func:`leave_one_out`, each a rank-one downdate solved by the secular
equation) and the specificity samples live in it, so squared distances are computed from
(n_s - 1)-vectors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from threadpoolctl import threadpool_limits

from . import evaluation_kernels


#: A direction of the shapes whose variance is below this share of the largest one's is no mode: it
#: holds rounding (identical cases differ there in the last digits), so the model spaces here and
#: the leave-one-out models leave it out, as :meth:`.shape_model.ShapeModel.from_shapes` leaves it
#: out of a model (its ``relative_tolerance``). The measures of aligned shapes and of the model's
#: own reconstruction of them (``mdlshapemodel compare`` reads those) are then the same.
ROUNDING_VARIANCE = 1e-10


def modes_kept(singular: np.ndarray) -> np.ndarray:
    """Which singular values of centred shapes are modes (variance above
    :data:`ROUNDING_VARIANCE` of the largest)."""
    largest = max(float(singular.max(initial=0.0)), 1e-300)
    return singular ** 2 > ROUNDING_VARIANCE * largest ** 2


@dataclass(frozen=True)
class ModelSpace:
    """The training shapes in model space.

    ``coordinates`` (n_s, r): the centred, area-weighted shapes in an orthonormal basis of their
    span (principal component scores: orthogonal columns, sums of squares descending);
    ``to_points`` (r, 3 n_p): the map from model-space differences back to point displacements.
    Every measure of :func:`.evaluation.evaluate` works from one :func:`model_space` of the shapes.
    """

    coordinates: np.ndarray
    to_points: np.ndarray


@dataclass(frozen=True)
class PrincipalAxes:
    """One singular value decomposition of aligned shapes, for both their model and their
    model space.

    ``mean`` (n_p, 3): the mean shape; ``singular``: every singular value of the centred,
    area-weighted shapes (n_s x 3 n_p), descending (the model's variances are their squares over
    n_s, :meth:`.shape_model.ShapeModel.from_shapes`); ``space``: the :class:`ModelSpace` of the
    directions above :data:`ROUNDING_VARIANCE`. A model keeps a leading part of those directions
    (:data:`.shape_model.NEGLIGIBLE_VARIANCE` is above :data:`ROUNDING_VARIANCE`), so its modes
    and scores are ``space.to_points`` and ``space.coordinates`` cut to its modes, and its
    evaluation (:func:`.evaluation.evaluate`) needs no decomposition of its own.
    """

    mean: np.ndarray
    singular: np.ndarray
    space: ModelSpace


def principal_axes(shapes: np.ndarray, weights: np.ndarray) -> PrincipalAxes:
    """The :class:`PrincipalAxes` of aligned, corresponded shapes (n_s, n_p, 3) with area
    weights (n_p,), from the n_s x 3 n_p centred shapes Z, each coordinate scaled by the square
    root of its point's weight (the inner product of eq. 15).

    Up to as many shapes as coordinates, one SVD of Z. With more (:func:`axes_route`), the
    eigendecomposition of the 3 n_p x 3 n_p matrix Z^T Z instead: its eigenvalues are the
    squared singular values and its eigenvectors the axes, and the scores are Z times them.
    The SVD would hold Z's copy, U and a workspace of about four times (3 n_p)^2 numbers beside
    Z; this holds Z^T Z and its eigenvectors. The two
    agree to rounding on every mode :func:`modes_kept` keeps (a variance of 1e-10 of the
    largest, where Z^T Z's rounding is about 1e-16 of it).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shapes, weights = rng.normal(size=(12, 2, 3)), np.full(2, 0.5)
    >>> many = principal_axes(shapes, weights).singular     # 12 shapes of 6 coordinates
    >>> few = np.linalg.svd(((shapes - shapes.mean(0)) * np.sqrt(0.5)).reshape(12, 6),
    ...                     compute_uv=False)
    >>> bool(np.allclose(many, few))
    True
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    n_s, n_p, _ = shapes.shape
    mean = shapes.mean(axis=0)
    root = np.sqrt(weights)
    z = ((shapes - mean) * root[None, :, None]).reshape(n_s, -1)
    unweighted = np.repeat(root, 3)
    if axes_route(n_s, z.shape[1]) == "covariance":
        singular, axes = _covariance_axes(z)
        keep = modes_kept(singular)
        kept = np.ascontiguousarray(axes[:, keep])
        del axes
        with threadpool_limits(limits=1, user_api="blas"):
            coordinates = z @ kept
        return PrincipalAxes(mean, singular, ModelSpace(coordinates, kept.T / unweighted))
    u, singular, vt = np.linalg.svd(z, full_matrices=False)
    keep = modes_kept(singular)
    return PrincipalAxes(mean, singular,
                         ModelSpace(u[:, keep] * singular[keep], vt[keep] / unweighted))


def axes_route(n_shapes: int, dimension: int) -> str:
    """How :func:`principal_axes` decomposes n_s centred shapes of ``dimension`` (3 n_p)
    coordinates: ``"svd"`` of the shapes, up to as many shapes as coordinates, else
    ``"covariance"`` (the dimension x dimension matrix, the smaller of the two)."""
    return "covariance" if n_shapes > dimension else "svd"


def _covariance_axes(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The singular values of ``z`` (n, d), n > d, descending, and its right singular vectors
    (d, d; columns), from Z^T Z: on one BLAS thread, so that the bits do not depend on the
    caller's threads; LAPACK's relatively robust representations (``evr``) in place, whose
    workspace is a few d-vectors (numpy's ``eigh`` would copy Z^T Z and work in 2 d^2 more)."""
    with threadpool_limits(limits=1, user_api="blas"):
        covariance = z.T @ z
        eigenvalues, vectors = scipy.linalg.eigh(covariance, overwrite_a=True,
                                                 check_finite=False, driver="evr")
    del covariance
    return np.sqrt(np.clip(eigenvalues[::-1], 0.0, None)), vectors[:, ::-1]


def model_space(shapes: np.ndarray, weights: np.ndarray) -> ModelSpace:
    """The :class:`ModelSpace` of aligned, corresponded shapes (n_s, n_p, 3) with area weights
    (that of their :func:`principal_axes`)."""
    return principal_axes(shapes, weights).space


def space_of(shapes: np.ndarray, weights: np.ndarray, space: ModelSpace | None):
    """(coordinates, to_points) of ``space``, or of the shapes' model space when it is None."""
    space = model_space(shapes, weights) if space is None else space
    return space.coordinates, space.to_points


#: rows of standard normals drawn at a time by :func:`sample_scores`
SAMPLE_ROWS = 256


def sample_scores(rng: np.random.Generator, n_samples: int, sd: np.ndarray,
                  modes: int) -> np.ndarray:
    """Principal scores of ``n_samples`` model samples on the first ``modes`` axes (at most
    ``len(sd)``): b_m = z_m sd_m, each sample's z the first of ``len(sd)`` standard normals
    (eq. 22's samples, their scores N(0, lambda_m)).

    The normals are drawn :data:`SAMPLE_ROWS` samples at a time: the same numbers as one
    (n_samples, len(sd)) draw, and ``rng`` left in the same state, without holding that matrix
    (10,000 samples of 10,000 shapes' model space would take 0.8 GB for 10 columns).

    Examples
    --------
    >>> a, b = np.random.default_rng(1), np.random.default_rng(1)
    >>> sd = np.array([2.0, 1.0, 0.5])
    >>> bool(np.array_equal(sample_scores(a, 600, sd, 2),
    ...                     b.standard_normal((600, 3))[:, :2] * sd[:2]))
    True
    """
    rank = len(sd)
    used = min(modes, rank)
    scores = np.empty((n_samples, used))
    for start in range(0, n_samples, SAMPLE_ROWS):
        stop = min(start + SAMPLE_ROWS, n_samples)
        scores[start:stop] = rng.standard_normal((stop - start, rank))[:, :used] * sd[:used]
    return scores


def displacements(difference: np.ndarray, to_points: np.ndarray) -> np.ndarray:
    """Point displacements (k, n_p, 3) of model-space differences (k, r)."""
    return (difference @ to_points).reshape(len(difference), -1, 3)


def leave_one_out(coordinates: np.ndarray, max_modes: int, cases=None):
    """For each shape i: (i, residuals (max_modes, r), modes used (max_modes,)).

    ``cases``: the shapes i left out in turn (indices, in the order given); default all of them.
    Each is still reconstructed by the model of all the others.

    ``residuals[M - 1]`` is x_i - x_i'(M) in model space: x_i minus its reconstruction by the model
    built without it, with M modes (at most the n_s - 2 that model has).

    The coordinates are principal component scores (centred, orthogonal columns with sums of
    squares d_j), so the scatter of the other shapes about their mean is a diagonal matrix less a
    rank-one term, diag(d) - rho x_i x_i^T with rho = n_s / (n_s - 1). Its leading eigenpairs
    come from the secular equation (:func:`_downdated_modes`), O(n_s max_modes) per shape instead
    of an O(n_s^3) decomposition; where that is ill-conditioned (repeated d_j), the others'
    decomposition is computed directly.
    """
    n_s, r = coordinates.shape
    scatter = np.sum(coordinates ** 2, axis=0)
    # the model without shape i has at most n_s - 2 modes: null directions would otherwise
    # hold the part of shape i that the others do not span
    wanted = min(max_modes, max(n_s - 2, 0), r)
    rho = n_s / (n_s - 1.0)
    for i in (range(n_s) if cases is None else cases):
        offset = coordinates[i] * rho          # x_i minus the others' mean
        directions = _downdated_modes(scatter, coordinates[i], rho, wanted)
        if directions is None:
            directions, rank = _modes_of_others(coordinates, i)
        else:
            rank = wanted
        residuals = []
        for m in range(1, max_modes + 1):
            kept = directions[:min(m, rank)]
            residuals.append(offset - (offset @ kept.T) @ kept)
        used = np.minimum(np.arange(1, max_modes + 1), rank)
        yield i, np.array(residuals), used


def _modes_of_others(coordinates: np.ndarray, i: int) -> tuple[np.ndarray, int]:
    """The principal directions (rows) of every shape but i, and their number (the rank)."""
    others = np.delete(coordinates, i, axis=0)
    _, singular, directions = np.linalg.svd(others - others.mean(axis=0), full_matrices=False)
    rank = int(np.sum(modes_kept(singular)))
    return directions, rank


def _downdated_modes(d: np.ndarray, v: np.ndarray, rho: float, count: int):
    """The ``count`` leading unit eigenvectors (rows) of diag(d) - rho v v^T, for d descending
    and positive, or None when the secular equation is ill-conditioned here.

    Each leading eigenvalue lies strictly between consecutive d (interlacing); it is the root of
    1 - rho sum_j v_j^2 / (d_j - lambda) in (d_{k+1}, d_k), found by bisection to the last bit,
    and its eigenvector is (diag(d) - lambda)^-1 v, normalised. The bisection is compiled
    (:func:`~.evaluation_kernels.secular_roots`): the generalization's jackknife solves it for
    every case of every group. Components of v that vanish, or
    d that repeat, would need deflation: then None.
    """
    r = len(d)
    if count == 0:
        return np.zeros((0, r))
    if count >= r or np.any(np.diff(d) >= 0.0):
        return None
    scale = float(np.sqrt(np.sum(v * v)))
    gaps = d[:-1] - d[1:]
    if scale == 0.0 or np.any(np.abs(v[:count + 1]) < 1e-8 * scale) or np.any(
            gaps[:count] < 1e-8 * d[0]):
        return None
    roots = evaluation_kernels.secular_roots(d, v, rho, count)
    vectors = v[None, :] / (d[None, :] - roots[:, None])
    return vectors / np.linalg.norm(vectors, axis=1, keepdims=True)


def subspace_coordinates(space: ModelSpace, keep) -> np.ndarray:
    """The coordinates of the :class:`ModelSpace` of the shapes ``keep`` (indices) alone, from
    that of all of them (the leave-one-out errors of :func:`leave_one_out` need no more).

    Their coordinates are centred on their own mean and turned to their principal axes; the turn
    is orthogonal, so every measure in model space comes out as from :func:`model_space` of
    those shapes, in O(n_s r^2) instead of a decomposition of the shapes.
    """
    coordinates = space.coordinates[np.asarray(keep)]
    coordinates = coordinates - coordinates.mean(axis=0)
    u, singular, _ = np.linalg.svd(coordinates, full_matrices=False)
    nonzero = modes_kept(singular)
    return u[:, nonzero] * singular[nonzero]
