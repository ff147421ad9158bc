"""How the residuals of a per-point test are resampled (:func:`.glm.permutation_test`): the
permutations of Freedman and Lane (1983), sign flips (independent and symmetric errors), both
within variance groups or exchangeability blocks, and permutations of whole blocks (Winkler et
al. 2014).

A resample is ``rows`` (case i is given the design row, and variance group, of case
``rows[b, i]``, against the fixed residuals of the reduced model) and ``signs`` (+1 or -1 per
case: the flipped residuals are ``signs * residuals``; None when nothing is flipped). Every draw
comes from ``numpy.random.default_rng(seed)``, :data:`CHUNK` resamples at a time.
"""

from __future__ import annotations

import numpy as np

# permutations handled at once: bounds the memory to CHUNK x (z + r) x p x q floats; fixed so
# that the drawn permutations (and so the p-values) do not depend on it changing
CHUNK = 250


def drawn_permutations(n: int, permutations: int, seed: int):
    """The permutations :func:`.glm.permutation_test` draws, chunk by chunk.

    Yields arrays (count, n) of :data:`CHUNK` rows (fewer in the last): in permutation b, case
    i is given the design row (and variance group) of case ``rows[b, i]``, against the fixed
    residuals of the reduced model; a plain loop over them recomputes every permuted statistic.

    Examples
    --------
    >>> rows = np.vstack(list(drawn_permutations(5, 300, seed=0)))
    >>> rows.shape, sorted(rows[0].tolist())
    ((300, 5), [0, 1, 2, 3, 4])
    """
    rng = np.random.default_rng(seed)
    done = 0
    while done < permutations:
        count = min(CHUNK, permutations - done)
        yield np.argsort(rng.random((CHUNK, n)), axis=1)[:count]
        done += count


def drawn_flips(groups: np.ndarray, count: int, seed: int):
    """The resamples of a test with variance groups, chunk by chunk: each a permutation within
    the groups and a sign per case.

    Parameters
    ----------
    groups : ndarray (n,) int
        Each case's variance group.
    count : int
        Resamples drawn (B).
    seed : int

    Yields
    ------
    rows : ndarray (b, n)
        Case i is given the design row of case ``rows[j, i]``, a case of its own group.
    signs : ndarray (b, n)
        +1 or -1 per case: the flipped data are ``signs * residuals``.

    Examples
    --------
    >>> groups = np.array([0, 0, 1, 1, 1])
    >>> rows, signs = next(drawn_flips(groups, 100, seed=0))
    >>> bool(np.all(groups[rows] == groups)), sorted(np.unique(signs).tolist())
    (True, [-1.0, 1.0])
    """
    rng = np.random.default_rng(seed)
    n = len(groups)
    order = np.argsort(groups, kind="stable")
    done = 0
    while done < count:
        size = min(CHUNK, count - done)
        keys = rng.random((CHUNK, n)) + 2.0 * groups[order]
        rows = np.empty((CHUNK, n), dtype=np.int64)
        rows[:, order] = order[np.argsort(keys, axis=1)]
        signs = rng.integers(0, 2, (CHUNK, n)) * 2.0 - 1.0
        yield rows[:size], signs[:size]
        done += size


def drawn_signs(n: int, count: int, seed: int):
    """Sign flips alone, chunk by chunk: each case's residual kept or negated at random, no
    case moved (the one-sample test; independent and symmetric errors).

    Yields
    ------
    rows : ndarray (b, n)
        The identity (every case keeps its own design row).
    signs : ndarray (b, n)
        +1 or -1 per case.

    Examples
    --------
    >>> rows, signs = next(drawn_signs(4, 300, seed=0))
    >>> rows.shape, bool(np.all(rows == np.arange(4))), sorted(np.unique(signs).tolist())
    ((250, 4), True, [-1.0, 1.0])
    """
    rng = np.random.default_rng(seed)
    done = 0
    while done < count:
        size = min(CHUNK, count - done)
        signs = rng.integers(0, 2, (CHUNK, n)) * 2.0 - 1.0
        yield np.broadcast_to(np.arange(n), (size, n)), signs[:size]
        done += size


def drawn_whole_blocks(blocks: np.ndarray, count: int, seed: int):
    """Permutations of whole blocks, chunk by chunk: each block's cases take the design rows of
    another block of the same size, case by case in their order (Winkler et al. 2014, whole-block
    exchangeability: a subject's cases stay together).

    Yields
    ------
    rows : ndarray (b, n)
        Case i is given the design row of case ``rows[j, i]``.
    signs : None

    Examples
    --------
    >>> blocks = np.array([0, 0, 1, 1, 2, 2, 2])
    >>> rows, _ = next(drawn_whole_blocks(blocks, 100, seed=0))
    >>> moved = blocks[rows]
    >>> bool(np.all(moved[:, 4:] == 2)), bool(np.all(moved[:, 0] == moved[:, 1]))
    (True, True)
    """
    blocks = np.asarray(blocks)
    members = [np.flatnonzero(blocks == b) for b in range(int(blocks.max()) + 1)]
    sizes = {len(m) for m in members}
    rng = np.random.default_rng(seed)
    done = 0
    while done < count:
        size = min(CHUNK, count - done)
        rows = np.empty((CHUNK, len(blocks)), dtype=np.int64)
        for length in sorted(sizes):
            alike = [m for m in members if len(m) == length]
            cases = np.array(alike)                                   # (blocks, length)
            order = np.argsort(rng.random((CHUNK, len(alike))), axis=1)
            rows[:, cases.reshape(-1)] = cases[order].reshape(CHUNK, -1)
        yield rows[:size], None
        done += size


def drawn_resamples(n: int, count: int, seed: int, codes, blocks, flips: bool,
                    whole_blocks: bool = False):
    """The resamples of one test: (rows, signs) chunks, ``signs`` None when nothing is flipped.

    Variance groups: permutations within the groups with sign flips (:func:`drawn_flips`).
    Exchangeability blocks: permutations within the blocks (and within the groups, when both),
    with sign flips if ``flips``. Flips alone: :func:`drawn_signs`. Whole blocks:
    :func:`drawn_whole_blocks`. Else all permutations.
    """
    if whole_blocks:
        return drawn_whole_blocks(blocks, count, seed)
    if codes is None and blocks is None:
        if flips:
            return drawn_signs(n, count, seed)
        return ((rows, None) for rows in drawn_permutations(n, count, seed))
    cells = np.zeros(n, dtype=np.int64)
    for codes_of in (codes, blocks):
        if codes_of is not None:
            cells = cells * (int(codes_of.max()) + 1) + codes_of
    cells = np.unique(cells, return_inverse=True)[1]
    draws = drawn_flips(cells, count, seed)
    if codes is not None or flips:
        return draws
    return ((rows, None) for rows, _ in draws)


def resampling_name(codes, blocks, flips: bool, whole_blocks: bool = False) -> str:
    """How the residuals are resampled, in words (for analysis.json and the page)."""
    if whole_blocks:
        return "permuted in whole blocks"
    flipped = codes is not None or flips
    moved = ("" if codes is None and blocks is None and flips else
             "permuted within the variance groups and blocks" if codes is not None
             and blocks is not None else
             "permuted within the variance groups" if codes is not None else
             "permuted within the blocks" if blocks is not None else "permuted")
    if flipped and moved:
        return f"sign-flipped and {moved}"
    return "sign-flipped" if flipped else moved
