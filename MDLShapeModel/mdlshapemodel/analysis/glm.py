"""Per-point linear models with permutation inference: the engine of every test of the analysis.

At each of p points the data are n observations of q numbers (q = 1: the displacement along the
mean surface's normal; q = 2 or 3: the displacement vector; q = k: a point's place is taken by
the first k principal scores in the global test). The model is

    Y = Z gamma + X beta + E,

Z the nuisance (an intercept and nuisance covariates, z columns), X the effect of interest (r
columns: group indicators against a reference group, or numeric covariates). The statistic is
Pillai's trace of the effect of X after Z,

    V = tr(H (H + E)^-1),   H + E = Y' (I - P_Z) Y,   H = Y' (P_[Z X] - P_Z) Y,

which is, for q = 1, the share of the residual sum of squares that X explains (F = (V / r) /
((1 - V) / df), df = n - z - r), and for r = 1 a monotone function of Hotelling's T^2
(T^2 = df V / (1 - V)): for two groups and no covariate, the two-sample T^2 of the point's
displacement (n1 n2 / n) d' S^-1 d with S the pooled covariance.

Inference by permutation, Freedman and Lane (1983): the residuals of the reduced model
R = (I - P_Z) Y are permuted and the statistic is recomputed with the full model. A permutation
sigma changes only which rows of the orthonormal bases of Z and of X after Z meet which rows of
R, so with the bases' rows permuted instead, the statistic of each permutation is one product of
an n x (z + r) matrix with the n x (p q) residuals, then q x q algebra per point. Family-wise
error over all points by the maximum statistic (Nichols and Holmes 2002); per-point p-values
count the observed statistic among the permuted ones, p = (1 + #{T_b >= T}) / (1 + B);
Benjamini-Hochberg q-values from the permuted statistics pooled over all points (which resolve
the p-values far below 1 / B that thousands of points need). Memory stays bounded: permutations are taken in chunks
and only each permutation's maximum and each point's count are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..progress import report

# permutations handled at once: bounds the memory to CHUNK x (z + r) x p x q floats; fixed so
# that the drawn permutations (and so the p-values) do not depend on it changing
CHUNK = 250
# a permuted statistic counts as reaching the observed one within this relative rounding, so that
# the identity permutation, recomputed along another path, always counts
TIES = 1e-10
# the null distribution pooled over all points (for the FDR q-values): a histogram of log(V) in
# this many bins from SMALLEST to LARGEST (a bin is 0.04 % of V wide); Pillai's trace is at
# most min(q, r), and only LARGEST is needed as an upper bound of the bins
HISTOGRAM_BINS = 1 << 16
SMALLEST, LARGEST = 1e-12, 64.0


@dataclass
class PointTest:
    """The result of :func:`permutation_test`.

    Attributes
    ----------
    pillai : ndarray (p,)
        Pillai's trace V of the effect at each point (the quantity permuted).
    statistic : ndarray (p,)
        The statistic reported: Hotelling's T^2 (q > 1) or F = t^2 (q = 1) when r = 1; else the
        F of Pillai's trace (q = 1: the exact one-way F).
    p : ndarray (p,)
        Uncorrected permutation p-value against the permuted statistics of all points pooled,
        (1 + #{b, k: V_bk >= V}) / (1 + B p) (to within a histogram bin, 0.04 % of V): the
        statistic is pivotal (under normal errors its null distribution is the same at every
        point), and the pooled distribution resolves p-values far below 1 / B, as a
        false-discovery rate over thousands of points needs.
    p_point : ndarray (p,)
        The point's own permutation p-value, (1 + #{b: V_b >= V}) / (1 + B).
    p_fwer, q_fdr : ndarray (p,)
        Family-wise corrected over all points by the maximum statistic, and the
        Benjamini-Hochberg q-value of ``p``.
    effect : ndarray (r, p, q)
        The least-squares coefficients of the effect columns, adjusted for the nuisance: for a
        group indicator the adjusted mean difference from the reference group; for a
        covariate the change per unit.
    df : int
        Residual degrees of freedom n - z - r.
    permutations : int
        Number of permutations drawn (B).
    maxima : ndarray (B,)
        Each permutation's largest Pillai trace over the points (the null distribution of the
        family-wise test).
    """

    pillai: np.ndarray
    statistic: np.ndarray
    p: np.ndarray
    p_point: np.ndarray
    p_fwer: np.ndarray
    q_fdr: np.ndarray
    effect: np.ndarray
    df: int
    permutations: int
    maxima: np.ndarray


def _bins(pillai: np.ndarray) -> np.ndarray:
    """The bin of each Pillai trace in the pooled null histogram: equal steps of log(V) from
    :data:`SMALLEST` to the largest trace possible (bin 0 holds everything below)."""
    logs = np.log(np.maximum(np.asarray(pillai, dtype=np.float64), SMALLEST))
    position = (logs - np.log(SMALLEST)) / (np.log(LARGEST) - np.log(SMALLEST))
    return np.clip(np.floor(position * HISTOGRAM_BINS).astype(np.int64) + 1, 0,
                   HISTOGRAM_BINS)


def benjamini_hochberg(p: np.ndarray) -> np.ndarray:
    """Benjamini-Hochberg q-values (adjusted p-values) of a vector of p-values.

    q_(i) = min over j >= i of p_(j) m / j, capped at 1 (Benjamini and Hochberg 1995); a point
    is significant at false-discovery rate alpha when q <= alpha.

    Examples
    --------
    >>> benjamini_hochberg(np.array([0.01, 0.04, 0.03, 0.5])).round(3).tolist()
    [0.04, 0.053, 0.053, 0.5]
    """
    p = np.asarray(p, dtype=np.float64)
    order = np.argsort(p, kind="stable")
    ranked = p[order] * len(p) / np.arange(1, len(p) + 1)
    ranked = np.minimum.accumulate(ranked[::-1])[::-1]
    q = np.empty_like(p)
    q[order] = np.minimum(ranked, 1.0)
    return q


def _basis(columns: np.ndarray, what: str, scale: float | None = None) -> np.ndarray:
    """An orthonormal basis (n, k) of the span of ``columns``; InputError when they are
    collinear (rank below k). ``scale``: the size of the columns before they were made
    orthogonal to others (a column that vanished then was a combination of those)."""
    q, r = np.linalg.qr(columns)
    diagonal = np.abs(np.diag(r))
    reference = max(diagonal.max(initial=0.0), scale or 0.0, 1e-300)
    if diagonal.size and diagonal.min() <= 1e-10 * reference:
        raise InputError(f"{what} are collinear (a column is a combination of the others)")
    return q


def _whitening(total: np.ndarray) -> np.ndarray:
    """Per point the inverse Cholesky factor L^-1 of the residual scatter (p, q, q), so that the
    whitened residuals R L^-T have scatter I at every point."""
    q = total.shape[-1]
    scale = np.trace(total, axis1=1, axis2=2) / q
    if np.any(scale <= 0):
        raise InputError("some points do not vary at all across the cases")
    jitter = 1e-12 * scale[:, None, None] * np.eye(q)
    factor = np.linalg.cholesky(total + jitter)
    return np.linalg.inv(factor)


def _pillai(coefficients: np.ndarray, z: int) -> np.ndarray:
    """Pillai's trace per permutation and point from the products of the permuted bases with the
    whitened residuals: ``coefficients`` (B, z + r, p, q), the first z rows of the nuisance basis
    (K), the rest of the effect's (G); V = tr(G A^-1 G') with A = I - K'K."""
    effect = coefficients[:, z:]
    if z == 0:
        return np.einsum("brpq,brpq->bp", effect, effect)
    nuisance = coefficients[:, :z]
    q = coefficients.shape[-1]
    if q == 1:
        return (np.sum(effect[..., 0] ** 2, axis=1)
                / (1.0 - np.sum(nuisance[..., 0] ** 2, axis=1)))
    a = np.eye(q) - np.einsum("bzpi,bzpj->bpij", nuisance, nuisance)
    g = np.moveaxis(effect, 1, 2)                                  # (B, p, r, q)
    solved = np.linalg.solve(a, np.swapaxes(g, -1, -2))            # A^-1 G'  (B, p, q, r)
    return np.einsum("bprq,bpqr->bp", g, solved)


