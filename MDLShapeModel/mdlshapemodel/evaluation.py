"""Model quality: compactness, generalization and specificity with standard errors (IV-B).

Distances use the area measure: the squared distance of two corresponded shapes is
sum_k w_k |a_k - b_k|^2 (mm^2, the paper's |x - y|^2 with the weights of eq. 15-17), and the mean
point-to-point distance is sum_k w_k |a_k - b_k| (mm).

Everything is computed in model space: the n_s training shapes span an (n_s - 1)-dimensional
affine space, and the leave-one-out models and the specificity samples all live in it, so squared
distances are computed from (n_s - 1)-vectors. Only the mm point-to-point distances need the points.
"""

from __future__ import annotations

import numpy as np


def _model_space(shapes: np.ndarray, weights: np.ndarray):
    """Coordinates of the centred, weighted shapes in an orthonormal basis of their span."""
    n_s, n_p, _ = shapes.shape
    root = np.sqrt(weights)
    z = ((shapes - shapes.mean(axis=0)) * root[None, :, None]).reshape(n_s, -1)
    u, singular, vt = np.linalg.svd(z, full_matrices=False)
    keep = singular > 1e-10 * max(singular.max(initial=0.0), 1e-300)
    coordinates = u[:, keep] * singular[keep]
    return coordinates, vt[keep], np.repeat(root, 3)


def _point_distances(difference: np.ndarray, basis: np.ndarray, root: np.ndarray,
                     weights: np.ndarray) -> np.ndarray:
    """Area-weighted mean point-to-point distance of model-space differences (k, r) -> (k,)."""
    displacement = (difference @ basis) / root
    per_point = np.linalg.norm(displacement.reshape(len(difference), -1, 3), axis=2)
    return per_point @ weights


def compactness(variances: np.ndarray, n_shapes: int, max_modes: int):
    """C(M) = sum_{m<=M} lambda_m and its standard error sum sqrt(2/n_s) lambda_m (eq. 24-25)."""
    variances = np.pad(np.asarray(variances, float), (0, max(0, max_modes - len(variances))))
    cumulative = np.cumsum(variances[:max_modes])
    return cumulative, np.sqrt(2.0 / n_shapes) * cumulative


def generalization(shapes: np.ndarray, weights: np.ndarray, max_modes: int):
    """Leave-one-out reconstruction error G(M) for M = 1..max_modes (eq. 20-21).

    Returns a dict of arrays (max_modes,): ``squared`` and ``squared_se`` (mm^2), ``distance`` and
    ``distance_se`` (mean point-to-point, mm).
    """
    coordinates, basis, root = _model_space(shapes, weights)
    n_s = len(coordinates)
    squared = np.zeros((n_s, max_modes))
    distance = np.zeros((n_s, max_modes))
    for i in range(n_s):
        others = np.delete(coordinates, i, axis=0)
        centre = others.mean(axis=0)
        _, singular, directions = np.linalg.svd(others - centre, full_matrices=False)
        # the model without shape i has at most n_s - 2 modes: drop null directions, which would
        # otherwise hold the part of shape i that the others do not span
        rank = int(np.sum(singular > 1e-10 * max(singular.max(initial=0.0), 1e-300)))
        offset = coordinates[i] - centre
        residuals = []
        for m in range(1, max_modes + 1):
            kept = directions[:min(m, rank)]
            residuals.append(offset - (offset @ kept.T) @ kept)
        residuals = np.array(residuals)
        squared[i] = np.sum(residuals ** 2, axis=1)
        distance[i] = _point_distances(residuals, basis, root, weights)
    return _mean_and_error(squared, distance, n_s)


def specificity(shapes: np.ndarray, weights: np.ndarray, max_modes: int, n_samples: int = 10_000,
                rng: np.random.Generator | None = None, chunk: int = 2000):
    """Specificity S(M): distance of model samples to their nearest training shape (eq. 22-23).

    Samples have scores b_m ~ N(0, lambda_m) on the first M modes (lambda_m the model variances,
    divisor n_s). Returns the same dict as :func:`generalization`.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    coordinates, basis, root = _model_space(shapes, weights)
    n_s, rank = coordinates.shape
    # the model-space coordinates are principal component scores: axis m has variance lambda_m
    sd = np.sqrt(np.sum(coordinates ** 2, axis=0) / n_s)
    squared = np.zeros((n_samples, max_modes))
    distance = np.zeros((n_samples, max_modes))
    normal = rng.standard_normal((n_samples, rank))
    train_sq = np.sum(coordinates ** 2, axis=1)
    for m in range(1, max_modes + 1):
        kept = min(m, rank)
        for start in range(0, n_samples, chunk):
            stop = min(start + chunk, n_samples)
            sample = np.zeros((stop - start, rank))
            sample[:, :kept] = normal[start:stop, :kept] * sd[:kept]
            d2 = (np.sum(sample ** 2, axis=1)[:, None] - 2 * sample @ coordinates.T
                  + train_sq[None, :])
            nearest = np.argmin(d2, axis=1)
            difference = sample - coordinates[nearest]
            squared[start:stop, m - 1] = np.sum(difference ** 2, axis=1)
            distance[start:stop, m - 1] = _point_distances(difference, basis, root, weights)
    return _mean_and_error(squared, distance, n_samples)


def _mean_and_error(squared: np.ndarray, distance: np.ndarray, n: int) -> dict:
    scale = 1.0 / np.sqrt(max(n - 1, 1))
    return {"squared": squared.mean(axis=0), "squared_se": squared.std(axis=0, ddof=1) * scale,
            "distance": distance.mean(axis=0), "distance_se": distance.std(axis=0, ddof=1) * scale}


def evaluate(shapes: np.ndarray, weights: np.ndarray, variances: np.ndarray, max_modes: int = 10,
             n_samples: int = 10_000, rng: np.random.Generator | None = None) -> dict:
    """Compactness, generalization and specificity for M = 1..max_modes, as JSON-ready lists."""
    n_s = len(shapes)
    max_modes = max(1, min(max_modes, n_s - 1))
    c, c_se = compactness(variances, n_s, max_modes)
    g = generalization(shapes, weights, max_modes)
    s = specificity(shapes, weights, max_modes, n_samples, rng)
    as_list = {"modes": list(range(1, max_modes + 1)),
               "compactness": c.tolist(), "compactness_se": c_se.tolist()}
    for name, result in (("generalization", g), ("specificity", s)):
        as_list[name] = result["squared"].tolist()
        as_list[name + "_se"] = result["squared_se"].tolist()
        as_list[name + "_mm"] = result["distance"].tolist()
        as_list[name + "_mm_se"] = result["distance_se"].tolist()
    as_list["specificity_samples"] = int(n_samples)
    return as_list
