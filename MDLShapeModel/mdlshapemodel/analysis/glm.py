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

With variance groups (the groups compared, when they may differ in variance), the statistic is
Welch's v / G or James' J instead (:mod:`.welch`); the pooled statistics assume one covariance
for all cases.

Inference by permutation, Freedman and Lane (1983): the residuals of the reduced model
R = (I - P_Z) Y are permuted and the statistic is recomputed with the full model. A permutation
sigma changes only which rows of the orthonormal bases of Z and of X after Z (and of the
variance groups) meet which rows of R, so with the bases' rows permuted instead, the pooled
statistic of each permutation is one product of an n x (z + r) matrix with the n x (p q)
residuals, then q x q algebra per point. Per-point p-values count each point's observed
statistic among its own permuted ones, p = (1 + #{b: T_b >= T}) / (1 + B), so they never
assume that the points share a null distribution (under heavy tails or unequal variances they
do not); their resolution is 1 / (B + 1). Benjamini-Hochberg q-values are computed from them.
Family-wise error over all points by the maximum statistic (Nichols and Holmes 2002), valid
always and balanced across the points when the statistic is pivotal (the same null distribution
at every point: Pillai's trace under normal errors, Welch's -log p approximately); or by min-p
(Westfall and Young 1993): each permutation's smallest per-point p-value over the points, each
against its own point's permutation distribution, is the null distribution of the smallest p,
so that no point dominates the correction because its statistic has heavier tails. Min-p keeps
every permuted statistic, (B + 1) x p 4-byte numbers; the maximum keeps one number per
permutation. The permutations are drawn in chunks.

With a surface, each resample's map is also enhanced by threshold-free cluster enhancement
(:mod:`.tfce`) and the family-wise p of each point's enhanced value is counted against the
maximum of the enhanced maps over the same resamples. What is enhanced is a map that means the
same at every point: the signed t (Welch's: the normal quantile of v's p, with v's sign), each
sign on its own, for one effect column and one number per point; else the square root of the
pooled statistic (its F, the same degrees of freedom at every point), the normal quantile of
Welch's G's p, or the square root of James' J.

This module fits the models and counts the resamples' statistics (:func:`permutation_test`); its
parts are rooms of their own: the resamples in :mod:`.resampling`, the pooled statistic in
:mod:`.pillai`, the corrections over the points (FDR, min-p) in :mod:`.correction`, the
statistics with a variance per group in :mod:`.welch` and the enhancement in :mod:`.tfce`. The
names its users import from it stay importable here (:data:`__all__`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scipy import special

from ..config import FAMILY_WISE, TAILS
from ..errors import ArgumentError, InputError
from ..progress import report
from . import welch
from .correction import benjamini_hochberg, smallest_p
from .pillai import orthonormal_basis, pillai_trace, statistic_of, whitening
from .resampling import (CHUNK, drawn_flips, drawn_permutations, drawn_resamples, drawn_signs,
                         drawn_whole_blocks, resampling_name)
from .tfce import Surface, enhance

# the names this module's users import from it, wherever they live
__all__ = ["CHUNK", "PointTest", "benjamini_hochberg", "drawn_flips", "drawn_permutations",
           "drawn_signs", "drawn_whole_blocks", "permutation_test", "smallest_p",
           "statistic_of"]

# a permuted statistic counts as reaching the observed one within this relative rounding, so that
# the identity permutation, recomputed along another path, always counts
TIES = 1e-10
# permutations of the general Welch statistic computed at once (bounds its memory to
# WELCH_CHUNK x n x p floats)
WELCH_CHUNK = 25


@dataclass
class PointTest:
    """The result of :func:`permutation_test`.

    Attributes
    ----------
    value : ndarray (p,)
        The quantity permuted at each point: Pillai's trace V of the effect (``variance``
        "pooled"); with variance groups, -log of Welch's G's parametric p-value (q = 1) or James'
        J (q > 1).
    statistic : ndarray (p,)
        The statistic reported. Pooled: Hotelling's T^2 (q > 1) or F = t^2 (q = 1) when r = 1,
        else the F of Pillai's trace (q = 1: the exact one-way F). Variance groups: Welch's G
        (q = 1; v^2 for two groups) or James' J (q > 1).
    p : ndarray (p,)
        The point's own permutation p-value, (1 + #{b: T_b >= T}) / (1 + B), at least
        1 / (B + 1).
    p_fwer : ndarray (p,)
        Family-wise corrected over all points: by the maximum of ``value`` over the points,
        (1 + #{b: max_k value_bk >= value}) / (1 + B), or by min-p, (1 + #{b: min over points of
        the permutation's per-point p <= p}) / (1 + B).
    q_fdr : ndarray (p,)
        The Benjamini-Hochberg q-value of ``p``.
    effect : ndarray (r, p, q)
        The least-squares coefficients of the effect columns, adjusted for the nuisance: for a
        group indicator the adjusted mean difference from the reference group; for a
        covariate the change per unit.
    df : int
        Residual degrees of freedom n - z - r.
    permutations : int
        Number of permutations drawn (B).
    family_null : ndarray (B,)
        The null distribution of the family-wise test: each permutation's largest ``value`` over
        the points ("maximum"), or its smallest per-point p-value ("min-p").
    variance : str
        "pooled" (one covariance for all cases) or "groups" (one per variance group).
    family_wise : str
        "maximum" or "min-p" (:data:`FAMILY_WISE`).
    t : ndarray (p,) or None
        For one effect column and one number per point, the signed statistic: Student's t of
        the effect's coefficient (pooled), or Welch's v (variance groups); its sign is the
        effect's (t^2 = ``statistic``). None otherwise.
    tail : str
        "both", or one-sided "greater" / "less" (:data:`TAILS`): then ``value``, ``p`` and
        ``p_fwer`` are of the signed statistic in that direction.
    resampling : str
        How the residuals were resampled, in words ("permuted", "sign-flipped", "permuted
        within the blocks", ...).
    tfce : ndarray (p,) or None
        With a surface, the threshold-free cluster enhancement of the map (:mod:`.tfce`), with
        the effect's sign where the map has one (negative: below 0); else None.
    tfce_p_fwer : ndarray (p,) or None
        Its family-wise p: (1 + #{b: max_k |TFCE_bk| >= |TFCE|}) / (1 + B).
    tfce_null : ndarray (B,) or None
        Each resample's largest enhanced value over the points (two-sided: of either sign).
    """

    value: np.ndarray
    statistic: np.ndarray
    p: np.ndarray
    p_fwer: np.ndarray
    q_fdr: np.ndarray
    effect: np.ndarray
    df: int
    permutations: int
    family_null: np.ndarray
    variance: str
    family_wise: str
    t: np.ndarray | None = None
    tail: str = "both"
    resampling: str = "permuted"
    tfce: np.ndarray | None = None
    tfce_p_fwer: np.ndarray | None = None
    tfce_null: np.ndarray | None = None

    @property
    def name(self) -> str:
        """What the statistic is, in words (for the page, the terminal and analysis.json)."""
        r, _, q = self.effect.shape
        if self.tail != "both":
            return ("Welch's v, one-sided (a variance per group)" if self.variance == "groups"
                    else "Student's t, one-sided (one pooled variance)")
        if self.variance == "groups":
            return ("James' statistic (a covariance per group)" if q > 1 else
                    "Welch's v^2 (a variance per group)" if r == 1 else
                    "Welch's G (a variance per group)")
        if r > 1:
            return "the F of Pillai's trace (one pooled covariance)"
        return ("Hotelling's T^2 (one pooled covariance)" if q > 1 else
                "F = t^2 (one pooled variance)")


def _one_way(interest: np.ndarray, codes: np.ndarray, count: int) -> bool:
    """Whether [1, interest] spans exactly the indicators of the variance groups (a one-way
    layout of the groups compared)."""
    indicators = (codes[:, None] == np.arange(count)).astype(np.float64)
    means = np.linalg.lstsq(indicators, interest, rcond=None)[0]
    scale = max(float(np.abs(interest).max(initial=0.0)), 1e-300)
    return bool(np.linalg.matrix_rank(np.hstack([np.ones((len(codes), 1)), interest])) == count
                and np.allclose(indicators @ means, interest, atol=1e-12 * scale))


def permutation_test(data: np.ndarray, interest: np.ndarray, nuisance: np.ndarray | None = None,
                     permutations: int = 10_000, seed: int = 0, progress=None,
                     variance_groups=None, family_wise: str = "maximum", *,
                     intercept: bool = True, blocks=None, flips: bool = False,
                     whole_blocks: bool = False, tail: str = "both",
                     surface: Surface | None = None) -> PointTest:
    """Test an effect on per-point data by permutation (Freedman-Lane), with family-wise and FDR
    correction over the points.

    Parameters
    ----------
    data : ndarray (n, p, q)
        n cases, p points, q numbers per point (a 2-D array (n, p) is q = 1).
    interest : ndarray (n, r)
        The effect's columns (group indicators against a reference group, or covariates).
    nuisance : ndarray (n, c), optional
        Covariates to adjust for; an intercept is added unless ``intercept`` is False.
    permutations : int
        B, the number of random permutations (seeded by ``seed``).
    progress : callable(fraction, message), optional
        The library's progress protocol (:mod:`mdlshapemodel.progress`), called after each
        chunk of permutations; cancelling raises :class:`~mdlshapemodel.errors.Cancelled`.
    variance_groups : sequence (n,), optional
        Each case's variance group (for a group comparison: its group). With two or more, the
        statistic is Welch's G (James' J for q > 1; :mod:`.welch`), valid when the groups
        differ in variance; without (or with one), the pooled statistic. James' J needs a
        one-way layout (the groups compared, nothing adjusted for).
    family_wise : {"maximum", "min-p"}
        The family-wise correction: the maximum over the points of the permuted statistic
        (pivotal: Pillai's trace has the same null distribution at every point under normal
        errors, Welch's -log p approximately), or min-p (no point dominates, whatever its
        tails; resolution-limited: with m roughly independent points the smallest ``p_fwer`` is
        about 1 - (1 - 1 / (B + 1))^m, so B should be well above m / alpha).
    intercept : bool
        Whether the nuisance has an intercept. Without one, ``interest`` may be a column of
        ones: the one-sample test of a mean (for example of each subject's change between two
        times), resampled by sign flips.
    blocks : sequence (n,), optional
        Exchangeability blocks (Winkler et al. 2014): cases are permuted only within their
        block (a subject's scans, tested for an effect of time within subjects).
    flips : bool
        Resample by flipping the sign of each case's residual (independent and symmetric
        errors, "ISE"), alone or with the permutations within ``blocks``. Variance groups are
        always flipped.
    whole_blocks : bool
        Permute whole ``blocks`` instead (a subject's cases together, in their order, among
        subjects with as many cases), for effects that are each block's own; the pooled
        statistic.
    tail : {"both", "greater", "less"}
        One-sided tests of one effect column and one number per point: "greater", an effect
        above 0 (with the pooled statistic, larger t); "less", below 0 (an inward displacement:
        atrophy). The resampled statistic is then the signed t (Welch's one-sided ``-log p``
        with variance groups).
    surface : Surface, optional
        The mesh of the points (:func:`.tfce.surface_of`): each resample's map is also enhanced
        (threshold-free cluster enhancement) and tested family-wise by the enhanced maps'
        maximum (``tfce``, ``tfce_p_fwer``).

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
    >>> welch = permutation_test(data, group, permutations=999, variance_groups=group[:, 0])
    >>> welch.variance, bool(np.allclose(welch.statistic, result.statistic))  # n1 = n2: v = t
    ('groups', True)
    >>> bool(np.all(welch.p[:5] < 0.01)), int(np.sum(welch.p_fwer[5:] < 0.05))
    (True, 0)
    >>> change = rng.normal(size=(12, 50)) + 2.0 * (np.arange(50) < 5)   # one-sample
    >>> mean = permutation_test(change, np.ones((12, 1)), intercept=False, flips=True,
    ...                         permutations=999, tail="greater")
    >>> mean.resampling, bool(np.all(mean.t[:5] > 0)), bool(np.all(mean.p[:5] < 0.01))
    ('sign-flipped', True, True)
    """
    data = np.asarray(data, dtype=np.float64)
    if data.ndim == 2:
        data = data[..., None]
    n, p, q = data.shape
    interest = np.asarray(interest, dtype=np.float64).reshape(n, -1)
    columns = [np.ones((n, 1))] if intercept else []
    if nuisance is not None and np.size(nuisance):
        columns.append(np.asarray(nuisance, dtype=np.float64).reshape(n, -1))
    z_columns = np.hstack(columns) if columns else np.zeros((n, 0))
    z, r = z_columns.shape[1], interest.shape[1]
    df = n - z - r
    if family_wise not in FAMILY_WISE:
        raise ArgumentError(f"family_wise must be one of {FAMILY_WISE}, not {family_wise!r}")
    if tail not in TAILS:
        raise ArgumentError(f"tail must be one of {TAILS}, not {tail!r}")
    signed = r == 1 and q == 1
    if tail != "both" and not signed:
        raise InputError(f"a one-sided test (tail {tail!r}) needs one effect column and one "
                         f"number per point (here {r} column(s), {q} number(s) per point)")
    if surface is not None and surface.n_points != p:
        raise ArgumentError(f"a surface of {surface.n_points} points for data of {p}")
    if df < q:
        raise InputError(f"too few cases: {n} cases for {z + r} model columns and {q} "
                         f"number(s) per point (need more than {z + r + q - 1})")
    codes, sizes = None, None
    if variance_groups is not None:
        levels, codes = np.unique(np.asarray(variance_groups), return_inverse=True)
        if len(codes) != n:
            raise InputError(f"{len(codes)} variance groups for {n} cases")
        sizes = np.bincount(codes, minlength=len(levels)).astype(np.float64)
        if len(levels) < 2:
            codes = None
        elif sizes.min() <= q:
            raise InputError(f"variance group {levels[np.argmin(sizes)]!r} has "
                             f"{int(sizes.min())} case(s); with {q} number(s) per point each "
                             f"needs more than {q} to estimate its own variance")
        elif not intercept or whole_blocks:
            raise ArgumentError("variance groups need the intercept in the nuisance and cases "
                             "permuted one by one")
    if blocks is not None:
        blocks = np.unique(np.asarray(blocks), return_inverse=True)[1].reshape(-1)
        if len(blocks) != n:
            raise InputError(f"{len(blocks)} exchangeability blocks for {n} cases")
    basis_z = orthonormal_basis(z_columns, "the nuisance columns")
    interest_after_z = interest - basis_z @ (basis_z.T @ interest)
    basis_x = orthonormal_basis(interest_after_z, "the variables of interest and the nuisance",
                                scale=float(np.abs(interest).max(initial=0.0)) * np.sqrt(n))
    if signed and basis_x[:, 0] @ interest_after_z[:, 0] < 0:
        basis_x = -basis_x                     # its coefficient has the effect's sign
    flat = data.reshape(n, p * q)
    residuals = flat - basis_z @ (basis_z.T @ flat)
    # the effect: least squares of the full model, the coefficients of the effect's columns
    design = np.hstack([z_columns, interest])
    coefficients, *_ = np.linalg.lstsq(design, flat, rcond=None)
    effect = coefficients[z:].reshape(r, p, q)

    stacked = residuals.reshape(n, p, q)
    # the intercept's basis is constant, so its permuted rows meet the centred residuals in zero:
    # it drops out of every permutation (not of sign flips); the other nuisance columns do not
    permuted_z = basis_z[:, 1:] if intercept and not flips else basis_z
    if whole_blocks and blocks is None:
        raise ArgumentError("whole_blocks needs blocks")
    bases = np.hstack([permuted_z, basis_x])
    zp = permuted_z.shape[1]
    if codes is None:
        total = np.einsum("npi,npj->pij", stacked, stacked)
        whitened = np.einsum("npj,pij->npi", stacked, whitening(total)).reshape(n, p * q)

        def measured(rows: np.ndarray, signs) -> tuple:
            """Pillai's V and, for one effect column, the signed t of each resample."""
            permuted = bases[rows] if signs is None else bases[rows] * signs[..., None]
            permuted = np.ascontiguousarray(np.swapaxes(permuted, 1, 2))       # (B, k, n)
            products = (permuted.reshape(-1, n) @ whitened).reshape(len(rows), zp + r, p, q)
            pillai = pillai_trace(products, zp)
            if not signed:
                return pillai, None
            return pillai, np.sign(products[:, zp, :, 0]) * np.sqrt(
                statistic_of(pillai, 1, 1, df))

        def values_of(rows: np.ndarray, signs) -> tuple:
            """The resampled quantity (Pillai's V, or the signed t one-sided) and the t."""
            pillai, t = measured(rows, signs)
            if tail == "both":
                return pillai, t
            return (t if tail == "greater" else -t), t
    else:
        one_way = z == 1 and _one_way(interest, codes, len(sizes))
        if q > 1 and not one_way:
            raise InputError("variance groups with a vector per point need the groups "
                             "compared alone, nothing adjusted for (James' statistic): test "
                             "the normal displacement, or use the pooled statistic")
        full = np.hstack([basis_z, basis_x])
        centred = welch.reduced_residuals(data, basis_z, full, codes, sizes)
        if one_way:
            # the sign of the second variance group's mean minus the first's, as the effect's
            orientation = (np.sign(interest[codes == 1, 0].mean() - interest[codes == 0, 0].mean())
                           if len(sizes) == 2 else 1.0)

            def welch_of(rows: np.ndarray, signs: np.ndarray) -> tuple:
                found, welch_df, direction = welch.one_way(centred, codes, sizes, signs)
                return found, welch_df, None if direction is None else orientation * direction
        else:
            def welch_of(rows: np.ndarray, signs: np.ndarray) -> tuple:
                parts = [welch.general(centred[..., 0], full, r, codes, sizes,
                                       rows[k:k + WELCH_CHUNK], signs[k:k + WELCH_CHUNK])
                         for k in range(0, len(rows), WELCH_CHUNK)]
                return tuple(None if found[0] is None else np.concatenate(found)
                             for found in zip(*parts))

        def values_of(rows: np.ndarray, signs: np.ndarray) -> tuple:
            """Welch's G as -log of its parametric p (q = 1; one-sided: of v), James' J (q > 1),
            and Welch's signed v for one effect column."""
            found, welch_df, direction = welch_of(rows, signs)
            if welch_df is None:
                return found, None
            v = None if direction is None else direction * np.sqrt(found)
            if tail == "both":
                return welch.pivotal(found, r, welch_df), v
            return welch.one_sided(v, welch_df, tail), v

    def enhanced_of(values: np.ndarray, t) -> np.ndarray:
        """TFCE of the resamples' maps (B, p), signed as the effect where it has a sign."""
        # with variance groups, values are -log of Welch's p (James' J for q > 1)
        p_values = None if codes is None else np.exp(-np.minimum(values, 690.0))
        if tail != "both":
            # the statistic towards the tail: the signed t, or the normal quantile of Welch's p
            toward = values if codes is None else -special.ndtri(p_values)
            found = enhance(np.maximum(toward, 0.0), surface)
            return found if tail == "greater" else 0.0 - found
        if t is not None:
            z = t if codes is None else np.sign(t) * -special.ndtri(p_values / 2.0)
            return (enhance(np.maximum(z, 0.0), surface)
                    - enhance(np.maximum(-z, 0.0), surface))
        if codes is None:
            return enhance(np.sqrt(statistic_of(values, q, r, df)), surface)
        return enhance(-special.ndtri(p_values) if q == 1 else np.sqrt(values), surface)

    resamples = drawn_resamples(n, permutations, seed, codes, blocks, flips, whole_blocks)
    identity = np.arange(n)[None], np.ones((1, n))
    observed, observed_t = values_of(*identity)
    tfce = None if surface is None else enhanced_of(observed, observed_t)[0]
    enhanced_maxima = np.empty(permutations if surface is not None else 0)
    observed = observed[0]
    threshold = observed - TIES * np.abs(observed)
    exceed = np.zeros(p, dtype=np.int64)
    minimum_p = family_wise == "min-p"
    # min-p keeps every permutation's statistic at every point (row 0: the observed); the
    # maximum keeps each permutation's largest
    table = np.empty((permutations + 1 if minimum_p else 0, p), dtype=np.float32)
    if minimum_p:
        table[0] = observed
    maxima = np.empty(permutations)
    done = 0
    for rows, signs in resamples:
        count = len(rows)
        values, t = values_of(rows, signs)
        exceed += np.sum(values >= threshold, axis=0)
        if surface is not None:
            enhanced_maxima[done:done + count] = np.abs(enhanced_of(values, t)).max(axis=1)
        if minimum_p:
            table[1 + done:1 + done + count] = values
        maxima[done:done + count] = values.max(axis=1)
        done += count
        report(progress, done / permutations, f"{done} of {permutations} permutations")
    at_least = 1 + exceed                         # the observed and the permuted reaching it
    p_point = at_least / (1.0 + permutations)
    if minimum_p:
        smallest = smallest_p(table)[1:]
        below = np.searchsorted(np.sort(smallest), at_least, side="right")
        family_null = smallest / (1.0 + permutations)
    else:
        below = permutations - np.searchsorted(np.sort(maxima), threshold, side="left")
        family_null = maxima
    p_fwer = np.maximum((1.0 + below) / (1.0 + permutations), p_point)
    if codes is None:
        statistic = statistic_of(measured(*identity)[0][0], q, r, df)
    else:
        statistic = welch_of(*identity)[0][0]
    tfce_p_fwer = None
    if surface is not None:
        enhanced = np.abs(tfce)
        reached = permutations - np.searchsorted(np.sort(enhanced_maxima),
                                                 enhanced - TIES * enhanced, side="left")
        tfce_p_fwer = (1.0 + reached) / (1.0 + permutations)
    return PointTest(value=observed, statistic=statistic, p=p_point, p_fwer=p_fwer,
                     q_fdr=benjamini_hochberg(p_point), effect=effect, df=df,
                     permutations=permutations, family_null=family_null,
                     variance="pooled" if codes is None else "groups",
                     family_wise=family_wise,
                     t=None if observed_t is None else observed_t[0], tail=tail,
                     resampling=resampling_name(codes, blocks, flips, whole_blocks),
                     tfce=tfce, tfce_p_fwer=tfce_p_fwer,
                     tfce_null=None if surface is None else enhanced_maxima)
