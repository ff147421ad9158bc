"""Where a surface model's sample points lie: evenly over the sphere, or evenly over the
population's mean surface.

A sphere map spreads a surface's area unevenly over the sphere: a thin process or a sharp ridge
gets a small part of it. An even grid on the sphere (an icosphere, ``placement="sphere"``) then
puts few sample points there, and the model's triangles are large where the anatomy is finest.

``placement="surface"`` chooses each part's grid for the population instead: a dense icosphere
of candidates (at least :data:`CANDIDATES_PER_POINT` per sample point) is sampled on every case
through its aligned sphere map (the initial correspondence), the cases are aligned (eq. 18) and
averaged, and the sample points are taken from the candidates by farthest-point sampling on that
mean surface, so that they cover its area evenly. The first points are those of a smaller
icosphere (the fast strategy's coarse grid), which the candidates contain: the coarse grid stays
the first part of the model's grid, as the coarse stage and the landmark guides need. The
triangles are the Delaunay triangulation of the points on the sphere. The grid is a function of
the prepared cases and the settings, so a resumed build finds the same one.
"""

from __future__ import annotations

import numpy as np

from .sampling import farthest_points, icosphere, spherical_triangles
from .state import CorrespondenceState, Example, PartState

# candidates per sample point of the dense icosphere the points are chosen from, and at most
# this many cases (evenly spaced in the population) make the mean surface they are spread over
CANDIDATES_PER_POINT = 16
MAX_CASES = 64
MAX_LEVEL = 7                  # 163,842 candidates


def icosphere_level(n_points: int) -> int | None:
    """k when ``n_points`` is the vertex count 10 * 4**k + 2 of an icosphere, else None."""
    k = 0
    while 10 * 4 ** k + 2 < n_points:
        k += 1
    return k if 10 * 4 ** k + 2 == n_points else None


def surface_grids(maps: list, n_points: int, first: int, scaling: bool = True) -> list:
    """Per part, a grid (points on the sphere, triangles) of ``n_points`` that covers the
    population's mean surface evenly.

    Parameters
    ----------
    maps : list
        Per part, the cases' aligned sphere maps (``vertices``, ``faces``, ``sphere``).
    n_points : int
        Sample points per part.
    first : int
        The grid starts with the ``first`` vertices of an icosphere (10 * 4**k + 2 of them, or
        0); ``first`` < ``n_points``.
    scaling : bool
        Whether the cases' alignment removes scale (as the build's).

    Examples
    --------
    >>> from mdlshapemodel.prepare.sphere import SphereMap
    >>> sphere, faces = icosphere(4)
    >>> spindle = sphere * [6.0, 1.0, 1.0]    # its middle has most of the area, not the sphere's
    >>> (grid, triangles), = surface_grids([[SphereMap(spindle, faces, sphere)] * 2], 162, 42)
    >>> bool(np.allclose(grid[:42], icosphere(1)[0]))
    True
    >>> in_the_middle = lambda points: int(np.sum(np.abs(points[:, 0]) < 0.5))
    >>> in_the_middle(grid) > in_the_middle(icosphere(2)[0])     # 162 points either way
    True
    """
    if first and icosphere_level(first) is None:
        raise ValueError(f"the grid's first points are an icosphere's: 10 * 4**k + 2, not {first}")
    if not 0 <= first < n_points:
        raise ValueError(f"{first} first points of a grid of {n_points}")
    level = 0
    while 10 * 4 ** level + 2 < CANDIDATES_PER_POINT * n_points and level < MAX_LEVEL:
        level += 1
    candidates, cells = icosphere(level)
    if n_points > len(candidates):
        raise ValueError(f"{n_points} sample points: more than {len(candidates)} candidates")
    n_cases = len(maps[0])
    picked = np.unique(np.linspace(0, n_cases - 1, min(n_cases, MAX_CASES)).round().astype(int))
    examples = [Example(str(i), [PartState(part[i].vertices, part[i].faces, part[i].sphere,
                                           candidates, cells) for part in maps])
                for i in picked]
    state = CorrespondenceState(examples, [(candidates, cells)] * len(maps), scaling=scaling)
    mean = state.shapes.mean(axis=0)
    grids = []
    for rows in state.part_slices:
        grid = candidates[farthest_points(mean[rows], n_points, first)]
        grids.append((grid, spherical_triangles(grid)))
    return grids
