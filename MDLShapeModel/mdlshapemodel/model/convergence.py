"""Comparing the convergence rates of optimisation strategies (section IV-A, eq. 19).

Two convergence curves, objective value against "time" t (CPU seconds or number of objective
evaluations), of strategies A and B are related by the three-parameter model

.. math:: f_A(t) = a + b\\, f_B(\\alpha t)                                       (19)

so time t of strategy A corresponds to time alpha t of strategy B.

Convention (the paper's): **alpha > 1 means strategy A converges faster** -- A reaches at t what
B reaches only at alpha t > t; alpha < 1 means B converges faster. In the scaling study the
reference strategy plays A and the strategy under test plays B, so alpha is the convergence rate
of B *relative to the reference*, and a higher alpha denotes *poorer* convergence (Figs. 8-11).

Fitting (:func:`fit_alpha`)
    For each candidate alpha, a and b come from linear least squares in closed form (the paper
    uses Gauss-Newton; the model is linear in a and b, so Gauss-Newton reaches this solution in
    one step). The residuals r(tau) = f_A(tau) - a - b f_B(alpha tau) are taken at the times tau
    where both curves are defined (nothing is extrapolated), sampled by *both* curves: A's
    sample times tau with alpha tau inside B's measured range (f_B interpolated at alpha tau)
    and B's sample times s with tau = s / alpha inside A's range (f_A interpolated at s / alpha).
    When both curves start near t = 0 the overlap then always holds all the samples of one of
    them, so it cannot shrink to a few points. An alpha is admissible only when the overlap
    holds at least ``min_points`` samples of each curve.

    The criterion minimised over alpha is, by default (``criterion="relative"``),

        sum_tau r(tau)^2 / (n - 2)  /  var_tau f_A(tau)

    (n points used; a and b take two degrees of freedom), i.e. 1 - adjusted R^2 of the linear
    relation between f_A(tau) and f_B(alpha tau): the *fraction* of A's variation over the
    overlap that eq. (19) leaves unexplained. ``criterion="absolute"`` minimises the paper's
    sum of squares, normalised per degree of freedom, sum r^2 / (n - 2). Dividing by the number
    of points keeps alpha from winning by shrinking the overlap, but with noisy curves the
    absolute criterion still has spurious minima at extreme alpha, where a short, almost
    straight piece of one curve is matched to the whole of the other with b -> 0 (seen in one
    or two bootstrap samples in a hundred on synthetic trials); the relative criterion removes
    them. It is
    moreover symmetric: swapping A and B gives 1/alpha (the point set and R^2 are the same).
    With exact curves both criteria vanish at the true alpha.

    alpha is searched over log(alpha) in ``bounds``: a scan on a regular grid of log(alpha)
    (robust to several local minima and to inadmissible stretches), then a golden-section search
    (as in the paper) within the two grid cells around the best scan point.

Interpolation
    ``kind="linear"`` (default) interpolates linearly between samples, which makes the misfit a
    continuous function of alpha; ``kind="step"`` holds each value until the next sample (the
    objective after the last completed step: exact for step curves, but the misfit is then
    piecewise constant in alpha, which the grid scan tolerates). At repeated times the last value
    counts (a trace records the value after a sweep's rebuild at the same evaluation count).
    Curves need not be monotone.

Standard error (:func:`compare_strategies`)
    Bootstrap (Efron and Tibshirani): each bootstrap sample resamples trials with replacement, as
    pairs (one trial of A, one trial of B); the resampled trials of each strategy are averaged on
    a fixed time grid (:func:`common_grid`, :func:`mean_curve`) and alpha is refitted; the
    standard deviation of the bootstrap alphas is the standard error. By default the two members
    of a pair are drawn independently (n_A draws of A, n_B of B); ``paired=True`` draws one index
    for both, for trials that correspond (same training set and seed). The grid (``n_grid``
    points, regular in t) must resolve the fast early part of the curves: too coarse a grid
    biases alpha through the linear interpolation of convex curves.
    ``spacing="log"`` makes the grid geometric instead (:func:`common_grid`): a time scaling
    then shifts the grid along itself, so a strategy hundreds of times slower than the reference
    still overlaps many grid points of the reference's early curve, and every decade of time
    weighs alike in the fit. It needs curves sampled finely at early times (e.g. traces with
    ``OptimisationSettings.trace_improvements``).

Scaling study (:func:`scaling_study`, :func:`scaling_gradient`)
    alpha of each strategy at each n_s relative to one reference (the paper: III-D4 at
    n_s = 15), and the gradient d alpha / d n_s by weighted least squares with weights
    1 / SE(alpha)^2, its standard error from the SEs taken as absolute (Tables II-III; the
    paper's figures show "a least-squares fit to the points").

Reading traces (:func:`trace_curve`, :func:`read_trace`)
    ``convergence.csv`` (columns of :attr:`mdlshapemodel.correspondence.trace.Trace.HEADER`). Its phases
    optimise different objectives ("fixed": eq. 13, "integrated": eq. 14) on different scales,
    so select one phase to compare. Times count from the start of the whole run.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping

import numpy as np

from ..correspondence.trace import Trace
from ..errors import ArgumentError, InputError
from ..prepare import io

TIME_COLUMNS = ("wall_seconds", "cpu_seconds", "evaluations")
KINDS = ("linear", "step")
CRITERIA = ("relative", "absolute")
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


# ---------------------------------------------------------------------------------------------
# curves


def _as_curve(times, values, name="curve"):
    """Validated (times, values) as float arrays; NaN values dropped; repeated times collapsed."""
    t = np.asarray(times, dtype=float).ravel()
    v = np.asarray(values, dtype=float).ravel()
    if t.shape != v.shape:
        raise ArgumentError(f"{name}: {t.size} times but {v.size} values")
    keep = ~np.isnan(v)
    t, v = t[keep], v[keep]
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
        raise ArgumentError(f"{name}: times and values must be finite")
    if np.any(np.diff(t) < 0):
        raise ArgumentError(f"{name}: times must be non-decreasing")
    if t.size:
        last = np.append(t[1:] != t[:-1], True)  # the last sample at each distinct time
        t, v = t[last], v[last]
    if t.size < 2:
        raise ArgumentError(f"{name}: needs at least two samples at distinct times")
    return t, v


def _interpolate(times, values, at, kind):
    """f(at) of a sampled curve; NaN outside [times[0], times[-1]] (no extrapolation)."""
    at = np.asarray(at, dtype=float)
    out = np.full(at.shape, np.nan)
    inside = (at >= times[0]) & (at <= times[-1])
    if kind == "linear":
        out[inside] = np.interp(at[inside], times, values)
    elif kind == "step":
        out[inside] = values[np.searchsorted(times, at[inside], side="right") - 1]
    else:
        raise ArgumentError(f"kind must be one of {KINDS}, not {kind!r}")
    return out


SPACINGS = ("linear", "log")


def common_grid(curves, n=200, hold_last=False, spacing="linear"):
    """Time grid over the range where every curve is defined, regular in t or in log t.

    Parameters
    ----------
    curves : sequence of (times, values)
        Trials of one strategy.
    n : int
        Number of grid points.
    hold_last : bool
        If true, a curve counts as defined after its last sample (held at its final value: the
        run stopped there because it converged), so the grid ends at the latest last sample.
    spacing : {"linear", "log"}
        "linear": regular in t. "log": the start, then ``n - 1`` points regular in log t from
        the latest *second* sample time of the curves (no grid point falls inside the first
        step of any trial) to the end; needs non-negative times.

    Returns
    -------
    grid : ndarray, shape (n,)
        ``linspace(max_k t_k,first, min_k t_k,last)`` (``max_k t_k,last`` with ``hold_last``),
        or with ``spacing="log"``: ``[max_k t_k,first, geomspace(max_k t_k,second, end, n - 1)]``.
    """
    if n < 2:
        raise ArgumentError("the grid needs at least two points")
    if spacing not in SPACINGS:
        raise ArgumentError(f"spacing must be one of {SPACINGS}, not {spacing!r}")
    checked = [_as_curve(t, v, f"trial {k}") for k, (t, v) in enumerate(curves)]
    if not checked:
        raise ArgumentError("no curves")
    start = max(t[0] for t, _ in checked)
    end = (max if hold_last else min)(t[-1] for t, _ in checked)
    if not end > start:
        raise ArgumentError("the curves share no time range")
    if spacing == "linear":
        return np.linspace(start, end, int(n))
    if start < 0:
        raise ArgumentError("a log-spaced grid needs non-negative times")
    low = max(start, max(t[1] for t, _ in checked))
    if not end > low or n < 3:
        raise ArgumentError("a log-spaced grid needs at least three points and curves that share "
                         "more than their first step")
    return np.concatenate([[start], np.geomspace(low, end, int(n) - 1)])


def mean_curve(curves, grid, kind="linear", hold_last=False):
    """Average of several trials' convergence curves on a common time grid.

    Parameters
    ----------
    curves : sequence of (times, values)
        Trials of one strategy: objective f(t) after each step.
    grid : array_like
        Times t at which to average.
    kind : {"linear", "step"}
        Interpolation between samples (module docstring).
    hold_last : bool
        Hold each curve at its last value after its last sample (see :func:`common_grid`).

    Returns
    -------
    mean : ndarray, same shape as ``grid``
        mean_k f_k(t); NaN where some trial is undefined (before its first or, without
        ``hold_last``, after its last sample). :func:`fit_alpha` ignores NaN values.
    """
    return _trial_matrix(curves, grid, kind, hold_last).mean(axis=0)


def _trial_matrix(curves, grid, kind, hold_last):
    """Values of every trial on ``grid``: shape (n_trials, n_grid), NaN where undefined."""
    grid = np.asarray(grid, dtype=float)
    checked = [_as_curve(t, v, f"trial {k}") for k, (t, v) in enumerate(curves)]
    if not checked:
        raise ArgumentError("no curves")
    return np.stack([_interpolate(t, v, np.minimum(grid, t[-1]) if hold_last else grid, kind)
                     for t, v in checked])


# ---------------------------------------------------------------------------------------------
# eq. (19) for one pair of curves


def _linear_fit(x, y):
    """a, b minimising sum (y - a - b x)^2, that sum, and sum (y - mean y)^2.

    b = 0 when x is constant.
    """
    xm, ym = x.mean(), y.mean()
    dx, dy = x - xm, y - ym
    sxx = float(dx @ dx)
    syy = float(dy @ dy)
    b = float(dx @ dy) / sxx if sxx > 0 else 0.0
    a = float(ym - b * xm)
    r = dy - b * dx
    return a, b, float(r @ r), syy


def _inside(times, values, at, kind):
    """:func:`_interpolate` for sorted times ``at`` known to lie in [times[0], times[-1]]."""
    if kind == "linear":
        return np.interp(at, times, values)
    return values[np.maximum(np.searchsorted(times, at, side="right") - 1, 0)]


class _Misfit:
    """Criterion of eq. (19) as a function of log(alpha) (module docstring)."""

    def __init__(self, ta, fa, tb, fb, kind, min_points, criterion):
        self.ta, self.fa, self.tb, self.fb = ta, fa, tb, fb
        self.kind, self.min_points, self.criterion = kind, min_points, criterion

    def __call__(self, log_alpha):
        return self.fit(log_alpha)[0]

    def fit(self, log_alpha):
        """(criterion, a, b, sum r^2 / (n - 2)); the criterion is inf for inadmissible alpha."""
        alpha = math.exp(log_alpha)
        ta, fa, tb, fb = self.ta, self.fa, self.tb, self.fb
        s = alpha * ta          # A's sample times in B's time
        tau = tb / alpha        # B's sample times in A's time
        a0, a1 = s.searchsorted(tb[0], "left"), s.searchsorted(tb[-1], "right")
        b0, b1 = tau.searchsorted(ta[0], "left"), tau.searchsorted(ta[-1], "right")
        if min(a1 - a0, b1 - b0) < self.min_points:
            return math.inf, math.nan, math.nan, math.nan
        y = np.concatenate([fa[a0:a1], _inside(ta, fa, tau[b0:b1], self.kind)])
        x = np.concatenate([_inside(tb, fb, s[a0:a1], self.kind), fb[b0:b1]])
        a, b, ssr, syy = _linear_fit(x, y)
        n = y.size
        residual = ssr / (n - 2)
        if self.criterion == "absolute":
            return residual, a, b, residual
        return (residual * (n - 1) / syy if syy > 0 else math.inf), a, b, residual


def _golden_section(f, lo, hi, tol):
    """Minimum of f on [lo, hi] by golden-section search to an interval narrower than ``tol``."""
    x1, x2 = hi - _GOLDEN * (hi - lo), lo + _GOLDEN * (hi - lo)
    f1, f2 = f(x1), f(x2)
    while hi - lo > tol:
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - _GOLDEN * (hi - lo)
            f1 = f(x1)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + _GOLDEN * (hi - lo)
            f2 = f(x2)
    return x1 if f1 <= f2 else x2


def fit_alpha(times_a, values_a, times_b, values_b, bounds=(1e-3, 1e3), *, kind="linear",
              min_points=5, criterion="relative", n_scan=241, tol=1e-9):
    """Time scaling alpha between two convergence curves, eq. (19): f_A(t) = a + b f_B(alpha t).

    Parameters
    ----------
    times_a, values_a : array_like
        Curve of strategy A: objective f_A after each step at times t (non-decreasing; CPU
        seconds or number of evaluations). NaN values are ignored.
    times_b, values_b : array_like
        Curve of strategy B, likewise.
    bounds : (float, float)
        Search range of alpha, 0 < low < high; the search is over log(alpha).
    kind : {"linear", "step"}
        Interpolation between samples (module docstring).
    min_points : int
        Least number of samples of each curve in the overlap (>= 3).
    criterion : {"relative", "absolute"}
        Minimise sum r^2 / (n - 2) divided by the variance of f_A over the overlap (default),
        or sum r^2 / (n - 2) itself (module docstring).
    n_scan : int
        Points of the scan of log(alpha) before the golden-section refinement.
    tol : float
        Final bracket width of the golden-section search, in log(alpha).

    Returns
    -------
    alpha : float
        Time scaling: A at t corresponds to B at alpha t; alpha > 1 means A converges faster.
    a, b : float
        Offset and scaling of the objective values.
    residual : float
        sum_tau |f_A(tau) - a - b f_B(alpha tau)|^2 / (n - 2) over the n times tau used
        (mean square residual in units of f_A^2, whichever the criterion).

    Raises
    ------
    ValueError
        Bad input, or no alpha in ``bounds`` gives an admissible overlap.

    Warns
    -----
    RuntimeWarning
        The best alpha lies at an end of ``bounds`` (widen them).
    """
    ta, fa = _as_curve(times_a, values_a, "curve A")
    tb, fb = _as_curve(times_b, values_b, "curve B")
    if kind not in KINDS:
        raise ArgumentError(f"kind must be one of {KINDS}, not {kind!r}")
    if criterion not in CRITERIA:
        raise ArgumentError(f"criterion must be one of {CRITERIA}, not {criterion!r}")
    low, high = (float(x) for x in bounds)
    if not 0 < low < high < math.inf:
        raise ArgumentError(f"bounds must satisfy 0 < low < high, got {bounds}")
    if min_points < 3:
        raise ArgumentError("min_points must be at least 3 (a and b are fitted)")
    misfit = _Misfit(ta, fa, tb, fb, kind, int(min_points), criterion)
    grid = np.linspace(math.log(low), math.log(high), max(int(n_scan), 3))
    values = np.array([misfit(x) for x in grid])
    if not np.any(np.isfinite(values)):
        raise ArgumentError(f"the curves overlap in fewer than {min_points} samples for every alpha "
                         f"in {bounds}")
    k = int(np.argmin(values))
    # refine in the admissible grid cells next to the best scan point
    lo = grid[k - 1] if k > 0 and np.isfinite(values[k - 1]) else grid[k]
    hi = grid[k + 1] if k + 1 < grid.size and np.isfinite(values[k + 1]) else grid[k]
    best = _golden_section(misfit, lo, hi, tol) if hi > lo else grid[k]
    if misfit(best) > values[k]:
        best = grid[k]
    _, a, b, residual = misfit.fit(best)
    if best - grid[0] < 1e-6 or grid[-1] - best < 1e-6:
        warnings.warn(f"alpha = {math.exp(best):.4g} lies at an end of the search range {bounds}",
                      RuntimeWarning, stacklevel=2)
    return math.exp(best), float(a), float(b), float(residual)


# ---------------------------------------------------------------------------------------------
# several trials per strategy: bootstrap standard error


def compare_strategies(trials_a, trials_b, n_bootstrap=100, rng=None, *, paired=False,
                       n_grid=200, spacing="linear", kind="linear", hold_last=False,
                       bounds=(1e-3, 1e3), min_points=5, criterion="relative"):
    """alpha of eq. (19) between the mean curves of two strategies, with a bootstrap SE.

    Parameters
    ----------
    trials_a, trials_b : sequence of (times, values)
        Convergence curves of the trials (runs) of strategies A and B.
    n_bootstrap : int
        Number of bootstrap samples (the paper: 100).
    rng : numpy.random.Generator, int or None
        Source of the resampling (a seed makes the bootstrap reproducible).
    paired : bool
        False: the members of a resampled pair are drawn independently (n_A draws of A's trials,
        n_B of B's). True: trial k of A goes with trial k of B (needs n_A = n_B).
    n_grid : int
        Points of each strategy's time grid (:func:`common_grid`), on which its trials are
        averaged.
    spacing : {"linear", "log"}
        Grid regular in t or in log t (:func:`common_grid`, module docstring).
    kind, hold_last
        See :func:`mean_curve`.
    bounds, min_points, criterion
        See :func:`fit_alpha`.

    Returns
    -------
    dict
        ``alpha``, ``a``, ``b``, ``residual``: :func:`fit_alpha` of the mean curves of all trials;
        ``alpha_se``: standard deviation (ddof = 1) of the bootstrap alphas; ``bootstrap``:
        the bootstrap alphas, shape (n_bootstrap,); ``n_a``, ``n_b``: numbers of trials.
        alpha > 1 means A converges faster.
    """
    trials_a, trials_b = list(trials_a), list(trials_b)
    if not trials_a or not trials_b:
        raise ArgumentError("each strategy needs at least one trial")
    if paired and len(trials_a) != len(trials_b):
        raise ArgumentError(f"paired trials need equal counts, got {len(trials_a)} and "
                         f"{len(trials_b)}")
    grid_a = common_grid(trials_a, n_grid, hold_last, spacing)
    grid_b = common_grid(trials_b, n_grid, hold_last, spacing)
    values_a = _trial_matrix(trials_a, grid_a, kind, hold_last)
    values_b = _trial_matrix(trials_b, grid_b, kind, hold_last)
    options = dict(bounds=bounds, kind=kind, min_points=min_points, criterion=criterion)

    def fit(index_a, index_b):
        return fit_alpha(grid_a, values_a[index_a].mean(axis=0),
                         grid_b, values_b[index_b].mean(axis=0), **options)

    n_a, n_b = len(trials_a), len(trials_b)
    alpha, a, b, residual = fit(np.arange(n_a), np.arange(n_b))
    rng = np.random.default_rng(rng)
    boot = np.empty(int(n_bootstrap))
    for r in range(boot.size):
        index_a = rng.integers(n_a, size=n_a)
        index_b = index_a if paired else rng.integers(n_b, size=n_b)
        boot[r] = fit(index_a, index_b)[0]
    se = float(np.std(boot, ddof=1)) if boot.size > 1 else math.nan
    return {"alpha": alpha, "alpha_se": se, "a": a, "b": b, "residual": residual,
            "bootstrap": boot, "n_a": n_a, "n_b": n_b}


# ---------------------------------------------------------------------------------------------
# scaling with the number of training shapes (Tables II-III)


def scaling_gradient(n_shapes, alphas, alpha_ses=None, *, absolute_sigma=True):
    """Gradient of alpha against the number of training shapes n_s by weighted least squares.

    Fits alpha = intercept + gradient * n_s with weights 1 / SE(alpha)^2.

    Parameters
    ----------
    n_shapes : array_like
        Training set sizes n_s (at least two distinct values).
    alphas : array_like
        alpha at each n_s (relative to one reference strategy).
    alpha_ses : array_like or None
        Standard errors of the alphas (all > 0). None: ordinary least squares, with the
        standard errors estimated from the scatter about the line (needs three points).
    absolute_sigma : bool
        With ``alpha_ses``: True takes them as absolute, so cov = (X^T W X)^-1; False scales
        that by the reduced chi-square (needs three points).

    Returns
    -------
    dict
        ``gradient``, ``gradient_se``, ``intercept``, ``intercept_se``; ``chi2`` (weighted
        sum of squared residuals) and ``dof`` (number of points - 2).
    """
    x = np.asarray(n_shapes, dtype=float).ravel()
    y = np.asarray(alphas, dtype=float).ravel()
    if x.shape != y.shape:
        raise ArgumentError(f"{x.size} n_s but {y.size} alphas")
    if np.unique(x).size < 2:
        raise ArgumentError("the gradient needs at least two distinct n_s")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ArgumentError("n_s and alpha must be finite")
    if alpha_ses is None:
        w = np.ones_like(x)
        scaled = True
    else:
        se = np.asarray(alpha_ses, dtype=float).ravel()
        if se.shape != x.shape:
            raise ArgumentError(f"{x.size} n_s but {se.size} standard errors")
        if not np.all(se > 0) or not np.all(np.isfinite(se)):
            raise ArgumentError("standard errors must be positive and finite")
        w = 1.0 / se ** 2
        scaled = not absolute_sigma
    design = np.column_stack([np.ones_like(x), x])
    normal = design.T @ (w[:, None] * design)
    cov = np.linalg.inv(normal)
    intercept, gradient = cov @ (design.T @ (w * y))
    residual = y - intercept - gradient * x
    chi2 = float(w @ residual ** 2)
    dof = x.size - 2
    if scaled:
        if dof < 1:
            raise ArgumentError("standard errors from the scatter need at least three points")
        cov = cov * chi2 / dof
    return {"gradient": float(gradient), "gradient_se": float(math.sqrt(cov[1, 1])),
            "intercept": float(intercept), "intercept_se": float(math.sqrt(cov[0, 0])),
            "chi2": chi2, "dof": dof}


def scaling_study(reference, runs, n_bootstrap=100, rng=None, **options):
    """alpha of each strategy and n_s relative to one reference, and its gradient in n_s.

    Parameters
    ----------
    reference : sequence of (times, values)
        Trials of the reference strategy (the paper: III-D4, one example at a time with pose,
        at n_s = 15). It plays A in eq. (19).
    runs : mapping
        ``{strategy: {n_s: trials}}``; each strategy plays B, so a higher alpha denotes
        poorer convergence than the reference.
    n_bootstrap, rng
        See :func:`compare_strategies`; one generator serves all comparisons in turn.
    **options
        Passed to :func:`compare_strategies`.

    Returns
    -------
    dict
        ``{strategy: {"n_shapes", "alpha", "alpha_se": arrays in increasing n_s, "a", "b",
        "gradient", "gradient_se", "intercept"}}``; the gradient entries are NaN with fewer
        than two n_s.
    """
    rng = np.random.default_rng(rng)
    study = {}
    for strategy, by_size in runs.items():
        sizes = sorted(by_size)
        results = [compare_strategies(reference, by_size[n], n_bootstrap, rng, **options)
                   for n in sizes]
        entry = {"n_shapes": np.array(sizes, dtype=float)}
        for key in ("alpha", "alpha_se", "a", "b"):
            entry[key] = np.array([r[key] for r in results])
        entry.update(gradient=math.nan, gradient_se=math.nan, intercept=math.nan)
        if len(sizes) >= 2:
            line = scaling_gradient(entry["n_shapes"], entry["alpha"], entry["alpha_se"])
            entry.update({k: line[k] for k in ("gradient", "gradient_se", "intercept")})
        study[strategy] = entry
    return study


# ---------------------------------------------------------------------------------------------
# convergence.csv


def trace_curve(rows, time="cpu_seconds", phase=None):
    """Convergence curve (times, objective values) from the rows of a convergence trace.

    Parameters
    ----------
    rows : iterable
        Rows of ``convergence.csv`` as read by :func:`mdlshapemodel.io.read_csv` (mappings of
        column name to text), or tuples in the order of ``Trace.HEADER`` (``Trace.rows``).
    time : {"cpu_seconds", "evaluations", "wall_seconds"}
        Column giving t.
    phase : str, collection of str, or None
        Keep only rows of these phases ("fixed": eq. 13; "integrated": eq. 14; "coarse fixed"
        and "coarse integrated" on the coarse grid); None keeps every row. Phases optimise differently scaled
        objectives, so compare one phase at a time.

    Returns
    -------
    times, values : ndarray
        t and the objective F of the selected rows, in trace order.

    Raises
    ------
    InputError
        A column is missing or not numeric, no row is selected, or the times decrease.
    """
    if time not in TIME_COLUMNS:
        raise ArgumentError(f"time must be one of {TIME_COLUMNS}, not {time!r}")
    phases = None if phase is None else ({phase} if isinstance(phase, str) else set(phase))
    times, values = [], []
    for number, row in enumerate(rows, start=1):
        if not isinstance(row, Mapping):
            row = dict(zip(Trace.HEADER, row))
        try:
            if phases is not None and row["phase"] not in phases:
                continue
            times.append(float(row[time]))
            values.append(float(row["objective"]))
        except KeyError as error:
            raise InputError(f"convergence trace row {number} has no column {error}") from None
        except (TypeError, ValueError):
            raise InputError(f"convergence trace row {number}: {time} or objective is not a "
                             "number") from None
    if not times:
        raise InputError("no convergence trace rows" +
                         ("" if phases is None else f" of phase {', '.join(sorted(phases))}"))
    times, values = np.array(times), np.array(values)
    if np.any(np.diff(times) < 0):
        raise InputError(f"convergence trace: {time} decreases")
    return times, values


def read_trace(path, time="cpu_seconds", phase="integrated"):
    """:func:`trace_curve` of a ``convergence.csv`` file (by default its eq.-14 phase)."""
    return trace_curve(io.read_csv(path), time, phase)
