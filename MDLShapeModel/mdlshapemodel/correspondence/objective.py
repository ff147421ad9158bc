"""The MDL objective function (section III-B; docs/method.md section 2).

For each mode m of the training set, with coded values Y_im (the n_s projections of the centred shapes
on mode m, so that (1/n_s) sum_i Y_im^2 = lambda_m = sigma_m^2), the description length is

- sigma_min = 2 Delta, sigma_max = R / 2 (R: range of the data), delta = min(1, sigma sqrt(12 / n_s));
- parameter cost L_param = ln((sigma_max - sigma_min) / delta) + 1 + |ln delta|;
- case 1, sigma_m > sigma_min (delta from sigma_m):
  L_data = -n_s ln Delta + (n_s/2) ln(2 pi sigma_m^2) + n_s/2 + n_s delta^2 / (12 sigma_m^2);
- case 2, sigma_m <= sigma_min (delta from sigma_min):
  L_data = -n_s ln Delta + (n_s/2) ln(2 pi sigma_min^2) + sum_i Y_im^2 / (2 sigma_min^2)
  + n_s delta^2 / (12 sigma_min^2);
- case 3, range of Y_m below Delta: the mode costs nothing.

Our default (``variant="continuous"``) keeps the term n_s delta^2 / (12 sigma_min^2) in case 2 and uses
the unquantised Y, which makes the cost continuous in sigma at sigma = sigma_min (the published
MATLAB code omits that term and quantises Y to Yhat = Delta round(Y / Delta), which gives a jump of
about 1 nat there; ``variant="reference"`` reproduces it). With delta < 1, case 1 reduces to the
paper's eq. 13.

The paper's objective (eq. 14) is the mean of F_MDL(Delta) over Delta uniform in
[Delta_min, Delta_max]. With the continuous variant every piece of the integrand is a combination of
ln(sigma_max - 2 Delta), ln Delta, 1 / Delta^2 and constants, so the average is computed exactly,
piece by piece (breaks at Delta = sigma_m / 2, Delta = range_m and Delta = 1 / (2 sqrt(12 / n_s))).
Logarithms are natural (nats).

Past the switch to the covariance route (:func:`covariance_route`), the three products with the
n_s x d data A (A^T A, the coded values A W and the gradient Y M) run in fixed blocks on
``Objective.threads`` threads, each block on one BLAS thread: the blocks do not depend on the
number of threads, so neither do the results (threaded BLAS itself gives other bits on 2 threads
than on 1). The d x d eigendecomposition stays on one thread. Within :meth:`Objective.pooled`
(the whole of :func:`~.strategies.optimise`; for eq. 14, the whole of a build's
:func:`~mdlshapemodel.build.correspond`, which measures it before and after) every evaluation
uses one pool of threads; outside it, each evaluation past the switch starts and ends its own.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError
from ..parallel import Threads

#: Rows of A (and of the coded values) per block of the products A W and Y M past the switch.
ROW_BLOCK = 256
#: Blocks of columns of A^T A past the switch (each the same work: with fewer, one BLAS call
#: packs fewer copies of A; with more, more threads share the work evenly).
COLUMN_BLOCKS = 4


def mode_statistics(coded: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """sigma_m, range_m and sum_i Y_im^2 of coded values Y (n_s, n_modes)."""
    coded = np.asarray(coded, dtype=np.float64)
    sum_squares = np.sum(coded * coded, axis=0)
    sigma = np.sqrt(sum_squares / coded.shape[0])
    ranges = np.ptp(coded, axis=0)
    return sigma, ranges, sum_squares


def _check_range(delta: float, data_range: float):
    if not data_range / 2.0 > 2.0 * delta:
        raise ConfigError(f"delta: the coding accuracy {delta:g} must be below a quarter of the data "
                          f"range {data_range:g} (sigma_max = R/2 must exceed sigma_min = 2 Delta)")


def _cost_terms(sigma, sum_squares, n_s, delta, data_range):
    """Pieces of the per-mode cost at coding accuracy ``delta`` (scalar, or one per mode):
    the case-1 mask, L_param, the common data term, and the case-1 and (continuous) case-2 L_data."""
    sigma_min = 2.0 * delta
    sigma_max = data_range / 2.0
    k = np.sqrt(12.0 / n_s)
    case1 = sigma > sigma_min
    sigma_used = np.where(case1, sigma, sigma_min)
    small = np.minimum(1.0, sigma_used * k)  # the parameter precision delta
    param = np.log((sigma_max - sigma_min) / small) + 1.0 + np.abs(np.log(small))
    base = -n_s * np.log(delta) + 0.5 * n_s * np.log(2 * np.pi * sigma_used ** 2)
    precision_term = n_s * small ** 2 / (12.0 * sigma_used ** 2)
    data1 = base + 0.5 * n_s + precision_term
    data2 = base + sum_squares / (2 * sigma_min ** 2) + precision_term
    return case1, param, base, data1, data2


def _case1_slope(sigma, n_s):
    """d(L_param + L_data)/d sigma in case 1 (delta from sigma; Delta drops out):
    (n_s - 2) / sigma while delta = sigma sqrt(12/n_s) < 1, else n_s / sigma - n_s / (6 sigma^3)."""
    sigma = np.where(sigma > 1e-100, sigma, 1.0)   # never used there: avoids 1 / 0
    return np.where(sigma * np.sqrt(12.0 / n_s) < 1.0, (n_s - 2.0) / sigma,
                    n_s / sigma - n_s / (6.0 * sigma ** 3))


def mode_costs(coded: np.ndarray, delta: float, data_range: float,
               variant: str = "continuous", free_below_delta: bool = True) -> np.ndarray:
    """Description length (nats) of each mode at coding accuracy ``delta``.

    Parameters
    ----------
    coded : ndarray (n_s, n_modes)
        Coded values Y_im of every shape on every mode.
    delta : float
        Coding accuracy Delta, in the units of the shapes.
    data_range : float
        R, the range of the data (same units); sigma_max = R / 2.
    variant : {"continuous", "reference"}
        See the module docstring.
    free_below_delta : bool
        Case 3: a mode whose coded values span less than Delta costs nothing (thesis form).
        Without it, every mode is coded by case 1 or 2, as in the paper's eq. 13.
    """
    _check_range(delta, data_range)
    coded = np.asarray(coded, dtype=np.float64)
    n_s = coded.shape[0]
    sigma, ranges, sum_squares = mode_statistics(coded)
    sigma_min = 2.0 * delta
    case1, param, base, data1, data2 = _cost_terms(sigma, sum_squares, n_s, delta, data_range)
    if variant == "reference":
        quantised = delta * np.round(coded / delta)
        data2 = base + np.sum(quantised ** 2, axis=0) / (2 * sigma_min ** 2)
    elif variant != "continuous":
        raise ConfigError(f"variant: unknown MDL variant {variant!r}")
    cost = param + np.where(case1, data1, data2)
    return np.where(ranges < delta, 0.0, cost) if free_below_delta else cost


def description_length(coded: np.ndarray, delta: float, data_range: float,
                       variant: str = "continuous", free_below_delta: bool = True) -> float:
    """F_MDL(Delta): the total description length at a fixed coding accuracy (eq. 13)."""
    return float(np.sum(mode_costs(coded, delta, data_range, variant, free_below_delta)))


def _integral_log_sigma_max(a, b, sigma_max):
    """Integral of ln(sigma_max - 2 x) dx from a to b (0 for empty pieces)."""
    def antiderivative(x):
        s = sigma_max - 2.0 * x
        return -0.5 * (s * np.log(s) - s)
    return _on_pieces(a, b, antiderivative)


def _integral_log(a, b):
    """Integral of ln x dx from a to b (a > 0; 0 for empty pieces)."""
    return _on_pieces(a, b, lambda x: x * np.log(x) - x)


def _integral_inverse_square(a, b):
    """Integral of x^-2 dx from a to b (a > 0; 0 for empty pieces)."""
    return _on_pieces(a, b, lambda x: -1.0 / x)


def _on_pieces(a, b, antiderivative):
    """antiderivative(b) - antiderivative(a) where b > a, else 0; empty pieces may lie outside
    the antiderivative's domain, so they are never evaluated."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    result = np.zeros(a.shape)
    nonempty = b > a
    result[nonempty] = antiderivative(b[nonempty]) - antiderivative(a[nonempty])
    return result


