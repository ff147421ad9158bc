"""Threshold-free cluster enhancement (TFCE) of a per-point map over the mean surface.

Smith and Nichols (2009, NeuroImage 44) enhance a statistic map h by the support that each point
gets from the connected region around it:

    TFCE(v) = sum over k = 1 .. floor(h(v) / dh) of e(v, k dh)^E (k dh)^H dh,

e(v, h) the extent of the connected component of {u: h(u) >= h} that holds v: here its area on
the mean surface (each point carries a third of the area of its triangles; on a curve, half the
length of its segments), two points being neighbours when an edge of the mesh joins them. E = 1,
H = 2 (:data:`~mdlshapemodel.config.TFCE_EXTENT`, :data:`~mdlshapemodel.config.TFCE_HEIGHT`), as
is usual for surface data; dh (:data:`~mdlshapemodel.config.TFCE_STEP`) in units of the map. A
broad effect of moderate height is raised above the noise of single points; a narrow peak keeps
its height's share. The enhancement is a fixed function of the map, so the family-wise maximum
of the enhanced map over the same resamples as the map's is a valid test (the resampling's
exchangeability, its blocks, sign flips and variance groups are kept).

The heights are computed by one sweep from the highest level down with a union-find over the
points (Tarjan's disjoint sets): a point enters at its own level and joins its neighbours'
components; a component's extent is constant between two merges, so its contribution over those
levels, extent^E times a difference of the cumulative sums of (k dh)^H dh, is added once to its
root and passed down to its members through offsets along the union-find's links. The cost is
that of sorting the points plus nearly linear in the edges, per map (numba, compiled on first use
and cached).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..config import TFCE_EXTENT, TFCE_HEIGHT, TFCE_LEVELS, TFCE_STEP
from ..errors import ArgumentError, InputError
from ..prepare.curve import segment_vertex_lengths
from ..prepare.surface import triangle_vertex_areas


@dataclass
class Surface:
    """The neighbourhood and the measure that TFCE needs of a mesh.

    Attributes
    ----------
    starts : ndarray (p + 1,) int64
        Point v's neighbours are ``neighbours[starts[v]:starts[v + 1]]`` (compressed rows).
    neighbours : ndarray (2 m,) int64
    areas : ndarray (p,) float64
        Each point's share of the surface's area (mm^2; of a curve's length, mm).
    """

    starts: np.ndarray
    neighbours: np.ndarray
    areas: np.ndarray

    @property
    def n_points(self) -> int:
        return len(self.areas)


def surface_of(points: np.ndarray, cells: np.ndarray) -> Surface:
    """The :class:`Surface` of a mesh: triangles (m, 3) or segments (m, 2) over ``points``.

    Examples
    --------
    >>> square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    >>> found = surface_of(square, np.array([[0, 1, 2], [0, 2, 3]]))
    >>> found.areas.round(3).tolist(), found.neighbours[found.starts[1]:found.starts[2]].tolist()
    ([0.333, 0.167, 0.333, 0.167], [0, 2])
    """
    points = np.asarray(points, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    if cells.ndim != 2 or len(cells) == 0 or cells.shape[1] not in (2, 3):
        raise InputError("TFCE needs the model's triangles or segments: the mean surface has "
                         "none")
    p = len(points)
    if cells.shape[1] == 3:
        areas = triangle_vertex_areas(points, cells)
        pairs = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    else:
        areas = segment_vertex_lengths(points, cells)
        pairs = cells
    pairs = np.concatenate([pairs, pairs[:, ::-1]])
    keys = np.unique(pairs[:, 0] * p + pairs[:, 1])
    first, second = keys // p, keys % p
    keep = first != second
    first, second = first[keep], second[keep]
    starts = np.zeros(p + 1, dtype=np.int64)
    np.cumsum(np.bincount(first, minlength=p), out=starts[1:])
    return Surface(starts, second.astype(np.int64), np.asarray(areas, dtype=np.float64))


@njit(cache=True, nogil=True)
def _root(parent, offset, path, v):
    """The root of v's set; the links on the way are pointed at it, each offset the sum of the
    offsets it skips (so that a point's value is its offset plus its root's)."""
    count = 0
    root = v
    while parent[root] != root:
        path[count] = root
        count += 1
        root = parent[root]
    carried = 0.0
    for i in range(count - 1, -1, -1):
        node = path[i]
        carried += offset[node]
        offset[node] = carried
        parent[node] = root
    return root


@njit(cache=True, nogil=True)
def _enhance_rows(heights, starts, neighbours, areas, extent_power, height_power, step,
                  levels_cap, out):
    """TFCE of each row of ``heights`` (B, p) into ``out`` (B, p)."""
    rows, p = heights.shape
    parent = np.empty(p, np.int64)
    offset = np.empty(p)
    extent = np.empty(p)
    top = np.empty(p, np.int64)
    level = np.empty(p, np.int64)
    path = np.empty(p, np.int64)
    above = np.empty(p, np.int64)
    for b in range(rows):
        highest = 0
        count = 0
        for v in range(p):
            h = heights[b, v]
            k = 0
            if h >= step:                     # false for NaN
                k = levels_cap if h / step >= levels_cap else int(np.floor(h / step))
                above[count] = v
                count += 1
            level[v] = k
            if k > highest:
                highest = k
        # cumulative[k]: sum over j = 1 .. k of (j dh)^H dh
        cumulative = np.zeros(highest + 1)
        for k in range(1, highest + 1):
            cumulative[k] = cumulative[k - 1] + (k * step) ** height_power * step
        # the points above the first level, highest first
        entering = above[:count][np.argsort(-level[above[:count]])]
        for v in range(p):
            parent[v] = -1
        for i in range(count):
            v = entering[i]
            k = level[v]
            parent[v] = v
            offset[v] = 0.0
            extent[v] = areas[v]
            top[v] = k
            for j in range(starts[v], starts[v + 1]):
                u = neighbours[j]
                if parent[u] < 0:
                    continue                  # not above this level yet
                a = _root(parent, offset, path, u)
                c = _root(parent, offset, path, v)
                if a == c:
                    continue
                # both components end at level k: their extents held from their tops down to
                # k + 1; the merged one holds from k down
                offset[a] += extent[a] ** extent_power * (cumulative[top[a]] - cumulative[k])
                offset[c] += extent[c] ** extent_power * (cumulative[top[c]] - cumulative[k])
                if extent[a] > extent[c]:
                    a, c = c, a
                parent[a] = c
                offset[a] -= offset[c]
                extent[c] += extent[a]
                top[c] = k
        for i in range(count):
            v = entering[i]
            if parent[v] == v:
                offset[v] += extent[v] ** extent_power * cumulative[top[v]]
        for v in range(p):
            out[b, v] = 0.0
        for i in range(count):
            v = entering[i]
            root = _root(parent, offset, path, v)
            out[b, v] = offset[v] + (offset[root] if root != v else 0.0)


def enhance(heights: np.ndarray, surface: Surface, extent: float = TFCE_EXTENT,
            height: float = TFCE_HEIGHT, step: float = TFCE_STEP) -> np.ndarray:
    """Threshold-free cluster enhancement of maps of non-negative heights.

    Parameters
    ----------
    heights : ndarray (p,) or (B, p)
        One map, or B maps, over the surface's points; only heights of at least ``step`` count
        (negative values and NaN are 0).
    surface : Surface
    extent, height : float
        E and H.
    step : float
        dh, in units of the heights.

    Returns
    -------
    ndarray, as ``heights``
        sum over k = 1 .. floor(h(v) / dh) of e(v, k dh)^E (k dh)^H dh.

    Examples
    --------
    Three points on a line 1 mm apart (each carries half of its segments' length):

    >>> line = surface_of(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]),
    ...                   np.array([[0, 1], [1, 2]]))
    >>> enhance(np.array([0.2, 0.2, 0.0]), line, step=0.1).round(4).tolist()
    [0.0075, 0.0075, 0.0]
    """
    heights = np.asarray(heights, dtype=np.float64)
    if heights.shape[-1] != surface.n_points:
        raise ArgumentError(f"maps of {heights.shape[-1]} points for a surface of "
                         f"{surface.n_points}")
    if not (step > 0 and extent >= 0 and height >= 0):
        raise ArgumentError("TFCE needs step > 0, extent >= 0 and height >= 0")
    rows = np.ascontiguousarray(heights.reshape(-1, surface.n_points))
    out = np.empty_like(rows)
    _enhance_rows(rows, surface.starts, surface.neighbours, surface.areas, float(extent),
                  float(height), float(step), TFCE_LEVELS, out)
    return out.reshape(heights.shape)


def signed_enhance(values: np.ndarray, surface: Surface, **settings) -> np.ndarray:
    """TFCE of a signed map, each sign on its own: TFCE(max(z, 0)) - TFCE(max(-z, 0)) (a
    point's value has its statistic's sign; the regions above 0 and below 0 never join).

    Examples
    --------
    >>> line = surface_of(np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]),
    ...                   np.array([[0, 1], [1, 2]]))
    >>> signed_enhance(np.array([0.2, -0.2, 0.0]), line, step=0.1).round(4).tolist()
    [0.0025, -0.005, 0.0]
    """
    values = np.asarray(values, dtype=np.float64)
    return (enhance(np.maximum(values, 0.0), surface, **settings)
            - enhance(np.maximum(-values, 0.0), surface, **settings))
