"""Isotropic remeshing of a closed triangle mesh (Botsch and Kobbelt 2004), compiled (numba).

Each iteration splits the edges longer than :data:`HIGH` times the target length at their
midpoints, collapses those shorter than :data:`LOW` times it into their midpoints, flips edges
towards valence 6, moves every vertex towards the centroid of its neighbours within its tangent
plane, and puts it back on the input surface (its closest point there). The mesh is held as half
edges in arrays: the two halves of edge ``e`` are ``2 e`` and ``2 e + 1`` (so the opposite of
``h`` is ``h ^ 1``), each with the vertex it points to, the next half edge of its triangle
(counter-clockwise) and its triangle. Every loop runs in index order and nothing is random, so
the output depends only on the input arrays, in any process and with any number of workers.

An operation is done only when the mesh stays a closed manifold of the same topology (a collapse
needs the link condition: the two end points share exactly the two neighbours opposite the
edge; a flip needs the new edge not to exist yet) and no triangle turns by more than 60 degrees
or loses its area (which would fold the surface). Closest points are searched by walking over
the input triangles from the one each vertex was on before: a vertex moves by a fraction of an
edge per iteration, and the walk does not jump across a thin part of the object to its other
side, as a global search could.
"""

from __future__ import annotations

import numba
import numpy as np

from .nearest import closest_point_and_region

# Edges longer than HIGH times the target length are split, shorter than LOW times it collapsed:
# the mean edge comes out close to the target (Botsch and Kobbelt's 4/3 and 4/5 give meshes
# about 5 % coarser, which the rule of config.target_vertices does not assume).
HIGH = 1.4
LOW = 0.7
# A collapse or flip is refused when a triangle's normal would turn by more than 60 degrees.
MIN_NORMAL_COSINE = 0.5
# Longest one-ring walked (a vertex of higher valence is left alone; none of a closed surface
# made of a label map or mesh input comes near it).
MAX_VALENCE = 64
# Steps of the walk towards a vertex's closest point on the input surface.
MAX_WALK = 32


@numba.njit(cache=True)
def _ring(v, v_out, to, nxt, ring):
    """The outgoing half edges of vertex ``v`` into ``ring``; their number (-1: more than
    ``ring`` holds)."""
    h = v_out[v]
    start = h
    count = 0
    while True:
        if count == ring.shape[0]:
            return -1
        ring[count] = h
        count += 1
        h = nxt[nxt[h]] ^ 1
        if h == start:
            return count


@numba.njit(cache=True)
def _normal(p, q, r, out):
    """(q - p) x (r - p) into ``out``; returns its length."""
    ux, uy, uz = q[0] - p[0], q[1] - p[1], q[2] - p[2]
    wx, wy, wz = r[0] - p[0], r[1] - p[1], r[2] - p[2]
    out[0] = uy * wz - uz * wy
    out[1] = uz * wx - ux * wz
    out[2] = ux * wy - uy * wx
    return np.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])


@numba.njit(cache=True)
def _turns_like(p, q, r, s, t, u, before, after):
    """Whether triangles (p, q, r) and (s, t, u) both have an area and their normals differ by
    less than 60 degrees (a triangle before and after a change: it does not fold)."""
    length_before = _normal(p, q, r, before)
    length_after = _normal(s, t, u, after)
    if not (length_before > 0.0 and length_after > 0.0):
        return False
    cosine = (before[0] * after[0] + before[1] * after[1] + before[2] * after[2]) / (
        length_before * length_after)
    return cosine >= MIN_NORMAL_COSINE


