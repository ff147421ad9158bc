"""A prior on smooth correspondence: the thin-plate bending energy of every example's displacement
from the mean shape (docs/method.md section 8).

With the mean's points m_k (the state's reference) and the thin-plate kernel of three dimensions,
U(r) = -r, the bending-energy matrix B (n_p x n_p) is the upper-left block of the inverse of
[[K, P], [P^T, 0]], K_jk = U(|m_j - m_k|), P = [1, m]: for displacements D (n_p x 3) given at
the points, tr(D^T B D) is the bending energy of the smoothest (thin-plate) deformation that
interpolates them, zero for an affine one. The prior adds

    E = (w / 2) sum_i tr(D_i^T B~ D_i) / h^2,   D_i = X_i - Xbar,

to F, B~ = s B scaled by the mean's RMS radius s (so that E does not change with the shapes'
size), h the mean voxel size and w ``--smoothness``. Sliding the sample points along the
surfaces in a way that makes the cases differ from the mean by a non-smooth displacement costs;
a correspondence in which the cases differ by smooth deformations, as anatomy tends to, costs
little. Since sum_i D_i = 0, dE/dX_i = (w / h^2) B~ D_i. B is computed from the mean at every
rebuild of the state and held fixed in between, as the area weights are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import hotloops


def bending_matrix(points: np.ndarray) -> np.ndarray:
    """B~ (n, n): the thin-plate bending-energy matrix of points (n, 3), times their RMS radius.

    Examples
    --------
    >>> import numpy as np
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> points = icosphere(1)[0] * [3.0, 2.0, 1.0]
    >>> b = bending_matrix(points)
    >>> affine = points @ np.array([[1.0, 0.2, 0], [0, 1, 0.3], [0.1, 0, 1]]) + [1.0, 2.0, 3.0]
    >>> bool(abs(np.trace(affine.T @ b @ affine)) < 1e-9)
    True
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    system = np.zeros((n + 4, n + 4))
    hotloops.negated_distances(points, system[:n, :n])    # K_jk = U(|m_j - m_k|) = -r
    system[:n, n] = system[n, :n] = 1.0
    system[:n, n + 1:] = points
    system[n + 1:, :n] = points.T
    inverse = np.linalg.inv(system)
    radius = float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))
    block = inverse[:n, :n] * radius
    return 0.5 * (block + block.T)


@dataclass
class Smoothness:
    """The prior's weight w and scale h (mm); :meth:`at` gives its terms about a mean shape."""

    weight: float
    scale: float

    def at(self, mean: np.ndarray) -> "SmoothnessTerms":
        return SmoothnessTerms(self.weight / self.scale ** 2, bending_matrix(mean))


@dataclass
class SmoothnessTerms:
    """The prior about one mean shape: ``factor`` w / h^2 and ``matrix`` B~ (the state keeps
    B~ D_i of its shapes and updates them as an example changes)."""

    factor: float
    matrix: np.ndarray

    def energy(self, shapes: np.ndarray) -> tuple[float, np.ndarray]:
        """E of shapes (n_s, n_p, 3) and B~ D_i of every example, (n_s, n_p, 3)."""
        displacements = shapes - shapes.mean(axis=0)
        n_s, n_p, _ = displacements.shape
        # one matrix product (BLAS) for all examples: B~ (n_p, n_p) by (n_p, 3 n_s)
        bent = np.ascontiguousarray((self.matrix @ displacements.transpose(1, 0, 2)
                                     .reshape(n_p, -1)).reshape(n_p, n_s, 3).transpose(1, 0, 2))
        return 0.5 * self.factor * float(np.sum(displacements * bent)), bent

    def trial(self, energy: float, bent: np.ndarray, delta: np.ndarray, n_s: int
              ) -> tuple[float, np.ndarray]:
        """E' with one example's shape moved by ``delta`` (n_p, 3), from the energy ``energy`` of
        n_s shapes and that example's B~ D_i (``bent``), and B~ Delta:
        E' = E + w/h^2 [tr(Delta^T B~ D_i) + (1 - 1/n_s) tr(Delta^T B~ Delta) / 2] (the other
        displacements move by -Delta / n_s, and sum_j D_j = 0)."""
        bent_delta = self.matrix @ delta
        change = self.factor * (float(np.sum(delta * bent))
                                + 0.5 * (1.0 - 1.0 / n_s) * float(np.sum(delta * bent_delta)))
        return energy + change, bent_delta
