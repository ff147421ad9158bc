"""Outward normals of corresponded shapes, and how well they agree across the cases: a check of
the correspondence that needs no ground truth.

Corresponded points that are the same anatomical place on every case have surface normals that
point the same way once the cases are aligned (up to the shapes' own variation). Where the
correspondence is wrong (a point sliding onto another side of a ridge, a case whose map is
twisted) the normals at that point disagree. Per model point k, with n_ik the unit outward normal
of case i there (in the model's frame):

- the mean resultant length R_k = |(1/n_s) sum_i n_ik|, in [0, 1] (1: every normal the same);
- the spread s_k = (1/n_s) sum_i angle(n_ik, m_k) in degrees, m_k = sum_i n_ik / |sum_i n_ik|
  the mean direction;

and per case and point the angle of its normal to the mean direction, so that a case whose
normals are off at many points can be named. A point where s_k exceeds :data:`SPREAD_DEGREES`
is flagged.

The check finds gross errors. It does not rank two correspondences of the same cases: the
shapes' own variation spreads normals too, and a correspondence that follows the surfaces more
smoothly than the true one can have the smaller spread (docs/benchmarks.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError

#: a point whose cases' normals lie on average more than this far from their mean direction is
#: flagged (the report, metrics.json), as is a case's normal this far from it (cases.csv)
SPREAD_DEGREES = 30.0
OFF_DEGREES = 60.0
#: a case whose normal is more than :data:`OFF_DEGREES` from the mean direction at more than this
#: share of the points is flagged (metrics.json ``flagged_cases``, the report, the build's
#: summary): a twisted correspondence has tens of such points where the other cases have 0 or 1
#: (docs/benchmarks.md, the femurs)
CASE_OFF_SHARE = 0.005


def outward_normals(points: np.ndarray, cells: np.ndarray, part_of=None) -> np.ndarray:
    """Unit normals at the points of a shape, turned out of what each part encloses: the
    area-weighted normals of its triangles (a part whose signed volume is negative is turned
    round), or for segments (2-D curves) the in-plane normals, a part turned round when they
    point into the area it encloses. ``part_of`` gives each cell's part (default: one part).
    A point in no cell gets a zero vector."""
    points = np.asarray(points, dtype=np.float64)
    cells = np.asarray(cells)
    part_of = np.zeros(len(cells), dtype=np.int64) if part_of is None else np.asarray(part_of)
    if cells.shape[1] == 3:
        a, b, c = (points[cells[:, k]] for k in range(3))
        face = np.cross(b - a, c - a)                  # length: twice the area
        inward = np.einsum("ij,ij->i", a, np.cross(b, c))     # 6 x signed volume per cell
    else:
        start, end = points[cells[:, 0]], points[cells[:, 1]]
        tangent = end - start
        face = np.stack([tangent[:, 1], -tangent[:, 0], np.zeros(len(tangent))], axis=1)
        inward = np.empty(len(cells))
        for part in np.unique(part_of):
            rows = part_of == part
            centre = points[np.unique(cells[rows])].mean(axis=0)
            inward[rows] = np.einsum("ij,ij->i", face[rows], (start + end)[rows] / 2 - centre)
    for part in np.unique(part_of):
        rows = part_of == part
        if inward[rows].sum() < 0:
            face[rows] = -face[rows]
    normals = np.zeros_like(points)
    for k in range(cells.shape[1]):
        for d in range(3):
            normals[:, d] += np.bincount(cells[:, k], weights=face[:, d], minlength=len(points))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


@dataclass(frozen=True)
class NormalAgreement:
    """How the cases' normals agree at each model point (see the module docstring)."""

    resultant: np.ndarray          # R_k, (n_p,)
    spread_degrees: np.ndarray     # s_k, (n_p,)
    angles_degrees: np.ndarray     # each case's normal to the mean direction, (n_s, n_p)

    @property
    def flagged(self) -> np.ndarray:
        """The points whose spread exceeds :data:`SPREAD_DEGREES`."""
        return self.spread_degrees > SPREAD_DEGREES

    def cases_off(self) -> np.ndarray:
        """Per case, how many points have its normal more than :data:`OFF_DEGREES` from the
        mean direction."""
        return np.count_nonzero(self.angles_degrees > OFF_DEGREES, axis=1)

    def cases_flagged(self) -> np.ndarray:
        """Per case, whether its normal is off (:meth:`cases_off`) at more than
        :data:`CASE_OFF_SHARE` of the points."""
        return self.cases_off() > CASE_OFF_SHARE * self.angles_degrees.shape[1]


def normal_agreement(shapes: np.ndarray, cells: np.ndarray, part_of=None) -> NormalAgreement:
    """The agreement of corresponded normals across aligned shapes.

    Parameters
    ----------
    shapes : ndarray (n_s, n_p, 3)
        Corresponded shapes in one frame (the model's aligned shapes).
    cells : ndarray (n_cells, 3) or (n_cells, 2)
        Triangles (or segments of 2-D curves) shared by every shape.
    part_of : ndarray (n_cells,), optional
        Each cell's part (parts are turned outwards one by one).

    Returns
    -------
    NormalAgreement

    Examples
    --------
    >>> square = np.array([[0., 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    >>> segments = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
    >>> turned = square[[1, 2, 3, 0]]          # the same square, its points moved round by one
    >>> agreement = normal_agreement(np.stack([square, turned]), segments)
    >>> agreement.spread_degrees.round(1).tolist()
    [45.0, 45.0, 45.0, 45.0]
    >>> agreement.resultant.round(3).tolist()
    [0.707, 0.707, 0.707, 0.707]
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 2:
        raise ArgumentError("shapes must be (n_s >= 2, n_p, 3)")
    normals = np.empty_like(shapes)        # filled case by case: no list of them to stack
    for normal, shape in zip(normals, shapes):
        normal[...] = outward_normals(shape, cells, part_of)
    total = normals.sum(axis=0)
    length = np.linalg.norm(total, axis=1)
    direction = total / np.where(length > 0, length, 1.0)[:, None]
    cosines = np.clip(np.einsum("ipk,pk->ip", normals, direction), -1.0, 1.0)
    angles = np.degrees(np.arccos(cosines))
    return NormalAgreement(resultant=length / len(shapes), spread_degrees=angles.mean(axis=0),
                           angles_degrees=angles)
