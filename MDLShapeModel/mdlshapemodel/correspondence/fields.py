"""Smooth tangent displacement fields on the sphere: small homeomorphisms with many parameters.

A field v(u) = (I - u u^T) sum_j g(|u - P_j| / r) c_j moves every sphere point u tangentially, by
a sum of compactly supported bumps centred at P_j (the vertices of an icosphere) with free vector
coefficients c_j in R^3 (their normal parts are projected away). The map

    u -> phi(u) = (u + v(u)) / |u + v(u)|

is a homeomorphism of the sphere when v is small in the C^1 sense: if |v| < 1 and the Lipschitz
constant of v is below 1, u + v(u) is injective and never zero, so phi is a local diffeomorphism of
degree 1, hence bijective. ``FieldBasis.max_coefficient`` gives a bound on |c_j| that guarantees
this; an optimiser also checks the sampling grid for flipped triangles, as for the kernels.

Unlike a composition of theta kernels, phi is linear in the coefficients before the projection, so
its derivative with respect to all coefficients at once is cheap: this is what a gradient-based
optimiser needs. Compositions of such maps (one per optimisation round, coarse to fine) represent
large reparameterizations.

The bump is Wendland's C^2 function g(d) = (1 - d)^4 (4 d + 1) for d < 1, 0 beyond (Wendland 1995).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from . import hotloops
from .sampling import icosphere

#: max |g'(d)| of the Wendland C^2 function on [0, 1] (at d = 1/4: 20 d (1 - d)^3 = 135/64)
WENDLAND_SLOPE = 135.0 / 64.0


def wendland(d: np.ndarray) -> np.ndarray:
    """g(d) = (1 - d)^4 (4 d + 1) on [0, 1), 0 beyond."""
    d = np.asarray(d, dtype=np.float64)
    return np.where(d < 1.0, (1.0 - d) ** 4 * (4.0 * d + 1.0), 0.0)


@functools.lru_cache(maxsize=None)
def _icosphere_centres(level: int) -> tuple[np.ndarray, float]:
    """The vertices of the ``level``-times subdivided icosahedron (read-only) and its mean edge
    length (a round builds one basis per example at the same level)."""
    centres, triangles = icosphere(level)
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    edge = float(np.mean(np.linalg.norm(centres[edges[:, 0]] - centres[edges[:, 1]], axis=1)))
    centres.flags.writeable = False
    return centres, edge


def apply_field(level: int, points: np.ndarray, coefficients: np.ndarray,
                support: float = 2.0) -> np.ndarray:
    """phi(u_k) of :meth:`FieldBasis.icosphere_level` ``(level, points, support)`` and
    ``coefficients`` (n_c, 3), bit for bit, without making the basis: for a map applied once
    (a field replayed on a grid), each point's bumps are found and summed in one pass."""
    centres, edge = _icosphere_centres(level)
    return hotloops.field_map(np.asarray(points, dtype=np.float64), centres, support * edge,
                              np.ascontiguousarray(coefficients, dtype=np.float64))[0]


@dataclass
class FieldBasis:
    """The bumps of one resolution level, evaluated at a fixed set of sphere points.

    Parameters
    ----------
    centres : ndarray (n_c, 3)
        Unit vectors P_j.
    radius : float
        Support radius r (chord length) of every bump.
    points : ndarray (n, 3)
        The sphere points u_k where the field is evaluated (e.g. the current sample positions).
    """

    centres: np.ndarray
    radius: float
    points: np.ndarray

    def __post_init__(self):
        self.centres = np.asarray(self.centres, dtype=np.float64)
        self.points = np.asarray(self.points, dtype=np.float64)
        indptr, indices, data = hotloops.bump_matrix(self.points, self.centres, self.radius)
        #: sparse (n, n_c) matrix of bump values g_j(u_k), columns sorted in each row; its values
        #: copied out of the buffer that bump_matrix grew (a round holds a basis per case and
        #: part, and that buffer's room beyond the filled part with it)
        self.weights = sparse.csr_matrix((data.copy(), indices, indptr),
                                         shape=(len(self.points), len(self.centres)))
        rows = np.diff(indptr)
        self.overlap = int(rows.max(initial=0))

    @classmethod
    def icosphere_level(cls, level: int, points: np.ndarray, support: float = 2.0) -> "FieldBasis":
        """Bumps at the vertices of the ``level``-times subdivided icosahedron, each reaching
        ``support`` times the mean edge length."""
        centres, edge = _icosphere_centres(level)
        return cls(centres, support * edge, points)

    @property
    def n_centres(self) -> int:
        return len(self.centres)

    def max_coefficient(self, safety: float = 0.5) -> float:
        """A bound B on every |c_j| (Euclidean) under which phi is a homeomorphism.

        With at most ``overlap`` bumps non-zero at any point, |v| <= overlap * B and the Lipschitz
        constant of v is at most overlap * B * (slope / r + 2) (the bump's slope, and the tangent
        projection, whose derivative is bounded by 2 |c|). Both stay below ``safety`` < 1.
        """
        per_unit = max(self.overlap, 1) * (WENDLAND_SLOPE / self.radius + 2.0)
        return safety / per_unit

    def displacement(self, coefficients: np.ndarray) -> np.ndarray:
        """v(u_k) (n, 3) for coefficients (n_c, 3)."""
        raw = self.weights @ coefficients
        return raw - np.einsum("kd,kd->k", raw, self.points)[:, None] * self.points

    def apply(self, coefficients: np.ndarray) -> np.ndarray:
        """phi(u_k) = (u_k + v_k) / |u_k + v_k|."""
        return self.map(coefficients)[0]

    def map(self, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """phi(u_k) (n, 3) and |u_k + v_k| (n,), which :meth:`coefficient_gradient` can reuse."""
        w = self.weights
        return hotloops.field_apply(w.indptr, w.indices, w.data, self.points,
                                    np.ascontiguousarray(coefficients, dtype=np.float64))

    def coefficient_gradient(self, coefficients: np.ndarray, position_gradient: np.ndarray,
                             mapped: tuple | None = None) -> np.ndarray:
        """Chain rule: dF/dc (n_c, 3) from dF/dphi(u_k) (n, 3); ``mapped``: :meth:`map` of the
        same coefficients, when already computed.

        phi = m / |m| with m = u + (I - u u^T) W c: dphi/dm = (I - phi phi^T) / |m|, and
        dm/dc_j = g_j(u) (I - u u^T).
        """
        phi, norms = self.map(coefficients) if mapped is None else mapped
        w = self.weights
        return hotloops.field_gradient(w.indptr, w.indices, w.data, self.points, phi, norms,
                                       np.ascontiguousarray(position_gradient, dtype=np.float64),
                                       self.n_centres)
