"""How large an effect is and how well it is known: per-point confidence intervals of a
coefficient along the normal, Cohen's d, partial eta^2, and the shapes an effect predicts.

At each of p points the model is the one the signed maps test (:mod:`.glm`),
``y = Z gamma + X beta + e`` with the intercept and the nuisance in Z, and the quantity of
interest a combination c'b of the effect's coefficients (one effect column, or a contrast of
levels). Its least-squares estimate is ``a'y`` with ``a' = c' (M'M)^+ M'``, M = [Z X].

- **One variance for all cases** (the pooled model): ``Var(c'b) = s^2 a'a`` with s^2 the residual
  mean square on n - rank(M) degrees of freedom; the interval is Student's,
  ``c'b +- t(1 - alpha / 2; n - rank M) s |a|`` (what statsmodels' OLS ``conf_int`` gives).
- **A variance per group** (the variance groups of Welch's v): the same estimate, its variance
  ``sum_g s_g^2 sum_{i in g} a_i^2`` with ``s_g^2`` group g's residual sum of squares over its
  residual degrees of freedom ``nu_g = sum_{i in g} (1 - h_ii)`` (h the hat matrix's diagonal),
  and the degrees of freedom by Satterthwaite (1946), ``V^2 / sum_g (s_g^2 sum a_i^2)^2 / nu_g``.
  For two groups compared alone this is Welch's interval of the difference of the means
  (variances s_1^2 / n_1 + s_2^2 / n_2, Welch-Satterthwaite df); with nuisance it is a
  heteroscedasticity-consistent interval with one variance per group. It is centred on the
  least-squares difference written beside it, not on the weighted estimate Welch's v tests, so
  its exclusion of 0 and the permutation test of v can disagree near the threshold.

Both assume independent cases and normal errors (approximately, by the central limit theorem,
otherwise); the pooled one also one variance for all cases.

Cohen's d is the estimate over the residual standard deviation of the groups compared: pooled,
``s`` (for two groups and no nuisance the classic ``(m_2 - m_1) / s_pooled``); with variance
groups, ``sqrt((s_ref^2 + s_level^2) / 2)`` (the root mean of the two groups' variances,
Cohen's d for unequal variances, Bonett 2008). With nuisance it is the adjusted difference over
the adjusted residual SD. Partial eta^2 is the share of the residual variation of the reduced
model (nuisance only) that the effect explains: for one number per point
``1 - SSE_full / SSE_reduced`` (``t^2 / (t^2 + df)`` for one column, ``F r / (F r + df)``
generally); for a vector per point Pillai's trace over ``min(q, r)`` (the multivariate partial
eta^2). Both are descriptive: they use the pooled residuals whatever the test's variance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

#: Percentiles of a tested covariate at which its predicted shapes are drawn.
PREDICTED_AT = (10.0, 90.0)


@dataclass
class Interval:
    """The confidence interval of c'b at every point (:func:`interval`).

    Attributes
    ----------
    estimate : ndarray (p,)
        The least-squares c'b (mm along the normal; per unit of a covariate).
    lower, upper : ndarray (p,)
        The interval's ends.
    df : ndarray (p,)
        Its degrees of freedom (n - rank M everywhere, pooled; Satterthwaite's per point with
        variance groups).
    level : float
        The confidence level (1 - alpha).
    variance : str
        "pooled" or "groups".
    spread : ndarray (G, p)
        The residual variance of each variance group (one row, pooled), for Cohen's d.
    """

    estimate: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    df: np.ndarray
    level: float
    variance: str
    spread: np.ndarray

    @property
    def name(self) -> str:
        """Which interval, in words (for analysis.json and the page)."""
        return ("Welch-Satterthwaite, a variance per group" if self.variance == "groups"
                else "Student's t, one pooled variance")


def _design(interest: np.ndarray, nuisance: np.ndarray | None, intercept: bool) -> np.ndarray:
    n = len(interest)
    columns = [np.ones((n, 1))] if intercept else []
    if nuisance is not None and np.size(nuisance):
        columns.append(np.asarray(nuisance, dtype=np.float64).reshape(n, -1))
    columns.append(np.asarray(interest, dtype=np.float64).reshape(n, -1))
    return np.hstack(columns)


def interval(data: np.ndarray, interest: np.ndarray, vector: np.ndarray,
             nuisance: np.ndarray | None = None, intercept: bool = True, groups=None,
             level: float = 0.95) -> Interval:
    """The per-point confidence interval of c'b, the effect columns' combination ``vector``.

    Parameters
    ----------
    data : ndarray (n, p)
        One number per case and point (the displacement along the normal).
    interest : ndarray (n, r)
        The effect's columns.
    vector : ndarray (r,)
        c: 1 at one column for that column's coefficient, or a contrast.
    nuisance : ndarray (n, c), optional
        Columns adjusted for (an intercept is added unless ``intercept`` is False).
    groups : sequence (n,) of int, optional
        Each case's variance group 0 .. G - 1: the Welch-Satterthwaite interval; None: pooled.
    level : float
        The confidence level.

    Returns
    -------
    Interval

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> first, second = rng.normal(0, 1, (8, 1)), rng.normal(2, 3, (5, 1))
    >>> group = np.r_[np.zeros(8), np.ones(5)]
    >>> found = interval(np.vstack([first, second]), group[:, None], np.ones(1),
    ...                  groups=group.astype(int))
    >>> welch = stats.ttest_ind(second[:, 0], first[:, 0], equal_var=False)
    >>> bool(np.allclose([found.lower[0], found.upper[0]], welch.confidence_interval()))
    True
    """
    data = np.asarray(data, dtype=np.float64)
    n = len(data)
    design = _design(interest, nuisance, intercept)
    full = np.zeros(design.shape[1])
    full[design.shape[1] - len(vector):] = vector
    inverse = np.linalg.pinv(design)                              # (m, n): (M'M)^+ M'
    weights = full @ inverse                                      # a (n,)
    estimate = weights @ data
    residuals = data - design @ (inverse @ data)
    rank = np.linalg.matrix_rank(design)
    if groups is None:
        spread = (np.sum(residuals ** 2, axis=0) / (n - rank))[None]
        variance = spread[0] * (weights @ weights)
        df = np.full(data.shape[1], float(n - rank))
    else:
        codes = np.asarray(groups, dtype=np.int64)
        members = (codes[:, None] == np.arange(codes.max() + 1)).astype(np.float64)
        leverage = np.sum(design * inverse.T, axis=1)               # h_ii
        residual_df = members.T @ (1.0 - leverage)                  # nu_g
        spread = (members.T @ residuals ** 2) / residual_df[:, None]
        parts = spread * (members.T @ weights ** 2)[:, None]        # (G, p)
        variance = parts.sum(axis=0)
        df = variance ** 2 / np.maximum(np.sum(parts ** 2 / residual_df[:, None], axis=0),
                                        1e-300)
    half = stats.t.ppf(0.5 + level / 2, df) * np.sqrt(variance)
    return Interval(estimate, estimate - half, estimate + half, df, level,
                    "pooled" if groups is None else "groups", spread)


def cohens_d(found: Interval, compared: tuple | None = None) -> np.ndarray:
    """Cohen's d of an interval's estimate: over the pooled residual SD, or with variance groups
    over the root mean of the variances of the two groups ``compared`` (their codes; None: of
    all groups).

    Examples
    --------
    >>> rng = np.random.default_rng(2)
    >>> a, b = rng.normal(0, 1, 10), rng.normal(1, 1, 12)
    >>> group = np.r_[np.zeros(10), np.ones(12)][:, None]
    >>> d = cohens_d(interval(np.r_[a, b][:, None], group, np.ones(1)))
    >>> pooled = np.sqrt((9 * a.var(ddof=1) + 11 * b.var(ddof=1)) / 20)
    >>> bool(np.isclose(d[0], (b.mean() - a.mean()) / pooled))
    True
    """
    spread = found.spread
    if found.variance == "groups":
        spread = spread[list(compared)] if compared is not None else spread
        spread = spread.mean(axis=0, keepdims=True)
    return found.estimate / np.sqrt(np.maximum(spread[0], 1e-300))


def partial_eta_squared(data: np.ndarray, interest: np.ndarray,
                        nuisance: np.ndarray | None = None, intercept: bool = True
                        ) -> np.ndarray:
    """The partial eta^2 of the effect columns at each point: for one number per point
    ``1 - SSE_full / SSE_reduced``; for q per point Pillai's trace over min(q, r).

    Parameters
    ----------
    data : ndarray (n, p) or (n, p, q)
    interest, nuisance, intercept
        As in :func:`interval`.

    Returns
    -------
    ndarray (p,)

    Examples
    --------
    >>> rng = np.random.default_rng(3)
    >>> x = rng.normal(size=(30, 1))
    >>> y = 0.5 * x + rng.normal(size=(30, 4))
    >>> eta = partial_eta_squared(y, x)
    >>> r = [np.corrcoef(x[:, 0], y[:, k])[0, 1] for k in range(4)]
    >>> bool(np.allclose(eta, np.square(r)))
    True
    """
    data = np.asarray(data, dtype=np.float64)
    if data.ndim == 2:
        data = data[..., None]
    n, p, q = data.shape
    full = _design(interest, nuisance, intercept)
    r = np.asarray(interest).reshape(n, -1).shape[1]
    reduced = full[:, :full.shape[1] - r]
    flat = data.reshape(n, -1)

    def scatter(columns: np.ndarray) -> np.ndarray:
        if columns.shape[1]:
            fitted = columns @ np.linalg.lstsq(columns, flat, rcond=None)[0]
        else:
            fitted = np.zeros_like(flat)
        errors = (flat - fitted).reshape(n, p, q)
        return np.einsum("npi,npj->pij", errors, errors)

    total, error = scatter(reduced), scatter(full)
    pillai = np.trace(np.linalg.solve(total, total - error), axis1=1, axis2=2)
    return pillai / min(q, r)


def predicted_offsets(values: np.ndarray, percentiles=PREDICTED_AT) -> np.ndarray:
    """A covariate's percentiles among the cases, as offsets from its mean (the design's
    covariate columns are centred, and a least-squares fit with an intercept passes through the
    means, so the shape predicted at offset u with every other column at its mean is the mean
    shape plus u times the covariate's coefficients).

    Examples
    --------
    >>> predicted_offsets(np.arange(11.0) - 5.0).tolist()
    [-4.0, 4.0]
    """
    return np.percentile(np.asarray(values, dtype=np.float64), percentiles)


__all__ = ["PREDICTED_AT", "Interval", "cohens_d", "interval", "partial_eta_squared",
           "predicted_offsets"]
