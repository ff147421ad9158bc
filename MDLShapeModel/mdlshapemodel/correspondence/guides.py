"""Landmarks as guides of the correspondence: a term of the objective that keeps each labelled
landmark at one shared place of the parameter sphere across the cases (docs/method.md section 7).

Each label l gets one sample point of the grid, k_l (the grid vertex nearest the label's shared
place g_l after the landmark-guided alignment of the parameterizations,
:func:`~mdlshapemodel.prepare.sphere.align_parameterizations`). The term

    C = (lambda / 2) sum_i sum_l m_il |y_i,k_l - p_il|^2 / h^2

adds to F: y_i,k_l = S_i(phi_i(u_k_l)) is example i's sample at that grid point, in its own
(unposed) coordinates, p_il its landmark l put on its surface, m_il whether it has one, h the
mean voxel size and lambda ``--landmark-weight``. A landmark one voxel from its sample point costs
lambda / 2 nats. C does not depend on the poses, so the strategies add it to F and its gradient
(dC/dy_i,k_l = lambda m_il (y_i,k_l - p_il) / h^2) to the chain rule of the sample points alone.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import ArgumentError
from ..prepare.landmarks import on_surface
from ..prepare.sphere import shared_places


#: a given landmark farther than this many voxels from its case's surface is reported
FAR_VOXELS = 5.0


@dataclass(frozen=True)
class Guides:
    """The landmark term of one correspondence state.

    labels : tuple of str, (n_l,)
    indices : ndarray (n_l,) int
        The row of the shape vector (the part's offset plus the grid vertex k_l) of each label.
    targets : ndarray (n_s, n_l, 3)
        Each example's landmarks on its surface, in its own coordinates (unused where absent).
    present : ndarray (n_s, n_l) bool
    weight : float
        lambda.
    scale : float
        h, mm.
    off_surface : ndarray (n_s, n_l), optional
        How far each given landmark was from its case's surface (mm; 0 where absent).
    """

    labels: tuple
    indices: np.ndarray
    targets: np.ndarray
    present: np.ndarray
    weight: float
    scale: float
    off_surface: np.ndarray | None = None

    def far_from_surface(self, names: list, voxels: float = FAR_VOXELS) -> list:
        """(case name, label, mm) of every given landmark more than ``voxels`` voxels from its
        case's surface: likely in other coordinates than the case's file (RAS for LPS)."""
        if self.off_surface is None:
            return []
        cases, labels = np.nonzero(self.present & (self.off_surface > voxels * self.scale))
        return [(names[i], self.labels[k], float(self.off_surface[i, k]))
                for i, k in zip(cases, labels)]

    def costs(self, raw: np.ndarray) -> np.ndarray:
        """C_i of every example (n_s,) from the unposed samples ``raw`` (n_s, n_p, 3)."""
        offsets = raw[:, self.indices] - self.targets
        squared = np.einsum("ild,ild->il", offsets, offsets) * self.present
        return 0.5 * self.weight / self.scale ** 2 * squared.sum(axis=1)

    def cost(self, i: int, raw: np.ndarray) -> float:
        """C_i of example i from its unposed samples ``raw`` (n_p, 3)."""
        offsets = (raw[self.indices] - self.targets[i]) * self.present[i][:, None]
        return 0.5 * self.weight / self.scale ** 2 * float(np.sum(offsets * offsets))

    def gradients(self, raw: np.ndarray) -> np.ndarray:
        """dC/dy at the guided rows ``indices`` (distinct), (n_s, n_l, 3), from ``raw``
        (n_s, n_p, 3)."""
        return (self.weight / self.scale ** 2 * (raw[:, self.indices] - self.targets)
                * self.present[..., None])

    def distances(self, raw: np.ndarray) -> np.ndarray:
        """|y_i,k_l - p_il| (n_s, n_l), mm; NaN where an example lacks the landmark."""
        offsets = np.linalg.norm(raw[:, self.indices] - self.targets, axis=2)
        return np.where(self.present, offsets, np.nan)

    def on_rows(self, rows: np.ndarray) -> "Guides":
        """The same guides on a shape vector made of ``rows`` of this one's (e.g. a coarse grid:
        its points are the first ones of every part's grid). Raises ValueError where a guided
        row is not among them."""
        where = {int(row): k for k, row in enumerate(rows)}
        missing = [label for label, row in zip(self.labels, self.indices) if int(row) not in where]
        if missing:
            raise ArgumentError(f"landmarks {', '.join(missing)} are guided at sample points "
                             "that the other grid lacks")
        return replace(self, indices=np.array([where[int(row)] for row in self.indices],
                                              dtype=np.int64))


@dataclass(frozen=True)
class PlacedLandmarks:
    """The landmarks of a population put on its cases' surfaces, before the alignment: the label
    set, which part holds each label, and per part and case the landmarks' placing
    (:class:`~mdlshapemodel.prepare.landmarks.SurfaceLandmarks` of the part's labels, None for
    a case without any) with a mask of what the case has."""

    labels: tuple
    part_of_label: np.ndarray            # (n_l,) int
    placed: list                         # [part][case] -> SurfaceLandmarks or None
    present: np.ndarray                  # (n_s, n_l) bool

    def images(self, part: int, maps: list) -> list:
        """Per case, the sphere images on ``maps`` (the part's maps, in case order) of the part's
        labels, (k, 3) with NaN rows where a case lacks one."""
        labels = np.flatnonzero(self.part_of_label == part)
        result = []
        for i, (placing, sphere_map) in enumerate(zip(self.placed[part], maps)):
            points = np.full((len(labels), 3), np.nan)
            if placing is not None:
                points[:] = placing.on_sphere(sphere_map.sphere, sphere_map.faces)
                points[~self.present[i, labels]] = np.nan
            result.append(points)
        return result


def place_landmarks(cases: list, landmarks: dict) -> PlacedLandmarks | None:
    """Put every case's landmarks on its surface (the part nearest each label: the part that
    holds it for most cases).

    Parameters
    ----------
    cases : list of PreparedCase
        Surfaces with sphere maps (not 2-D curves).
    landmarks : dict of case name -> Landmarks
        In the coordinates of each case's input file; a mirrored case's are mirrored as its
        surface was. A case may be missing, or lack labels.

    Returns None when no case has a landmark.
    """
    labels = tuple(sorted({label for marks in landmarks.values() for label in marks.labels}))
    if not labels:
        return None
    n_parts = len(cases[0].parts)
    present = np.zeros((len(cases), len(labels)), dtype=bool)
    points = np.zeros((len(cases), len(labels), 3))
    for i, case in enumerate(cases):
        marks = landmarks.get(case.name)
        if marks is None:
            continue
        for label, point in zip(marks.labels, marks.points):
            k = labels.index(label)
            present[i, k] = True
            points[i, k] = point * ([-1.0, 1.0, 1.0] if case.mirrored else 1.0)
    # which part each label is on: nearest, by majority over the cases that have it
    votes = np.zeros((len(labels), n_parts), dtype=np.int64)
    if n_parts > 1:
        for i, case in enumerate(cases):
            if present[i].any():
                distances = np.stack([on_surface(part.map.vertices, part.map.faces,
                                                 part.map.sphere, points[i]).distance
                                      for part in case.parts], axis=1)
                votes[np.flatnonzero(present[i]), np.argmin(distances[present[i]], axis=1)] += 1
    part_of_label = np.argmax(votes, axis=1)
    placed = [[None] * len(cases) for _ in range(n_parts)]
    for j in range(n_parts):
        mine = np.flatnonzero(part_of_label == j)
        for i, case in enumerate(cases):
            if len(mine) and present[i, mine].any():
                sphere_map = case.parts[j].map
                placed[j][i] = on_surface(sphere_map.vertices, sphere_map.faces,
                                          sphere_map.sphere, points[i, mine])
    return PlacedLandmarks(labels, part_of_label, placed, present)


def guides_on_grid(placed: PlacedLandmarks, aligned: list, grids: list, candidates: int,
                   part_offsets, weight: float, scale: float) -> Guides:
    """The :class:`Guides` of landmarks placed on aligned maps.

    Parameters
    ----------
    placed : PlacedLandmarks
    aligned : list
        Per part, the aligned sphere maps of the cases (in case order).
    grids : list of ndarray (n, 3)
        Per part, its sampling grid's points on the sphere.
    candidates : int
        Guide sample points are chosen among each grid's first ``candidates`` points (the
        coarse grid's, which the build's grid starts with, so that the same guides apply to
        both).
    part_offsets : sequence of int
        The first row of each part in the shape vector.
    """
    n_l = len(placed.labels)
    indices = np.zeros(n_l, dtype=np.int64)
    targets = np.zeros((placed.present.shape[0], n_l, 3))
    off_surface = np.zeros((placed.present.shape[0], n_l))
    for j, maps in enumerate(aligned):
        mine = np.flatnonzero(placed.part_of_label == j)
        if not len(mine):
            continue
        places = shared_places(placed.images(j, maps), [np.eye(3)] * len(maps))
        taken = set()
        for k, place in zip(mine, places):
            # the nearest grid point that no other label has: landmarks closer together than
            # the grid's spacing are guided at neighbouring points
            order = np.argsort(-(grids[j][:candidates] @ np.nan_to_num(place)), kind="stable")
            vertex = next(int(v) for v in order if int(v) not in taken)
            taken.add(vertex)
            indices[k] = part_offsets[j] + vertex
        for i, placing in enumerate(placed.placed[j]):
            if placing is not None:
                targets[i, mine] = placing.surface
                off_surface[i, mine] = placing.distance
    return Guides(placed.labels, indices, targets, placed.present, float(weight), float(scale),
                  off_surface * placed.present)