@numba.njit(cache=True)
def _length2(position, a, b):
    dx = position[a, 0] - position[b, 0]
    dy = position[a, 1] - position[b, 1]
    dz = position[a, 2] - position[b, 2]
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True)
def _split(e, position, v_out, valence, home, to, nxt, face, f_half, v_alive, e_alive, f_alive,
           counts):
    """Split edge ``e`` at its midpoint: one new vertex, three new edges, two new triangles."""
    h0 = 2 * e
    h1 = h0 + 1
    a = to[h1]
    b = to[h0]
    h0n = nxt[h0]
    h0p = nxt[h0n]
    h1n = nxt[h1]
    h1p = nxt[h1n]
    c = to[h0n]
    d = to[h1n]
    f0 = face[h0]
    f1 = face[h1]
    m = counts[0]
    e1 = counts[1]
    f2 = counts[2]
    f3 = f2 + 1
    counts[0] += 1
    counts[1] += 3
    counts[2] += 2
    h2, h3 = 2 * e1, 2 * e1 + 1          # m -> b, b -> m
    h4, h5 = 2 * e1 + 2, 2 * e1 + 3      # m -> c, c -> m
    h6, h7 = 2 * e1 + 4, 2 * e1 + 5      # m -> d, d -> m
    for k in range(3):
        position[m, k] = 0.5 * (position[a, k] + position[b, k])
    home[m] = home[a]
    to[h0] = m
    to[h2], to[h3], to[h4], to[h5], to[h6], to[h7] = b, m, c, m, d, m
    # f0 = (a, m, c), f2 = (m, b, c), f1 = (m, a, d), f3 = (b, m, d)
    nxt[h0], nxt[h4], nxt[h0p] = h4, h0p, h0
    nxt[h2], nxt[h0n], nxt[h5] = h0n, h5, h2
    nxt[h1], nxt[h1n], nxt[h7] = h1n, h7, h1
    nxt[h3], nxt[h6], nxt[h1p] = h6, h1p, h3
    face[h0], face[h4], face[h0p] = f0, f0, f0
    face[h2], face[h0n], face[h5] = f2, f2, f2
    face[h1], face[h1n], face[h7] = f1, f1, f1
    face[h3], face[h6], face[h1p] = f3, f3, f3
    f_half[f0], f_half[f2], f_half[f1], f_half[f3] = h0, h2, h1, h3
    v_out[m] = h2
    v_out[b] = h3
    v_alive[m] = True
    e_alive[e1] = True
    e_alive[e1 + 1] = True
    e_alive[e1 + 2] = True
    f_alive[f2] = True
    f_alive[f3] = True
    valence[m] = 4
    valence[c] += 1
    valence[d] += 1


@numba.njit(cache=True)
def split_long_edges(position, v_out, valence, home, to, nxt, face, f_half, v_alive, e_alive,
                     f_alive, counts, high, start, edges):
    """Split every edge longer than ``high`` from ``start`` to ``edges`` (in index order; the
    new ones are not revisited). Returns the edge it stopped at for want of room in the
    arrays, or ``edges`` when done."""
    high2 = high * high
    for e in range(start, edges):
        if e_alive[e] and _length2(position, to[2 * e], to[2 * e + 1]) > high2:
            if counts[0] >= position.shape[0] or counts[1] + 3 > e_alive.shape[0] \
                    or counts[2] + 2 > f_half.shape[0]:
                return e
            _split(e, position, v_out, valence, home, to, nxt, face, f_half, v_alive, e_alive,
                   f_alive, counts)
    return edges


@numba.njit(cache=True)
def _star_may_move(v, other, ring, count, moved, position, to, nxt, face, f0, f1, high2,
                   before, after):
    """Whether vertex v, its outgoing half edges ``ring``, may move to ``moved`` in a collapse
    with ``other``: no edge to a neighbour gets longer than sqrt(high2) and no triangle (but
    f0 and f1, which go) folds."""
    for i in range(count):
        x = to[ring[i]]
        dx = position[x, 0] - moved[0]
        dy = position[x, 1] - moved[1]
        dz = position[x, 2] - moved[2]
        if x != other and dx * dx + dy * dy + dz * dz > high2:
            return False
    for i in range(count):
        g = ring[i]
        if face[g] == f0 or face[g] == f1:
            continue
        if not _turns_like(position[v], position[to[g]], position[to[nxt[g]]], moved,
                           position[to[g]], position[to[nxt[g]]], before, after):
            return False
    return True


