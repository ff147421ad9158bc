"""Landmark transfer: how far a correspondence carries each case's landmarks to the others.

For a template case i, a target case j != i and a label l that both have: i's landmark is located
on i's corresponded mesh (its closest point there: a triangle and barycentric coordinates),
put at the same triangle and coordinates of j's corresponded mesh (the sample points are the
same places in every case), and projected to the closest point of j's surface; the error is the
distance to j's landmark l. The *median of templates* takes, for each (j, l), the coordinate-wise
median of the predictions of every template that has l, projected to j's surface again, against
j's landmark: one template's misplaced landmark does not move it.

A landmark that guided the correspondence lands close to the given one by construction; only a
label that did not guide it (:func:`transfer_errors` on a correspondence made without it) shows
how well the correspondence lands where no landmark holds it (:class:`LandmarkCheck`).

Examples
--------
Carrying a landmark through the identity correspondence puts it where it was::

    >>> import numpy as np
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> vertices, faces = icosphere(2)
    >>> shapes = np.stack([10.0 * vertices] * 3)
    >>> marks = np.array([[[0.0, 0.0, 10.0]]] * 3)
    >>> errors = transfer_errors(shapes, faces, marks, [(10.0 * vertices, faces)] * 3)
    >>> float(np.nanmax(errors.median)) < 1e-9, errors.per_label()[1].tolist()
    (True, [3])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ArgumentError
from ..prepare.landmarks import barycentric
from ..prepare.surface import SurfaceDistance


def locate(mesh_points: np.ndarray, triangles: np.ndarray, points: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The closest point of each of ``points`` (k, 3) on the mesh (``mesh_points``,
    ``triangles``): its triangle (k,), barycentric coordinates (k, 3) and distance (k,), mm."""
    mesh_points = np.asarray(mesh_points, dtype=np.float64)
    triangles = np.asarray(triangles)
    closest, distance, face = SurfaceDistance(mesh_points, triangles).closest(
        np.asarray(points, dtype=np.float64).reshape(-1, 3))
    return face, barycentric(closest, mesh_points[triangles[face]]), distance


def transfer(points_i: np.ndarray, triangles: np.ndarray, landmarks_i: np.ndarray,
             points_j: np.ndarray) -> np.ndarray:
    """Carry the landmarks of case i to case(s) j through a correspondence.

    Parameters
    ----------
    points_i : ndarray (n_p, 3)
        Corresponded sample points of case i (point k is the same place on every case).
    triangles : ndarray (m, 3)
        The triangles of the corresponded meshes, shared by all cases.
    landmarks_i : ndarray (L, 3)
        Landmarks of case i, in the frame of ``points_i``.
    points_j : ndarray (n_p, 3), or (n_t, n_p, 3) for several targets at once
        Corresponded sample points of the target case(s).

    Returns
    -------
    ndarray (L, 3), or (n_t, L, 3)
        The landmarks' places on the target's corresponded mesh (not projected to its surface).
    """
    triangles = np.asarray(triangles)
    face, weights, _ = locate(points_i, triangles, landmarks_i)
    corners = np.asarray(points_j, dtype=np.float64)[..., triangles[face], :]   # (..., L, 3, 3)
    return np.einsum("...lkd,lk->...ld", corners, weights)


@dataclass(frozen=True)
class TransferErrors:
    """The landmark-transfer errors of one correspondence, mm (NaN where not defined).

    single : ndarray (n, n, L) or None
        [i, j, l]: template i's landmark l carried to case j, against j's (NaN for i = j and
        where i or j lacks l); None where not kept.
    median : ndarray (n, L)
        [j, l]: the median of templates against j's landmark l (NaN where j lacks l or no other
        case has it).
    located : ndarray (n, L)
        [i, l]: the distance of i's landmark l from i's own corresponded mesh (how closely the
        sample points' triangles cover the surface there; NaN where i lacks l).
    """

    single: np.ndarray | None
    median: np.ndarray
    located: np.ndarray

    def per_label(self) -> tuple[np.ndarray, np.ndarray]:
        """The mean over the target cases of the median of templates, per label (L,), and the
        number of target cases it is the mean of (L,) (NaN where there are none)."""
        counts = np.isfinite(self.median).sum(axis=0)
        sums = np.nansum(self.median, axis=0)
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan), counts


