"""How unusual a shape is in a model: Mahalanobis distance in the model space and its p-value.

Over the first k modes the squared distance of a shape with scores b is

    d^2 = sum_m b_m^2 / lambda_m,

lambda_m the mode variances (divisor n, :class:`~.shape_model.ShapeModel`). Its reference
distribution depends on whether the shape helped make the model (Wilks 1963; Gnanadesikan and
Kettenring 1972; with S = n Lambda / (n - 1) the usual covariance and D^2 = d^2 (n - 1) / n):

- a training case: d^2 / (n - 1) ~ Beta(k / 2, (n - k - 1) / 2), so d can never exceed
  sqrt(n - 1), whatever the case;
- a new case (fitted with ``fit``): (n - k) d^2 / (k (n + 1)) ~ F(k, n - k) (Hotelling's T^2 of a
  prediction).

A chi-square reference, right only as n grows, under-flags training cases at every n (with
n = 5 no case can ever pass its 99% quantile).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError

# the share of the variance whose modes the distance is taken over, and the level at which a
# case is flagged (cases.csv's score_outlier, metrics.json, the report and the analysis)
EXPLAINED = 0.95
ALPHA = 0.01


@dataclass
class Distances:
    """Mahalanobis distances of shapes in a model and their p-values."""

    modes: int                 # k
    distance: np.ndarray       # d, one per shape
    p: np.ndarray              # against the reference distribution of the shape's kind
    threshold: float           # the distance above which p < alpha
    outlier: np.ndarray        # p < alpha


def modes_explaining(variances: np.ndarray, explained: float = EXPLAINED,
                     n_cases: int | None = None) -> int:
    """The number of leading modes that explain ``explained`` of the variance; at most
    n_cases - 2, so that the reference distributions exist."""
    variances = np.asarray(variances, dtype=np.float64)
    cumulative = np.cumsum(variances) / max(variances.sum(), 1e-300)
    k = int(min(np.searchsorted(cumulative, explained) + 1, len(variances)))
    if n_cases is not None:
        k = min(k, n_cases - 2)
    return max(k, 1)


def training_distances(scores: np.ndarray, variances: np.ndarray, modes: int,
                       alpha: float = ALPHA) -> Distances:
    """Distances of the training cases (``scores`` (n, m)) over the first ``modes`` modes, with
    p-values from the scaled Beta distribution of a training case's own distance.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> x = rng.normal(size=(6, 3)); x -= x.mean(0)
    >>> u, s, vt = np.linalg.svd(x, full_matrices=False)
    >>> result = training_distances(u * s, s ** 2 / 6, modes=2)
    >>> bool(np.all(result.distance <= np.sqrt(5)))
    True
    """
    from scipy.stats import beta

    n = len(scores)
    k = int(modes)
    if not 1 <= k <= n - 2:
        raise ArgumentError(f"{k} modes for {n} cases: need 1 <= modes <= n - 2")
    squared = np.sum(np.asarray(scores)[:, :k] ** 2 / np.asarray(variances)[:k], axis=1)
    reference = beta(k / 2, (n - k - 1) / 2)
    p = reference.sf(np.clip(squared / (n - 1), 0.0, 1.0))
    threshold = float(np.sqrt((n - 1) * reference.isf(alpha)))
    return Distances(k, np.sqrt(squared), p, threshold, p < alpha)


def new_case_distances(scores: np.ndarray, variances: np.ndarray, n_training: int, modes: int,
                       alpha: float = ALPHA) -> Distances:
    """Distances of new cases (not in the model: ``scores`` (c, m) of their fits) over the first
    ``modes`` modes, with p-values from the F distribution of a new case's distance."""
    from scipy.stats import f

    n, k = int(n_training), int(modes)
    if not 1 <= k <= n - 2:
        raise ArgumentError(f"{k} modes for {n} training cases: need 1 <= modes <= n - 2")
    squared = np.sum(np.atleast_2d(scores)[:, :k] ** 2 / np.asarray(variances)[:k], axis=1)
    scale = (n - k) / (k * (n + 1))
    p = f.sf(scale * squared, k, n - k)
    threshold = float(np.sqrt(f.isf(alpha, k, n - k) / scale))
    return Distances(k, np.sqrt(squared), p, threshold, p < alpha)
