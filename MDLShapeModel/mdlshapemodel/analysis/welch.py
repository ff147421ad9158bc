"""Per-point statistics that stay valid when groups differ in variance (the Behrens-Fisher
problem): Welch's v and G with variance groups (Winkler et al. 2014, NeuroImage 92, "Variance
groups"), James' statistic for a vector per point, and the resampling that goes with them.

Pooled-covariance statistics (Student's t, the F, Pillai's trace, Hotelling's T^2) assume one
error variance for all cases. When a small group varies more than a large one, their null
distribution depends on the variances, and permuting cases between the groups does not
recover it: cases of unequal variance are not exchangeable. The statistics here weight each
case by the inverse residual variance of its variance group (the groups compared).

One number per point (q = 1), r effect columns (s = r numerator degrees of freedom), the model
``Y = M psi + E`` with M = [Z X]:

- per variance group g, from the least-squares residuals e = (I - H) y of the full model, the
  weight of each of its cases ``W_nn = (sum_{g} R_nn) / (sum_{g} e_n^2)`` (R = I - H: the
  group's residual degrees of freedom over its residual sum of squares);
- the weighted least-squares estimate ``psi = (M'WM)^-1 M'Wy`` and the Wald statistic of the
  effect's coefficients ``psi_X' [(M'WM)^-1]_XX^-1 psi_X``;
- ``G = Wald / (s Lambda)``, ``Lambda = 1 + 2 (s - 1) / (s (s + 2)) sum_g (1 - sum_g W_nn /
  tr W)^2 / sum_g R_nn``; for s = 1, G = v^2 with v Welch's t (the two-sample case:
  ``(m2 - m1) / sqrt(s1^2 / n1 + s2^2 / n2)``), for one-way layouts Welch's (1951) F. Its
  approximate denominator degrees of freedom are ``nu = s (s + 2) / (3 sum_g (1 - sum_g W_nn /
  tr W)^2 / sum_g R_nn)`` (Welch-Satterthwaite for s = 1).

A vector per point (q > 1) in a one-way layout (the groups compared, nothing adjusted for):
James' (1954) statistic ``J = sum_g (m_g - m)' W_g (m_g - m)`` with ``W_g = n_g S_g^-1`` (S_g
the group's covariance) and ``m = (sum_g W_g)^-1 sum_g W_g m_g``; for two groups
``d' (S_1 / n_1 + S_2 / n_2)^-1 d``, and for q = 1 it is s Lambda G.

Resampling (Winkler et al. 2014, independent and symmetric errors): under the null hypothesis
the cases within a variance group are exchangeable, cases of different groups are not, and each
case's error is as likely as its negative. So the residuals of the reduced model are
sign-flipped case by case and permuted only within the variance groups
(:func:`~.resampling.drawn_flips`);
no case changes group, and each keeps its variance. The reduced model is fitted by weighted least
squares with the variance groups' weights (:func:`reduced_residuals`), so that a small, highly
variable group does not move the others' residuals. The statistic is flipped as ``-log`` of its
parametric p-value under F(s, nu) (:func:`pivotal`; nu differs between points and resamples),
which puts every point on one scale for the maximum over the points; James' J as it is.
"""

from __future__ import annotations

import numpy as np
from scipy import special

# a group's variance at a point is at least this share of the point's total variance, so that a
# group whose cases coincide at a point gives a large statistic, not a division by zero
SMALLEST_VARIANCE = 1e-12


def pivotal(statistic: np.ndarray, s: int, df: np.ndarray) -> np.ndarray:
    """``-log p`` of G under its approximate F(s, df) distribution (larger: more extreme).

    Examples
    --------
    >>> from scipy import stats
    >>> bool(np.isclose(pivotal(np.array([2.5]), 2, np.array([17.3]))[0],
    ...                 -np.log(stats.f.sf(2.5, 2, 17.3))))
    True
    """
    return -np.log(np.maximum(special.fdtrc(s, df, statistic), 1e-300))


def one_sided(v: np.ndarray, df: np.ndarray, tail: str) -> np.ndarray:
    """``-log p`` of Welch's v under Student's t(df), one-sided: ``tail`` "greater" (p = P(T >=
    v)) or "less" (p = P(T <= v)); larger is more extreme.

    Examples
    --------
    >>> from scipy import stats
    >>> bool(np.isclose(one_sided(np.array([2.1]), np.array([9.4]), "greater")[0],
    ...                 -np.log(stats.t.sf(2.1, 9.4))))
    True
    """
    toward = v if tail == "greater" else -v
    return -np.log(np.maximum(special.stdtr(df, -toward), 1e-300))


