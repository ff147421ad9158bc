"""How unusual a shape is in a model: Mahalanobis distance in the model space and its p-value.

Over the first k modes the squared distance of a shape with scores b is

    d^2 = sum_m b_m^2 / lambda_m,

lambda_m the mode variances (divisor n, :class:`~.shape_model.ShapeModel`). Under multivariate
normality its reference distribution depends on whether the shape helped make the model (Wilks
1963; Gnanadesikan and Kettenring 1972; with S = n Lambda / (n - 1) the usual covariance and
D^2 = d^2 (n - 1) / n), and gives the **normal-theory p** (``p_normal``):

- a training case: d^2 / (n - 1) ~ Beta(k / 2, (n - k - 1) / 2), so d can never exceed
  sqrt(n - 1), whatever the case;
- a new case (fitted with ``fit``): (n - k) d^2 / (k (n + 1)) ~ F(k, n - k) (Hotelling's T^2 of a
  prediction).

Real shapes are not normal in this way: some cases lie far out in many small modes at once (a
scale mixture, each case with its own spread), so the distances are overdispersed against these
references and they flag many times the level (on 82 hippocampi, 12 cases at p < 0.01 instead of
about 1). The **p that flags** (``p``) is therefore taken against an empirical null (Efron 2004)
of the *other* training cases. Each case's normal-theory p becomes a z-value,
z = Phi^-1(1 - p_normal), N(0, 1) under normality, and the other N = n - 1 cases' z-values give
the null in two parts, of which the case's p is the larger:

- the body: a normal with their median as centre and (their 90 % quantile - their median) /
  1.2816 as spread, with centre >= 0 and spread >= 1, so that p >= p_normal wherever
  p_normal <= 1/2:

      p_body = 1 - Phi((z - centre) / spread);

- the tail, from N = 15 on: the r = round(N / 10) largest of the N z-values (rounded half
  up), measured from the next one, u (the (r + 1)-th largest), as an exponential tail whose
  mean excess is theirs, S / r (S the sum of their excesses over u: the maximum-likelihood
  scale of an exponential), entered with (r + 1) / (N + 1), the chance of a case being among
  the r + 1 largest of N + 1:

      p_tail = (r + 1) / (N + 1) exp(-r max(z - u, 0) / S).

The body alone assumes that the z-values beyond the 90 % quantile go on as a normal's. Those
of heavy-tailed cases fall off more slowly (cases scaled as a t with 3 to 10 degrees of freedom:
at n = 82 the 99 % quantile is 2.0-2.3 times as far from the median as the 90 %, against 1.8
for a normal), and the body flags about twice the level at 0.01. The tail takes the fall-off
beyond the 90 % quantile from the cases themselves; an exponential falls off more slowly than a
normal and more quickly than a power. With it such cases and real shapes are flagged at about
the level at 0.01 (at most about 1.2 times it), and fewer than the level under normality
(benchmarks/unusual_calibration.py, docs/analysis.md). Below 15 other cases the tail's scale
would rest on one excess, and the body alone is used. A new case is taken against the null of
all the training cases. A case never enters its own null, so one far case is found at any n.
The rule assumes that at most about a tenth of the other cases are unusual: a far case among
the largest tenth lengthens the tail for the others, and a tenth of the cases with twice the
spread of the rest (two groups) is flagged above the level at 0.05.

A chi-square reference, right only as n grows, under-flags training cases at every n (with
n = 5 no case can ever pass its 99% quantile).

References
----------
B. Efron, "Large-scale simultaneous hypothesis testing: the choice of a null hypothesis",
J. Am. Stat. Assoc. 99 (2004) 96-104.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError

# the share of the variance whose modes the distance is taken over, and the level at which a
# case is flagged (cases.csv's score_outlier, metrics.json, the report and the analysis)
EXPLAINED = 0.95
ALPHA = 0.01
# the quantile of the training cases' z-values that, with their median, gives the empirical
# null's body (its upper spread)
NULL_QUANTILE = 0.9
# one in TAIL_EVERY of the training cases' z-values (the largest, rounded half up) give the
# null's tail by their excesses, from TAIL_FEWEST z-values on (2 excesses: from 1 its scale is
# a guess)
TAIL_EVERY = 10
TAIL_FEWEST = 15
# the smallest normal-theory p taken into a z-value (a p of 0 would give an infinite z), and the
# smallest z (a p of 1 would give -infinity: the tail's excesses would be infinite)
SMALLEST_P = 1e-300
SMALLEST_Z = -10.0


def z_values(p_normal) -> np.ndarray:
    """The z-values Phi^-1(1 - p_normal) of normal-theory p-values, held within
    [``SMALLEST_Z``, Phi^-1(1 - ``SMALLEST_P``)]."""
    from scipy.stats import norm

    p_normal = np.clip(np.asarray(p_normal, dtype=np.float64), SMALLEST_P, 1.0)
    return np.maximum(norm.isf(p_normal), SMALLEST_Z)


@dataclass
class EmpiricalNull:
    """The null of the training cases' z-values, z = Phi^-1(1 - p_normal) (module docstring):
    a normal body N(centre, spread^2) and an exponential tail from ``tail_from``; a case's p is
    the larger of the two."""

    centre: float              # the median of the z-values, at least 0
    spread: float              # (their NULL_QUANTILE quantile - the median) / Phi^-1(NULL_QUANTILE),
    #                            at least 1
    tail_from: float = np.inf  # u: the (r + 1)-th largest z-value (no tail: infinite)
    tail_cases: int = 0        # r = round(N / TAIL_EVERY) of the N z-values, the largest
    tail_excess: float = 0.0   # S: the sum of their excesses over u (S / r: the mean excess)
    tail_share: float = 0.0    # (r + 1) / (N + 1): the tail's p at u (no tail: 0)

    def p(self, p_normal: np.ndarray) -> np.ndarray:
        """The p-values against this null of cases with normal-theory p-values ``p_normal``:
        max(p_body, p_tail) of the module docstring."""
        from scipy.stats import norm

        z = z_values(p_normal)
        body = norm.sf((z - self.centre) / self.spread)
        over = np.maximum(z - self.tail_from, 0.0)
        if self.tail_cases == 0:
            return body
        if self.tail_excess > 0:
            tail = self.tail_share * np.exp(-over * self.tail_cases / self.tail_excess)
        else:                      # tied z-values: no tail beyond them
            tail = np.where(over > 0, 0.0, self.tail_share)
        return np.maximum(body, tail)

    def p_normal_at(self, alpha: float) -> float:
        """The normal-theory p at which a case's p (against this null) is ``alpha``: the larger
        of the z-values at which the body's and the tail's p are ``alpha``."""
        from scipy.stats import norm

        z = self.centre + self.spread * norm.isf(alpha)
        if alpha < self.tail_share:
            z = max(z, self.tail_from + self.tail_excess / self.tail_cases
                    * np.log(self.tail_share / alpha))
        return float(norm.sf(z))

    def to_json(self) -> dict:
        tail = None if self.tail_cases == 0 else {
            "from": self.tail_from, "cases": self.tail_cases, "excess": self.tail_excess,
            "share": self.tail_share}
        return {"centre": self.centre, "spread": self.spread, "quantile": NULL_QUANTILE,
                "tail": tail}


@dataclass
class Distances:
    """Mahalanobis distances of shapes in a model and their p-values."""

    modes: int                 # k
    distance: np.ndarray       # d, one per shape
    p: np.ndarray              # against the empirical null of the training cases (flags)
    p_normal: np.ndarray       # against the reference distribution of the shape's kind, which
    #                            assumes multivariate normal scores
    threshold: np.ndarray      # per shape, the distance above which its p < alpha
    outlier: np.ndarray        # p < alpha
    null: EmpiricalNull        # the null of all the training cases (a new case's)


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


def tail_cases(count: int) -> int:
    """r: how many of ``count`` z-values (the largest) make the null's tail, one in
    :data:`TAIL_EVERY` rounded half up (none below :data:`TAIL_FEWEST` values)."""
    return 0 if count < TAIL_FEWEST else (count + TAIL_EVERY // 2) // TAIL_EVERY


def empirical_null(p_normal: np.ndarray) -> EmpiricalNull:
    """The empirical null of the training cases' normal-theory p-values ``p_normal``: the body
    (the median of their z-values and their upper spread, held at 0 and 1 at least) and the tail
    (the excesses of the largest tenth over the next z-value, from ``TAIL_FEWEST`` z-values on)
    of the module docstring.

    Examples
    --------
    >>> from scipy.stats import norm
    >>> null = empirical_null(norm.sf(np.array([-1.0, 0.0, 0.5, 2.0, 6.0])))
    >>> round(null.centre, 6), round(null.spread, 4), null.tail_cases
    (0.5, 3.0432, 0)
    >>> null = empirical_null(norm.sf(np.arange(16.0)))
    >>> null.tail_cases, round(null.tail_from, 6), round(null.tail_excess, 6), null.tail_share
    (2, 13.0, 3.0, 0.17647058823529413)
    """
    from scipy.stats import norm

    p_normal = np.asarray(p_normal, dtype=np.float64)
    if p_normal.ndim != 1 or len(p_normal) < 2 or not np.all(np.isfinite(p_normal)):
        raise ArgumentError(f"an empirical null needs 2 or more finite p-values, not {p_normal!r}")
    z = np.sort(z_values(p_normal))
    centre = float(np.median(z))
    spread = (float(np.quantile(z, NULL_QUANTILE)) - centre) / float(norm.isf(1 - NULL_QUANTILE))
    body = EmpiricalNull(max(centre, 0.0), max(spread, 1.0))
    count = len(z)
    if count < TAIL_FEWEST:
        return body
    r = tail_cases(count)
    tail_from = float(z[count - r - 1])
    return EmpiricalNull(body.centre, body.spread, tail_from, r,
                         float(np.sum(z[count - r:] - tail_from)), (r + 1) / (count + 1))


def _checked_modes(k: int, n: int) -> int:
    if not 1 <= k <= n - 2:
        raise ArgumentError(f"{k} modes for {n} training cases: need 1 <= modes <= n - 2")
    return k


def _training_p_normal(scores: np.ndarray, variances: np.ndarray, k: int):
    """Squared distances of the training cases and their p-values against the scaled Beta."""
    from scipy.stats import beta

    n = len(scores)
    squared = np.sum(np.asarray(scores)[:, :k] ** 2 / np.asarray(variances)[:k], axis=1)
    reference = beta(k / 2, (n - k - 1) / 2)
    p = reference.sf(np.clip(squared / (n - 1), 0.0, 1.0))
    return squared, p, reference


def training_distances(scores: np.ndarray, variances: np.ndarray, modes: int,
                       alpha: float = ALPHA) -> Distances:
    """Distances of the training cases (``scores`` (n, m)) over the first ``modes`` modes, with
    normal-theory p-values from the scaled Beta distribution of a training case's own distance
    and p-values against the empirical null of the other cases' (module docstring).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> x = rng.normal(size=(6, 3)); x -= x.mean(0)
    >>> u, s, vt = np.linalg.svd(x, full_matrices=False)
    >>> result = training_distances(u * s, s ** 2 / 6, modes=2)
    >>> bool(np.all(result.distance <= np.sqrt(5)))
    True
    >>> bool(np.all((result.distance > result.threshold) == result.outlier))
    True
    """
    n = len(scores)
    k = _checked_modes(int(modes), n)
    squared, p_normal, reference = _training_p_normal(scores, variances, k)
    nulls, which = leave_one_out_nulls(p_normal)     # each case's null without itself
    p = np.empty(n)
    for group, null in enumerate(nulls):
        members = which == group
        p[members] = null.p(p_normal[members])
    at_alpha = np.array([null.p_normal_at(alpha) for null in nulls])[which]
    threshold = np.sqrt((n - 1) * reference.isf(at_alpha))
    return Distances(k, np.sqrt(squared), p, p_normal, threshold, p < alpha,
                     empirical_null(p_normal))


def leave_one_out_nulls(p_normal: np.ndarray) -> tuple[list, np.ndarray]:
    """Every case's :func:`empirical_null` of the *other* cases' p-values, exactly
    ``empirical_null(np.delete(p_normal, i))``, in time n log n rather than n^2.

    The null reads the others' z-values only at some sorted positions (those of the median, of
    the :data:`NULL_QUANTILE` quantile and of the tail, the largest tenth and the one below it).
    Leaving out the case of rank r shifts the sorted values at position j down by one where
    j >= r, so the cases split into groups (by which of those positions their rank lies before)
    whose left-out sets have the same values there: one null is computed per group, leaving out
    one member. The groups are a few below the tail and one per case in it, about n / 10 in all.

    Returns
    -------
    nulls : list of EmpiricalNull
        One per group.
    which : ndarray of int (n,)
        Each case's group: its null is ``nulls[which[i]]``.

    Examples
    --------
    >>> p_normal = np.random.default_rng(1).uniform(size=200)
    >>> nulls, which = leave_one_out_nulls(p_normal)
    >>> len(nulls) < 40
    True
    >>> all(nulls[which[i]] == empirical_null(np.delete(p_normal, i)) for i in range(200))
    True
    """
    from scipy.stats import norm

    p_normal = np.asarray(p_normal, dtype=np.float64)
    n = len(p_normal)
    if n < 3:
        raise ArgumentError(f"leave-one-out nulls need 3 or more p-values, not {n}")
    kept = n - 1
    middle = kept // 2
    quantile = int(np.floor((kept - 1) * NULL_QUANTILE))
    # the positions the median and the quantile read, and their neighbours
    read = [middle - 2, middle - 1, middle, middle + 1,
            quantile - 1, quantile, quantile + 1, quantile + 2]
    if kept >= TAIL_FEWEST:     # the tail's from and its largest r values
        r = tail_cases(kept)
        read.extend(range(kept - r - 1, kept))
    read = np.unique(np.clip(read, 0, kept - 1))
    z = norm.isf(np.clip(p_normal, SMALLEST_P, 1.0))
    rank = np.empty(n, dtype=np.int64)
    rank[np.argsort(z, kind="stable")] = np.arange(n)
    # a case's group: how many of the positions read lie before its rank
    group = np.searchsorted(read, rank, side="left")
    keys, which = np.unique(group, return_inverse=True)
    nulls = [empirical_null(np.delete(p_normal, int(np.flatnonzero(group == key)[0])))
             for key in keys]
    return nulls, which.ravel()


def new_case_distances(scores: np.ndarray, variances: np.ndarray, training: np.ndarray,
                       modes: int, alpha: float = ALPHA) -> Distances:
    """Distances of new cases (not in the model: ``scores`` (c, m) of their fits) over the first
    ``modes`` modes, with normal-theory p-values from the F distribution of a new case's
    distance and p-values against the empirical null of the model's training cases
    (``training``, their scores (n, m))."""
    from scipy.stats import f

    training = np.asarray(training, dtype=np.float64)
    n = len(training)
    k = _checked_modes(int(modes), n)
    null = empirical_null(_training_p_normal(training, variances, k)[1])
    squared = np.sum(np.atleast_2d(scores)[:, :k] ** 2 / np.asarray(variances)[:k], axis=1)
    scale = (n - k) / (k * (n + 1))
    p_normal = f.sf(scale * squared, k, n - k)
    p = null.p(p_normal)
    threshold = np.full(len(squared), np.sqrt(f.isf(null.p_normal_at(alpha), k, n - k) / scale))
    return Distances(k, np.sqrt(squared), p, p_normal, threshold, p < alpha, null)