def transfer_errors(shapes: np.ndarray, triangles: np.ndarray, landmarks: np.ndarray,
                    surfaces: list, single: bool = True) -> TransferErrors:
    """The landmark-transfer errors of a correspondence (see the module docstring).

    Parameters
    ----------
    shapes : ndarray (n, n_p, 3)
        Every case's corresponded sample points, each in its case's own frame.
    triangles : ndarray (m, 3)
        Their triangles, shared by all cases.
    landmarks : ndarray (n, L, 3)
        Every case's landmarks in the same frame, a row of NaN where a case lacks a label.
    surfaces : list of (vertices, faces)
        Every case's surface in the same frame: the predictions are projected to it.
    single : bool
        Keep every single template's error (``TransferErrors.single``, n^2 L numbers; else
        None). The memory otherwise grows as n L.

    Returns
    -------
    TransferErrors
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    landmarks = np.asarray(landmarks, dtype=np.float64)
    n, n_l = landmarks.shape[:2]
    if len(shapes) != n or len(surfaces) != n:
        raise ArgumentError(f"{len(shapes)} shapes, {n} landmark sets and {len(surfaces)} surfaces")
    present = np.isfinite(landmarks).all(axis=2)
    # where each template's landmarks lie on its corresponded mesh: a triangle and weights
    faces = np.zeros((n, n_l), dtype=np.int64)
    weights = np.zeros((n, n_l, 3))
    located = np.full((n, n_l), np.nan)
    triangles = np.asarray(triangles)
    for i in range(n):
        rows = np.flatnonzero(present[i])
        if len(rows):
            faces[i, rows], weights[i, rows], located[i, rows] = locate(
                shapes[i], triangles, landmarks[i, rows])
    singles = np.full((n, n, n_l), np.nan) if single else None
    median = np.full((n, n_l), np.nan)
    for j in range(n):
        wanted = present & present[j] & (np.arange(n) != j)[:, None]        # [i, l]
        if not wanted.any():
            continue
        surface = SurfaceDistance(*surfaces[j])
        # every template's landmarks at their triangles and weights of j's corresponded mesh
        carried = np.einsum("ilcd,ilc->ild", shapes[j][triangles[faces]], weights)
        projected = np.full((n, n_l, 3), np.nan)
        projected[wanted] = surface.closest(carried[wanted])[0]
        if single:
            truth = np.broadcast_to(landmarks[j], projected.shape)
            singles[:, j][wanted] = np.linalg.norm(projected[wanted] - truth[wanted], axis=1)
        labels = np.flatnonzero(wanted.any(axis=0))
        consensus = np.stack([np.median(projected[wanted[:, l], l], axis=0) for l in labels])
        median[j, labels] = np.linalg.norm(surface.closest(consensus)[0] - landmarks[j, labels],
                                           axis=1)
    return TransferErrors(singles, median, located)


def landmark_array(prepared: list, landmarks: dict, labels) -> np.ndarray:
    """Every prepared case's landmarks of ``labels`` in the case's own frame (a mirrored case's
    mirrored as its surface was), (n, L, 3), a row of NaN where a case lacks a label.

    ``landmarks``: case name -> :class:`~mdlshapemodel.prepare.landmarks.Landmarks`, in the
    coordinates of each case's input file.
    """
    result = np.full((len(prepared), len(labels), 3), np.nan)
    for i, case in enumerate(prepared):
        marks = landmarks.get(case.name)
        for k, label in enumerate(labels):
            point = None if marks is None else marks.get(label)
            if point is not None:
                result[i, k] = point * ([-1.0, 1.0, 1.0] if case.mirrored else 1.0)
    return result


#: what the landmark check's numbers are, in words (metrics.json and the report)
CHECK_MEASURE = ("per case, every other case's landmark carried to it through the "
                 "correspondence (the same place on the corresponded meshes, put on the case's "
                 "surface), the median of those predictions against the case's own landmark; "
                 "the mean over the cases that have the label, mm")


@dataclass(frozen=True)
class LandmarkCheck:
    """How far a build's correspondence carries each landmark label (:func:`transfer_errors`,
    the median of templates, its mean over the cases), where the label does not guide it.

    labels : tuple of str, (L,)
    held_out : ndarray (L,)
        mm, from the correspondence optimised with the label left out of the guides (its fold
        of ``folds``), or from the build itself where nothing guides it.
    guided : ndarray (L,) or None
        mm, the same from the build's correspondence, which the label guided; None where the
        landmarks guided nothing (``folds`` empty).
    cases : ndarray (L,) int
        The cases each error is the mean over (those with the label, when another has it too).
    folds : list of tuple
        The labels left out of the guides together, one optimisation each.
    """

    labels: tuple
    held_out: np.ndarray
    guided: np.ndarray | None
    cases: np.ndarray
    folds: list

    def to_json(self) -> dict:
        """metrics.json's ``landmark_check``: per label the held-out error, the guided one and
        the number of cases; their means over the labels; the folds; what is measured."""
        guided = self.guided if self.guided is not None else np.full(len(self.labels), np.nan)
        return {"guided": self.guided is not None,
                "folds": [list(fold) for fold in self.folds],
                "per_label": {label: {"held_out_mm": _number(held), "guided_mm": _number(guide),
                                      "cases": int(cases)}
                              for label, held, guide, cases in zip(self.labels, self.held_out,
                                                                    guided, self.cases)},
                "mean": {"held_out_mm": _mean(self.held_out), "guided_mm": _mean(guided)},
                "measure": CHECK_MEASURE}


def _number(value: float) -> float | None:
    """A JSON number, None for NaN."""
    return float(value) if np.isfinite(value) else None


def _mean(values: np.ndarray) -> float | None:
    """The mean of the finite values, None where there are none."""
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if len(finite) else None
