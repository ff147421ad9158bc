"""The pooled statistic of the per-point test (:func:`.glm.permutation_test`): Pillai's trace of
the effect after the nuisance,

    V = tr(H (H + E)^-1),   H + E = Y' (I - P_Z) Y,   H = Y' (P_[Z X] - P_Z) Y,

from orthonormal bases of the design's columns and the residuals whitened at each point, so that
each resample's V is the product of its permuted bases with the whitened residuals and q x q
algebra per point; and the statistic reported of it (Hotelling's T^2, F).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError


def orthonormal_basis(columns: np.ndarray, what: str, scale: float | None = None) -> np.ndarray:
    """An orthonormal basis (n, k) of the span of ``columns``; InputError when they are
    collinear (rank below k). ``scale``: the size of the columns before they were made
    orthogonal to others (a column that vanished then was a combination of those)."""
    q, r = np.linalg.qr(columns)
    diagonal = np.abs(np.diag(r))
    reference = max(diagonal.max(initial=0.0), scale or 0.0, 1e-300)
    if diagonal.size and diagonal.min() <= 1e-10 * reference:
        raise InputError(f"{what} are collinear (a column is a combination of the others)")
    return q


def whitening(total: np.ndarray) -> np.ndarray:
    """Per point the inverse Cholesky factor L^-1 of the residual scatter (p, q, q), so that the
    whitened residuals R L^-T have scatter I at every point."""
    q = total.shape[-1]
    scale = np.trace(total, axis1=1, axis2=2) / q
    if np.any(scale <= 0):
        raise InputError("some points do not vary at all across the cases")
    jitter = 1e-12 * scale[:, None, None] * np.eye(q)
    factor = np.linalg.cholesky(total + jitter)
    return np.linalg.inv(factor)


def pillai_trace(coefficients: np.ndarray, z: int) -> np.ndarray:
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
