"""Homeomorphisms of the sphere that move sample points (section III-A, eq. 8-12, and the Appendix).

The symmetric theta transformation about a point P moves every point along its great circle through
P, from polar angle theta (measured from P) to f(theta) (eq. 10), where f is the scaled cumulative
distribution of a constant plus a wrapped Cauchy density of width omega (a = exp(-omega), eq. 11) and
amplitude A. f(0) = 0, f(pi) = pi and f is strictly increasing, so the map is a homeomorphism: it
cannot fold or tear. Compositions (eq. 12) are applied by transforming the current sample positions.

The Appendix adds two more families, and a global rotation is a homeomorphism too:

* asymmetric theta transformation (eq. 27-29): the amplitude of eq. 10 becomes a smooth function
  A(psi') of the angle psi around P, a second wrapped Cauchy of width b with minimum zero;
* shear and twist (eq. 30-31): psi -> psi + g(theta), every circle of latitude about P is rotated
  about the axis through P by an angle g that depends on theta only;
* a global rotation of the parameter sphere (docs/method.md section 3), Rodrigues' formula.

Polar coordinates about P: theta = angle from P; psi = angle around P, measured in the tangent plane
from the projection of a ``reference_direction`` (psi = 0), counter-clockwise seen from outside at P
(right-handed about P).

Every kind is one small dataclass, the ONE representation of a warp that every strategy uses and
the optimisation state records (``PartState.warps``): :class:`SymmetricTheta` (the paper's kernel),
:class:`AsymmetricTheta`, :class:`ShearTwist`, :class:`Rotation`, and :class:`FieldWarp` (a smooth
tangent displacement field, :mod:`.fields`, one per round of the ``fast`` strategy). Each has
``apply(points)``, ``parameters()``, ``bounds()``, ``is_valid()``, ``to_vector()`` and
``from_vector()`` (an exact round trip through one float array, for checkpoints), and all but the
field ``inverse(points)``; :func:`apply_warp` applies a kind by name, :func:`apply_warps` /
:func:`invert_warps` a sequence. Random draws in the style of
:func:`random_width` are :func:`random_symmetric_theta`, :func:`random_asymmetric_theta`,
:func:`random_shear_twist` and :func:`random_rotation`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Callable, ClassVar, Mapping, Sequence

import numpy as np

from ..errors import ArgumentError
from ..geometry import rotation_from_vector
from .fields import apply_field


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


# ------------------------------------------------------------------------------------------------
# Polar coordinates about a point P


def _unit(vector, name: str) -> np.ndarray:
    """The unit vector along ``vector``; a vector that is unit to rounding (within 4 ulp) is kept
    as given, so that a warp built from a drawn point applies exactly as that point."""
    v = np.asarray(vector, dtype=np.float64).reshape(3)
    norm = float(np.linalg.norm(v))
    if not np.isfinite(norm) or norm < 1e-12:
        raise ArgumentError(f"{name} must be a finite, non-zero 3-vector, got {v}")
    if abs(norm - 1.0) <= 4.0 * np.finfo(np.float64).eps:
        return v.copy()
    return v / norm


def perpendicular(center: np.ndarray) -> np.ndarray:
    """A fixed unit vector orthogonal to ``center`` (a default psi = 0 direction)."""
    p = _unit(center, "center")
    helper = np.zeros(3)
    helper[int(np.argmin(np.abs(p)))] = 1.0
    e1 = helper - (helper @ p) * p
    return e1 / np.linalg.norm(e1)


def polar_frame(center: np.ndarray,
                reference_direction: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (P, e1, e2), e1 x e2 = P: the polar axis and the directions psi = 0 and pi/2.

    e1 is the unit projection of ``reference_direction`` onto the plane orthogonal to P, e2 = P x e1;
    psi grows counter-clockwise seen from outside at P. Raises ValueError when the reference
    direction is (nearly) parallel to P.
    """
    p = _unit(center, "center")
    r = np.asarray(reference_direction, dtype=np.float64).reshape(3)
    r_norm = float(np.linalg.norm(r))
    e1 = r - (r @ p) * p
    e1_norm = float(np.linalg.norm(e1))
    if not np.isfinite(e1_norm) or e1_norm <= 1e-9 * max(r_norm, 1e-300):
        raise ArgumentError("reference_direction must be a non-zero vector not parallel to center")
    e1 = e1 / e1_norm
    return p, e1, np.cross(p, e1)


