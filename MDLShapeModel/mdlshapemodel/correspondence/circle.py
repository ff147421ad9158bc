"""Closed 2-D curves in the optimisation: the sampling grid on the circle, warps of the circle, and
:class:`CurvePart`, the curve counterpart of :class:`~.state.PartState`.

A curve S(t) is parameterised by arc length on the unit circle (:func:`~..prepare.curve.curve_map`)
and sampled at n_p equally spaced angles u_k (:func:`circle_grid`). Its reparameterization phi is a
monotonic homeomorphism of the circle, kept as the sample positions phi(u_k): real numbers (lifts
of the angles), strictly increasing and spanning less than one turn, so a correspondence can
never fold. Three kinds of warps make phi (docs/method.md section 3, last bullet):

* :class:`CircleKernel`: the circle analogue of the symmetric theta map (eq. 10), t -> c + f(t - c)
  with f odd, f(x) = [x + A C(x)] / (1 + A) on [0, pi], C the CDF of the wrapped Cauchy of width
  omega (Davies et al., IVC 2003): the CDF of constant + wrapped Cauchy, strictly increasing for
  A > -(1 - a)/(1 + a), fixing the centre c and its antipode;
* :class:`CircleShift`: a shift of the origin, t -> t + s;
* :class:`CircleField`: the ``fast`` strategy's displacement field, t -> t + s + v(t),
  v(t) = sum_j g(d(t, c_j) / r) a_j (Wendland bumps at equally spaced centres), monotone while
  |v'| < 1 (:meth:`CircleFieldBasis.max_coefficient`).

They are :class:`~.warps.Warp` dataclasses like the sphere's, registered in
:data:`~.warps.WARP_KINDS` when this module is imported (it is, wherever a curve state exists).

Shapes stay (n_p, 3) arrays: a curve's samples are 3-D points with z = 0, and a state made only of
curves is *planar* (:attr:`CorrespondenceState.planar`): its poses rotate about z only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Sequence

import numpy as np

from ..errors import ArgumentError
from ..prepare.curve import CurveMap, align_curve_origins, check_curve, curve_map
from .fields import WENDLAND_SLOPE, wendland
from .state import CorrespondenceState, Example, PartState
from .warps import (WARP_KINDS, DisplacementField, Warp, minimum_amplitude, theta_map,
                    theta_map_inverse)

TWO_PI = 2.0 * np.pi


def circle_grid(n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The sampling grid on the circle: ``n_points`` equally spaced angles u_k = 2 pi k / n_p and
    the cyclic segments (n_p, 2) joining consecutive ones (the 2-D counterpart of
    :func:`~.sampling.sphere_grid`'s triangles)."""
    if n_points < 8:
        raise ArgumentError(f"at least 8 sample points are needed on a curve, got {n_points}")
    k = np.arange(n_points)
    return TWO_PI * k / n_points, np.stack([k, (k + 1) % n_points], axis=1).astype(np.int64)


def circular_offset(t: np.ndarray, center: float) -> np.ndarray:
    """t - center wrapped into [-pi, pi]."""
    x = np.asarray(t, dtype=np.float64) - center
    return x - TWO_PI * np.round(x / TWO_PI)


def apply_circle_kernel(t: np.ndarray, center: float, amplitude: float, omega: float,
                        inverse: bool = False) -> np.ndarray:
    """The circle kernel (eq. 10 on the circle) about ``center``, or its inverse, on angles t.

    With x = t - c wrapped into [-pi, pi], t -> t + sign(x) f(|x|) - x, f(theta) =
    :func:`~.warps.theta_map` (theta, A, omega); the lift is kept (t + 2 pi maps to its image
    + 2 pi). f(0) = 0, f(pi) = pi and f' = (1 + A rho) / (1 + A) > 0 (rho the wrapped Cauchy
    density, scaled to peak (1 + a)/(1 - a)): a homeomorphism of the circle for every
    A > :func:`~.warps.minimum_amplitude` (omega).
    """
    t = np.asarray(t, dtype=np.float64)
    if amplitude == 0.0:
        return t
    x = circular_offset(t, center)
    magnitude = np.abs(x)
    if inverse:
        moved = theta_map_inverse(magnitude, amplitude, omega)
    else:
        moved = theta_map(magnitude, amplitude, omega)
    return t + (np.sign(x) * moved - x)


@dataclass(frozen=True, eq=False)
class CircleKernel(Warp):
    """The circle kernel about the angle ``center``: see :func:`apply_circle_kernel`."""

    center: float
    amplitude: float
    omega: float
    kind: ClassVar[str] = "circle_kernel"

    def __post_init__(self):
        object.__setattr__(self, "center", float(self.center))

    def apply(self, points):
        return apply_circle_kernel(points, self.center, self.amplitude, self.omega)

    def inverse(self, points):
        return apply_circle_kernel(points, self.center, self.amplitude, self.omega, inverse=True)

    def bounds(self):
        return {"amplitude": (minimum_amplitude(self.omega), np.inf), "omega": (0.0, np.inf)}


