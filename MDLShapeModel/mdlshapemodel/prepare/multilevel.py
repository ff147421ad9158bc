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

This is the certain path of :func:`~.sphere.sphere_map`, used when the conformal map is not
fold-free (on strongly elongated surfaces, e.g. a 20:1 ellipsoid or a femur, the conformal map
fails and a spherical Tutte map folds). The simplification and the re-insertion are compiled
(numba); the mesh is held as its triangles, with each vertex's corners (corner ``3 f + k`` is
corner k of triangle f) in a doubly linked list.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

from ..errors import SphereMapError

# Splits whose new vertex cannot be placed after this many halvings of its distance from its
# partner (beyond double precision) fail; never seen, but the loop must end.
MAX_HALVINGS = 60
# The middle of a returning vertex's neighbours is taken without trying the small step when its
# thinnest triangle is at least this fraction of an even share of the star.
FAIR_SHARE = 0.1
# Iterations of the distortion minimisation of each level's map (see :func:`_spread`).
SPREAD_ITERATIONS = 200


@numba.njit(cache=True)
def _link(v, corner, head, after, before):
    """Put ``corner`` first in vertex v's list."""
    first = head[v]
    after[corner] = first
    before[corner] = -1
    if first >= 0:
        before[first] = corner
    head[v] = corner


@numba.njit(cache=True)
def _unlink(v, corner, head, after, before):
    """Take ``corner`` out of vertex v's list."""
    if before[corner] >= 0:
        after[before[corner]] = after[corner]
    else:
        head[v] = after[corner]
    if after[corner] >= 0:
        before[after[corner]] = before[corner]


@numba.njit(cache=True)
def _neighbours(v, faces, head, after, stamp, mark, out):
    """The distinct neighbours of v into ``out``; their number. ``mark`` (one entry per vertex)
    remembers which were seen, by the fresh value ``stamp``."""
    count = 0
    corner = head[v]
    while corner >= 0:
        f = corner // 3
        for k in range(3):
            w = faces[f, k]
            if w != v and mark[w] != stamp:
                mark[w] = stamp
                out[count] = w
                count += 1
        corner = after[corner]
    return count


