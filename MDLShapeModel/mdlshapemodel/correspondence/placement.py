"""Where a surface model's sample points lie: evenly over the sphere, or evenly over the
population's mean surface.

A sphere map spreads a surface's area unevenly over the sphere: a thin process or a sharp ridge
gets a small part of it. An even grid on the sphere (an icosphere, ``placement="sphere"``) then
puts few sample points there, and the model's triangles are large where the anatomy is finest.

``placement="surface"`` chooses each part's grid for the population instead. The cases are
sampled on an icosphere and aligned (the initial correspondence, eq. 18); their mean, interpolated
over the icosphere's triangles, is the mean surface. A dense icosphere of candidates (at least
:data:`CANDIDATES_PER_POINT` per sample point) is placed on it through that interpolation, and the
sample points are taken from the candidates by farthest-point sampling on the mean surface, so
that they cover its area evenly. The first points are those of a smaller icosphere (the fast
strategy's coarse grid), which the candidates contain: the coarse grid stays the first part of
the model's grid, as the coarse stage and the landmark guides need. The triangles are the
Delaunay triangulation of the points on the sphere. The grid is a function of the prepared cases
and the settings, so a resumed build finds the same one.
"""

from __future__ import annotations

import numpy as np

from ..errors import ArgumentError
from .sampling import SphereLocator, farthest_points, icosphere, spherical_triangles
from .state import CorrespondenceState

# candidates per sample point of the dense icosphere the points are chosen from
CANDIDATES_PER_POINT = 16
MAX_LEVEL = 7                  # 163,842 candidates


def icosphere_level(n_points: int) -> int | None:
    """k when ``n_points`` is the vertex count 10 * 4**k + 2 of an icosphere, else None."""
    k = 0
    while 10 * 4 ** k + 2 < n_points:
        k += 1
    return k if 10 * 4 ** k + 2 == n_points else None


def surface_grids(state: CorrespondenceState, first: int) -> list:
    """Per part, a grid (points on the sphere, triangles) of as many points as ``state``'s that
    covers the population's mean surface evenly.

    Parameters
    ----------
    state : CorrespondenceState
        The aligned cases on their initial grids (sphere parts): the mean of their samples,
        interpolated over each grid's triangles, is the mean surface.
    first : int
        The grid starts with the ``first`` vertices of an icosphere (10 * 4**k + 2 of them, or
        0), fewer than the state's points per part.

    Examples
    --------
    >>> from mdlshapemodel.correspondence.state import Example, PartState
    >>> sphere, faces = icosphere(4)
    >>> spindle = sphere * [6.0, 1.0, 1.0]    # its middle has most of the area, not the sphere's
    >>> grid = icosphere(2)
    >>> state = CorrespondenceState([Example(str(i), [PartState(spindle, faces, sphere, *grid)])
    ...                              for i in range(2)], [grid])
    >>> (points, triangles), = surface_grids(state, 42)
    >>> bool(np.allclose(points[:42], icosphere(1)[0]))
    True
    >>> in_the_middle = lambda points: int(np.sum(np.abs(points[:, 0]) < 0.5))
    >>> in_the_middle(points) > in_the_middle(grid[0])       # 162 points either way
    True
    """
    if first and icosphere_level(first) is None:
        raise ArgumentError(f"the grid's first points are an icosphere's: 10 * 4**k + 2, not {first}")
    mean = state.shapes.mean(axis=0)
    grids = []
    for rows, (points, triangles) in zip(state.part_slices, state.grids):
        n_points = len(points)
        if not 0 <= first < n_points:
            raise ArgumentError(f"{first} first points of a grid of {n_points}")
        level = 0
        while 10 * 4 ** level + 2 < CANDIDATES_PER_POINT * n_points and level < MAX_LEVEL:
            level += 1
        candidates = icosphere(level)[0]
        # the mean surface at the candidates: the mean's samples interpolated over the grid
        on_mean = SphereLocator(points, triangles).evaluate(mean[rows], candidates)[0]
        grid = candidates[farthest_points(on_mean, n_points, first)]
        grids.append((grid, spherical_triangles(grid)))
    return grids
