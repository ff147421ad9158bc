"""Homeomorphisms of the sphere that move sample points (section III-A, eq. 8-12).

The symmetric theta transformation about a point P moves every point along its great circle through
P, from polar angle theta (measured from P) to f(theta) (eq. 10), where f is the scaled cumulative
distribution of a constant plus a wrapped Cauchy density of width omega (a = exp(-omega), eq. 11) and
amplitude A. f(0) = 0, f(pi) = pi and f is strictly increasing, so the map is a homeomorphism: it
cannot fold or tear. Compositions (eq. 12) are applied by transforming the current sample positions.
"""

from __future__ import annotations

import numpy as np


def minimum_amplitude(omega: float) -> float:
    """Smallest amplitude keeping f strictly increasing: A > -(1 - a) / (1 + a), a = exp(-omega).

    f'(theta) is proportional to 1 + A (1 - a^2) / (1 + a^2 - 2 a cos theta), whose Cauchy term peaks
    at theta = 0 with value (1 + a) / (1 - a). The paper uses A >= 0 only.
    """
    a = np.exp(-omega)
    return -(1.0 - a) / (1.0 + a)


def symmetric_theta(theta: np.ndarray, amplitude: float, omega: float) -> np.ndarray:
    """f(theta) of eq. 10 for a kernel of width ``omega`` and amplitude ``amplitude``."""
    a = np.exp(-omega)
    cos_theta = np.cos(theta)
    argument = ((1 + a * a) * cos_theta - 2 * a) / (1 + a * a - 2 * a * cos_theta)
    return (theta + amplitude * np.arccos(np.clip(argument, -1.0, 1.0))) / (1.0 + amplitude)


def symmetric_theta_derivative(theta: np.ndarray, amplitude: float, omega: float) -> np.ndarray:
    """df/dtheta = pi * rho(theta) (eq. 9): positive for every theta when A > minimum_amplitude."""
    a = np.exp(-omega)
    cauchy = (1 - a * a) / (1 + a * a - 2 * a * np.cos(theta))
    return (1.0 + amplitude * cauchy) / (1.0 + amplitude)


def apply_symmetric_theta(points: np.ndarray, center: np.ndarray, amplitude: float,
                          omega: float) -> np.ndarray:
    """Move unit vectors ``points`` by the symmetric theta transformation about ``center``."""
    if amplitude == 0.0:
        return points
    center = np.asarray(center, dtype=np.float64)
    center = center / np.linalg.norm(center)
    cos_theta = np.clip(points @ center, -1.0, 1.0)
    theta = np.arccos(cos_theta)
    tangent = points - cos_theta[:, None] * center
    sin_theta = np.linalg.norm(tangent, axis=1)
    moving = sin_theta > 1e-12  # the kernel centre and its antipode are fixed points
    new_theta = symmetric_theta(theta[moving], amplitude, omega)
    direction = tangent[moving] / sin_theta[moving, None]
    result = points.copy()
    result[moving] = np.cos(new_theta)[:, None] * center + np.sin(new_theta)[:, None] * direction
    return result


def random_unit_vector(rng: np.random.Generator) -> np.ndarray:
    """A point uniformly distributed on the unit sphere."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_width(rng: np.random.Generator, sigma_g: float) -> float:
    """omega from the positive half of N(0, sigma_G) (III-D2), kept away from zero."""
    return max(abs(float(rng.normal(0.0, sigma_g))), 1e-4)