@numba.njit(cache=True)
def _collapse(h, position, v_out, valence, to, nxt, face, f_half, v_alive, e_alive, f_alive,
              high2, ring_a, ring_b, before, after, midpoint):
    """Collapse half edge ``h`` (a -> b) into its midpoint, keeping b; False (nothing done) when
    the mesh would stop being a closed manifold sphere, an edge would get longer than
    sqrt(high2), or a triangle would fold."""
    o = h ^ 1
    a = to[o]
    b = to[h]
    hn = nxt[h]
    hp = nxt[hn]
    on = nxt[o]
    op = nxt[on]
    c = to[hn]
    d = to[on]
    if c == d or valence[c] <= 3 or valence[d] <= 3 or valence[a] + valence[b] - 4 < 3:
        return False
    count_a = _ring(a, v_out, to, nxt, ring_a)
    count_b = _ring(b, v_out, to, nxt, ring_b)
    if count_a < 0 or count_b < 0 or count_a + count_b - 4 > ring_a.shape[0]:
        return False
    # link condition: a and b have no common neighbour but c and d
    for i in range(count_a):
        x = to[ring_a[i]]
        if x == b or x == c or x == d:
            continue
        for j in range(count_b):
            if to[ring_b[j]] == x:
                return False
    for k in range(3):
        midpoint[k] = 0.5 * (position[a, k] + position[b, k])
    f0 = face[h]
    f1 = face[o]
    if not (_star_may_move(a, b, ring_a, count_a, midpoint, position, to, nxt, face, f0, f1,
                           high2, before, after)
            and _star_may_move(b, a, ring_b, count_b, midpoint, position, to, nxt, face, f0, f1,
                               high2, before, after)):
        return False
    # every half edge into a now ends at b
    for i in range(count_a):
        to[ring_a[i] ^ 1] = b
    # triangle f0 goes: its edges (b, c) and (c, a) become one, kept as hn, hn ^ 1; hn takes
    # the place of a -> c (now b -> c) in the triangle beyond
    x = hp ^ 1
    nx = nxt[x]
    px = nxt[nx]
    nxt[hn] = nx
    nxt[px] = hn
    face[hn] = face[x]
    f_half[face[x]] = hn
    # triangle f1 goes: (a, d) and (d, b) become one, kept as op, op ^ 1; op takes the place of
    # d -> a (now d -> b)
    y = on ^ 1
    ny = nxt[y]
    py = nxt[ny]
    nxt[op] = ny
    nxt[py] = op
    face[op] = face[y]
    f_half[face[y]] = op
    e_alive[h >> 1] = False
    e_alive[hp >> 1] = False
    e_alive[on >> 1] = False
    f_alive[f0] = False
    f_alive[f1] = False
    v_alive[a] = False
    v_out[b] = hn
    v_out[c] = hn ^ 1
    v_out[d] = op
    valence[b] = valence[a] + valence[b] - 4
    valence[c] -= 1
    valence[d] -= 1
    for k in range(3):
        position[b, k] = midpoint[k]
    return True


@numba.njit(cache=True)
def collapse_short_edges(position, v_out, valence, to, nxt, face, f_half, v_alive, e_alive,
                         f_alive, counts, low, high):
    """Collapse every edge shorter than ``low`` into its midpoint where allowed (in index
    order; an edge made shorter by an earlier collapse of the same pass is taken in turn)."""
    low2 = low * low
    high2 = high * high
    ring_a = np.empty(MAX_VALENCE, dtype=np.int64)
    ring_b = np.empty(MAX_VALENCE, dtype=np.int64)
    before = np.empty(3)
    after = np.empty(3)
    midpoint = np.empty(3)
    alive = 0
    for v in range(counts[0]):
        alive += v_alive[v]
    for e in range(counts[1]):
        if alive <= 4:
            break
        if not e_alive[e]:
            continue
        h = 2 * e
        if _length2(position, to[h], to[h + 1]) >= low2:
            continue
        # keep the end of higher valence: the merged vertex's valence stays nearer 6
        if valence[to[h + 1]] > valence[to[h]]:
            h = h + 1
        if _collapse(h, position, v_out, valence, to, nxt, face, f_half, v_alive, e_alive,
                     f_alive, high2, ring_a, ring_b, before, after, midpoint):
            alive -= 1