def polar_coordinates(points: np.ndarray, center: np.ndarray,
                      reference_direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, psi) of unit vectors about P: theta in [0, pi] from P, psi in (-pi, pi] around P.

    psi is 0 (by convention) at P and at -P, where it is undefined.
    """
    p, e1, e2 = polar_frame(center, reference_direction)
    points = np.asarray(points, dtype=np.float64)
    cos_theta = points @ p
    tangent = points - cos_theta[..., None] * p
    theta = np.arctan2(np.linalg.norm(tangent, axis=-1), cos_theta)
    psi = np.arctan2(tangent @ e2, tangent @ e1)
    return theta, psi


# ------------------------------------------------------------------------------------------------
# The theta map of eq. 10 with an amplitude per point, and its inverse


def wrapped_cauchy_cdf(theta: np.ndarray, omega: float) -> np.ndarray:
    """int_0^theta (1 - a^2) / (1 + a^2 - 2 a cos s) ds = 2 arctan((1 + a)/(1 - a) tan(theta/2)).

    The same function as the arccos of eq. 10 on [0, pi] (a = exp(-omega)), written in a form that
    keeps full precision near theta = 0 (arccos of a number close to 1 loses half the digits).
    """
    a = np.exp(-omega)
    half = 0.5 * np.asarray(theta, dtype=np.float64)
    return 2.0 * np.arctan2((1.0 + a) * np.sin(half), -np.expm1(-omega) * np.cos(half))


def theta_map(theta: np.ndarray, amplitude, omega: float) -> np.ndarray:
    """f(theta) of eq. 10, [theta + A C(theta)] / (1 + A); ``amplitude`` may be one value per theta.

    Equals :func:`symmetric_theta` (to its rounding, about 1e-8 near theta = 0).
    """
    theta = np.asarray(theta, dtype=np.float64)
    amplitude = np.asarray(amplitude, dtype=np.float64)
    return (theta + amplitude * wrapped_cauchy_cdf(theta, omega)) / (1.0 + amplitude)


def theta_map_inverse(target: np.ndarray, amplitude, omega: float,
                      iterations: int = 64) -> np.ndarray:
    """theta in [0, pi] with :func:`theta_map` (theta, A, omega) = target, elementwise.

    f is strictly increasing from f(0) = 0 to f(pi) = pi whenever A > :func:`minimum_amplitude`
    (omega), so bisection on [0, pi] converges to the unique root; 64 halvings reach the float
    resolution. ``amplitude`` may be one value per target.
    """
    target = np.clip(np.asarray(target, dtype=np.float64), 0.0, np.pi)
    amplitude = np.broadcast_to(np.asarray(amplitude, dtype=np.float64), target.shape)
    low = np.zeros_like(target)
    high = np.full_like(target, np.pi)
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        below = theta_map(middle, amplitude, omega) < target
        low = np.where(below, middle, low)
        high = np.where(below, high, middle)
    return 0.5 * (low + high)


def apply_psi_modulated_theta(points: np.ndarray, center: np.ndarray,
                              reference_direction: np.ndarray,
                              amplitude_of_psi: Callable[[np.ndarray], np.ndarray], omega: float,
                              inverse: bool = False) -> np.ndarray:
    """theta -> f(theta, psi) = eq. 10 with amplitude A(psi) (Appendix eq. 27-28), psi unchanged.

    Each point moves along its great circle through P (its psi is kept) from theta to
    :func:`theta_map` (theta, A(psi), omega). ``amplitude_of_psi`` maps an array of psi in (-pi, pi]
    to amplitudes; with a constant function this is the symmetric theta transformation.

    Homeomorphism when A is continuous, 2 pi-periodic and A(psi) > :func:`minimum_amplitude` (omega)
    for every psi: for each psi, theta -> f(theta, psi) is a strictly increasing bijection of
    [0, pi] with f(0) = 0, f(pi) = pi, so the map is one-to-one and onto; f is continuous in
    (theta, psi), and at P and -P (where psi is undefined) continuity holds because
    |f(theta, psi)| <= max_psi f'(0) * theta -> 0 (likewise at pi). Away from P and -P the Jacobian
    determinant in (theta, psi) is df/dtheta * sin f / sin theta > 0 (the psi derivative of f only
    shears), so orientation is preserved. P and -P are fixed; the map need not be differentiable
    there (paper, footnote 2). ``inverse=True`` applies the inverse map (same psi, theta from
    :func:`theta_map_inverse`).
    """
    p, e1, e2 = polar_frame(center, reference_direction)
    points = np.asarray(points, dtype=np.float64)
    cos_theta = np.clip(points @ p, -1.0, 1.0)
    tangent = points - cos_theta[:, None] * p
    sin_theta = np.linalg.norm(tangent, axis=1)
    moving = sin_theta > 1e-12  # P and -P are fixed points
    theta = np.arctan2(sin_theta[moving], cos_theta[moving])
    direction = tangent[moving] / sin_theta[moving, None]
    psi = np.arctan2(direction @ e2, direction @ e1)
    amplitude = np.broadcast_to(np.asarray(amplitude_of_psi(psi), dtype=np.float64), psi.shape)
    if inverse:
        new_theta = theta_map_inverse(theta, amplitude, omega)
    else:
        new_theta = theta_map(theta, amplitude, omega)
    result = points.copy()
    result[moving] = np.cos(new_theta)[:, None] * p + np.sin(new_theta)[:, None] * direction
    return result


# ------------------------------------------------------------------------------------------------
# Asymmetric theta transformation (Appendix, eq. 27-29)


def asymmetric_amplitude(psi: np.ndarray, amplitude: float, psi0: float, b: float) -> np.ndarray:
    """A(psi') of eq. 29 with psi' = psi - psi0 and beta = exp(-b):

        A(psi') = A0 [(1 - beta^2) / (1 + beta^2 - 2 beta cos psi') - (1 - beta^2) / (1 + beta)^2].

    The subtracted constant is the minimum of the wrapped Cauchy (at psi' = pi), so A(psi') runs from
    0 (psi' = pi) to A0 * 4 beta / (1 - beta^2) = 2 A0 / sinh(b) (psi' = 0) for A0 >= 0. Small b is a
    narrow lobe around psi0. The denominator is evaluated as (1 - beta)^2 + 4 beta sin^2(psi'/2).
    """
    beta = np.exp(-b)
    half = 0.5 * (np.asarray(psi, dtype=np.float64) - psi0)
    one_minus_beta_squared = -np.expm1(-2.0 * b)
    one_minus_beta = -np.expm1(-b)
    cauchy = one_minus_beta_squared / (one_minus_beta ** 2 + 4.0 * beta * np.sin(half) ** 2)
    return amplitude * np.maximum(cauchy - one_minus_beta / (1.0 + beta), 0.0)


def maximum_asymmetric_amplitude(amplitude: float, b: float) -> float:
    """A(psi' = 0) = A0 * 4 beta / (1 - beta^2) = 2 A0 / sinh(b): the largest value of eq. 29."""
    return 2.0 * amplitude / np.sinh(b)


def minimum_asymmetric_amplitude(omega: float, b: float) -> float:
    """Smallest A0 keeping the asymmetric map a homeomorphism: minimum_amplitude(omega) sinh(b)/2.

    For A0 >= 0 every A(psi') >= 0 (the paper's case). For A0 < 0 the smallest amplitude is
    2 A0 / sinh(b), which must stay above :func:`minimum_amplitude` (omega).
    """
    return minimum_amplitude(omega) * np.sinh(b) / 2.0


def asymmetric_theta(theta: np.ndarray, psi: np.ndarray, amplitude: float, omega: float,
                     psi0: float, b: float) -> np.ndarray:
    """f(theta, psi) of eq. 27: eq. 10 with amplitude A(psi - psi0) of eq. 29."""
    return theta_map(theta, asymmetric_amplitude(psi, amplitude, psi0, b), omega)


def apply_asymmetric_theta(points: np.ndarray, center: np.ndarray,
                           reference_direction: np.ndarray, amplitude: float, omega: float,
                           psi0: float, b: float, inverse: bool = False) -> np.ndarray:
    """Move unit vectors by the asymmetric theta transformation about ``center`` (eq. 27-29).

    theta (angle from P = ``center``) -> f(theta, psi) = eq. 10 with width ``omega`` and amplitude
    A(psi - psi0) of eq. 29 (subsidiary wrapped Cauchy of width ``b``, minimum zero, maximum
    2 A0 / sinh(b) at psi = psi0); psi is measured around P from ``reference_direction`` (psi = 0,
    see :func:`polar_frame`) and is unchanged: each point slides along its great circle through P,
    most strongly on the side psi0, not at all on the opposite side psi0 + pi.

    Why it is a homeomorphism: for every psi, theta -> f(theta, psi) is eq. 10 with the amplitude
    A(psi'), strictly increasing with f(0) = 0 and f(pi) = pi as long as A(psi') > -(1 - a)/(1 + a);
    psi is unchanged and A is a smooth, 2 pi-periodic function of psi, so the map is a continuous
    bijection of the sphere (continuous also at the fixed points P and -P, where psi is undefined),
    hence a homeomorphism (see :func:`apply_psi_modulated_theta`). Parameter bounds that guarantee
    it: omega > 0, b > 0, any psi0, and A0 > :func:`minimum_asymmetric_amplitude` (omega, b); in
    particular every A0 >= 0 (the paper's case: A(psi') >= 0 everywhere). A0 = 0 is the identity.
    ``inverse=True`` applies the inverse map.
    """
    points = np.asarray(points, dtype=np.float64)
    if amplitude == 0.0:
        return points.copy()
    return apply_psi_modulated_theta(
        points, center, reference_direction,
        lambda psi: asymmetric_amplitude(psi, amplitude, psi0, b), omega, inverse=inverse)


# ------------------------------------------------------------------------------------------------
# Shear and twist (Appendix, eq. 30-31)


def shear_twist_angle(theta: np.ndarray, amplitude: float, width: float,
                      theta0: float) -> np.ndarray:
    """g(theta) of eq. 31: (B / 2 pi) (1 - gamma^2) / (1 + gamma^2 - 2 gamma cos(theta - theta0)).

    gamma = exp(-c), c = ``width`` > 0, B = ``amplitude`` (the integral of g over a full period),
    theta0 the centre of the band. The peak value, at theta = theta0, is B / (2 pi tanh(c / 2)).
    """
    gamma = np.exp(-width)
    half = 0.5 * (np.asarray(theta, dtype=np.float64) - theta0)
    one_minus_gamma = -np.expm1(-width)
    return (amplitude / (2.0 * np.pi)) * (-np.expm1(-2.0 * width)) \
        / (one_minus_gamma ** 2 + 4.0 * gamma * np.sin(half) ** 2)


def apply_shear_twist(points: np.ndarray, center: np.ndarray, amplitude: float, width: float,
                      theta0: float, inverse: bool = False) -> np.ndarray:
    """Shear/twist about the axis through P = ``center``: psi -> psi + g(theta) (eq. 30-31).

    Each point is rotated about the axis through P by the angle g(theta) of eq. 31
    (:func:`shear_twist_angle`), where theta is its angle from P, counter-clockwise seen from outside
    at P for B > 0. theta is unchanged. No reference direction is needed: adding g(theta) to psi
    does not depend on where psi = 0 is.

    Why it is a homeomorphism, for every B, every c > 0 and every theta0: it rotates each circle of
    latitude about P rigidly by an angle depending only on theta, so it maps each circle onto itself
    one-to-one; the inverse is psi -> psi - g(theta) (``inverse=True``, or B -> -B). g is smooth, so
    the map and its inverse are continuous away from the poles; at P and -P (theta = 0, pi), where
    psi is undefined and g(0), g(pi) need not vanish, the poles are fixed points of every rotation
    about P and the map keeps theta, so points near a pole stay equally near it: continuous there
    too. In (theta, psi) its Jacobian is [[1, 0], [g'(theta), 1]]: orientation and area preserving.
    B = 0 is the identity. (A mesh of sample points can still have triangles turned over when g
    changes by a large angle across one triangle; the continuous map cannot.)
    """
    points = np.asarray(points, dtype=np.float64)
    if amplitude == 0.0:
        return points.copy()
    p = _unit(center, "center")
    cos_theta = points @ p
    cross = np.cross(np.broadcast_to(p, points.shape), points)       # P x x, |P x x| = sin theta
    theta = np.arctan2(np.linalg.norm(cross, axis=1), cos_theta)
    angle = shear_twist_angle(theta, amplitude, width, theta0)
    if inverse:
        angle = -angle
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    # Rodrigues' rotation about P by the angle g(theta) of each point
    return points * c + cross * s + np.outer(cos_theta, p) * (1.0 - c)


# ------------------------------------------------------------------------------------------------
# Global rotation


def apply_rotation(points: np.ndarray, rotation_vector: np.ndarray,
                   inverse: bool = False) -> np.ndarray:
    """Rotate unit vectors by a rotation vector (axis * angle; Rodrigues, pose.rotation_from_vector).

    An isometry of the sphere, hence a homeomorphism for every rotation vector; the zero vector is
    the identity. ``inverse=True`` rotates back (R^T).
    """
    rotation = rotation_from_vector(rotation_vector)
    points = np.asarray(points, dtype=np.float64)
    return points @ (rotation if inverse else rotation.T)


# ------------------------------------------------------------------------------------------------
# A common interface


class Warp:
    """Shared behaviour of the warp dataclasses.

    ``apply(points)`` and ``inverse(points)`` map arrays (n, 3) of unit vectors; ``parameters()`` is
    a dict of the constructor arguments (``make_warp(kind, parameters)`` rebuilds the warp);
    ``bounds()`` maps each bounded scalar parameter to the open interval (low, high) that keeps the
    map a homeomorphism given the other parameters; ``is_valid()`` checks them (and finiteness).
    Vector parameters are checked (and unit-normalised) on construction. ``to_vector()`` and
    ``from_vector()`` store and restore the parameters exactly (no normalisation on the way back).
    """

    kind: ClassVar[str]
    #: the length of each parameter in :meth:`to_vector` (scalars 1; -1: the rest, at most once)
    _sizes: ClassVar[dict] = {}
    #: the scalar parameters that are integers (stored as floats, given back as int)
    _integers: ClassVar[tuple] = ()

    def to_vector(self) -> np.ndarray:
        """Every parameter, in field order, as one float64 array."""
        return np.concatenate([np.ravel(np.asarray(getattr(self, f.name), dtype=np.float64))
                               for f in fields(self)])

    @classmethod
    def from_vector(cls, vector: np.ndarray) -> "Warp":
        """The warp whose :meth:`to_vector` is ``vector``, bit for bit."""
        vector = np.asarray(vector, dtype=np.float64)
        names = [f.name for f in fields(cls)]
        sizes = [cls._sizes.get(name, 1) for name in names]
        if -1 in sizes:
            sizes[sizes.index(-1)] = len(vector) - (sum(sizes) + 1)
        if min(sizes) < 0 or sum(sizes) != len(vector):
            raise ArgumentError(f"{cls.__name__}: a parameter vector of {len(vector)} values does "
                             f"not fit its fields {names}")
        values, start = {}, 0
        for name, size in zip(names, sizes):
            chunk = vector[start:start + size]
            values[name] = (chunk.copy() if cls._sizes.get(name, 1) != 1 else
                            int(chunk[0]) if name in cls._integers else float(chunk[0]))
            start += size
        warp = object.__new__(cls)          # the stored values exactly: no __post_init__
        for name, value in values.items():
            object.__setattr__(warp, name, value)
        return warp

    def apply(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def inverse(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def parameters(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def bounds(self) -> dict[str, tuple[float, float]]:
        return {}

    def is_valid(self) -> bool:
        values = self.parameters()
        if not all(np.all(np.isfinite(value)) for value in values.values()):
            return False
        return all(low < values[name] < high for name, (low, high) in self.bounds().items())


@dataclass(frozen=True, eq=False)
class SymmetricTheta(Warp):
    """The symmetric theta map (eq. 10) about ``center``, see :func:`apply_symmetric_theta`."""

    center: np.ndarray
    amplitude: float
    omega: float
    kind: ClassVar[str] = "symmetric_theta"
    _sizes: ClassVar[dict] = {"center": 3}

    def __post_init__(self):
        object.__setattr__(self, "center", _unit(self.center, "center"))

    def apply(self, points):
        return apply_symmetric_theta(np.asarray(points, dtype=np.float64), self.center,
                                     self.amplitude, self.omega)

    def inverse(self, points):
        if self.amplitude == 0.0:
            return np.array(points, dtype=np.float64)
        return apply_psi_modulated_theta(points, self.center, perpendicular(self.center),
                                         lambda psi: self.amplitude, self.omega, inverse=True)

    def bounds(self):
        return {"amplitude": (minimum_amplitude(self.omega), np.inf), "omega": (0.0, np.inf)}


@dataclass(frozen=True, eq=False)
class AsymmetricTheta(Warp):
    """Asymmetric theta transformation (Appendix eq. 27-29): see :func:`apply_asymmetric_theta`."""

    center: np.ndarray
    reference_direction: np.ndarray
    amplitude: float
    omega: float
    psi0: float
    b: float
    kind: ClassVar[str] = "asymmetric_theta"
    _sizes: ClassVar[dict] = {"center": 3, "reference_direction": 3}

    def __post_init__(self):
        p, e1, _ = polar_frame(self.center, self.reference_direction)
        object.__setattr__(self, "center", p)
        object.__setattr__(self, "reference_direction", e1)

    def apply(self, points):
        return apply_asymmetric_theta(points, self.center, self.reference_direction,
                                      self.amplitude, self.omega, self.psi0, self.b)

    def inverse(self, points):
        return apply_asymmetric_theta(points, self.center, self.reference_direction,
                                      self.amplitude, self.omega, self.psi0, self.b, inverse=True)

    def bounds(self):
        return {"amplitude": (minimum_asymmetric_amplitude(self.omega, self.b), np.inf),
                "omega": (0.0, np.inf), "b": (0.0, np.inf)}


@dataclass(frozen=True, eq=False)
class ShearTwist(Warp):
    """Shear/twist about the axis through ``center`` (eq. 30-31): see :func:`apply_shear_twist`.

    Every amplitude and theta0 is allowed; only the width must be positive.
    """

    center: np.ndarray
    amplitude: float
    width: float
    theta0: float
    kind: ClassVar[str] = "shear_twist"
    _sizes: ClassVar[dict] = {"center": 3}

    def __post_init__(self):
        object.__setattr__(self, "center", _unit(self.center, "center"))

    def apply(self, points):
        return apply_shear_twist(points, self.center, self.amplitude, self.width, self.theta0)

    def inverse(self, points):
        return apply_shear_twist(points, self.center, self.amplitude, self.width, self.theta0,
                                 inverse=True)

    def bounds(self):
        return {"width": (0.0, np.inf)}


@dataclass(frozen=True, eq=False)
class Rotation(Warp):
    """Global rotation of the parameter sphere by ``rotation_vector`` (axis * angle); no bounds."""

    rotation_vector: np.ndarray
    kind: ClassVar[str] = "rotation"
    _sizes: ClassVar[dict] = {"rotation_vector": 3}

    def __post_init__(self):
        vector = np.asarray(self.rotation_vector, dtype=np.float64).reshape(3).copy()
        object.__setattr__(self, "rotation_vector", vector)

    def apply(self, points):
        return apply_rotation(points, self.rotation_vector)

    def inverse(self, points):
        return apply_rotation(points, self.rotation_vector, inverse=True)


class DisplacementField(Warp):
    """Shared behaviour of the fast strategy's field warps (:class:`FieldWarp` on the sphere,
    :class:`~.circle.CircleField` on the circle): an integer ``level``, ``coefficients`` of the
    shape ``_coefficient_shape`` (also when read back by :meth:`from_vector`), and no closed-form
    inverse."""

    _sizes: ClassVar[dict] = {"coefficients": -1}
    _integers: ClassVar[tuple] = ("level",)
    #: the shape of ``coefficients``
    _coefficient_shape: ClassVar[tuple] = (-1,)

    def __post_init__(self):
        object.__setattr__(self, "level", int(self.level))
        object.__setattr__(self, "coefficients", np.asarray(
            self.coefficients, dtype=np.float64).reshape(self._coefficient_shape))

    @classmethod
    def from_vector(cls, vector):
        warp = super().from_vector(vector)
        object.__setattr__(warp, "coefficients",
                           warp.coefficients.reshape(cls._coefficient_shape))
        return warp

    def inverse(self, points):
        raise NotImplementedError("a displacement field has no closed-form inverse")


@dataclass(frozen=True, eq=False)
class FieldWarp(DisplacementField):
    """A smooth tangent displacement field (:mod:`.fields`): bumps at the vertices of the
    ``level``-times subdivided icosahedron, each reaching ``support`` mean edge lengths, with
    vector coefficients (n_c, 3); u -> (u + v(u)) / |u + v(u)|. A homeomorphism while the
    coefficients stay within :meth:`.fields.FieldBasis.max_coefficient` (the fast strategy's
    bounds). Its inverse has no closed form: ``inverse`` is not available."""

    level: int
    support: float
    coefficients: np.ndarray
    kind: ClassVar[str] = "field"
    _coefficient_shape: ClassVar[tuple] = (-1, 3)

    def apply(self, points):
        return apply_field(self.level, points, self.coefficients, self.support)


WARP_KINDS: dict[str, type] = {cls.kind: cls for cls in
                               (SymmetricTheta, AsymmetricTheta, ShearTwist, Rotation, FieldWarp)}


def make_warp(kind: str, parameters: Mapping):
    """The warp of kind ``kind`` (a key of :data:`WARP_KINDS`) with these constructor parameters."""
    if kind not in WARP_KINDS:
        raise ArgumentError(f"unknown warp kind {kind!r}; expected one of {sorted(WARP_KINDS)}")
    return WARP_KINDS[kind](**parameters)


def apply_warp(points: np.ndarray, kind: str, parameters: Mapping) -> np.ndarray:
    """Apply one warp given by name and parameters, e.g.
    ``apply_warp(u, "shear_twist", {"center": p, "amplitude": 1, "width": 0.3, "theta0": 1})``."""
    return make_warp(kind, parameters).apply(points)


def apply_warps(points: np.ndarray, warps: Sequence) -> np.ndarray:
    """Apply ``warps`` in order, ``warps[0]`` first: each warp moves the current positions (eq. 12 as
    used in practice: every newly accepted warp is applied to the current sample positions)."""
    points = np.asarray(points, dtype=np.float64)
    for warp in warps:
        points = warp.apply(points)
    return points


def invert_warps(points: np.ndarray, warps: Sequence) -> np.ndarray:
    """Undo :func:`apply_warps` (``warps``): the inverses in reverse order."""
    points = np.asarray(points, dtype=np.float64)
    for warp in reversed(list(warps)):
        points = warp.inverse(points)
    return points


def with_amplitude(warp, amplitude: float):
    """A copy of a symmetric, asymmetric or shear/twist warp with another amplitude."""
    return replace(warp, amplitude=amplitude)


# ------------------------------------------------------------------------------------------------
# Random draws (III-D2 style): new warps start with amplitude zero, the identity, to be optimised


def random_symmetric_theta(rng: np.random.Generator, sigma_g: float,
                           center: np.ndarray | None = None,
                           amplitude: float = 0.0) -> SymmetricTheta:
    """Centre uniform on the sphere unless given, omega from :func:`random_width` (III-D2)."""
    center = random_unit_vector(rng) if center is None else center
    return SymmetricTheta(center, amplitude, random_width(rng, sigma_g))


def random_asymmetric_theta(rng: np.random.Generator, sigma_g: float,
                            center: np.ndarray | None = None, amplitude: float = 0.0,
                            b_range: tuple[float, float] = (0.1, 2.0)) -> AsymmetricTheta:
    """Centre uniform unless given; omega from :func:`random_width` as for the symmetric kernel
    (III-D2, sigma_G = 1/32 in Table I); psi0 uniform on [0, 2 pi) about the fixed
    :func:`perpendicular` reference; b log-uniform on ``b_range`` (the paper gives no
    distribution for b; the default spans lobes from about +-0.1 rad to nearly a cosine)."""
    center = random_unit_vector(rng) if center is None else center
    omega = random_width(rng, sigma_g)
    psi0 = float(rng.uniform(0.0, 2.0 * np.pi))
    b = float(np.exp(rng.uniform(np.log(b_range[0]), np.log(b_range[1]))))
    return AsymmetricTheta(center, perpendicular(center), amplitude, omega, psi0, b)


def random_shear_twist(rng: np.random.Generator, sigma_g: float,
                       center: np.ndarray | None = None, amplitude: float = 0.0) -> ShearTwist:
    """Centre uniform unless given; band width c from :func:`random_width` (half-normal sigma_G, by
    analogy with omega: the paper gives no distribution for c); theta0 with cos(theta0) uniform on
    [-1, 1], so the band's centre circle passes through a uniformly distributed point."""
    center = random_unit_vector(rng) if center is None else center
    width = random_width(rng, sigma_g)
    theta0 = float(np.arccos(rng.uniform(-1.0, 1.0)))
    return ShearTwist(center, amplitude, width, theta0)


def random_rotation(rng: np.random.Generator, sigma: float | None = None) -> Rotation:
    """A uniformly distributed rotation (Haar measure, via a random unit quaternion) when ``sigma``
    is None; else a uniform axis and an angle from the positive half of N(0, sigma), at most pi."""
    if sigma is None:
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        if q[0] < 0:
            q = -q
        vector_norm = float(np.linalg.norm(q[1:]))
        if vector_norm < 1e-15:
            return Rotation(np.zeros(3))
        angle = 2.0 * np.arctan2(vector_norm, q[0])
        return Rotation(q[1:] / vector_norm * angle)
    axis = random_unit_vector(rng)
    return Rotation(axis * min(abs(float(rng.normal(0.0, sigma))), np.pi))
