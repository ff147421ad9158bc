"""The statistical shape model: area-weighted PCA of corresponded, aligned shapes.

Shapes are (n_p, 3) arrays whose point k corresponds across examples. With the area weights w
(sum 1) the inner product of two shape differences is sum_k w_k a_k . b_k (eq. 15), so the mode
variances are mean squared displacements (mm^2). Modes are orthonormal in that inner product and a
shape is ``mean + sum_m b_m mode_m``; training scores have variance lambda_m (divisor n_s, as the
eigenvalues of D' / n_s in the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ShapeModel:
    """Mean, modes, variances and training scores of a point distribution model."""

    mean: np.ndarray                 # (n_p, 3)
    modes: np.ndarray                # (n_modes, n_p, 3), orthonormal in the weighted inner product
    variances: np.ndarray            # (n_modes,) lambda_m, descending
    weights: np.ndarray              # (n_p,) area weights, sum 1
    scores: np.ndarray               # (n_s, n_modes)
    names: list = field(default_factory=list)
    triangles: np.ndarray | None = None      # (m, 3) connectivity of the points (all parts)
    part_sizes: list = field(default_factory=list)
    metadata: dict = field(default_factory=dict)

    @classmethod
    def from_shapes(cls, shapes: np.ndarray, weights: np.ndarray, names=None, triangles=None,
                    part_sizes=None, relative_tolerance: float = 1e-10, **metadata):
        """Area-weighted PCA of aligned shapes (n_s, n_p, 3)."""
        shapes = np.asarray(shapes, dtype=np.float64)
        n_s, n_p, _ = shapes.shape
        mean = shapes.mean(axis=0)
        root = np.sqrt(weights)[None, :, None]
        z = ((shapes - mean) * root).reshape(n_s, -1)
        u, singular, vt = np.linalg.svd(z, full_matrices=False)
        variances = singular ** 2 / n_s
        keep = variances > relative_tolerance * max(variances.max(initial=0.0), 1e-300)
        modes = vt[keep].reshape(-1, n_p, 3) / root
        scores = u[:, keep] * singular[keep]
        return cls(mean=mean, modes=modes, variances=variances[keep], weights=np.asarray(weights),
                   scores=scores, names=list(names or [f"case_{i}" for i in range(n_s)]),
                   triangles=triangles, part_sizes=list(part_sizes or [n_p]), metadata=metadata)

    @property
    def n_modes(self) -> int:
        return len(self.variances)

    def instance(self, scores: np.ndarray) -> np.ndarray:
        """Shape for the first len(scores) mode scores."""
        scores = np.asarray(scores, dtype=np.float64)
        return self.mean + np.tensordot(scores, self.modes[:len(scores)], axes=1)

    def project(self, shape: np.ndarray, n_modes: int | None = None) -> np.ndarray:
        """Scores of a corresponded, aligned shape (weighted least squares = projection)."""
        modes = self.modes[:n_modes]
        return np.einsum("mkd,kd->m", modes, (shape - self.mean) * self.weights[:, None])

    def save(self, path):
        """Write the model to an HDF5 file."""
        import h5py

        with h5py.File(path, "w") as f:
            f.attrs["format"] = "mdlshapemodel"
            f.attrs["format_version"] = 1
            for key in ("mean", "modes", "variances", "weights", "scores"):
                f.create_dataset(key, data=getattr(self, key))
            if self.triangles is not None:
                f.create_dataset("triangles", data=self.triangles)
            f.create_dataset("part_sizes", data=np.asarray(self.part_sizes, dtype=np.int64))
            f.create_dataset("names", data=np.array(self.names, dtype=object),
                             dtype=h5py.string_dtype())
            for key, value in self.metadata.items():
                f.attrs[key] = value

    @classmethod
    def load(cls, path) -> "ShapeModel":
        """Read a model written by :meth:`save`."""
        import h5py

        with h5py.File(path, "r") as f:
            names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["names"][()]]
            return cls(mean=f["mean"][()], modes=f["modes"][()], variances=f["variances"][()],
                       weights=f["weights"][()], scores=f["scores"][()], names=names,
                       triangles=f["triangles"][()] if "triangles" in f else None,
                       part_sizes=[int(s) for s in f["part_sizes"][()]],
                       metadata={k: v for k, v in f.attrs.items()
                                 if k not in ("format", "format_version")})
