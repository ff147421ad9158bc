"""Resistant superimposition: generalized Procrustes that a local change cannot move.

Least-squares generalized Procrustes (eq. 18) lets every point pull on each case's pose in
proportion to its squared residual, so a change confined to one region of some cases (a dent,
a retracted tip) also rotates and shifts those cases as a whole: the unchanged points then differ
between groups, and the change itself looks smaller where it is. Iteratively reweighted
Procrustes (in the spirit of the resistant fits of Siegel and Benson 1982 and the robust
Procrustes of Dryden and Walker 1999) down-weights the points a case fits badly: each case is
aligned to the mean with the area weights times Tukey's biweight of its points' residual norms,
scaled by the case's median residual norm, and the mean is the weighted mean of the aligned
cases; both are repeated until the poses settle.

It assumes that in each case most of the surface (by count, more than half the points) is fitted
well by a rigid motion onto the mean, and that a change of interest is local; it is not meant for
changes spread over the whole surface (a global bending), where no part is unchanged to align on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from ..errors import InputError
from ..geometry import align, apply_poses, centroid_size, weighted_centroid

# Tukey's biweight tuning constant, in robust standard deviations of a coordinate: 95 %
# efficiency under normal errors
BIWEIGHT = 4.685


@dataclass
class Superimposition:
    """Aligned shapes and how they were found.

    Attributes
    ----------
    aligned : ndarray (n_s, n_p, d)
        The shapes after their poses.
    poses : list of Pose
        Per shape, input -> aligned.
    robust : ndarray (n_s, n_p)
        Each point's robust weight in its case's alignment (0 to 1; all 1 for least squares).
    iterations : int
        Reweighting rounds until the poses settled.
    """

    aligned: np.ndarray
    poses: list
    robust: np.ndarray
    iterations: int


def biweight(residuals: np.ndarray, tuning: float = BIWEIGHT, dimensions: int = 3) -> np.ndarray:
    """Tukey's biweight of residual norms (n_s, n_p), each case scaled by its own median
    residual norm: w = (1 - u^2)^2 for u < 1, else 0, with u = r / (tuning * sigma).

    sigma = median(r) / sqrt(median of chi^2 with ``dimensions`` degrees of freedom) is the
    standard deviation per coordinate of normal residuals with that median norm (1.538 sigma in
    3-D, 1.177 sigma in 2-D), so that ``tuning`` has its usual meaning.

    Examples
    --------
    >>> r = np.array([[1.0, 1.0, 1.0, 1.0, 50.0]])
    >>> biweight(r).round(3).tolist()
    [[0.796, 0.796, 0.796, 0.796, 0.0]]
    """
    residuals = np.asarray(residuals, dtype=np.float64)
    if not np.isfinite(tuning):
        return np.ones_like(residuals)
    sigma = np.median(residuals, axis=1, keepdims=True) / np.sqrt(chi2.median(dimensions))
    # a case that fits exactly: every point counts
    sigma = np.where(sigma > 0, sigma, np.inf)
    u = residuals / (tuning * sigma)
    return np.where(u < 1, (1 - u ** 2) ** 2, 0.0)


def resistant_procrustes(shapes: np.ndarray, weights: np.ndarray, tuning: float = BIWEIGHT,
                         planar: bool = False, iterations: int = 100,
                         tolerance: float = 1e-9) -> Superimposition:
    """Align shapes to their common mean by iteratively reweighted generalized Procrustes
    (rotation and translation; eq. 18 with per-case weights).

    Each round: the mean is the robust-weighted mean of the aligned shapes, centred and scaled
    to the inputs' mean centroid size (as :func:`~..geometry.generalized_procrustes`
    keeps it); each shape is aligned to it with the weights ``weights * biweight(residual)``
    (:func:`biweight`: a point far off the mean, relative to the case's median residual,
    counts less or not at all). With ``tuning=np.inf`` every robust weight is 1 and this is
    least-squares generalized Procrustes.

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        Corresponded points.
    weights : ndarray (n_p,)
        Non-negative area weights (normalised here to sum to 1).
    tuning : float
        The biweight's constant in robust standard deviations of a coordinate (``np.inf``:
        least squares).
    planar : bool
        Shapes in the plane z = 0, rotated about z only.
    iterations : int
        At most this many rounds.
    tolerance : float
        Stop when no aligned point moved more than ``tolerance`` times the mean centroid size.

    Returns
    -------
    Superimposition

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> base = rng.normal(size=(40, 3))
    >>> shapes = np.stack([base + 3.0 * k for k in range(4)])      # translated copies
    >>> shapes[1, :4] += 20.0                                      # a few points far off
    >>> found = resistant_procrustes(shapes, np.full(40, 1 / 40))
    >>> float(np.abs(found.aligned[1, 4:] - found.aligned[0, 4:]).max()) < 1e-6
    True
    >>> found.robust[1, :4].tolist()
    [0.0, 0.0, 0.0, 0.0]
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 2:
        raise InputError(f"shapes must be (n_s >= 2, n_p, 3), not {shapes.shape}")
    if weights.shape != shapes.shape[1:2] or np.any(weights < 0) or weights.sum() <= 0:
        raise InputError(f"weights must be {shapes.shape[1]} non-negative numbers, not all 0")
    if not tuning > 0:
        raise InputError(f"the biweight's tuning constant must be positive, not {tuning!r}")
    weights = weights / weights.sum()
    target_size = float(np.mean([centroid_size(x, weights) for x in shapes]))
    poses = [align(x, shapes[0], weights, scaling=False, planar=planar) for x in shapes]
    aligned = apply_poses(poses, shapes)
    robust = np.ones(shapes.shape[:2])
    rounds = 0
    for rounds in range(1, iterations + 1):
        mean = _robust_mean(aligned, robust)
        mean = mean - weighted_centroid(mean, weights)
        mean *= target_size / centroid_size(mean, weights)
        poses = [align(x, mean, _normalised(weights * r), scaling=False, planar=planar)
                 for x, r in zip(shapes, robust)]
        previous, aligned = aligned, apply_poses(poses, shapes)
        robust = biweight(np.linalg.norm(aligned - mean, axis=2), tuning, 2 if planar else 3)
        if np.abs(aligned - previous).max() <= tolerance * target_size:
            break
    return Superimposition(aligned, poses, robust, rounds)


def _apply(poses: list, shapes: np.ndarray) -> np.ndarray:
    return np.stack([p.apply(x) for p, x in zip(poses, shapes)])


def _normalised(weights: np.ndarray) -> np.ndarray:
    return weights / weights.sum()


def _robust_mean(aligned: np.ndarray, robust: np.ndarray) -> np.ndarray:
    """Per point, the robust-weighted mean over the cases (the plain mean where every case's
    weight there is 0)."""
    total = robust.sum(axis=0)
    weighted = np.einsum("np,npd->pd", robust, aligned) / np.where(total > 0, total, 1)[:, None]
    return np.where(total[:, None] > 0, weighted, aligned.mean(axis=0))


__all__ = ["BIWEIGHT", "Superimposition", "biweight", "resistant_procrustes"]