def statistic_of(pillai: np.ndarray, q: int, r: int, df: int) -> np.ndarray:
    """The reported statistic of Pillai's trace: T^2 (F when q = 1) for r = 1, else the F
    approximation of Pillai's trace (exact for q = 1)."""
    pillai = np.asarray(pillai, dtype=np.float64)
    if r == 1:
        return df * pillai / np.maximum(1.0 - pillai, 1e-300)
    s = min(q, r)
    m = (abs(q - r) - 1) / 2
    nn = (df - q - 1) / 2
    return (2 * nn + s + 1) / (2 * m + s + 1) * pillai / np.maximum(s - pillai, 1e-300)


def permutation_test(data: np.ndarray, interest: np.ndarray, nuisance: np.ndarray | None = None,
                     permutations: int = 10_000, seed: int = 0, progress=None) -> PointTest:
    """Test an effect on per-point data by permutation (Freedman-Lane), with family-wise and FDR
    correction over the points.

    Parameters
    ----------
    data : ndarray (n, p, q)
        n cases, p points, q numbers per point (a 2-D array (n, p) is q = 1).
    interest : ndarray (n, r)
        The effect's columns (group indicators against a reference group, or covariates).
    nuisance : ndarray (n, c), optional
        Covariates to adjust for; an intercept is always added.
    permutations : int
        B, the number of random permutations (seeded by ``seed``).
    progress : callable(fraction, message), optional
        The library's progress protocol (:mod:`mdlshapemodel.progress`), called after each
        chunk of permutations; cancelling raises :class:`~mdlshapemodel.errors.Cancelled`.

    Returns
    -------
    PointTest

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> group = np.repeat([0.0, 1.0], 10)[:, None]
    >>> data = rng.normal(size=(20, 50)) + 3.0 * group * (np.arange(50) < 5)
    >>> result = permutation_test(data, group, permutations=999)
    >>> bool(np.all(result.p_fwer[:5] < 0.05)), int(np.sum(result.p_fwer[5:] < 0.05))
    (True, 0)
    """
    data = np.asarray(data, dtype=np.float64)
    if data.ndim == 2:
        data = data[..., None]
    n, p, q = data.shape
    interest = np.asarray(interest, dtype=np.float64).reshape(n, -1)
    columns = [np.ones((n, 1))]
    if nuisance is not None and np.size(nuisance):
        columns.append(np.asarray(nuisance, dtype=np.float64).reshape(n, -1))
    z_columns = np.hstack(columns)
    z, r = z_columns.shape[1], interest.shape[1]
    df = n - z - r
    if df < q:
        raise InputError(f"too few cases: {n} cases for {z + r} model columns and {q} "
                         f"number(s) per point (need more than {z + r + q - 1})")
    basis_z = _basis(z_columns, "the nuisance columns")
    interest_after_z = interest - basis_z @ (basis_z.T @ interest)
    basis_x = _basis(interest_after_z, "the variables of interest and the nuisance",
                     scale=float(np.abs(interest).max(initial=0.0)) * np.sqrt(n))
    flat = data.reshape(n, p * q)
    residuals = flat - basis_z @ (basis_z.T @ flat)
    # the effect: least squares of the full model, the coefficients of the effect's columns
    design = np.hstack([z_columns, interest])
    coefficients, *_ = np.linalg.lstsq(design, flat, rcond=None)
    effect = coefficients[z:].reshape(r, p, q)

    stacked = residuals.reshape(n, p, q)
    total = np.einsum("npi,npj->pij", stacked, stacked)
    whitened = np.einsum("npj,pij->npi", stacked, _whitening(total)).reshape(n, p * q)
    # the intercept's basis is constant, so its permuted rows meet the centred residuals in zero:
    # it drops out of every permutation; the other nuisance columns do not
    permuted_z = basis_z[:, 1:]
    bases = np.hstack([permuted_z, basis_x])
    zp = permuted_z.shape[1]

    def pillai_of(rows: np.ndarray) -> np.ndarray:
        """V for each permutation (rows: (B, n) indices into the bases)."""
        permuted = np.ascontiguousarray(np.swapaxes(bases[rows], 1, 2))   # (B, k, n)
        products = permuted.reshape(-1, n) @ whitened                      # one BLAS product
        return _pillai(products.reshape(len(rows), zp + r, p, q), zp)

    observed = pillai_of(np.arange(n)[None])[0]
    threshold = observed - TIES * np.abs(observed)
    rng = np.random.default_rng(seed)
    exceed = np.zeros(p, dtype=np.int64)
    pooled = np.zeros(HISTOGRAM_BINS + 1, dtype=np.int64)
    maxima = np.empty(permutations)
    done = 0
    while done < permutations:
        count = min(CHUNK, permutations - done)
        rows = np.argsort(rng.random((CHUNK, n)), axis=1)[:count]
        values = pillai_of(rows)
        exceed += np.sum(values >= threshold, axis=0)
        pooled += np.bincount(_bins(values.ravel()), minlength=HISTOGRAM_BINS + 1)
        maxima[done:done + count] = values.max(axis=1)
        done += count
        report(progress, done / permutations, f"{done} of {permutations} permutations")
    p_point = (1.0 + exceed) / (1.0 + permutations)
    at_least = np.cumsum(pooled[::-1])[::-1]          # null values in this bin or above
    p_pooled = (1.0 + at_least[_bins(threshold)]) / (1.0 + permutations * p)
    sorted_maxima = np.sort(maxima)
    above = permutations - np.searchsorted(sorted_maxima, threshold, side="left")
    p_fwer = (1.0 + above) / (1.0 + permutations)
    p_pooled = np.minimum(p_pooled, 1.0)
    return PointTest(pillai=observed, statistic=statistic_of(observed, q, r, df), p=p_pooled,
                     p_point=p_point, p_fwer=p_fwer, q_fdr=benjamini_hochberg(p_pooled),
                     effect=effect, df=df, permutations=permutations, maxima=maxima)
