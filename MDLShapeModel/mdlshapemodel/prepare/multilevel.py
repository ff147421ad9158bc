"""A sphere map that is bijective by construction: simplify to a tetrahedron, then re-insert.

The mesh is simplified by half-edge collapses (shortest edge first) that keep it a triangulated
sphere (the link condition: the two end points of a collapsed edge share exactly the two
neighbours opposite the edge). Every triangulated sphere other than the tetrahedron has such an
edge, so the simplification always reaches 4 vertices, which are placed at the corners of a
regular tetrahedron inscribed in the unit sphere: a bijective map of the coarsest mesh.

The collapses are then undone in reverse order. Each vertex split puts the returning vertex
``t`` next to the vertex ``s`` it was merged into, at ``s + e d`` on the sphere, with ``d`` a
tangent direction between the two neighbours opposite the split edge: for small enough ``e``
every triangle keeps a positive orientation (the two new ones have areas proportional to ``e``
with the sign of a 2-D cross product that ``d`` is chosen to make positive; the others move by
O(e)). ``e`` is halved until all of ``t``'s triangles are positively oriented (and still cover
what they covered). Whenever the vertex count doubles, the level's map is spread out by the
fold-free distortion minimisation, with every triangle counted as equilateral, which keeps the
re-inserted vertices from crowding. So every intermediate map, and the result, is fold-free; its
distortion is then lowered by :func:`~.sphere.minimise_distortion` like any other initial map.

This is the slow but certain path of :func:`~.sphere.sphere_map`, used when the conformal map is
not fold-free (on strongly elongated surfaces, e.g. a 20:1 ellipsoid, the conformal map fails
and a spherical Tutte map folds).
"""

from __future__ import annotations

import heapq

import numpy as np

from ..errors import SphereMapError
from .spherical import cross_rows, orientation, solid_angles

# Splits whose new vertex cannot be placed after this many halvings of its distance from its
# partner (beyond double precision) fail; never seen, but the loop must end.
MAX_HALVINGS = 60
# The middle of a returning vertex's neighbours is taken without trying the small step when its
# thinnest triangle is at least this fraction of an even share of the star.
FAIR_SHARE = 0.1
# Iterations of the distortion minimisation of each level's map (see :func:`_spread`).
SPREAD_ITERATIONS = 200


def _valid_star(x: np.ndarray, rows: np.ndarray, covered: float) -> bool:
    """The triangles around a moved vertex are positively oriented and still cover the area
    ``covered`` (the solid angle inside their outer ring, which the move does not change): all
    positive alone would allow a star that winds twice around the vertex."""
    if not np.all(orientation(x, rows) > 0):
        return False
    return abs(solid_angles(x, rows).sum() - covered) < 1e-6 * max(covered, 1.0)


class _Mesh:
    """The simplified mesh: face rows, which faces and vertices are alive, faces per vertex."""

    def __init__(self, faces: np.ndarray, n_vertices: int):
        self.faces = np.array(faces, dtype=np.int64)
        self.alive = np.ones(len(faces), dtype=bool)
        self.vertex_alive = np.ones(n_vertices, dtype=bool)
        self.faces_of = [set() for _ in range(n_vertices)]
        for index, row in enumerate(self.faces):
            for v in row:
                self.faces_of[v].add(index)

    def neighbours(self, v: int) -> set:
        result = set()
        for index in self.faces_of[v]:
            result.update(self.faces[index].tolist())
        result.discard(v)
        return result

    def collapse(self, s: int, t: int):
        """Merge ``t`` into ``s`` if the result is still a triangulated sphere; return the record
        of the change (None when the collapse is not allowed)."""
        shared = [index for index in self.faces_of[t] if s in self.faces[index]]
        if len(shared) != 2:
            return None
        opposite = {int(v) for index in shared for v in self.faces[index]} - {s, t}
        if self.neighbours(s) & self.neighbours(t) != opposite:
            return None
        changed = np.array(sorted(self.faces_of[t] - set(shared)), dtype=np.int64)
        record = (s, t, changed, self.faces[changed].copy(), shared)
        for index in shared:
            self.alive[index] = False
            for v in self.faces[index]:
                self.faces_of[v].discard(index)
        for index in changed:
            row = self.faces[index]
            row[row == t] = s
            self.faces_of[s].add(int(index))
        self.faces_of[t] = set()
        self.vertex_alive[t] = False
        return record

    def split(self, record):
        """Undo a collapse."""
        s, t, changed, rows, shared = record
        for index in changed:
            self.faces_of[s].discard(int(index))
        self.faces[changed] = rows
        self.faces_of[t] = set(changed.tolist()) | set(shared)
        for index in shared:
            self.alive[index] = True
            for v in self.faces[index]:
                self.faces_of[v].add(index)
        self.vertex_alive[t] = True


def _simplify(vertices: np.ndarray, mesh: _Mesh) -> list:
    """Collapse shortest edges first until 4 vertices are left; the records, in order."""
    def push(heap, a, b):
        heapq.heappush(heap, (float(np.linalg.norm(vertices[a] - vertices[b])), a, b))

    records = []
    alive = int(mesh.vertex_alive.sum())
    while alive > 4:
        heap = []
        for v in np.flatnonzero(mesh.vertex_alive):
            for w in mesh.neighbours(int(v)):
                if v < w:
                    push(heap, int(v), int(w))
        progress = False
        while heap and alive > 4:
            _, a, b = heapq.heappop(heap)
            if not (mesh.vertex_alive[a] and mesh.vertex_alive[b]) or a not in mesh.neighbours(b):
                continue
            # remove the vertex of lower valence: keeps the valences even
            s, t = (a, b) if len(mesh.faces_of[a]) >= len(mesh.faces_of[b]) else (b, a)
            record = mesh.collapse(s, t)
            if record is None:
                continue
            records.append(record)
            alive -= 1
            progress = True
            for w in mesh.neighbours(s):
                push(heap, s, w)
        if not progress:
            raise SphereMapError("the surface cannot be simplified to a tetrahedron (it is not a "
                                 "triangulated sphere)")
    return records


