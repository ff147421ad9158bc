"""How well the shapes tell the groups apart on cases the classifier has not seen.

Repeated stratified k-fold cross-validation (scikit-learn's ``RepeatedStratifiedKFold``). In each
fold, fitted on the training cases only and applied to the held-out ones:

1. the nuisance columns are regressed out of the aligned shapes (least squares with an
   intercept; without nuisance, the training mean is subtracted);
2. area-weighted principal component analysis of the residuals (eq. 1-3 with the inner product
   of eq. 15), k modes explaining 95% of the variance, at most (training cases - 3);
3. linear discriminant analysis on the k scores with each group's covariance shrunk by the
   Ledoit-Wolf (2004) intensity after standardising its scores, averaged over the groups, and
   equal priors: the estimator of scikit-learn's ``LinearDiscriminantAnalysis(solver="lsqr",
   shrinkage="auto", priors=equal)``.

Per fold, the AUC of the held-out cases (for more than two groups the macro average of each
group against the rest, over the held-out posterior probabilities) and the balanced accuracy (the
mean of the groups' recalls); the estimates are their means over all folds and repeats. The
intervals are the corrected resampled t intervals of Nadeau and Bengio (2003) for repeated k-fold
(Bouckaert and Frank 2004): the folds' variance scaled by (1/J + n_test/n_train) for J folds, as
the folds share their training cases. The p-value of the AUC is a permutation test (Ojala and
Garriga 2010): the group labels permuted and the whole cross-validation redone, folds included;
all distinct labelings when there are no more of them than permutations asked for (exact).

The folds run in numpy on the cases' Gram matrix (an n x n problem per fold, whatever the number
of points), fast enough for the permutations; ``Testing/test_analysis_classify.py`` checks every
held-out value against scikit-learn's pipeline.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError
from ..model.outliers import EXPLAINED, modes_explaining

#: Numbers below this fraction of a scale are zero (eigenvalues, standard deviations).
TINY = 1e-12


@dataclass
class Classification:
    """Repeated cross-validated classification of the groups by the shapes.

    Attributes
    ----------
    levels : list of str
        The groups, in the order of the columns of ``predicted`` (more than two) or with the
        second one positive (two).
    folds, repeats : int
        k of the k-fold cross-validation and how many times it is repeated (each with other
        folds).
    adjusted_for : int
        The nuisance columns regressed out in each training fold.
    auc : float
        The mean over folds of the held-out AUC (two groups) or of the macro one-vs-rest AUC.
    auc_interval : tuple of float
        Its 95% corrected resampled t interval (Nadeau and Bengio 2003), clipped to [0, 1].
    balanced_accuracy : float
        The mean over folds of the held-out balanced accuracy (each case assigned to the group
        of the largest posterior probability).
    balanced_accuracy_interval : tuple of float
        Its 95% corrected resampled t interval.
    p : float or None
        The permutation p-value of the AUC (None with no permutations).
    permutations : int
        Labelings compared, the observed one included (the p-value's denominator).
    exact : bool
        Whether they are all the distinct labelings of the cases.
    null_auc : ndarray (permutations - 1,)
        The AUC of each permuted labeling (its distribution under no difference).
    fold_auc, fold_balanced_accuracy : ndarray (folds * repeats,)
        The per-fold values.
    predicted : ndarray
        The held-out values of the first repeat: for two groups each case's discriminant value
        (n,) (positive: the second group); for more, each case's posterior probabilities (n, g).
    """

    levels: list
    folds: int
    repeats: int
    adjusted_for: int
    auc: float
    auc_interval: tuple
    balanced_accuracy: float
    balanced_accuracy_interval: tuple
    p: float | None
    permutations: int
    exact: bool
    null_auc: np.ndarray
    fold_auc: np.ndarray
    fold_balanced_accuracy: np.ndarray
    predicted: np.ndarray


def ledoit_wolf_intensity(centred: np.ndarray) -> float:
    """The Ledoit-Wolf (2004) shrinkage intensity of centred rows (n, k) towards mu I.

    min(b^2, d^2) / d^2 with d^2 = |S - mu I|^2 and b^2 = sum_i |x_i x_i' - S|^2 / n^2, written
    as b^2 = (sum_i |x_i|^4 / n - |S|^2) / n (S = X'X / n; Frobenius norms); 0 for one column.
    """
    n, k = centred.shape
    if k == 1:
        return 0.0
    sample = centred.T @ centred / n
    mu = np.trace(sample) / k
    d2 = np.sum(sample ** 2) - 2 * mu * np.trace(sample) + k * mu ** 2
    b2 = (np.sum(np.sum(centred ** 2, axis=1) ** 2) / n - np.sum(sample ** 2)) / n
    b2 = min(b2, d2)
    return 0.0 if b2 <= 0 else float(b2 / d2)


def _shrunk_covariance(rows: np.ndarray) -> np.ndarray:
    """One group's covariance: its scores standardised, shrunk by the Ledoit-Wolf intensity
    towards the identity, scaled back."""
    centred = rows - rows.mean(axis=0)
    scale = centred.std(axis=0)
    scale[scale < 10 * np.finfo(np.float64).eps] = 1.0
    standard = centred / scale
    n, k = standard.shape
    sample = standard.T @ standard / n
    intensity = ledoit_wolf_intensity(standard)
    shrunk = (1 - intensity) * sample + intensity * (np.trace(sample) / k) * np.eye(k)
    return scale[:, None] * shrunk * scale[None, :]


def discriminant_values(train: np.ndarray, labels: np.ndarray, groups: int,
                        test: np.ndarray) -> np.ndarray:
    """Shrinkage LDA with equal priors fitted on ``train`` (n, k) with integer ``labels`` in
    [0, groups), evaluated on ``test`` (m, k): the linear discriminant functions (m, groups)
    less their mean over the groups (the log posterior odds up to a constant per case)."""
    means = np.array([train[labels == g].mean(axis=0) for g in range(groups)])
    covariance = sum(_shrunk_covariance(train[labels == g]) for g in range(groups)) / groups
    coefficients = np.linalg.solve(covariance, means.T).T
    values = test @ coefficients.T - 0.5 * np.einsum("gk,gk->g", means, coefficients)
    return values - values.mean(axis=1, keepdims=True)


def posteriors(values: np.ndarray) -> np.ndarray:
    """Posterior probabilities (softmax) of discriminant functions (m, groups)."""
    shifted = np.exp(values - values.max(axis=1, keepdims=True))
    return shifted / shifted.sum(axis=1, keepdims=True)


def auc_of(labels: np.ndarray, scores: np.ndarray) -> float:
    """The AUC of ``scores`` (m,) for the positive ``labels`` (bool, m): the Mann-Whitney U over
    (positives x negatives), ties counting half."""
    ranks = _ranks(scores)
    m = int(labels.sum())
    n = len(labels) - m
    return float((ranks[labels].sum() - m * (m + 1) / 2) / (m * n))


def _ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, ties given their mean rank."""
    order = np.argsort(values, kind="mergesort")
    ordered = values[order]
    starts = np.concatenate([[True], ordered[1:] != ordered[:-1]])
    first = np.flatnonzero(starts)
    last = np.concatenate([first[1:], [len(values)]]) - 1
    mean_rank = (first + last) / 2 + 1
    ranks = np.empty(len(values))
    ranks[order] = np.repeat(mean_rank, last - first + 1)
    return ranks


def fold_measures(labels: np.ndarray, probabilities: np.ndarray) -> tuple[float, float]:
    """The AUC (two groups: of the second group's probability; more: the macro average over
    the groups of each against the rest) and the balanced accuracy (each case assigned to its
    most probable group) of held-out posterior probabilities (m, groups); NaN when a group
    has no held-out case (possible only when whole subjects are held out)."""
    groups = probabilities.shape[1]
    if np.any(np.bincount(labels, minlength=groups) == 0):
        return np.nan, np.nan
    if groups == 2:
        auc = auc_of(labels == 1, probabilities[:, 1])
    else:
        auc = float(np.mean([auc_of(labels == g, probabilities[:, g]) for g in range(groups)]))
    assigned = probabilities.argmax(axis=1)
    recall = [np.mean(assigned[labels == g] == g) for g in range(groups)]
    return auc, float(np.mean(recall))


class _Folds:
    """The label-free part of every fold: the cases' Gram matrix, the nuisance design, and the
    principal scores of a training set and its held-out cases."""

    def __init__(self, features: np.ndarray, nuisance: np.ndarray, explained: float):
        self.gram = features @ features.T
        n = len(features)
        self.design = np.hstack([np.ones((n, 1)), nuisance])
        self.explained = explained

    def scores(self, train: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Principal scores of the training cases' residuals (the nuisance fitted on them) and
        of the held-out cases' residuals on the same basis."""
        design = self.design[train]
        solve = np.linalg.pinv(design)                   # (c + 1, n_train)
        residual = np.eye(len(train)) - design @ solve   # I - H, symmetric
        transfer = self.design[test] @ solve             # (n_test, n_train)
        g_tt = self.gram[np.ix_(train, train)]
        g_st = self.gram[np.ix_(test, train)]
        inner = residual @ g_tt @ residual
        across = (g_st - transfer @ g_tt) @ residual
        eigenvalues, vectors = np.linalg.eigh((inner + inner.T) / 2)
        eigenvalues, vectors = eigenvalues[::-1], vectors[:, ::-1]
        kept = eigenvalues > TINY * max(eigenvalues[0], 1e-300)
        k = modes_explaining(eigenvalues[kept], self.explained)
        k = max(1, min(k, len(train) - 3, int(kept.sum())))
        root = np.sqrt(eigenvalues[:k])
        return vectors[:, :k] * root, across @ vectors[:, :k] / root


def _cross_validated(folds: _Folds, labels: np.ndarray, groups: int, splits: list):
    """Per-fold AUC and balanced accuracy over ``splits`` [(train, test)], and the held-out
    discriminant values of the first ``len(labels)`` cases covered (the first repeat)."""
    aucs, accuracies = np.empty(len(splits)), np.empty(len(splits))
    held = np.zeros((len(labels), groups))
    seen = np.zeros(len(labels), dtype=bool)
    for j, (train, test) in enumerate(splits):
        train_scores, test_scores = folds.scores(train, test)
        values = discriminant_values(train_scores, labels[train], groups, test_scores)
        probabilities = posteriors(values)
        aucs[j], accuracies[j] = fold_measures(labels[test], probabilities)
        fresh = ~seen[test]
        held[test[fresh]] = values[fresh]
        seen[test] = True
    return aucs, accuracies, held


def _splits(labels: np.ndarray, folds: int, repeats: int, seed: int,
            blocks: np.ndarray | None = None) -> list:
    """The (train, test) index pairs of every fold and repeat: stratified by the labels, and
    with ``blocks`` each block (a subject's cases) kept in one fold."""
    from sklearn.model_selection import RepeatedStratifiedKFold, StratifiedGroupKFold

    if blocks is None:
        splitter = RepeatedStratifiedKFold(n_splits=folds, n_repeats=repeats, random_state=seed)
        return list(splitter.split(np.zeros(len(labels)), labels))
    return [split for r in range(repeats)
            for split in StratifiedGroupKFold(n_splits=folds, shuffle=True,
                                              random_state=seed + r).split(
                np.zeros(len(labels)), labels, blocks)]


def _block_permutation(labels: np.ndarray, blocks: np.ndarray, rng) -> np.ndarray:
    """The labels of whole blocks permuted among the blocks of as many cases (each block's
    cases keep one label)."""
    permuted = labels.copy()
    first = np.array([np.flatnonzero(blocks == b)[0] for b in range(int(blocks.max()) + 1)])
    sizes = np.bincount(blocks)
    for size in np.unique(sizes):
        alike = np.flatnonzero(sizes == size)
        moved = rng.permutation(labels[first[alike]])
        for block, label in zip(alike, moved):
            permuted[blocks == block] = label
    return permuted


def corrected_interval(values: np.ndarray, test_share: float, level: float = 0.95) -> tuple:
    """The corrected resampled t interval of a mean over J cross-validation folds (Nadeau and
    Bengio 2003): mean +- t(J - 1) sqrt((1/J + n_test/n_train) s^2), s^2 the folds' variance;
    ``test_share`` is n_test / n_train; NaN values (a fold without a group) left out. Clipped
    to [0, 1]."""
    from scipy.stats import t as student

    values = np.asarray(values)[np.isfinite(values)]
    j = len(values)
    spread = np.sqrt((1 / j + test_share) * np.var(values, ddof=1)) if j > 1 else np.inf
    half = student.ppf(0.5 + level / 2, max(j - 1, 1)) * spread
    mean = float(np.mean(values))
    return (float(max(0.0, mean - half)), float(min(1.0, mean + half)))


def labelings(labels: np.ndarray, groups: int):
    """Every distinct assignment of the same group sizes to the cases, the given one first."""
    n = len(labels)
    sizes = np.bincount(labels, minlength=groups)

    def assign(free: tuple, group: int):
        if group == groups - 1:
            yield {group: free}
            return
        for chosen in itertools.combinations(free, int(sizes[group])):
            rest = tuple(i for i in free if i not in set(chosen))
            for tail in assign(rest, group + 1):
                yield {group: chosen, **tail}

    yield labels.copy()
    for assignment in assign(tuple(range(n)), 0):
        drawn = np.empty(n, dtype=np.int64)
        for group, cases in assignment.items():
            drawn[list(cases)] = group
        if not np.array_equal(drawn, labels):
            yield drawn


def count_labelings(labels: np.ndarray, groups: int) -> int:
    """How many distinct assignments of the group sizes to the cases there are (multinomial)."""
    count, left = 1, len(labels)
    for size in np.bincount(labels, minlength=groups):
        count *= math.comb(left, int(size))
        left -= int(size)
    return count


def classify(shapes: np.ndarray, weights: np.ndarray, groups, nuisance: np.ndarray | None = None,
             folds: int = 10, repeats: int = 5, permutations: int = 200, seed: int = 0,
             levels: list | None = None, blocks: np.ndarray | None = None,
             explained: float = EXPLAINED, progress=None) -> Classification:
    """Repeated cross-validated shrinkage LDA of the groups on aligned shapes, the nuisance
    regressed out inside each training fold, with a permutation p-value of the AUC.

    Parameters
    ----------
    shapes : ndarray (n, p, d)
        Aligned shapes.
    weights : ndarray (p,)
        The points' area weights (the inner product of eq. 15).
    groups : sequence (n,)
        Each case's group: booleans (True: the second group), integers or level names; at
        least two groups of at least three cases (two in every training fold).
    nuisance : ndarray (n, c), optional
        Columns regressed out of the shapes in each training fold (fitted on the training
        cases, applied to the held-out ones).
    folds : int
        k of the stratified k-fold (at most the smallest group's size).
    repeats : int
        Repetitions with other folds.
    permutations : int
        Permuted labelings for the p-value of the AUC (0: none). When the cases have at most
        this many distinct labelings, all of them are used (an exact p-value).
    seed : int
        The folds' and the permutations' random state.
    levels : list, optional
        The groups' order (the first is the reference; with two groups the second is
        positive); default: sorted (False before True).
    blocks : ndarray (n,) of int, optional
        Each case's subject (0 .. subjects - 1), when a subject has several cases, all of one
        group: a subject's cases stay in one fold (scikit-learn's ``StratifiedGroupKFold``,
        reshuffled per repeat) and the permutations move whole subjects' labels among subjects
        of as many cases (exchangeability blocks); never exact.
    explained : float
        The share of the variance the principal scores keep in each fold.
    progress : callable, optional
        The library's progress protocol.

    Returns
    -------
    Classification

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> second = np.arange(40) >= 20
    >>> shapes = rng.normal(size=(40, 10, 3)); shapes[second, :3, 0] += 2.0
    >>> result = classify(shapes, np.full(10, 0.1), second, repeats=2, permutations=99)
    >>> result.auc > 0.9, result.balanced_accuracy > 0.8, result.p == 0.01
    (True, True, True)
    """
    from threadpoolctl import threadpool_limits

    shapes = np.asarray(shapes, dtype=np.float64)
    n = len(shapes)
    groups = np.asarray(groups).tolist()
    names = list(levels) if levels is not None else sorted(set(groups))
    labels = np.array([names.index(v) for v in groups], dtype=np.int64)
    count = len(names)
    sizes = np.bincount(labels, minlength=count)
    if count < 2 or sizes.min() < 3:
        raise ArgumentError(f"classify needs two or more groups of at least 3 cases "
                         f"(sizes {sizes.tolist()})")
    nuisance = np.zeros((n, 0)) if nuisance is None else np.asarray(nuisance, dtype=np.float64)
    if blocks is not None:
        blocks = np.unique(np.asarray(blocks), return_inverse=True)[1].reshape(-1)
        if any(len(set(labels[blocks == b])) > 1 for b in range(int(blocks.max()) + 1)):
            raise ArgumentError("classify: a block (subject) has cases in more than one group")
        first = np.unique(blocks, return_index=True)[1]
        sizes = np.bincount(labels[first], minlength=count)     # subjects per group
    folds = int(max(2, min(folds, sizes.min())))
    features = (shapes * np.sqrt(weights)[None, :, None]).reshape(n, -1)
    with threadpool_limits(limits=1, user_api="blas"):
        # n x n problems: one thread each is faster than a team
        engine = _Folds(features, nuisance, explained)
        aucs, accuracies, held = _cross_validated(engine, labels, count,
                                                  _splits(labels, folds, repeats, seed, blocks))
        null = _null(engine, labels, count, folds, repeats, permutations, seed, progress,
                     blocks)
    exact = (permutations > 0 and blocks is None
             and count_labelings(labels, count) <= permutations + 1)
    auc = float(np.nanmean(aucs))
    p = (None if permutations == 0 else
         float((1 + np.sum(null >= auc - 1e-12)) / (len(null) + 1)))
    test_share = 1 / (folds - 1)
    predicted = held[:, 1] - held[:, 0] if count == 2 else posteriors(held)
    return Classification([str(v) for v in names], folds, repeats, nuisance.shape[1], auc,
                          corrected_interval(aucs, test_share), float(np.nanmean(accuracies)),
                          corrected_interval(accuracies, test_share), p, len(null) + 1, exact,
                          null, aucs, accuracies, predicted)


def _null(engine: _Folds, labels: np.ndarray, count: int, folds: int, repeats: int,
          permutations: int, seed: int, progress, blocks: np.ndarray | None = None
          ) -> np.ndarray:
    """The mean fold AUC of every permuted labeling, the cross-validation redone (folds
    included): all the other distinct labelings when there are at most ``permutations`` of
    them, else ``permutations`` drawn at random (with ``blocks``, whole blocks' labels)."""
    from ..progress import report

    null = []
    if permutations > 0:
        exact = blocks is None and count_labelings(labels, count) <= permutations + 1
        rng = np.random.default_rng(seed)
        if exact:
            drawn = itertools.islice(labelings(labels, count), 1, None)
        elif blocks is not None:
            drawn = (_block_permutation(labels, blocks, rng) for _ in range(permutations))
        else:
            drawn = (rng.permutation(labels) for _ in range(permutations))
        total = count_labelings(labels, count) - 1 if exact else permutations
        for b, permuted in enumerate(drawn):
            null.append(np.nanmean(_cross_validated(
                engine, permuted, count, _splits(permuted, folds, repeats, seed, blocks))[0]))
            if (b + 1) % 50 == 0:
                report(progress, (b + 1) / total, "classification permutations")
    return np.array(null)