@numba.njit(cache=True)
def flip_to_valence_six(position, v_out, valence, to, nxt, face, f_half, e_alive, counts):
    """Flip every edge whose flip brings the valences of its four vertices nearer 6 (in index
    order), unless the new edge exists already or a triangle would fold."""
    ring = np.empty(MAX_VALENCE, dtype=np.int64)
    before = np.empty(3)
    after = np.empty(3)
    for e in range(counts[1]):
        if not e_alive[e]:
            continue
        h = 2 * e
        o = h + 1
        hn = nxt[h]
        hp = nxt[hn]
        on = nxt[o]
        op = nxt[on]
        a = to[o]
        b = to[h]
        c = to[hn]
        d = to[on]
        if valence[a] <= 3 or valence[b] <= 3 or c == d:
            continue
        deviation = (abs(valence[a] - 6) + abs(valence[b] - 6) + abs(valence[c] - 6)
                     + abs(valence[d] - 6))
        flipped = (abs(valence[a] - 7) + abs(valence[b] - 7) + abs(valence[c] - 5)
                   + abs(valence[d] - 5))
        if flipped >= deviation:
            continue
        count = _ring(c, v_out, to, nxt, ring)
        if count < 0:
            continue
        exists = False
        for i in range(count):
            if to[ring[i]] == d:
                exists = True
        if exists:
            continue
        # each new triangle, (d, c, a) and (c, d, b), against each old one, (b, c, a) and
        # (a, d, b): the first against the first is b moved to d, and so on
        if not (_turns_like(position[b], position[c], position[a], position[d], position[c],
                            position[a], before, after)
                and _turns_like(position[a], position[d], position[b], position[c], position[d],
                                position[b], before, after)
                and _turns_like(position[b], position[c], position[a], position[c], position[d],
                                position[b], before, after)
                and _turns_like(position[a], position[d], position[b], position[d], position[c],
                                position[a], before, after)):
            continue
        f0 = face[h]
        f1 = face[o]
        # f0 = (d, c, a): h d -> c, hp c -> a, on a -> d; f1 = (c, d, b): o c -> d, op d -> b,
        # hn b -> c
        to[h] = c
        to[o] = d
        nxt[h], nxt[hp], nxt[on] = hp, on, h
        nxt[o], nxt[op], nxt[hn] = op, hn, o
        face[h], face[hp], face[on] = f0, f0, f0
        face[o], face[op], face[hn] = f1, f1, f1
        f_half[f0] = h
        f_half[f1] = o
        if v_out[a] == h:
            v_out[a] = on
        if v_out[b] == o:
            v_out[b] = hn
        valence[a] -= 1
        valence[b] -= 1
        valence[c] += 1
        valence[d] += 1


@numba.njit(cache=True)
def relax_tangentially(position, v_out, to, nxt, v_alive, counts, moved):
    """Move every vertex to the centroid of its neighbours, projected into its tangent plane
    (the plane normal to the area-weighted normal of its triangles); all from the old
    positions, into ``moved``."""
    ring = np.empty(MAX_VALENCE, dtype=np.int64)
    normal = np.empty(3)
    for v in range(counts[0]):
        if not v_alive[v]:
            continue
        count = _ring(v, v_out, to, nxt, ring)
        if count < 0:
            moved[v, 0] = position[v, 0]   # element by element: a row assignment would
            moved[v, 1] = position[v, 1]   # compile numba's shape-mismatch message too
            moved[v, 2] = position[v, 2]
            continue
        cx = cy = cz = 0.0
        nx = ny = nz = 0.0
        for i in range(count):
            x = to[ring[i]]
            y = to[nxt[ring[i]]]
            cx += position[x, 0]
            cy += position[x, 1]
            cz += position[x, 2]
            _normal(position[v], position[x], position[y], normal)
            nx += normal[0]
            ny += normal[1]
            nz += normal[2]
        cx /= count
        cy /= count
        cz /= count
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        dx = cx - position[v, 0]
        dy = cy - position[v, 1]
        dz = cz - position[v, 2]
        if length > 0.0:
            nx /= length
            ny /= length
            nz /= length
            along = dx * nx + dy * ny + dz * nz
            dx -= along * nx
            dy -= along * ny
            dz -= along * nz
        moved[v, 0] = position[v, 0] + dx
        moved[v, 1] = position[v, 1] + dy
        moved[v, 2] = position[v, 2] + dz


@numba.njit(cache=True, inline="always")
def _closest_on_triangle(px, py, pz, f, vertices, faces, out):
    """The point of input triangle ``f`` nearest to p, into ``out``; its squared distance and
    region (:func:`.nearest.closest_point_and_region`)."""
    a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
    return closest_point_and_region(px, py, pz, vertices[a, 0], vertices[a, 1], vertices[a, 2],
                                    vertices[b, 0], vertices[b, 1], vertices[b, 2],
                                    vertices[c, 0], vertices[c, 1], vertices[c, 2], out)


