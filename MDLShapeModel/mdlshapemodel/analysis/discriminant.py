"""Two groups told apart in the model space: the discriminant shape change and how well it
classifies new cases.

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


@dataclass
class Discriminant:
    """The discriminant direction of two groups in the model space."""

    modes: int                # k, principal scores used
    shrinkage: float          # Ledoit-Wolf intensity in [0, 1]
    pattern: np.ndarray       # (p, 3) mm of shape change per SD of the discriminant score
    scores: np.ndarray        # (n,) each case's discriminant score, in SD units
    mean: np.ndarray          # (p, 3) the mean shape


@dataclass
class Classification:
    """Cross-validated classification of two groups by the discriminant."""

    folds: int
    accuracy: float
    accuracy_se: float
    auc: float
    auc_se: float
    predicted: np.ndarray     # (n,) held-out discriminant values (positive: the second group)


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
    """The Ledoit-Wolf shrunk covariance of centred rows (n, k) and its intensity."""
    n, k = centred.shape
    sample = centred.T @ centred / n
    mu = np.trace(sample) / k
    target = mu * np.eye(k)
    d2 = np.sum((sample - target) ** 2)
    b2 = np.sum([np.sum((np.outer(x, x) - sample) ** 2) for x in centred]) / n ** 2
    intensity = 0.0 if d2 <= 0 else float(min(b2, d2) / d2)
    return (1 - intensity) * sample + intensity * target, intensity


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


def _auc(values: np.ndarray, second: np.ndarray) -> tuple[float, float]:
    """Area under the ROC curve (Mann-Whitney, ties count half) and its standard error
    (Hanley and McNeil 1982)."""
    positive, negative = values[second], values[~second]
    greater = (positive[:, None] > negative[None, :]).sum()
    ties = (positive[:, None] == negative[None, :]).sum()
    m, n = len(positive), len(negative)
    auc = float((greater + 0.5 * ties) / (m * n))
    q1, q2 = auc / (2 - auc), 2 * auc ** 2 / (1 + auc)
    variance = (auc * (1 - auc) + (m - 1) * (q1 - auc ** 2) + (n - 1) * (q2 - auc ** 2)) / (m * n)
    return auc, float(np.sqrt(max(variance, 0.0)))


def classify(shapes: np.ndarray, weights: np.ndarray, second: np.ndarray, folds: int = 10,
             seed: int = 0) -> Classification:
    """Stratified k-fold cross-validated LDA (the PCA and the discriminant fitted on each
    training fold only): accuracy with its binomial SE, and the AUC with its SE.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> second = np.arange(40) >= 20
    >>> shapes = rng.normal(size=(40, 10, 3)); shapes[second, :3, 0] += 2.0
    >>> result = classify(shapes, np.full(10, 0.1), second)
    >>> result.accuracy > 0.8, result.auc > 0.9
    (True, True)
    """
    second = np.asarray(second, dtype=bool)
    n = len(shapes)
    folds = int(max(2, min(folds, second.sum(), (~second).sum())))
    rng = np.random.default_rng(seed)
    fold_of = np.empty(n, dtype=np.int64)
    for label in (False, True):
        members = np.flatnonzero(second == label)
        fold_of[rng.permutation(members)] = np.arange(len(members)) % folds
    predicted = np.empty(n)
    for fold in range(folds):
        test, train = fold_of == fold, fold_of != fold
        mean, basis, scores = principal_scores(shapes[train], weights,
                                               max_modes=int(train.sum()) - 3)
        w, threshold, _ = _fit(scores, second[train])
        root = np.sqrt(weights)[None, :, None]
        test_scores = ((shapes[test] - mean) * root).reshape(int(test.sum()), -1) @ basis.T
        predicted[test] = test_scores @ w - threshold
    accuracy = float(np.mean((predicted > 0) == second))
    auc, auc_se = _auc(predicted, second)
    return Classification(folds, accuracy, float(np.sqrt(accuracy * (1 - accuracy) / n)), auc,
                          auc_se, predicted)