@numba.njit(cache=True)
def _collapse(s, t, faces, f_alive, v_alive, head, after, before, valence, mark, stamp,
              neighbours_s, neighbours_t, record, pool, pool_used):
    """Merge t into s if the mesh stays a triangulated sphere (the link condition). The record
    (s, t, the two triangles that go, the first and last used slot of ``pool``) goes into
    ``record``; ``pool`` gets the corners that were t's and become s's. Returns the new
    ``pool_used``, or -1 when the collapse is not allowed."""
    shared0 = -1
    shared1 = -1
    corner = head[t]
    while corner >= 0:
        f = corner // 3
        if faces[f, 0] == s or faces[f, 1] == s or faces[f, 2] == s:
            if shared0 < 0:
                shared0 = f
            elif shared1 < 0:
                shared1 = f
            else:
                return -1
        corner = after[corner]
    if shared1 < 0:
        return -1
    # the neighbours both share must be exactly the two opposite the edge
    count_s = _neighbours(s, faces, head, after, stamp, mark, neighbours_s)
    _neighbours(t, faces, head, after, stamp + 1, mark, neighbours_t)      # marks them
    common = 0
    for i in range(count_s):
        if mark[neighbours_s[i]] == stamp + 1:
            w = neighbours_s[i]
            opposite = False
            for f in (shared0, shared1):
                for k in range(3):
                    if faces[f, k] == w:
                        opposite = True
            if not opposite:
                return -1
            common += 1
    if common != 2:
        return -1
    record[0] = s
    record[1] = t
    record[2] = shared0
    record[3] = shared1
    record[4] = pool_used
    for f in (shared0, shared1):
        f_alive[f] = False
        for k in range(3):
            _unlink(faces[f, k], 3 * f + k, head, after, before)
            valence[faces[f, k]] -= 1
    corner = head[t]
    while corner >= 0:
        following = after[corner]
        faces[corner // 3, corner % 3] = s
        _link(s, corner, head, after, before)
        valence[s] += 1
        pool[pool_used] = corner
        pool_used += 1
        corner = following
    head[t] = -1
    valence[t] = 0
    v_alive[t] = False
    record[5] = pool_used
    return pool_used


@numba.njit(cache=True)
def _split(record, faces, f_alive, v_alive, head, after, before, valence, pool):
    """Undo the collapse of ``record``."""
    s, t = record[0], record[1]
    for slot in range(record[4], record[5]):
        corner = pool[slot]
        _unlink(s, corner, head, after, before)
        valence[s] -= 1
        faces[corner // 3, corner % 3] = t
        _link(t, corner, head, after, before)
        valence[t] += 1
    for f in (record[2], record[3]):
        f_alive[f] = True
        for k in range(3):
            _link(faces[f, k], 3 * f + k, head, after, before)
            valence[faces[f, k]] += 1
    v_alive[t] = True


@numba.njit(cache=True)
def simplify(vertices, faces, f_alive, v_alive, head, after, before, valence, records, pool):
    """Collapse shortest edges first until 4 vertices are left; the records into ``records``
    (one row per collapse, in order), the corners they moved into ``pool`` (or a larger copy of
    it). Returns their number, or -1 when no edge can be collapsed before (the mesh is not a
    triangulated sphere), and the pool."""
    n = vertices.shape[0]
    mark = np.full(n, -1, dtype=np.int64)
    stamp = 0
    neighbours_s = np.empty(n, dtype=np.int64)
    neighbours_t = np.empty(n, dtype=np.int64)
    around = np.empty(n, dtype=np.int64)
    alive = 0
    for v in range(n):
        alive += v_alive[v]
    done = 0
    pool_used = 0
    while alive > 4:
        heap = [(0.0, 0, 0)]
        heap.pop()
        for v in range(n):
            if not v_alive[v]:
                continue
            stamp += 2
            count = _neighbours(v, faces, head, after, stamp, mark, around)
            for i in range(count):
                w = around[i]
                if v < w:
                    heapq.heappush(heap, (_distance(vertices, v, w), v, w))
        progress = False
        while len(heap) > 0 and alive > 4:
            _, a, b = heapq.heappop(heap)
            if not (v_alive[a] and v_alive[b]):
                continue
            stamp += 2
            count = _neighbours(b, faces, head, after, stamp, mark, around)
            if mark[a] != stamp:
                continue
            # remove the vertex of lower valence: keeps the valences even
            if valence[a] >= valence[b]:
                s, t = a, b
            else:
                s, t = b, a
            if pool_used + valence[t] > pool.shape[0]:
                larger = np.empty(2 * pool.shape[0] + valence[t], dtype=np.int64)
                for i in range(pool_used):   # a loop: a slice assignment compiles far more
                    larger[i] = pool[i]
                pool = larger
            stamp += 2
            used = _collapse(s, t, faces, f_alive, v_alive, head, after, before, valence, mark,
                             stamp, neighbours_s, neighbours_t, records[done], pool, pool_used)
            if used < 0:
                continue
            pool_used = used
            done += 1
            alive -= 1
            progress = True
            stamp += 2
            count = _neighbours(s, faces, head, after, stamp, mark, around)
            for i in range(count):
                heapq.heappush(heap, (_distance(vertices, s, around[i]), s, around[i]))
        if not progress:
            return -1, pool
    return done, pool


@numba.njit(cache=True)
def _distance(vertices, a, b):
    dx = vertices[a, 0] - vertices[b, 0]
    dy = vertices[a, 1] - vertices[b, 1]
    dz = vertices[a, 2] - vertices[b, 2]
    return np.sqrt(dx * dx + dy * dy + dz * dz)


@numba.njit(cache=True)
def _orientation(x, a, b, c):
    """det[x_a, x_b, x_c]: positive when the triangle is counter-clockwise seen from outside."""
    return (x[a, 0] * (x[b, 1] * x[c, 2] - x[b, 2] * x[c, 1])
            + x[a, 1] * (x[b, 2] * x[c, 0] - x[b, 0] * x[c, 2])
            + x[a, 2] * (x[b, 0] * x[c, 1] - x[b, 1] * x[c, 0]))


@numba.njit(cache=True)
def _solid_angle(x, a, b, c):
    """Signed solid angle of the spherical triangle (Van Oosterom and Strackee)."""
    numerator = _orientation(x, a, b, c)
    denominator = 1.0 + (x[a, 0] * x[b, 0] + x[a, 1] * x[b, 1] + x[a, 2] * x[b, 2]) \
        + (x[b, 0] * x[c, 0] + x[b, 1] * x[c, 1] + x[b, 2] * x[c, 2]) \
        + (x[c, 0] * x[a, 0] + x[c, 1] * x[a, 1] + x[c, 2] * x[a, 2])
    return 2.0 * np.arctan2(numerator, denominator)


@numba.njit(cache=True)
def _star(x, faces, rows, count, covered):
    """The smallest orientation of the ``count`` triangles ``rows`` around a moved vertex, or
    -1 when one is not positive or they no longer cover the solid angle ``covered`` (all
    positive alone would allow a star that winds twice around the vertex)."""
    smallest = np.inf
    total = 0.0
    for i in range(count):
        f = rows[i]
        det = _orientation(x, faces[f, 0], faces[f, 1], faces[f, 2])
        if not det > 0.0:
            return -1.0
        smallest = min(smallest, det)
        total += _solid_angle(x, faces[f, 0], faces[f, 1], faces[f, 2])
    if abs(total - covered) >= 1e-6 * max(covered, 1.0):
        return -1.0
    return smallest


@numba.njit(cache=True)
def _unit(x, t, px, py, pz):
    norm = np.sqrt(px * px + py * py + pz * pz)
    x[t, 0] = px / norm
    x[t, 1] = py / norm
    x[t, 2] = pz / norm


@numba.njit(cache=True)
def insert(records, first, last, x, faces, f_alive, v_alive, head, after, before, valence,
           pool):
    """Undo the collapses ``records[first - 1]`` down to ``records[last]`` (the newest first),
    placing each returning vertex so that no triangle flips (see the module's docstring).
    Returns -1 when all were placed, else the record that failed."""
    n = x.shape[0]
    rows = np.empty(n, dtype=np.int64)
    mark = np.full(n, -1, dtype=np.int64)
    around = np.empty(n, dtype=np.int64)
    stamp = 0
    best = np.empty(3)
    for r in range(first - 1, last - 1, -1):
        record = records[r]
        s, t = record[0], record[1]
        _split(record, faces, f_alive, v_alive, head, after, before, valence, pool)
        count = 0
        corner = head[t]
        while corner >= 0:
            rows[count] = corner // 3
            count += 1
            corner = after[corner]
        rows[:count].sort()
        px, py, pz = x[s, 0], x[s, 1], x[s, 2]
        x[t, 0], x[t, 1], x[t, 2] = px, py, pz
        covered = 0.0              # the two new triangles are empty here
        for i in range(count):
            f = rows[i]
            covered += _solid_angle(x, faces[f, 0], faces[f, 1], faces[f, 2])
        stamp += 1
        neighbours = _neighbours(t, faces, head, after, stamp, mark, around)
        around[:neighbours].sort()
        # two candidates, the better kept (largest smallest orientation: the middle of a
        # degenerate ring can be positive only by rounding):
        # 1. the middle of t's neighbours;
        # 2. a small step e d from s. To first order in e, a new triangle's orientation is
        #    d . g with g the cross product of its other two corners (in order): d = the sum of
        #    the two unit tangent parts of g makes both positive; e is halved until the star is
        #    valid.
        found = False
        best_margin = 0.0
        cx = cy = cz = 0.0
        for i in range(neighbours):
            cx += x[around[i], 0]
            cy += x[around[i], 1]
            cz += x[around[i], 2]
        cx /= neighbours
        cy /= neighbours
        cz /= neighbours
        if np.sqrt(cx * cx + cy * cy + cz * cz) > 1e-12:
            _unit(x, t, cx, cy, cz)
            margin = _star(x, faces, rows, count, covered)
            if margin >= 0.0:
                found = True
                best_margin = margin
                best[0], best[1], best[2] = x[t, 0], x[t, 1], x[t, 2]
                # well inside the ring (its thinnest triangle a fair fraction of an even
                # share): no need for the second candidate. det ~ twice the solid angle.
                if best_margin >= FAIR_SHARE * 2.0 * covered / count:
                    continue
        dx = dy = dz = 0.0
        for f in (record[2], record[3]):
            slot = 0
            for k in range(3):
                if faces[f, k] == t:
                    slot = k
            u = faces[f, (slot + 1) % 3]
            w = faces[f, (slot + 2) % 3]
            gx = x[u, 1] * x[w, 2] - x[u, 2] * x[w, 1]
            gy = x[u, 2] * x[w, 0] - x[u, 0] * x[w, 2]
            gz = x[u, 0] * x[w, 1] - x[u, 1] * x[w, 0]
            along = gx * px + gy * py + gz * pz
            gx -= along * px
            gy -= along * py
            gz -= along * pz
            length = np.sqrt(gx * gx + gy * gy + gz * gz)
            dx += gx / length
            dy += gy / length
            dz += gz / length
        length = np.sqrt(dx * dx + dy * dy + dz * dz)
        dx /= length
        dy /= length
        dz /= length
        step = np.inf
        for i in range(neighbours):
            w = around[i]
            if w != s:
                ex, ey, ez = x[w, 0] - px, x[w, 1] - py, x[w, 2] - pz
                step = min(step, np.sqrt(ex * ex + ey * ey + ez * ez))
        step *= 0.5
        for _ in range(MAX_HALVINGS):
            _unit(x, t, px + step * dx, py + step * dy, pz + step * dz)
            margin = _star(x, faces, rows, count, covered)
            if margin >= 0.0:
                if margin > best_margin:
                    found = True
                    best[0], best[1], best[2] = x[t, 0], x[t, 1], x[t, 2]
                break
            step *= 0.5
        if not found:
            return r
        x[t, 0], x[t, 1], x[t, 2] = best[0], best[1], best[2]
    return -1


def _spread(faces: np.ndarray, f_alive: np.ndarray, v_alive: np.ndarray, x: np.ndarray,
            iterations: int = SPREAD_ITERATIONS):
    """Lower the distortion of the current level's map as if every triangle were equilateral
    and of equal area (the coarse meshes' own triangles can be degenerate), with the fold-free
    minimiser of the final map: keeps re-inserted vertices from crowding."""
    from .sphere_kernels import lbfgs, no_factor

    kept = np.flatnonzero(v_alive)
    index = np.full(len(x), -1, dtype=np.int64)
    index[kept] = np.arange(len(kept))
    level_faces = np.ascontiguousarray(index[faces[f_alive]])
    cot = np.full(level_faces.shape, 1.0 / np.sqrt(3.0))
    area = np.full(len(level_faces), 4.0 * np.pi / len(level_faces))
    level = np.ascontiguousarray(x[kept])
    lbfgs(level, level_faces, cot, area, 1.0, int(iterations), 1e-6, 10, no_factor(), 20)
    x[kept] = level


def _corner_lists(faces: np.ndarray, n: int):
    """Each vertex's corners as a doubly linked list in corner order: ``head``, ``after``,
    ``before``."""
    corners = faces.ravel()
    order = np.argsort(corners, kind="stable")
    head = np.full(n, -1, dtype=np.int64)
    after = np.full(len(corners), -1, dtype=np.int64)
    before = np.full(len(corners), -1, dtype=np.int64)
    same = corners[order[1:]] == corners[order[:-1]]
    after[order[:-1][same]] = order[1:][same]
    before[order[1:][same]] = order[:-1][same]
    starts = np.concatenate([[True], ~same])
    head[corners[order[starts]]] = order[starts]
    return head, after, before


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
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.array(faces, dtype=np.int64)
    n = len(vertices)
    head, after, before = _corner_lists(faces, n)
    f_alive = np.ones(len(faces), dtype=np.bool_)
    v_alive = np.zeros(n, dtype=np.bool_)
    v_alive[np.unique(faces)] = True
    valence = np.bincount(faces.ravel(), minlength=n).astype(np.int64)
    records = np.zeros((max(n, 1), 6), dtype=np.int64)
    pool = np.zeros(3 * len(faces), dtype=np.int64)
    done = 0
    if int(v_alive.sum()) > 4:
        done, pool = simplify(vertices, faces, f_alive, v_alive, head, after, before, valence,
                              records, pool)
    if done < 0 or int(v_alive.sum()) != 4 or int(f_alive.sum()) != 4:
        raise SphereMapError("the surface cannot be simplified to a tetrahedron (it is not a "
                             "triangulated sphere)")
    x = np.zeros_like(vertices)
    remaining = np.flatnonzero(v_alive)
    x[remaining] = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / np.sqrt(3)
    first_face = faces[f_alive][0]
    a, b, c = x[first_face]
    if np.dot(a, np.cross(b, c)) < 0:       # all four triangles share one orientation
        x[remaining[:2]] = x[remaining[1::-1]]
    # undo the collapses level by level: spread the map whenever the vertex count doubles
    count, next_level, r = 4, 8, done
    while r > 0:
        steps = min(r, next_level - count)
        failed = insert(records, r, r - steps, x, faces, f_alive, v_alive, head, after, before,
                        valence, pool)
        if failed >= 0:
            raise SphereMapError("a vertex could not be re-inserted without a fold (the surface "
                                 "has nearly coincident vertices)")
        r -= steps
        count += steps
        if count == next_level or r == 0:
            _spread(faces, f_alive, v_alive, x)
            next_level *= 2
    return x