def integrated_description_length(coded: np.ndarray, delta_min: float, delta_max: float,
                                  data_range: float) -> float:
    """The paper's objective (eq. 14): F_MDL(Delta) averaged over Delta uniform in [min, max].

    Exact integration of the continuous variant, piece by piece.
    """
    if not 0 < delta_min < delta_max:
        raise ConfigError(f"delta_range: need 0 < Delta_min < Delta_max, got {delta_min}, {delta_max}")
    _check_range(delta_max, data_range)
    sigma, ranges, sum_squares = mode_statistics(coded)
    return float(np.sum(_integrated_mode_costs(sigma, ranges, sum_squares, np.shape(coded)[0],
                                               delta_min, delta_max, data_range)))


def _integrated_mode_costs(sigma, ranges, sum_squares, n_s, delta_min, delta_max, data_range):
    sigma_max = data_range / 2.0
    k = np.sqrt(12.0 / n_s)
    upper = np.minimum(delta_max, ranges)            # above the range, a mode costs nothing
    switch = np.clip(sigma / 2.0, delta_min, None)   # case 1 below, case 2 above
    saturate = 1.0 / (2.0 * k)                       # delta = 2 k Delta reaches 1 here

    def piece(a, b):
        b = np.maximum(a, b)
        return a, b, b - a

    # case 1 on [delta_min, min(upper, sigma/2)]
    a1, b1, length1 = piece(np.full_like(sigma, delta_min), np.minimum(upper, switch))
    small = np.minimum(1.0, np.maximum(sigma, 1e-300) * k)
    with np.errstate(divide="ignore", invalid="ignore"):
        constant1 = (-np.log(small) + 1.0 + np.abs(np.log(small))
                     + 0.5 * n_s * np.log(2 * np.pi * np.maximum(sigma, 1e-300) ** 2) + 0.5 * n_s
                     + n_s * small ** 2 / (12.0 * np.maximum(sigma, 1e-300) ** 2))
    constant1 = np.where(length1 > 0, constant1, 0.0)
    cost1 = (_integral_log_sigma_max(a1, b1, sigma_max) + constant1 * length1
             - n_s * _integral_log(a1, b1))
    # case 2 with delta = 2 k Delta < 1 on [switch, min(upper, saturate)]
    a2, b2, length2 = piece(switch, np.minimum(upper, saturate))
    constant2 = 2.0 - 2.0 * np.log(2.0 * k) + 0.5 * n_s * np.log(8 * np.pi)
    cost2 = (_integral_log_sigma_max(a2, b2, sigma_max) + constant2 * length2
             - 2.0 * _integral_log(a2, b2) + sum_squares / 8.0 * _integral_inverse_square(a2, b2))
    # case 2 with delta = 1 on [max(switch, saturate), upper]
    a3, b3, length3 = piece(np.maximum(switch, saturate), upper)
    constant3 = 1.0 + 0.5 * n_s * np.log(8 * np.pi)
    cost3 = (_integral_log_sigma_max(a3, b3, sigma_max) + constant3 * length3
             + (sum_squares / 8.0 + n_s / 48.0) * _integral_inverse_square(a3, b3))
    return (cost1 + cost2 + cost3) / (delta_max - delta_min)