def _place_tetrahedron(mesh: _Mesh, x: np.ndarray):
    corners = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3)
    remaining = np.flatnonzero(mesh.vertex_alive)
    x[remaining] = corners
    rows = mesh.faces[mesh.alive]
    if orientation(x, rows[:1])[0] < 0:       # all four faces share one orientation
        x[remaining[:2]] = x[remaining[1::-1]]


def _insert(mesh: _Mesh, x: np.ndarray, record):
    """Undo a collapse and place the returning vertex so that no triangle flips."""
    s, t, _, _, shared = record
    mesh.split(record)
    rows = mesh.faces[sorted(mesh.faces_of[t])]
    p = x[s]
    x[t] = p
    covered = float(solid_angles(x, rows).sum())   # the two new triangles are empty here
    neighbours = np.array(sorted(mesh.neighbours(t)))
    # two candidates, the better kept (largest smallest orientation: the middle of a degenerate
    # ring can be positive only by rounding):
    # 1. the middle of t's neighbours;
    # 2. a small step e d from s. To first order in e, a new triangle's orientation is d . g with
    #    g the cross product of its other two corners (in order): d = the sum of the two unit
    #    tangent parts of g makes both positive; e is halved until the star is valid.
    best, best_margin = None, 0.0
    centre = x[neighbours].mean(axis=0)
    if np.linalg.norm(centre) > 1e-12:
        x[t] = centre / np.linalg.norm(centre)
        if _valid_star(x, rows, covered):
            best, best_margin = x[t].copy(), float(orientation(x, rows).min())
            # well inside the ring (its thinnest triangle a fair fraction of an even share):
            # no need for the second candidate. det ~ twice the solid angle when small.
            if best_margin >= FAIR_SHARE * 2.0 * covered / len(rows):
                return
    direction = np.zeros(3)
    for row in mesh.faces[list(shared)]:
        slot = int(np.flatnonzero(row == t)[0])
        g = cross_rows(x[row[(slot + 1) % 3]], x[row[(slot + 2) % 3]])
        g -= np.dot(g, p) * p
        direction += g / np.linalg.norm(g)
    direction /= np.linalg.norm(direction)
    step = 0.5 * np.min(np.linalg.norm(x[neighbours[neighbours != s]] - p, axis=1))
    for _ in range(MAX_HALVINGS):
        candidate = p + step * direction
        x[t] = candidate / np.linalg.norm(candidate)
        if _valid_star(x, rows, covered):
            margin = float(orientation(x, rows).min())
            if margin > best_margin:
                best = x[t].copy()
            break
        step *= 0.5
    if best is None:
        raise SphereMapError("a vertex could not be re-inserted without a fold (the surface has "
                             "nearly coincident vertices)")
    x[t] = best


def _spread(mesh: _Mesh, x: np.ndarray, iterations: int = SPREAD_ITERATIONS):
    """Lower the distortion of the current level's map as if every triangle were equilateral
    and of equal area (the coarse meshes' own triangles can be degenerate), with the fold-free
    minimiser of the final map: keeps re-inserted vertices from crowding."""
    from .sphere_kernels import lbfgs

    kept = np.flatnonzero(mesh.vertex_alive)
    index = np.full(len(x), -1, dtype=np.int64)
    index[kept] = np.arange(len(kept))
    faces = np.ascontiguousarray(index[mesh.faces[mesh.alive]])
    cot = np.full(faces.shape, 1.0 / np.sqrt(3.0))
    area = np.full(len(faces), 4.0 * np.pi / len(faces))
    level = np.ascontiguousarray(x[kept])
    lbfgs(level, faces, cot, area, 1.0, int(iterations), 1e-6, 10)
    x[kept] = level


def multilevel_map(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Fold-free map of a closed genus-0 triangle mesh onto the unit sphere, by construction.

    Parameters
    ----------
    vertices : ndarray (n, 3)
        Surface points; only used to choose the order of the simplification (shortest edges
        first).
    faces : ndarray (m, 3)
        Triangles of a closed genus-0 manifold, oriented outwards.

    Returns
    -------
    ndarray (n, 3)
        Unit vectors; every triangle positively oriented.

    Raises
    ------
    SphereMapError
        When the mesh is not a triangulated sphere, or (never seen) when double precision runs
        out while a vertex is re-inserted.

    Examples
    --------
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> from mdlshapemodel.prepare.sphere import check_bijective
    >>> points, triangles = icosphere(2)
    >>> sphere = multilevel_map(points * [20.0, 1.0, 1.0], triangles)
    >>> check_bijective(sphere, triangles)   # flipped triangles
    0
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    mesh = _Mesh(faces, len(vertices))
    records = _simplify(vertices, mesh)
    x = np.zeros_like(vertices)
    _place_tetrahedron(mesh, x)
    next_level = 8
    for count, record in enumerate(reversed(records), start=5):
        _insert(mesh, x, record)
        if count == next_level or count == len(vertices):
            _spread(mesh, x)
            next_level *= 2
    return x
