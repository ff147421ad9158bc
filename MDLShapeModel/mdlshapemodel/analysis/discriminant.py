"""Two groups told apart in the model space: the discriminant shape change (how well it
classifies new cases: :mod:`.classification`).

The shapes are reduced to their first k principal scores (area-weighted PCA, eq. 1-3 with the
inner product of eq. 15; k explaining 95% of the variance, at most n - 3). Linear discriminant
analysis there uses the within-group covariance shrunk towards a multiple of the identity by the
Ledoit-Wolf (2004) intensity, which keeps it well conditioned when k approaches n. The shape
change shown is the pattern of the discriminant (Haufe et al. 2014): the regression of the
shapes on the discriminant score, from one group's side to the other's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.outliers import EXPLAINED, modes_explaining
from .classification import ledoit_wolf_intensity


@dataclass
class Discriminant:
    """The discriminant direction of two groups in the model space."""

    modes: int                # k, principal scores used
    shrinkage: float          # Ledoit-Wolf intensity in [0, 1]
    pattern: np.ndarray       # (p, 3) mm of shape change per SD of the discriminant score
    scores: np.ndarray        # (n,) each case's discriminant score, in SD units
    mean: np.ndarray          # (p, 3) the mean shape


def principal_scores(shapes: np.ndarray, weights: np.ndarray, explained: float = EXPLAINED,
                     max_modes: int | None = None):
    """The mean, the area-weighted principal directions and the scores of shapes (n, p, d).

    Returns ``mean`` (p, d), ``basis`` (k, p * d) orthonormal rows in the weighted space and
    ``scores`` (n, k), k the modes explaining ``explained`` of the variance (at most
    ``max_modes``)."""
    n = len(shapes)
    mean = shapes.mean(axis=0)
    root = np.sqrt(weights)[None, :, None]
    z = ((shapes - mean) * root).reshape(n, -1)
    u, singular, vt = np.linalg.svd(z, full_matrices=False)
    variances = singular ** 2 / n
    k = modes_explaining(variances[variances > 1e-12 * variances.max()], explained)
    if max_modes is not None:
        k = max(1, min(k, max_modes))
    return mean, vt[:k], u[:, :k] * singular[:k]


def ledoit_wolf(centred: np.ndarray) -> tuple[np.ndarray, float]:
    """The Ledoit-Wolf shrunk covariance of centred rows (n, k) and its intensity
    (:func:`~.classification.ledoit_wolf_intensity`)."""
    n, k = centred.shape
    sample = centred.T @ centred / n
    intensity = ledoit_wolf_intensity(centred)
    return (1 - intensity) * sample + intensity * (np.trace(sample) / k) * np.eye(k), intensity


def _fit(scores: np.ndarray, second: np.ndarray):
    """LDA weights and threshold on scores (n, k) for the boolean labels ``second``."""
    means = [scores[~second].mean(axis=0), scores[second].mean(axis=0)]
    centred = np.concatenate([scores[~second] - means[0], scores[second] - means[1]])
    covariance, intensity = ledoit_wolf(centred)
    w = np.linalg.solve(covariance, means[1] - means[0])
    threshold = float(w @ (means[0] + means[1]) / 2)
    return w, threshold, intensity


def discriminant(shapes: np.ndarray, weights: np.ndarray, second: np.ndarray) -> Discriminant:
    """The regularised LDA direction between two groups of aligned shapes (n, p, d) and its
    shape pattern (mm per SD of the discriminant score; positive towards ``second``)."""
    second = np.asarray(second, dtype=bool)
    n = len(shapes)
    mean, basis, scores = principal_scores(shapes, weights, max_modes=n - 3)
    w, threshold, intensity = _fit(scores, second)
    value = scores @ w
    value = (value - value.mean()) / value.std()
    pattern = np.einsum("n,npd->pd", value, shapes - mean) / n
    return Discriminant(len(w), intensity, pattern, value, mean)