def _integrated_mode_slopes(sigma, ranges, sum_squares, n_s, delta_min, delta_max, data_range):
    """Partial derivatives of :func:`_integrated_mode_costs` with respect to sigma_m, S_m = sum_i
    Y_im^2 and range_m (each treated as independent, as the code computes them).

    The integrand is continuous at Delta = sigma_m / 2 and at the saturation of delta, so by Leibniz
    the moving breakpoints there contribute nothing; it drops to 0 at Delta = range_m (case 3), so
    the upper limit min(Delta_max, range_m) contributes the integrand's value just below range_m.
    """
    length = delta_max - delta_min
    upper = np.minimum(delta_max, ranges)
    switch = np.clip(sigma / 2.0, delta_min, None)
    length1 = np.maximum(np.minimum(upper, switch) - delta_min, 0.0)
    d_sigma = np.where(length1 > 0, length1 * _case1_slope(sigma, n_s), 0.0) / length
    # case 2 on [switch, upper]: the integrand holds S / (8 Delta^2)
    d_sum = np.where(upper > switch, (1.0 / switch - 1.0 / np.maximum(upper, switch)) / 8.0,
                     0.0) / length
    moving = (ranges > delta_min) & (ranges < delta_max)
    at = np.where(moving, ranges, delta_max)
    case1, param, _, data1, data2 = _cost_terms(sigma, sum_squares, n_s, at, data_range)
    d_range = np.where(moving, param + np.where(case1, data1, data2), 0.0) / length
    return d_sigma, d_sum, d_range