def lambda_and_df(weights: np.ndarray, sizes: np.ndarray, residual_df: np.ndarray, s: int):
    """Welch's Lambda and the denominator degrees of freedom of G.

    Parameters
    ----------
    weights : ndarray (..., G, p)
        Each variance group's weight per case (its residual df over its residual sum of squares).
    sizes : ndarray (G,)
        Cases per group.
    residual_df : ndarray (..., G, 1) or (G, 1)
        Each group's residual degrees of freedom, sum over its cases of R_nn.
    s : int
        Numerator degrees of freedom (rank of the contrast).

    Returns
    -------
    Lambda, df : ndarray (..., p)
    """
    shares = sizes[:, None] * weights
    shares = shares / shares.sum(axis=-2, keepdims=True)
    spread = np.sum((1.0 - shares) ** 2 / residual_df, axis=-2)
    lam = 1.0 + 2.0 * (s - 1) / (s * (s + 2)) * spread
    return lam, s * (s + 2) / (3.0 * np.maximum(spread, 1e-300))


def reduced_residuals(data: np.ndarray, basis_z: np.ndarray, full: np.ndarray,
                      groups: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """The residuals of the reduced model (the nuisance) fitted by weighted least squares, each
    case weighted by its variance group's inverse residual variance in the full model.

    Parameters
    ----------
    data : ndarray (n, p, q)
    basis_z, full : ndarray (n, z), (n, m)
        Orthonormal bases of the nuisance and of the full model.
    groups, sizes
        Each case's variance group (0 .. G - 1) and the groups' sizes.

    Returns
    -------
    ndarray (n, p, q)
        For q = 1 the weights are one number per group and point; for q > 1 (only with the
        intercept as nuisance) a q x q matrix, the inverse of the group's covariance.
    """
    n, p, q = data.shape
    members = (groups[:, None] == np.arange(len(sizes))).astype(np.float64)   # (n, G)
    flat = data.reshape(n, -1)
    errors = (flat - full @ (full.T @ flat)).reshape(n, p, q)
    residual_df = members.T @ (1.0 - np.sum(full ** 2, axis=1))                 # (G,)
    floor = SMALLEST_VARIANCE * np.einsum("npi,npi->p", data, data) / n
    if q == 1:
        sums = members.T @ errors[..., 0] ** 2                                   # (G, p)
        weights = residual_df[:, None] / np.maximum(sums, floor * residual_df[:, None])
        cross = np.einsum("ng,ni,nj->gij", members, basis_z, basis_z)
        normal = np.einsum("gp,gij->pij", weights, cross)                        # (p, z, z)
        moments = np.einsum("ng,ni,np->gip", members, basis_z, data[..., 0], optimize=True)
        right = np.einsum("gp,gip->pi", weights, moments)
        fitted = basis_z @ np.linalg.solve(normal, right[..., None])[..., 0].T
        return data - fitted[..., None]
    scatter = np.einsum("ng,npi,npj->gpij", members, errors, errors)
    covariance = scatter / residual_df[:, None, None, None] + floor[:, None, None] * np.eye(q)
    weights = np.linalg.inv(covariance)                                          # (G, p, q, q)
    means = np.einsum("ng,npi->gpi", members, data) / sizes[:, None, None]
    weighted = np.einsum("gpij,gpj->gpi", weights * sizes[:, None, None, None], means)
    total = np.einsum("gpij->pij", weights * sizes[:, None, None, None])
    centre = np.linalg.solve(total, weighted.sum(axis=0)[..., None])[..., 0]   # (p, q)
    return data - centre[None]


def small_inverse(matrices: np.ndarray) -> np.ndarray:
    """The inverses of many 2 x 2 or 3 x 3 matrices (..., q, q) by their adjugates, written out
    over the entries (much faster than a batched LAPACK call for so small matrices); other sizes
    by :func:`numpy.linalg.inv`.

    Examples
    --------
    >>> a = np.array([[[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]]])
    >>> bool(np.allclose(small_inverse(a), np.linalg.inv(a)))
    True
    """
    q = matrices.shape[-1]
    m = matrices
    if q == 2:
        determinant = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
        adjugate = np.stack([np.stack([m[..., 1, 1], -m[..., 0, 1]], -1),
                             np.stack([-m[..., 1, 0], m[..., 0, 0]], -1)], -2)
        return adjugate / determinant[..., None, None]
    if q != 3:
        return np.linalg.inv(matrices)
    cofactor = np.empty_like(m)
    for i in range(3):
        for j in range(3):
            r0, r1 = [k for k in range(3) if k != i]
            c0, c1 = [k for k in range(3) if k != j]
            cofactor[..., j, i] = (-1) ** (i + j) * (m[..., r0, c0] * m[..., r1, c1]
                                                     - m[..., r0, c1] * m[..., r1, c0])
    determinant = np.einsum("...j,...j->...", m[..., 0, :], cofactor[..., :, 0])
    return cofactor / determinant[..., None, None]


def one_way(residuals: np.ndarray, groups: np.ndarray, sizes: np.ndarray,
            signs: np.ndarray) -> tuple:
    """Welch's G (q = 1) or James' J (q > 1) of a one-way layout for each sign flip.

    Parameters
    ----------
    residuals : ndarray (n, p, q)
        The reduced model's residuals (:func:`reduced_residuals`).
    groups : ndarray (n,) int
        Each case's group, 0 .. G - 1.
    sizes : ndarray (G,)
        Cases per group.
    signs : ndarray (B, n)
        The flips (permutations within the groups do not change a one-way statistic).

    Returns
    -------
    statistic : ndarray (B, p)
    df : ndarray (B, p) or None
        G's denominator degrees of freedom (None for James' J).
    direction : ndarray (B, p) or None
        For two groups and q = 1, the sign of the second group's mean minus the first's (so
        that ``direction * sqrt(statistic)`` is Welch's v); else None.
    """
    n, p, q = residuals.shape
    count = len(sizes)
    chunk = len(signs)
    flat = residuals.reshape(n, p * q)
    members = (groups[:, None] == np.arange(count)).astype(np.float64)          # (n, G)
    # the flipped groups' sums: one product; their squares and cross products do not flip
    signed = (signs[:, None, :] * members.T[None]).reshape(-1, n)               # (B G, n)
    means = (signed @ flat).reshape(chunk, count, p, q) / sizes[None, :, None, None]
    upper = np.triu_indices(q)
    products = (residuals[:, :, upper[0]] * residuals[:, :, upper[1]]).reshape(n, -1)
    scatter = np.zeros((count, p, q, q))
    scatter[..., upper[0], upper[1]] = (members.T @ products).reshape(count, p, -1)
    scatter[..., upper[1], upper[0]] = scatter[..., upper[0], upper[1]]
    size = sizes[None, :, None]
    # the groups' scatter about their flipped means
    scatter = scatter[None] - size[..., None, None] * means[..., :, None] * means[..., None, :]
    floor = SMALLEST_VARIANCE * np.einsum("npi,npi->p", residuals, residuals) / n
    if q == 1:
        variance = np.maximum(scatter[..., 0, 0] / (size - 1), floor)           # (B, G, p)
        weights = size / variance                                                # n_g / s_g^2
        mean = means[..., 0]
        centre = np.sum(weights * mean, axis=1, keepdims=True) / weights.sum(axis=1,
                                                                              keepdims=True)
        wald = np.sum(weights * (mean - centre) ** 2, axis=1)
        s = count - 1
        lam, df = lambda_and_df(1.0 / variance, sizes, (sizes - 1.0)[:, None], s)
        direction = np.sign(mean[:, 1] - mean[:, 0]) if count == 2 else None
        return wald / (s * lam), df, direction
    covariance = scatter / (size - 1)[..., None, None]
    covariance += floor[:, None, None] * np.eye(q)
    weights = size[..., None, None] * small_inverse(covariance)               # (B, G, p, q, q)
    weighted = np.einsum("bgpij,bgpj->bgpi", weights, means)
    combined = weighted.sum(axis=1)
    centre = np.einsum("bpij,bpj->bpi", small_inverse(weights.sum(axis=1)), combined)
    return (np.einsum("bgpi,bgpi->bp", means, weighted)
            - np.einsum("bpi,bpi->bp", combined, centre)), None, None


def wald_tail(normal: np.ndarray, right: np.ndarray, r: int) -> tuple:
    """The Wald statistic of the last r coefficients of the weighted least-squares problems
    ``normal psi = right``, ``psi_X' [normal^-1]_XX^-1 psi_X``, for many small problems at once,
    and the sign of the last coefficient.

    With the Cholesky factor ``normal = L L'`` and ``u = L^-1 right``, ``[normal^-1]_XX =
    L_XX^-T L_XX^-1`` and ``psi_X = L_XX^-T u_X``, so the statistic is ``|u_X|^2``: the sum of
    squares of the last r entries of u. Written out over the matrix entries, each an array over
    all problems, because the matrices are small (the model's columns) and many (permutations
    x points).

    Parameters
    ----------
    normal : ndarray (m, m, ...)
        Symmetric positive definite matrices (the entries first).
    right : ndarray (m, ...)
    r : int

    Returns
    -------
    wald : ndarray (...)
    direction : ndarray (...)
        The sign of the last coefficient (``u``'s last entry has it: ``L_XX`` is positive).

    Examples
    --------
    >>> a = np.array([[4.0, 1.0], [1.0, 3.0]]); b = np.array([1.0, 2.0])
    >>> psi = np.linalg.solve(a, b)
    >>> wald, direction = wald_tail(a[..., None], b[..., None], 1)
    >>> bool(np.isclose(wald[0], psi[1] ** 2 / np.linalg.inv(a)[1, 1]))
    True
    >>> bool(direction[0] == np.sign(psi[1]))
    True
    """
    m = len(right)
    factor = [[None] * m for _ in range(m)]
    solved = []
    for j in range(m):
        diagonal = np.sqrt(np.maximum(
            normal[j, j] - sum(factor[j][k] ** 2 for k in range(j)), 1e-300))
        factor[j][j] = diagonal
        for i in range(j + 1, m):
            factor[i][j] = (normal[i, j] - sum(factor[i][k] * factor[j][k] for k in range(j))
                            ) / diagonal
        solved.append((right[j] - sum(factor[j][k] * solved[k] for k in range(j))) / diagonal)
    return sum(u ** 2 for u in solved[m - r:]), np.sign(solved[-1])


def general(residuals: np.ndarray, basis: np.ndarray, r: int, groups: np.ndarray,
            sizes: np.ndarray, rows: np.ndarray, signs: np.ndarray) -> tuple:
    """Winkler's G (v^2 for one effect column) of any design with variance groups, one number
    per point, for each resample.

    Parameters
    ----------
    residuals : ndarray (n, p)
        The reduced model's residuals (:func:`reduced_residuals`).
    basis : ndarray (n, m)
        An orthonormal basis of the full model [Z X] whose last r columns span X after Z (the
        Wald statistic of X's coefficients does not depend on the basis of either span).
    r : int
        Effect columns.
    groups, sizes
        As in :func:`one_way`.
    rows, signs : ndarray (B, n)
        The resamples (:func:`~.resampling.drawn_flips`): case i, its residual flipped by
        ``signs[b, i]``, is given the design row of case ``rows[b, i]`` of its own group.

    Returns
    -------
    statistic, df : ndarray (B, p)
        G and its denominator degrees of freedom.
    direction : ndarray (B, p) or None
        For r = 1, the sign of the effect's coefficient on the basis's last column (so that
        ``direction * sqrt(statistic)`` is Welch's v); else None.
    """
    n, p = residuals.shape
    count = len(sizes)
    chunk, m = len(rows), basis.shape[1]
    members = (groups[:, None] == np.arange(count)).astype(np.float64)          # (n, G)
    # a permutation within the groups leaves each group's sums of P_n P_n' and of y_n^2 (P the
    # basis) as they are: only the sums of P_n y_n change, one matrix product for all
    cross = np.einsum("ng,ni,nj->gij", members, basis, basis)                   # (G, m, m)
    squares = members.T @ residuals ** 2                                         # (G, p)
    residual_df = members.T @ (1.0 - np.sum(basis ** 2, axis=1))                 # (G,)
    flipped = basis[rows] * signs[..., None]                                     # (B, n, m)
    split = np.swapaxes(members[None, :, :, None] * flipped[:, :, None, :], 1, 3)  # (B, m, G, n)
    moments = (split.reshape(-1, n) @ residuals).reshape(chunk, m, count, p)
    fit = moments.sum(axis=2)                                                    # P'y (B, m, p)
    # each group's residual sum of squares of the least-squares fit, sum_g (y - P P'y)^2
    sums = (squares[None] - 2.0 * np.einsum("bjp,bjgp->bgp", fit, moments)
            + np.einsum("bjp,gjk,bkp->bgp", fit, cross, fit, optimize=True))
    floor = SMALLEST_VARIANCE * np.sum(residuals ** 2, axis=0) / n
    weights = residual_df[None, :, None] / np.maximum(sums, floor * residual_df[None, :, None])
    # M'WM and M'Wy per point, as sums over the groups, each entry an array over (B, p)
    normal = np.einsum("bgp,gij->ijbp", weights, cross)                         # (m, m, B, p)
    right = np.einsum("bgp,bigp->ibp", weights, moments)                        # (m, B, p)
    wald, direction = wald_tail(normal, right, r)
    lam, df = lambda_and_df(weights, sizes, residual_df[:, None], r)
    return wald / (r * lam), df, direction if r == 1 else None