@dataclass(frozen=True, eq=False)
class CircleShift(Warp):
    """A shift of the circle's origin, t -> t + ``shift`` (a rotation of the parameter circle)."""

    shift: float
    kind: ClassVar[str] = "circle_shift"

    def apply(self, points):
        return np.asarray(points, dtype=np.float64) + self.shift

    def inverse(self, points):
        return np.asarray(points, dtype=np.float64) - self.shift


class CircleFieldBasis:
    """Wendland bumps g(d(t, c_j) / r) at ``8 * 2**level`` equally spaced centres c_j, each reaching
    ``support`` centre spacings (r), evaluated at angles ``points`` (a dense (n, n_c) matrix:
    curves have few samples)."""

    def __init__(self, level: int, support: float, points: np.ndarray):
        self.level, self.support = int(level), float(support)
        self.points = np.asarray(points, dtype=np.float64)
        self.n_centres = 8 * 2 ** self.level
        self.centres = TWO_PI * np.arange(self.n_centres) / self.n_centres
        self.radius = self.support * TWO_PI / self.n_centres
        distance = np.abs(circular_offset(self.points[:, None], self.centres[None, :]))
        self.weights = wendland(distance / self.radius)
        #: the most bumps non-zero at any angle (not only at ``points``): an open interval of
        #: 2 r = 2 support spacings holds at most ceil(2 support) centres
        self.overlap = int(np.ceil(2.0 * self.support))

    def max_coefficient(self, safety: float = 0.5) -> float:
        """A bound B on every |a_j| under which t -> t + s + v(t) is strictly increasing on the
        whole circle: |v'| <= overlap * B * slope / r <= ``safety`` < 1."""
        return safety * self.radius / (max(self.overlap, 1) * WENDLAND_SLOPE)

    def apply(self, coefficients: np.ndarray, shift: float = 0.0) -> np.ndarray:
        """t_k + s + v(t_k)."""
        return (self.points + shift) + self.weights @ np.asarray(coefficients, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class CircleField(DisplacementField):
    """The fast strategy's map of one round on a curve: t -> t + ``shift`` + v(t) with bumps of
    ``level`` and ``support`` (:class:`CircleFieldBasis`) and coefficients a_j. A homeomorphism
    while |a_j| <= :meth:`CircleFieldBasis.max_coefficient`; no closed-form inverse."""

    level: int
    support: float
    shift: float
    coefficients: np.ndarray
    kind: ClassVar[str] = "circle_field"

    def apply(self, points):
        return CircleFieldBasis(self.level, self.support, points).apply(self.coefficients,
                                                                        self.shift)


WARP_KINDS.update({cls.kind: cls for cls in (CircleKernel, CircleShift, CircleField)})
#: the warp kinds of curves
CIRCLE_WARP_KINDS = (CircleKernel.kind, CircleShift.kind, CircleField.kind)


class CurvePart(PartState):
    """One closed 2-D curve of one example: the counterpart of :class:`~.state.PartState` with the
    same interface, the sphere replaced by the circle.

    ``positions`` are angles (n_p,) (lifts: strictly increasing, within one turn), ``points`` the
    samples (n_p, 3) with z = 0, ``hint`` the segment of the curve each sample lies in, ``grid``
    the grid angles and ``grid_triangles`` the grid's segments (n_p, 2). ``propose``, ``commit``,
    ``replay``, ``feasible_parameter`` and ``warp_counts`` are the sphere part's.

    Parameters
    ----------
    curve : CurveMap
        The curve and its arc-length parameterization.
    grid, grid_segments : ndarray
        :func:`circle_grid`.
    """

    planar = True
    kind = "circle"

    def __init__(self, curve: CurveMap, grid: np.ndarray, grid_segments: np.ndarray):
        self.curve = curve
        self.knots = np.append(curve.parameter, TWO_PI)
        closed = np.vstack([curve.points, curve.points[:1]])
        self.vertices = np.column_stack([curve.points, np.zeros(len(curve.points))])
        #: dS/dt on each segment of the curve (n, 3), z = 0
        self.tangents = np.column_stack([np.diff(closed, axis=0) / np.diff(self.knots)[:, None],
                                         np.zeros(len(curve.points))])
        self.start_at(grid, grid_segments)

    def sample(self, positions: np.ndarray, hint: np.ndarray | None = None):
        """S(phi(u_k)) (n, 3) at angles ``positions`` and the curve segment of each (``hint`` is
        not needed: a segment is found by bisection)."""
        t = np.mod(np.asarray(positions, dtype=np.float64), TWO_PI)
        segment = np.searchsorted(self.knots, t, side="right") - 1
        segment = np.clip(segment, 0, len(self.tangents) - 1)
        points = self.vertices[segment] + (t - self.knots[segment])[:, None] * \
            self.tangents[segment]
        return points, segment

    def tangent(self, segments: np.ndarray) -> np.ndarray:
        """dS/dt (n, 3) on the given curve segments: the polyline's direction times L / (2 pi)."""
        return self.tangents[segments]

    def random_surface_parameter(self, rng: np.random.Generator) -> float:
        """An angle drawn uniformly over the curve's arc length (uniform on the circle, since the
        parameterization is by arc length)."""
        return TWO_PI * float(rng.random())

    def folds(self, positions: np.ndarray) -> bool:
        """True unless ``positions`` are strictly increasing cyclically: every forward difference
        (modulo 2 pi, the last to the first plus a turn) positive, winding exactly once."""
        positions = np.asarray(positions, dtype=np.float64)
        steps = np.mod(np.diff(positions, append=positions[0] + TWO_PI), TWO_PI)
        return bool(np.any(steps <= 0.0) or round(float(steps.sum()) / TWO_PI) != 1)

    def kernel(self, center, amplitude: float, omega: float) -> CircleKernel:
        """The part's kernel warp (the strategies draw kernels through this)."""
        return CircleKernel(center, amplitude, omega)

    def shift(self, shift: float) -> CircleShift:
        """A shift of the part's origin (one-at-a-time steps on curves also try one)."""
        return CircleShift(shift)

    def feasible_amplitude(self, center, omega: float, upper: float, steps: int = 12) -> float:
        """Largest amplitude in [0, upper] (to 2**-steps relative) that folds no sample pair."""
        return self.feasible_parameter(
            lambda amplitude: apply_circle_kernel(self.positions, center, amplitude, omega),
            upper, steps)

    @staticmethod
    def kernel_centres(level: int) -> np.ndarray:
        """The kernel centres that level ``level`` of III-D1 adds: 4 at level 0, then halfway
        between all earlier ones (4 * 2**(level - 1) at level >= 1)."""
        if level == 0:
            return TWO_PI * np.arange(4) / 4
        earlier = 4 * 2 ** (level - 1)
        return TWO_PI * (np.arange(earlier) + 0.5) / earlier


def curve_state(curves: Sequence, names: Sequence[str], n_points, scaling: bool = True,
                align_origins: bool = True) -> CorrespondenceState:
    """The initial correspondence state of a population of closed curves.

    Parameters
    ----------
    curves : sequence
        Per example: its curve (a :class:`~..prepare.curve.CurveMap`, or points (n, 2) that
        :func:`~..prepare.curve.check_curve` accepts), or a list of them, one per part (all
        examples with the same number of parts).
    names : sequence of str
        The examples' names.
    n_points : int or sequence of int
        Samples per part (:func:`circle_grid`).
    scaling : bool
        Whether Procrustes alignment removes scale.
    align_origins : bool
        Align each part's origins across the population first
        (:func:`~..prepare.curve.align_curve_origins`).

    Returns
    -------
    CorrespondenceState
        Planar (poses rotate about z only), every part a :class:`CurvePart` sampled at its grid,
        Procrustes-aligned (eq. 18), with the length weights of eq. 17 in 2-D.
    """
    per_example = [list(c) if isinstance(c, (list, tuple)) else [c] for c in curves]
    if len(per_example) != len(names):
        raise ArgumentError(f"{len(per_example)} examples but {len(names)} names")
    n_parts = len(per_example[0])
    if any(len(parts) != n_parts for parts in per_example):
        raise ArgumentError("every example must have the same number of parts")
    counts = [int(n_points)] * n_parts if np.isscalar(n_points) else [int(n) for n in n_points]
    if len(counts) != n_parts:
        raise ArgumentError(f"{len(counts)} sample counts for {n_parts} parts")
    maps = [[c if isinstance(c, CurveMap) else curve_map(check_curve(c)) for c in parts]
            for parts in per_example]
    if align_origins:
        by_part = [align_curve_origins([parts[j] for parts in maps]) for j in range(n_parts)]
        maps = [[by_part[j][i] for j in range(n_parts)] for i in range(len(maps))]
    grids = [circle_grid(n) for n in counts]
    examples = [Example(str(name), [CurvePart(m, *grid) for m, grid in zip(parts, grids)])
                for name, parts in zip(names, maps)]
    return CorrespondenceState(examples, grids, scaling=scaling)
