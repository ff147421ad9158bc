"""Limited-memory quasi-Newton minimisation within box bounds, for the fast strategy's rounds.

A projected L-BFGS: the search direction is the two-loop recursion of L-BFGS (Nocedal 1980)
applied to the projected gradient (0 on the variables held at a bound by a gradient pushing
outwards) and kept at 0 on those variables; the step is projected back into the box and accepted
by the Armijo condition along the projected path, each rejected step shortened tenfold where F
rose, else to the minimiser of the parabola that fits it (within [0.1, 0.5] of it). Curvature
pairs (s, y) are kept only where s.y > 0, so the implied inverse Hessian stays positive definite.

The pairs are most of a large round's memory (``memory`` pairs of two vectors of the round's
size). They can be kept in single precision (:func:`pair_dtype`): their products and scalars are
still formed in double precision, so the direction changes only by the rounding of s and y,
and the line search, its Armijo test and the bounds work on the double-precision point.

Why not SciPy's L-BFGS-B: a round of the fast strategy has up to about 160,000 parameters (field
coefficients of every example at the finest level), and there SciPy's routine spends tens of
milliseconds per iteration in its own bookkeeping (its generalized Cauchy point over all
breakpoints, and the conversion of the bounds, element by element in Python, on every call):
more than an evaluation of the objective. Here an iteration costs a few vector operations of
length n per stored pair. The arithmetic is plain numpy in a fixed order: the same inputs give the
same iterates on any machine with the same libraries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...config import CURVATURE_PAIRS, SINGLE_PRECISION_PAIRS_FROM
from ...errors import ArgumentError

#: Armijo's sufficient-decrease constant (the usual 1e-4)
ARMIJO = 1e-4
#: the largest number of step reductions in one line search (each by a factor in [0.1, 0.5])
MAX_BACKTRACKS = 10


def _backtrack(value: float, trial_value: float, predicted: float) -> float:
    """The factor of the next, shorter step. Where F at the trial is above F at the start (or not
    finite), 0.1: the linear model is wrong at that length, and a parabola through the two values
    and the slope would put its minimum near half of it whenever the predicted decrease is large,
    which on a kinked objective (eq. 14's range terms with hundreds of small modes, or a small
    mode's cost, whose slope grows as 1/sigma) halves the step for many evaluations. Otherwise
    (F lower, but not by enough) the minimiser of that parabola, kept within [0.1, 0.5]."""
    if not np.isfinite(trial_value) or trial_value > value:
        return 0.1
    curvature = trial_value - value - predicted
    if curvature <= 0.0:
        return 0.5
    return min(max(-predicted / (2.0 * curvature), 0.1), 0.5)


@dataclass
class BoxResult:
    """The end of :func:`minimize_box`: the best point, its value and gradient, the iterations
    done, and why it stopped: ``"iterations"`` (``max_iterations`` reached), ``"ftol"`` (the
    relative decrease of an iteration fell below ``ftol``), ``"gtol"`` (the projected gradient is
    below ``gtol``) or ``"line search"`` (no step along the direction decreased F)."""

    x: np.ndarray
    value: float
    gradient: np.ndarray
    iterations: int
    stop: str


def projected_gradient(x: np.ndarray, gradient: np.ndarray, lower: np.ndarray,
                       upper: np.ndarray) -> np.ndarray:
    """The gradient with the components that push against an active bound set to 0."""
    held = ((x <= lower) & (gradient > 0)) | ((x >= upper) & (gradient < 0))
    return np.where(held, 0.0, gradient)


def pair_dtype(choice: str, size: int) -> type:
    """The precision of the curvature pairs of a round of ``size`` variables.

    ``choice`` is :data:`~mdlshapemodel.config.CURVATURE_PAIRS`' kind: ``"double"``,
    ``"single"`` (half the memory; the optimisation's path changes by the rounding of the
    pairs), or ``"auto"``: single from :data:`~mdlshapemodel.config.SINGLE_PRECISION_PAIRS_FROM`
    variables, where the pairs in double precision would hold several hundred megabytes.

    Examples
    --------
    >>> pair_dtype("auto", 1000).__name__, pair_dtype("single", 1000).__name__
    ('float64', 'float32')
    """
    if choice not in CURVATURE_PAIRS:
        raise ArgumentError(f"pair_dtype: {choice!r} is not one of {', '.join(CURVATURE_PAIRS)}")
    if choice == "single" or (choice == "auto" and size >= SINGLE_PRECISION_PAIRS_FROM):
        return np.float32
    return np.float64


@dataclass
class CurvaturePair:
    """One stored step ``s`` and gradient change ``y`` (in the round's pair precision), with
    ``rho`` = 1 / s.y and ``scale`` = s.y / y.y, both from the double-precision s and y."""

    s: np.ndarray
    y: np.ndarray
    rho: float
    scale: float


def _direction(projected: np.ndarray, pairs: list) -> np.ndarray:
    """-H g by the two-loop recursion over the stored :class:`CurvaturePair` (oldest first),
    with the initial scaling s.y / y.y of the newest pair, applied to the projected gradient and
    held at 0 on the variables that the projection holds at a bound. Every product is formed in
    double precision (single-precision pairs are widened by numpy's type promotion)."""
    q = projected.copy()
    alphas = []
    for pair in reversed(pairs):
        alpha = pair.rho * np.dot(pair.s, q)
        q -= alpha * pair.y
        alphas.append(alpha)
    if pairs:
        q *= pairs[-1].scale
    for pair, alpha in zip(pairs, reversed(alphas)):
        beta = pair.rho * np.dot(pair.y, q)
        q += (alpha - beta) * pair.s
    q[projected == 0.0] = 0.0
    return -q


def minimize_box(fun, x0: np.ndarray, lower: np.ndarray | None, upper: np.ndarray,
                 max_iterations: int = 30, memory: int = 10, ftol: float = 1e-9,
                 gtol: float = 1e-10, pairs_dtype: type = np.float64) -> BoxResult:
    """Minimise ``fun`` (x -> (value, gradient)) over lower <= x <= upper (infinite bounds allowed).

    Parameters
    ----------
    fun : callable
        Returns F(x) and dF/dx. Exceptions it raises pass through (e.g. a time limit).
    x0 : ndarray
        The start, projected into the box.
    lower, upper : ndarray
        The bounds, lower <= upper. ``lower`` None: the symmetric box -upper <= x <= upper, whose
        lower bounds are formed where they are used rather than held (one vector of the size of
        x less through the minimisation: a large round's fields have tens of millions of
        coefficients); the same iterates as with ``lower = -upper`` given.
    max_iterations : int
        Iterations at most (each one line search: usually one evaluation).
    memory : int
        Curvature pairs kept.
    ftol : float
        Stop when an iteration lowers F by at most ftol * max(|F|, |F_new|, 1).
    gtol : float
        Stop when the largest component of the projected gradient is at most this.
    pairs_dtype : numpy type
        The precision the curvature pairs are kept in (:func:`pair_dtype`).

    Returns
    -------
    BoxResult

    Examples
    --------
    >>> import numpy as np
    >>> result = minimize_box(lambda x: (float(np.sum((x - 2.0) ** 2)), 2.0 * (x - 2.0)),
    ...                       np.zeros(3), np.full(3, -1.0), np.array([1.0, 5.0, 5.0]))
    >>> np.round(result.x, 6).tolist()
    [1.0, 2.0, 2.0]
    """
    upper = np.asarray(upper, dtype=np.float64)
    if lower is None:
        if np.any(upper < 0.0):
            raise ArgumentError("minimize_box: a symmetric box needs upper bounds >= 0")

        def low():
            return -upper
    else:
        lower = np.asarray(lower, dtype=np.float64)
        if np.any(lower > upper):
            raise ArgumentError("minimize_box: a lower bound exceeds its upper bound")

        def low():
            return lower
    x = np.clip(np.asarray(x0, dtype=np.float64), low(), upper)
    value, gradient = fun(x)
    pairs: list = []
    for iteration in range(max_iterations):
        projected = projected_gradient(x, gradient, low(), upper)
        if np.max(np.abs(projected), initial=0.0) <= gtol:
            return BoxResult(x, value, gradient, iteration, "gtol")
        direction = _direction(projected, pairs)
        slope = np.dot(projected, direction)
        if not pairs or slope >= 0.0:
            # no curvature yet, or a direction that does not descend: steepest descent, with a
            # first step of unit length (as L-BFGS-B's first iteration)
            pairs.clear()
            direction = -projected
            step = 1.0 / max(np.linalg.norm(direction), 1e-300)
        else:
            step = 1.0
        del projected       # not needed by the line search, whose evaluations hold their own
        for _ in range(MAX_BACKTRACKS):
            trial = np.clip(x + step * direction, low(), upper)
            trial_value, trial_gradient = fun(trial)
            predicted = np.dot(gradient, trial - x)
            if trial_value <= value + ARMIJO * min(predicted, 0.0) and trial_value < value:
                break
            step *= _backtrack(value, trial_value, predicted)
        else:
            return BoxResult(x, value, gradient, iteration, "line search")
        s, y = trial - x, trial_gradient - gradient     # double precision
        curvature = np.dot(s, y)
        if curvature > 1e-10 * np.linalg.norm(s) * np.linalg.norm(y):
            pairs.append(CurvaturePair(s.astype(pairs_dtype, copy=False),
                                       y.astype(pairs_dtype, copy=False), 1.0 / curvature,
                                       curvature / np.dot(y, y)))
            if len(pairs) > memory:
                pairs.pop(0)
        decrease = value - trial_value
        x, value, gradient = trial, trial_value, trial_gradient
        if decrease <= ftol * max(abs(value), abs(value + decrease), 1.0):
            return BoxResult(x, value, gradient, iteration + 1, "ftol")
    return BoxResult(x, value, gradient, max_iterations, "iterations")
