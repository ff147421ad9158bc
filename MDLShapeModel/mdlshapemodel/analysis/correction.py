"""Corrections for testing every point (:func:`.glm.permutation_test`): Benjamini-Hochberg
q-values (the false discovery rate), and each resample's smallest per-point p-value, each point's
statistic ranked against its own permutation distribution (min-p, Westfall and Young 1993: the
null distribution of the family-wise test that no point dominates).
"""

from __future__ import annotations

import numpy as np

# per-point p-values of the permuted statistics are ranked this many points at a time (bounds the
# memory of the sort to BLOCK x (B + 1) indices)
BLOCK = 256


def benjamini_hochberg(p: np.ndarray) -> np.ndarray:
    """Benjamini-Hochberg q-values (adjusted p-values) of a vector of p-values.

    q_(i) = min over j >= i of p_(j) m / j, capped at 1 (Benjamini and Hochberg 1995); a point
    is significant at false-discovery rate alpha when q <= alpha. Computed by
    ``scipy.stats.false_discovery_control(p, method="bh")``.

    Examples
    --------
    >>> benjamini_hochberg(np.array([0.01, 0.04, 0.03, 0.5])).round(3).tolist()
    [0.04, 0.053, 0.053, 0.5]
    """
    from scipy.stats import false_discovery_control

    p = np.asarray(p, dtype=np.float64)
    if p.size == 0:
        return p.copy()
    return np.asarray(false_discovery_control(p, method="bh"), dtype=np.float64)


def smallest_p(table: np.ndarray) -> np.ndarray:
    """Each row's smallest per-point p-value, every column's values ranked against that column.

    Parameters
    ----------
    table : ndarray (m, p)
        m values of a statistic at each of p points (larger: more extreme).

    Returns
    -------
    ndarray (m,) int
        For each row, the smallest over the points of #{rows whose value at the point is at
        least the row's}: the row's smallest p-value times m.

    Examples
    --------
    >>> smallest_p(np.array([[3.0, 0.0], [1.0, 5.0], [2.0, 5.0]])).tolist()
    [1, 2, 2]
    """
    m, p = table.shape
    index = np.arange(m)[:, None]
    smallest = np.full(m, m, dtype=np.int64)
    for start in range(0, p, BLOCK):
        block = table[:, start:start + BLOCK]
        order = np.argsort(block, axis=0)
        ordered = np.take_along_axis(block, order, axis=0)
        starts = np.ones(ordered.shape, dtype=bool)
        starts[1:] = ordered[1:] != ordered[:-1]
        # values below a row's: the position where its run of equal values starts
        below = np.maximum.accumulate(np.where(starts, index, 0), axis=0)
        counts = np.empty_like(below)
        np.put_along_axis(counts, order, m - below, axis=0)
        smallest = np.minimum(smallest, counts.min(axis=1))
    return smallest
