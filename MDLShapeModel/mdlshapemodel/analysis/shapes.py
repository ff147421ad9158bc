"""The corresponded shapes an analysis compares: read from a build, aligned, and the mean
surface's outward normals along which displacements are measured.

A build writes each case's corresponded points in the physical space of its input (a mirrored
case reflected back over its input). The analysis takes them in the model's frame (mirrored cases
reflected again, so that all are of one side: :meth:`~mdlshapemodel.folders.BuildFolder.shapes`)
and aligns them by weighted generalized Procrustes (eq. 18, the model's area weights):

- ``size="kept"`` (default): rotation and translation only, so that a difference in size (a loss
  of volume) shows as a difference of shape, in mm;
- ``size="removed"``: each case first scaled to the population's mean centroid size, so that only
  shape differences remain (units: mm at the mean size).
"""

from __future__ import annotations

import numpy as np

from ..config import ANALYSIS_SIZES as SIZES
from ..config import SUPERIMPOSITIONS, AnalysisConfig
from ..geometry import centroid_size, generalized_procrustes
from ..errors import InputError
from ..folders import BuildFolder, BuildShapes
from ..model.normals import outward_normals
from .superimposition import resistant_procrustes


def read_build(folder) -> BuildShapes:
    """The model and corresponded shapes of a build folder (``mdlshapemodel build -o FOLDER``)
    in the model's frame (:meth:`~mdlshapemodel.folders.BuildFolder.shapes`).

    Raises InputError naming the folder and what is missing when it is not a finished build.
    """
    return BuildFolder(folder).shapes()


def align(shapes: np.ndarray, weights: np.ndarray, size: str = "kept",
          planar: bool = False,
          superimposition: str = AnalysisConfig.superimposition) -> np.ndarray:
    """Shapes (n, p, 3) aligned by weighted generalized Procrustes without scaling (eq. 18);
    ``size="removed"`` scales each to the mean centroid size first; ``superimposition=
    "resistant"`` (the analysis's default) reweights each case's points by a biweight of their
    residuals (:func:`~.superimposition.resistant_procrustes`), ``"least-squares"`` does not.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> base = rng.normal(size=(30, 3))
    >>> shapes = np.stack([base + 5.0 * k for k in range(4)])      # translated copies
    >>> aligned = align(shapes, np.full(30, 1 / 30))
    >>> float(np.abs(aligned - aligned[0]).max()) < 1e-9
    True
    """
    if size not in SIZES:
        raise InputError(f"size must be one of {', '.join(SIZES)}, not {size!r}")
    if superimposition not in SUPERIMPOSITIONS:
        raise InputError(f"superimposition must be one of {', '.join(SUPERIMPOSITIONS)}, "
                         f"not {superimposition!r}")
    shapes = np.asarray(shapes, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    weights = weights / weights.sum()          # Procrustes takes weights that sum to 1
    if size == "removed":
        sizes = np.array([centroid_size(x, weights) for x in shapes])
        centres = np.einsum("p,npd->nd", weights, shapes)
        shapes = ((shapes - centres[:, None]) * (sizes.mean() / sizes)[:, None, None]
                  + centres[:, None])
    if superimposition == "resistant":
        return resistant_procrustes(shapes, weights, planar=planar).aligned
    aligned, _ = generalized_procrustes(shapes, weights, scaling=False, planar=planar)
    return aligned


def vertex_normals(points: np.ndarray, cells: np.ndarray | None, part_of=None) -> np.ndarray:
    """Unit outward normals at the points of a mean shape (:func:`outward_normals`), each
    point's defined: InputError when the model has no cells or a point lies in none.

    Examples
    --------
    >>> square = np.array([[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    >>> segments = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    >>> vertex_normals(square, segments)[0].round(3).tolist()
    [-0.707, -0.707, 0.0]
    """
    if cells is None or len(cells) == 0:
        raise InputError("the model has no triangles or segments: no normals to measure along")
    normals = outward_normals(points, cells, part_of)
    if np.any(np.linalg.norm(normals, axis=1) == 0):
        raise InputError("the mean shape has points with no normal (degenerate cells)")
    return normals