def _fixed_mode_slopes(sigma, ranges, n_s, delta, variant, free_below_delta):
    """Partial derivatives of :func:`mode_costs` with respect to sigma_m and S_m (range_m only
    switches case 3 on and off: its derivative is 0 almost everywhere)."""
    sigma_min = 2.0 * delta
    case1 = sigma > sigma_min
    d_sigma = np.where(case1, _case1_slope(sigma, n_s), 0.0)
    # reference variant: the quantised Yhat are piecewise constant, so their derivative is 0 a.e.
    slope2 = 1.0 / (2.0 * sigma_min ** 2) if variant == "continuous" else 0.0
    d_sum = np.where(case1, 0.0, slope2)
    if free_below_delta:
        free = ranges < delta
        d_sigma, d_sum = np.where(free, 0.0, d_sigma), np.where(free, 0.0, d_sum)
    return d_sigma, d_sum, np.zeros_like(sigma)


def coded_values_from_gram(gram: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decompose a centred (reduced) covariance D' (n_s, n_s).

    Returns the mode variances lambda_m = eigenvalue / n_s (descending) and the coded values
    Y = U sqrt(eigenvalue), (n_s, n_s), with (1/n_s) sum_i Y_im^2 = lambda_m.
    """
    raw, vectors = _eigen(gram)
    eigenvalues = np.clip(raw, 0.0, None)
    return eigenvalues / gram.shape[0], vectors * np.sqrt(eigenvalues)


def _eigen(gram: np.ndarray, triangle: str = "L") -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (descending, unclipped) and unit eigenvectors (columns) of a symmetric matrix
    given by its lower (``triangle`` "L") or upper ("U") triangle."""
    eigenvalues, vectors = np.linalg.eigh(gram, UPLO=triangle)
    return eigenvalues[::-1], vectors[:, ::-1]


class _WholeProducts:
    """The products of the covariance route as single numpy calls (up to the switch)."""

    def covariance(self, data: np.ndarray) -> np.ndarray:
        return data.T @ data

    def times(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        return left @ right

    def eigen(self, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _eigen(covariance)


class _BlockProducts:
    """The products of the covariance route in fixed blocks on ``threads`` (past the switch).

    Every block is one BLAS call on one BLAS thread and writes its own part of the output, so
    which thread runs it changes nothing; the blocks (:data:`ROW_BLOCK`, :data:`COLUMN_BLOCKS`) do
    not depend on the number of threads. The sums within a block differ from those of one call
    on the whole matrices by rounding only.
    """

    def __init__(self, threads: Threads):
        self.threads = threads

    def covariance(self, data: np.ndarray) -> np.ndarray:
        """A^T A, its upper triangle and diagonal (the lower triangle is left 0), in
        :data:`COLUMN_BLOCKS` blocks of columns of about equal work: block [b, e) is
        A[:, :e]^T A[:, b:e], with e = d sqrt(k / COLUMN_BLOCKS)."""
        d = data.shape[1]
        out = np.zeros((d, d))
        edges = sorted({int(round(d * np.sqrt(k / COLUMN_BLOCKS)))
                        for k in range(COLUMN_BLOCKS + 1)})

        def blocks(indices):
            for k in indices:
                begin, end = edges[k], edges[k + 1]
                out[:end, begin:end] = data[:, :end].T @ data[:, begin:end]
        self.threads.over(len(edges) - 1, blocks)
        return out

    def times(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """left @ right, by blocks of :data:`ROW_BLOCK` rows of ``left``."""
        n = left.shape[0]
        out = np.empty((n, right.shape[1]))
        right = np.ascontiguousarray(right)

        def blocks(indices):
            for k in indices:
                rows = slice(k * ROW_BLOCK, min((k + 1) * ROW_BLOCK, n))
                np.matmul(left[rows], right, out=out[rows])
        self.threads.over(-(-n // ROW_BLOCK), blocks)
        return out

    def eigen(self, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _eigen(covariance, triangle="U")


@contextlib.contextmanager
def _products(data: np.ndarray, threads: int, pool: Threads | None = None):
    """The products for :meth:`Objective.from_data` and :meth:`Objective.data_gradient` on
    ``data`` (n_s, d): whole up to the switch (the caller's BLAS threads), in blocks past it on
    ``pool``, or without one on a pool of ``threads`` threads for this call alone (one BLAS
    thread each, and for the eigendecomposition)."""
    if not covariance_route(*data.shape):
        yield _WholeProducts()
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"), contextlib.ExitStack() as stack:
        if pool is None:
            pool = stack.enter_context(Threads(threads))
        yield _BlockProducts(pool)


def covariance_route(n_shapes: int, dimension: int) -> bool:
    """Whether eq. 14 and its gradient for n_s shapes of ``dimension`` coordinates (3 n_p) go
    through the dimension x dimension covariance (:meth:`Objective.data_gradient`) rather than the
    n_s x n_s Gram matrix (:meth:`Objective.gradient`): where it is the smaller of the two (both
    routes cost the cube of their matrix's size plus n_s d min(n_s, d) for the products)."""
    return n_shapes > dimension


@dataclass
class Objective:
    """F as a function of the centred covariance D' of the training set.

    ``kind`` "integrated" is eq. 14 (Delta averaged over [delta_min, delta_max]); "fixed" is eq. 13 at
    ``delta``. Every length is in the units of the aligned shapes. ``threads``: the threads of the
    products with the data past the switch (:func:`covariance_route`); the results do not depend
    on it. They are one pool within :meth:`pooled`, else one per evaluation.
    """

    kind: str
    data_range: float
    delta: float = 0.1
    delta_min: float = 1e-4
    delta_max: float = 0.5
    variant: str = "continuous"
    free_below_delta: bool = True
    threads: int = 1
    _pool: Threads | None = field(default=None, init=False, repr=False, compare=False)

    @contextlib.contextmanager
    def pooled(self):
        """Within, the evaluations past the switch share one pool of ``threads`` threads (an
        optimisation's thousands of them would otherwise each start and end their own); the
        threads end with it. Nested uses share the outermost's pool."""
        if self._pool is not None:
            yield self
            return
        with Threads(self.threads) as self._pool:
            try:
                yield self
            finally:
                self._pool = None

    def __getstate__(self):
        """A copy (pickled) holds no pool: its evaluations start their own."""
        return {**self.__dict__, "_pool": None}

    def __call__(self, gram: np.ndarray) -> float:
        _, coded = coded_values_from_gram(gram)
        return self.from_coded(coded)

    def gradient(self, gram: np.ndarray) -> tuple[float, np.ndarray]:
        """F(D') and its gradient G = dF/dD', a symmetric (n_s, n_s) matrix such that
        dF = sum_ij G_ij dD'_ij for every symmetric perturbation dD'.

        With D' = sum_m mu_m u_m u_m^T (eigh, unit u_m), the code sees mu_m only through
        sigma_m = sqrt(mu_m / n_s), S_m = sum_i Y_im^2 = mu_m and range_m = sqrt(mu_m) ptp(u_m)
        (Y_m = sqrt(mu_m) u_m). With d mu_m = u_m^T dD' u_m,

            G = sum_m [dF/dsigma_m / (2 n_s sigma_m) + dF/dS_m + dF/drange_m ptp(u_m) / (2 sqrt(mu_m))]
                      u_m u_m^T
                + sum_m dF/drange_m sqrt(mu_m) sym(v_m u_m^T),
            v_m = sum_{n != m} (u_{a n} - u_{b n}) / (mu_m - mu_n) u_n   (a, b: argmax, argmin of u_m),

        the last line being the eigenvector derivative of the range, which only the "integrated"
        kind needs (modes whose range lies inside [Delta_min, Delta_max] move the upper end of
        their Delta integral). Modes with mu_m <= 0 (clipped to 0) get no gradient. Case 3 of
        "fixed" is a step in range_m: its derivative is taken as 0 (F jumps where range_m = Delta).
        The terms within a repeated eigenvalue sum to a well-defined matrix, except the
        eigenvector term, whose 1 / (mu_m - mu_n) is dropped for exactly equal eigenvalues (F is
        not differentiable there when a range term is active).
        """
        gram = np.asarray(gram, dtype=np.float64)
        n_s = gram.shape[0]
        raw, vectors = _eigen(gram)
        mu = np.clip(raw, 0.0, None)
        root = np.sqrt(mu)
        coded = vectors * root
        value = self.from_coded(coded)
        slope, d_range, positive = self._mode_slopes(coded, raw, root, n_s)
        spread = np.ptp(vectors, axis=0)
        safe_root = np.where(positive, root, 1.0)
        slope = np.where(positive, slope + d_range * spread / (2.0 * safe_root), 0.0)
        grad = (vectors * slope) @ vectors.T
        active = np.flatnonzero(positive & (d_range != 0))
        if active.size:
            columns = vectors[:, active]
            top, bottom = np.argmax(columns, axis=0), np.argmin(columns, axis=0)
            difference = vectors[top, :] - vectors[bottom, :]       # (n_active, n_s)
            gaps = raw[active][:, None] - raw[None, :]
            with np.errstate(divide="ignore", invalid="ignore"):
                coefficients = np.where(gaps != 0, difference / gaps, 0.0)
            coefficients[np.arange(active.size), active] = 0.0
            directions = vectors @ coefficients.T                   # v_m, (n_s, n_active)
            part = (directions * (d_range[active] * root[active])) @ columns.T
            grad += 0.5 * (part + part.T)
        return value, 0.5 * (grad + grad.T)

    def _mode_slopes(self, coded, raw, root, n_s):
        """Per mode, dF/dmu_m from sigma_m and S_m (0 where mu_m <= 0), dF/drange_m, and which
        modes have mu_m > 0: the pieces of :meth:`gradient` and :meth:`data_gradient`."""
        sigma, ranges, sum_squares = mode_statistics(coded)
        if self.kind == "fixed":
            d_sigma, d_sum, d_range = _fixed_mode_slopes(sigma, ranges, n_s, self.delta,
                                                         self.variant, self.free_below_delta)
        else:
            d_sigma, d_sum, d_range = _integrated_mode_slopes(
                sigma, ranges, sum_squares, n_s, self.delta_min, self.delta_max, self.data_range)
        positive = raw > 0
        safe_sigma = np.where(positive & (sigma > 0), sigma, 1.0)
        return d_sigma / (2.0 * n_s * safe_sigma) + d_sum, d_range, positive

    def from_data(self, data: np.ndarray) -> float:
        """F(D') for D' = A A^T, from A (n_s, d) through the d x d matrix A^T A (its nonzero
        eigenvalues are D''s): O(n_s d^2 + d^3) work and O(n_s d) memory, where the n_s x n_s
        route costs O(n_s^3) and O(n_s^2). The same value as ``self(data @ data.T)`` to rounding."""
        data = np.asarray(data, dtype=np.float64)
        with _products(data, self.threads, self._pool) as products:
            raw, axes = products.eigen(products.covariance(data))
            coded = products.times(data, axes)
        coded[:, raw <= 0] = 0.0
        return self._value_of_modes(coded, data.shape[0])

    def _value_of_modes(self, coded, n_s):
        """F from the coded values of the covariance's d modes: D' has n_s eigenvalues, the
        d of A^T A and n_s - d zeros (fewer if d > n_s), whose cost is added (0 but for the
        fixed kind without case 3)."""
        value = self.from_coded(coded)
        missing = n_s - coded.shape[1]
        if missing:
            value += missing * self.from_coded(np.zeros((n_s, 1)))
        return value

    def data_gradient(self, data: np.ndarray) -> tuple[float, np.ndarray]:
        """F(D') and dF/dA = 2 (dF/dD') A for D' = A A^T, through the d x d matrix A^T A
        (:meth:`from_data`): linear in n_s, and nothing n_s x n_s is formed.

        With A^T A = sum_m mu_m w_m w_m^T (eigh), Y_m = A w_m = sqrt(mu_m) u_m are D''s coded
        values and u_m its unit eigenvectors. The terms of :meth:`gradient` become

            2 sum_m g_m u_m u_m^T A = 2 sum_m g_m Y_m w_m^T,

        and for the range term P = sum_m c_m v_m u_m^T (c_m = dF/drange_m sqrt(mu_m)), (P + P^T) A
        with u_m^T A = sqrt(mu_m) w_m^T. D''s eigenvectors beyond the r resolved modes (mu_n
        <= 1e-12 mu_1: its null space, of which A^T A knows nothing) enter v_m only as a whole,
        sum_{n null} (u_an - u_bn) u_n / mu_m = (e_a - e_b - U_r (U_r[a] - U_r[b])^T) / mu_m, so
        that v_m = (e_a - e_b) / mu_m + U_r beta_m with beta_mn = delta_mn / (mu_m - mu_n)
        - delta_mn / mu_m (delta_m = U_r[a] - U_r[b], the first term 0 for n = m).
        """
        data = np.asarray(data, dtype=np.float64)
        with _products(data, self.threads, self._pool) as products:
            return self._data_gradient(data, products)

    def _data_gradient(self, data, products):
        n_s = data.shape[0]
        raw, axes = products.eigen(products.covariance(data))
        mu = np.clip(raw, 0.0, None)
        root = np.sqrt(mu)
        coded = products.times(data, axes)
        coded[:, raw <= 0] = 0.0
        value = self._value_of_modes(coded, n_s)
        slope, d_range, positive = self._mode_slopes(coded, raw, root, n_s)
        safe_mu = np.where(positive, mu, 1.0)
        slope = np.where(positive, slope + d_range * np.ptp(coded, axis=0) / (2.0 * safe_mu),
                         0.0)
        # grad = Y M: the d x d matrix M gathers every term of the form Y (...) before the one
        # product with Y (n_s x d x d, the cost of an evaluation with A^T A and Y = A W)
        mixing = 2.0 * slope[:, None] * axes.T
        resolved = int(np.count_nonzero(raw > 1e-12 * max(raw[0], 0.0)))
        active = np.flatnonzero(positive[:resolved] & (d_range[:resolved] != 0))
        if not active.size:
            return value, products.times(coded, mixing)
        top, bottom = np.argmax(coded, axis=0)[active], np.argmin(coded, axis=0)[active]
        difference = (coded[top, :resolved] - coded[bottom, :resolved]) / root[:resolved]
        gaps = raw[active][:, None] - raw[None, :resolved]                # delta_m: (n_active, r)
        with np.errstate(divide="ignore", invalid="ignore"):
            coefficients = np.where(gaps != 0, difference / gaps, 0.0)
        coefficients[np.arange(active.size), active] = 0.0
        beta = coefficients - difference / raw[active][:, None]
        along = d_range[active]                           # c_m sqrt(mu_m) / mu_m = dF/drange_m
        # P A = sum_m c_m sqrt(mu_m) v_m w_m^T: its U_r beta part through M, its e_a - e_b part
        # on rows a and b
        rows = along[:, None] * axes[:, active].T                        # (n_active, d)
        mixing[:resolved] += (beta.T / root[:resolved, None]) @ (mu[active, None] * rows)
        # P^T A = sum_m c_m u_m (v_m^T A), v_m^T A = (A[a] - A[b]) / mu_m + beta_m^T U_r^T A
        projected = ((data[top] - data[bottom]) / raw[active][:, None]
                     + (beta * root[:resolved]) @ axes[:, :resolved].T)
        mixing[active] += along[:, None] * projected
        grad = products.times(coded, mixing)
        np.add.at(grad, top, rows)
        np.subtract.at(grad, bottom, rows)
        return value, grad

    def from_coded(self, coded: np.ndarray) -> float:
        if self.kind == "fixed":
            return description_length(coded, self.delta, self.data_range, self.variant,
                                      self.free_below_delta)
        if self.kind == "integrated":
            return integrated_description_length(coded, self.delta_min, self.delta_max,
                                                 self.data_range)
        raise ConfigError(f"objective: unknown kind {self.kind!r}")


@contextlib.contextmanager
def pooled(objectives):
    """Each :class:`Objective` of ``objectives`` :meth:`~Objective.pooled` while within (the
    others, such as :class:`NoDescription`, have no threads)."""
    with contextlib.ExitStack() as stack:
        for objective in objectives:
            if isinstance(objective, Objective):
                stack.enter_context(objective.pooled())
        yield


def objectives(config, voxel: float, data_range: float) -> tuple:
    """(fixed-Delta objective eq. 13, full objective eq. 14) with Delta in units of ``voxel``."""
    return (Objective("fixed", data_range, delta=config.fixed_delta * voxel,
                      threads=config.workers),
            Objective("integrated", data_range, delta_min=config.delta_range[0] * voxel,
                      delta_max=config.delta_range[1] * voxel, threads=config.workers))


@dataclass(frozen=True)
class NoDescription:
    """An objective that is 0 for every covariance: with landmark guides, the state's F is then
    their term alone (the landmark phase of :func:`~.strategies.optimise`)."""

    kind: str = "none"

    def __call__(self, gram: np.ndarray) -> float:
        return 0.0

    def gradient(self, gram: np.ndarray) -> tuple[float, np.ndarray]:
        return 0.0, np.zeros_like(np.asarray(gram, dtype=np.float64))

    def from_data(self, data: np.ndarray) -> float:
        return 0.0

    def data_gradient(self, data: np.ndarray) -> tuple[float, np.ndarray]:
        return 0.0, np.zeros_like(np.asarray(data, dtype=np.float64))