@numba.njit(cache=True)
def project_by_walking(position, v_alive, home, counts, vertices, faces, star_start, star):
    """Put every vertex on the closest point of the input surface (``vertices``, ``faces``)
    near its ``home`` triangle, and make that triangle its home.

    When the nearest point of the home triangle is on its boundary, the triangles around the
    corner or the two ends of the edge it is on are tried, and the nearest becomes the home;
    until the nearest point is inside the home triangle, no neighbour is nearer, or after
    :data:`MAX_WALK` steps. ``star`` lists the triangles around each input vertex (compressed
    rows, ``star_start``)."""
    found = np.empty(3)
    best_point = np.empty(3)
    corners = np.empty(2, dtype=np.int64)
    for v in range(counts[0]):
        if not v_alive[v]:
            continue
        px, py, pz = position[v, 0], position[v, 1], position[v, 2]
        current = home[v]
        best, region = _closest_on_triangle(px, py, pz, current, vertices, faces, best_point)
        for _ in range(MAX_WALK):
            if region < 0:
                break
            if region < 3:
                corners[0] = faces[current, region]
                count = 1
            else:
                corners[0] = faces[current, (region - 2) % 3]
                corners[1] = faces[current, (region - 1) % 3]
                count = 2
            step_to = current
            step_region = region
            for i in range(count):
                corner = corners[i]
                for s in range(star_start[corner], star_start[corner + 1]):
                    f = star[s]
                    if f == current:
                        continue
                    d, where = _closest_on_triangle(px, py, pz, f, vertices, faces, found)
                    if d < best:
                        best = d
                        best_point[0], best_point[1], best_point[2] = found[0], found[1], found[2]
                        step_to = f
                        step_region = where
            if step_to == current:
                break
            current = step_to
            region = step_region
        home[v] = current
        position[v, 0], position[v, 1], position[v, 2] = best_point[0], best_point[1], best_point[2]


