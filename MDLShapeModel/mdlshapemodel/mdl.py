"""The MDL objective function (section III-B; METHOD.md section 2).

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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ConfigError


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
    sigma_max = data_range / 2.0
    k = np.sqrt(12.0 / n_s)
    case1 = sigma > sigma_min
    sigma_used = np.where(case1, sigma, sigma_min)
    small = np.minimum(1.0, sigma_used * k)  # the parameter precision delta
    param = np.log((sigma_max - sigma_min) / small) + 1.0 + np.abs(np.log(small))
    base = -n_s * np.log(delta) + 0.5 * n_s * np.log(2 * np.pi * sigma_used ** 2)
    precision_term = n_s * small ** 2 / (12.0 * sigma_used ** 2)
    data1 = base + 0.5 * n_s + precision_term
    if variant == "continuous":
        data2 = base + sum_squares / (2 * sigma_min ** 2) + precision_term
    elif variant == "reference":
        quantised = delta * np.round(coded / delta)
        data2 = base + np.sum(quantised ** 2, axis=0) / (2 * sigma_min ** 2)
    else:
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


def coded_values_from_gram(gram: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-decompose a centred (reduced) covariance D' (n_s, n_s).

    Returns the mode variances lambda_m = eigenvalue / n_s (descending) and the coded values
    Y = U sqrt(eigenvalue), (n_s, n_s), with (1/n_s) sum_i Y_im^2 = lambda_m.
    """
    eigenvalues, vectors = np.linalg.eigh(gram)
    eigenvalues = np.clip(eigenvalues[::-1], 0.0, None)
    vectors = vectors[:, ::-1]
    return eigenvalues / gram.shape[0], vectors * np.sqrt(eigenvalues)


@dataclass
class Objective:
    """F as a function of the centred covariance D' of the training set.

    ``kind`` "integrated" is eq. 14 (Delta averaged over [delta_min, delta_max]); "fixed" is eq. 13 at
    ``delta``. Every length is in the units of the aligned shapes.
    """

    kind: str
    data_range: float
    delta: float = 0.1
    delta_min: float = 1e-4
    delta_max: float = 0.5
    variant: str = "continuous"
    free_below_delta: bool = True

    def __call__(self, gram: np.ndarray) -> float:
        _, coded = coded_values_from_gram(gram)
        return self.from_coded(coded)

    def from_coded(self, coded: np.ndarray) -> float:
        if self.kind == "fixed":
            return description_length(coded, self.delta, self.data_range, self.variant,
                                      self.free_below_delta)
        if self.kind == "integrated":
            return integrated_description_length(coded, self.delta_min, self.delta_max,
                                                 self.data_range)
        raise ConfigError(f"objective: unknown kind {self.kind!r}")