def _half_edges(faces: np.ndarray, n_vertices: int, capacity: tuple):
    """The half-edge arrays of a closed manifold triangle mesh, with room for ``capacity`` =
    (vertices, edges, triangles): ``to``, ``nxt``, ``face``, ``v_out``, ``valence``,
    ``f_half``, each vertex's first triangle, and the corners in the order of their vertices;
    None when the mesh is not a closed manifold with every vertex used (each edge in exactly two
    triangles that run it in opposite directions)."""
    cap_vertices, cap_edges, cap_faces = capacity
    m = len(faces)
    tail = faces.ravel()                         # corner 3 f + k: the edge from corner k to k + 1
    head = faces[:, [1, 2, 0]].ravel()
    if m % 2 or tail.min() < 0 or tail.max() >= n_vertices or np.any(tail == head):
        return None
    valence = np.bincount(tail, minlength=n_vertices)
    if np.any(valence == 0):
        return None
    key = np.minimum(tail, head) * n_vertices + np.maximum(tail, head)
    order = np.argsort(key, kind="stable")       # the two corners of each edge side by side
    first, second = order[0::2], order[1::2]
    if not (np.array_equal(key[first], key[second]) and np.all(np.diff(key[first]) > 0)
            and np.array_equal(tail[first], head[second])):
        return None
    half = np.empty(3 * m, dtype=np.int64)
    half[first] = 2 * np.arange(3 * m // 2)
    half[second] = 2 * np.arange(3 * m // 2) + 1
    corners = half.reshape(m, 3)
    to = np.full(2 * cap_edges, -1, dtype=np.int64)
    nxt = np.full(2 * cap_edges, -1, dtype=np.int64)
    face = np.full(2 * cap_edges, -1, dtype=np.int64)
    to[half] = head
    nxt[half] = corners[:, [1, 2, 0]].ravel()
    face[half] = np.repeat(np.arange(m), 3)
    corner_order = np.argsort(tail, kind="stable")
    first_corner = corner_order[np.concatenate([[0], np.cumsum(valence)[:-1]])]
    v_out = np.full(cap_vertices, -1, dtype=np.int64)
    v_out[:n_vertices] = half[first_corner]
    valences = np.zeros(cap_vertices, dtype=np.int64)
    valences[:n_vertices] = valence
    f_half = np.full(cap_faces, -1, dtype=np.int64)
    f_half[:m] = corners[:, 0]
    return to, nxt, face, v_out, valences, f_half, first_corner // 3, corner_order


class _Mesh:
    """The half-edge arrays of the mesh being remeshed, with room to grow (see the module's
    docstring); ``counts`` = vertices, edges, triangles used so far (the dead ones included)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, room: int, arrays: tuple):
        """``arrays``: those of :func:`_half_edges` with room for ``room`` vertices."""
        n, m = len(vertices), len(faces)
        (self.to, self.nxt, self.face, self.v_out, self.valence, self.f_half,
         first_face, _) = arrays
        self.position = np.zeros((room, 3))
        self.position[:n] = vertices
        self.home = np.zeros(room, dtype=np.int64)     # the input triangle a vertex is on
        self.home[:n] = first_face
        self.v_alive = np.zeros(room, dtype=np.bool_)
        self.v_alive[:n] = True
        self.e_alive = np.zeros(3 * room, dtype=np.bool_)
        self.e_alive[:3 * m // 2] = True
        self.f_alive = np.zeros(2 * room, dtype=np.bool_)
        self.f_alive[:m] = True
        self.counts = np.array([n, 3 * m // 2, m], dtype=np.int64)

    def grow(self):
        """Twice the room."""
        def doubled(array, fill):
            bigger = np.full((2 * len(array),) + array.shape[1:], fill, dtype=array.dtype)
            bigger[:len(array)] = array
            return bigger

        for name, fill in (("to", -1), ("nxt", -1), ("face", -1), ("v_out", -1),
                           ("valence", 0), ("f_half", -1), ("position", 0.0), ("home", 0),
                           ("v_alive", False), ("e_alive", False), ("f_alive", False)):
            setattr(self, name, doubled(getattr(self, name), fill))

    def split(self, high: float):
        """:func:`split_long_edges`, with more room whenever it runs out."""
        done, edges = 0, int(self.counts[1])
        while True:
            done = split_long_edges(self.position, self.v_out, self.valence, self.home, self.to,
                                    self.nxt, self.face, self.f_half, self.v_alive,
                                    self.e_alive, self.f_alive, self.counts, high, done, edges)
            if done == edges:
                return
            self.grow()

    def compacted(self) -> tuple[np.ndarray, np.ndarray]:
        """The living vertices and triangles, renumbered in index order."""
        nv, _, nf = self.counts
        alive = np.flatnonzero(self.v_alive[:nv])
        index = np.full(nv, -1, dtype=np.int64)
        index[alive] = np.arange(len(alive))
        first = self.f_half[:nf][self.f_alive[:nf]]
        second = self.nxt[first]
        # a half edge points to the corner after its tail: (tail, head, next head)
        triangles = index[np.stack([self.to[self.nxt[second]], self.to[first], self.to[second]],
                                   axis=1)]
        return self.position[alive].copy(), triangles


def remesh_isotropic(vertices: np.ndarray, faces: np.ndarray, edge_length: float,
                     iterations: int = 5) -> tuple[np.ndarray, np.ndarray] | None:
    """Isotropic remeshing of a closed, consistently oriented manifold triangle mesh to edges of
    about ``edge_length`` (between :data:`LOW` and :data:`HIGH` times it).

    Parameters
    ----------
    vertices : ndarray (n, 3)
    faces : ndarray (m, 3)
        Every vertex used; every edge shared by exactly two triangles that traverse it in
        opposite directions.
    edge_length : float
        The target edge length.
    iterations : int
        Rounds of split, collapse, flip, relaxation and projection.

    Returns
    -------
    (vertices, faces) or None
        The new mesh, its vertices on the input surface; None when the input is not a closed
        manifold (then nothing was done).

    Examples
    --------
    >>> from mdlshapemodel.correspondence.sampling import icosphere
    >>> points, triangles = icosphere(3)                  # edges of about 0.16
    >>> new_points, new_triangles = remesh_isotropic(points, triangles, 0.3)
    >>> len(new_points) < len(points)
    True
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    n = len(vertices)
    room = n + n // 2 + 16
    arrays = _half_edges(faces, n, (room, 3 * room, 2 * room)) if len(faces) >= 4 else None
    if arrays is None:
        return None
    star = arrays[7] // 3                        # the triangles around each vertex, in rows
    star_start = np.concatenate([[0], np.cumsum(arrays[4][:n])])
    mesh = _Mesh(vertices, faces, room, arrays)
    high, low = HIGH * float(edge_length), LOW * float(edge_length)
    for _ in range(iterations):
        mesh.split(high)
        collapse_short_edges(mesh.position, mesh.v_out, mesh.valence, mesh.to, mesh.nxt,
                             mesh.face, mesh.f_half, mesh.v_alive, mesh.e_alive, mesh.f_alive,
                             mesh.counts, low, high)
        flip_to_valence_six(mesh.position, mesh.v_out, mesh.valence, mesh.to, mesh.nxt,
                            mesh.face, mesh.f_half, mesh.e_alive, mesh.counts)
        moved = np.empty_like(mesh.position)
        relax_tangentially(mesh.position, mesh.v_out, mesh.to, mesh.nxt, mesh.v_alive,
                           mesh.counts, moved)
        used = int(mesh.counts[0])
        mesh.position[:used] = moved[:used]
        project_by_walking(mesh.position, mesh.v_alive, mesh.home, mesh.counts, vertices, faces,
                           star_start, star)
    return mesh.compacted()
