"""Tests of the sphere sampling grids, spherical point location and interpolation."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import (INT16_INDEX_LIMIT, SphereLocator, fibonacci_sphere,
                                                   grid_order, icosphere, index_dtype,
                                                   orient_triangles, sphere_grid,
                                                   spherical_triangles)
from mdlshapemodel.errors import ArgumentError
from mdlshapemodel.prepare.surface import triangle_vertex_areas


def orientation(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def undirected_edges(faces):
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return edges, np.unique(np.sort(edges, axis=1), axis=0)


def random_unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def brute_force_barycentric(points, faces, queries):
    """Solve [a b c] lam = q for every face and every query: (n_queries, n_faces, 3)."""
    matrices = np.stack([points[faces[:, k]] for k in range(3)], axis=2)     # columns a, b, c
    rhs = np.broadcast_to(queries[:, None, :, None], (len(queries), len(faces), 3, 1))
    return np.linalg.solve(np.broadcast_to(matrices, rhs.shape[:2] + (3, 3)), rhs)[..., 0]


@pytest.mark.parametrize("level", [0, 1, 2, 3, 4])
def test_icosphere_counts_norms_orientation_and_euler(level):
    points, faces = icosphere(level)
    assert points.shape == (10 * 4 ** level + 2, 3)
    assert faces.shape == (20 * 4 ** level, 3)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=1e-14)
    assert np.all(orientation(points, faces) > 0)                 # counter-clockwise from outside
    directed, edges = undirected_edges(faces)
    assert len(points) - len(edges) + len(faces) == 2              # Euler characteristic
    # closed and consistently oriented: every directed edge appears once, its reverse once
    assert len(np.unique(directed, axis=0)) == len(directed)
    assert len(edges) * 2 == len(directed)
    # no duplicated points; all points are used
    assert len(np.unique(np.round(points, 12), axis=0)) == len(points)
    assert np.array_equal(np.unique(faces), np.arange(len(points)))


def test_icosphere_is_nearly_uniform():
    points, faces = icosphere(3)
    areas = triangle_vertex_areas(points, faces)
    assert areas.max() / areas.min() < 1.6
    # the flat triangles approximate the sphere's area 4 pi from below
    assert 0.98 * 4 * np.pi < areas.sum() < 4 * np.pi


def test_sphere_grid_picks_icosphere_or_fibonacci():
    points, faces = sphere_grid(2562)
    ico_points, ico_faces = icosphere(4)
    np.testing.assert_array_equal(points, ico_points)
    np.testing.assert_array_equal(faces, ico_faces)
    assert len(sphere_grid(12)[0]) == 12
    assert len(sphere_grid(642)[0]) == 642
    points, faces = sphere_grid(1000)
    assert points.shape == (1000, 3)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=1e-12)
    assert np.all(orientation(points, faces) > 0)
    _, edges = undirected_edges(faces)
    assert len(points) - len(edges) + len(faces) == 2
    assert len(np.unique(np.round(points, 10), axis=0)) == 1000
    with pytest.raises(ValueError):
        sphere_grid(11)


def test_fibonacci_sphere_is_nearly_uniform():
    points, faces = fibonacci_sphere(500)
    # the nearest-neighbour distance varies little over the sphere
    from scipy.spatial import cKDTree

    distances = cKDTree(points).query(points, k=2)[0][:, 1]
    assert distances.max() / distances.min() < 1.6
    np.testing.assert_allclose(points.mean(axis=0), 0.0, atol=1e-2)


def test_orient_triangles_fixes_reversed_faces(rng):
    points, faces = icosphere(2)
    scrambled = faces.copy()
    reverse = rng.random(len(faces)) < 0.5
    scrambled[reverse] = scrambled[reverse][:, [2, 1, 0]]
    fixed = orient_triangles(points, scrambled)
    assert np.all(orientation(points, fixed) > 0)
    np.testing.assert_array_equal(np.sort(fixed, axis=1), np.sort(faces, axis=1))


@pytest.mark.parametrize("grid", ["icosphere", "fibonacci"])
def test_locate_agrees_with_brute_force(rng, grid):
    points, faces = icosphere(2) if grid == "icosphere" else fibonacci_sphere(300)
    locator = SphereLocator(points, faces)
    queries = random_unit_vectors(rng, 400)
    face, coords = locator.locate(queries)
    assert np.all(coords >= 0)
    np.testing.assert_allclose(coords.sum(axis=1), 1.0, atol=1e-14)
    lam = brute_force_barycentric(points, faces, queries)
    containing = lam.min(axis=2) >= -1e-12
    assert np.all(containing.sum(axis=1) >= 1)
    assert np.all(containing[np.arange(len(queries)), face])
    expected = lam[np.arange(len(queries)), face]
    np.testing.assert_allclose(coords, expected / expected.sum(axis=1, keepdims=True), atol=1e-12)
    # the query is a positive multiple of the barycentric combination of the triangle's corners
    combination = np.einsum("ik,ikd->id", coords, points[faces[face]])
    direction = combination / np.linalg.norm(combination, axis=1, keepdims=True)
    np.testing.assert_allclose(direction, queries, atol=1e-12)


def test_locate_a_block_at_a_time_gives_what_all_at_once_gives(rng, monkeypatch):
    """Points not found by walking are located LOCATE_BLOCK at a time: blocks of 7 (the last one
    short), with and without hints, give the faces and coordinates of one block, bit for bit."""
    from mdlshapemodel.correspondence import sampling

    points, faces = icosphere(2)
    locator = SphereLocator(points, faces)
    queries = random_unit_vectors(rng, 400)
    hint = rng.integers(0, len(faces), len(queries))
    whole = [locator.locate(queries), locator.locate(queries, hint, walk_steps=1)]
    monkeypatch.setattr(sampling, "LOCATE_BLOCK", 7)
    blocks = [locator.locate(queries), locator.locate(queries, hint, walk_steps=1)]
    for (face, coords), (block_face, block_coords) in zip(whole, blocks):
        assert np.all(block_face >= 0)
        np.testing.assert_array_equal(block_face, face)
        np.testing.assert_array_equal(block_coords, coords)


def test_locate_on_a_warped_triangulation(rng):
    """Point location on a strongly non-uniform (but fold-free) triangulation, as after warping."""
    from mdlshapemodel.correspondence.warps import apply_symmetric_theta

    points, faces = icosphere(3)
    warped = points
    for centre in random_unit_vectors(rng, 4):
        warped = apply_symmetric_theta(warped, centre, 1.0, 0.5)
    assert np.all(orientation(warped, faces) > 0)
    locator = SphereLocator(warped, faces)
    queries = random_unit_vectors(rng, 300)
    face, coords = locator.locate(queries)
    lam = brute_force_barycentric(warped, faces, queries)
    assert np.all(lam[np.arange(len(queries)), face].min(axis=1) >= -1e-12)
    combination = np.einsum("ik,ikd->id", coords, warped[faces[face]])
    np.testing.assert_allclose(combination / np.linalg.norm(combination, axis=1, keepdims=True),
                               queries, atol=1e-12)


def test_interpolation_at_the_vertices_is_exact(rng):
    points, faces = icosphere(2)
    locator = SphereLocator(points, faces)
    values = rng.normal(size=(len(points), 3))
    result, face = locator.evaluate(values, points)
    np.testing.assert_allclose(result, values, atol=1e-12)
    scalar, _ = locator.evaluate(values[:, 0], points)
    np.testing.assert_allclose(scalar, values[:, 0], atol=1e-12)


def test_interpolation_of_a_linear_field(rng):
    """v -> A v + b at the vertices interpolates to A p' + b, p' = central projection of the query
    onto the plane of its triangle."""
    points, faces = fibonacci_sphere(200)
    locator = SphereLocator(points, faces)
    matrix, offset = rng.normal(size=(3, 3)), rng.normal(size=3)
    values = points @ matrix.T + offset
    queries = random_unit_vectors(rng, 300)
    result, face = locator.evaluate(values, queries)
    a, b, c = (points[faces[face, k]] for k in range(3))
    normal = np.cross(b - a, c - a)
    scale = np.einsum("ij,ij->i", normal, a) / np.einsum("ij,ij->i", normal, queries)
    projected = queries * scale[:, None]
    np.testing.assert_allclose(result, projected @ matrix.T + offset, atol=1e-12)


def test_hints_do_not_change_the_answer(rng):
    points, faces = icosphere(3)
    locator = SphereLocator(points, faces)
    queries = random_unit_vectors(rng, 500)
    face, coords = locator.locate(queries)
    for hint in (face, rng.integers(0, len(faces), size=len(queries)),
                 np.where(rng.random(len(queries)) < 0.5, face, 0)):
        hinted_face, hinted_coords = locator.locate(queries, hint=hint)
        np.testing.assert_array_equal(hinted_face, face)
        np.testing.assert_allclose(hinted_coords, coords, atol=1e-14)


def test_locate_when_nearest_vertices_are_not_corners(rng):
    """On a strongly warped triangulation the nearest vertex is often not a corner of the triangle
    holding the query; location must still be right (with any number of neighbours tried)."""
    from mdlshapemodel.correspondence.warps import apply_symmetric_theta

    points, faces = icosphere(2)
    for centre in random_unit_vectors(np.random.default_rng(1), 5):
        points = apply_symmetric_theta(points, centre, 1.0, 0.5)
    assert np.all(orientation(points, faces) > 0)
    queries = random_unit_vectors(rng, 1000)
    lam = brute_force_barycentric(points, faces, queries)
    truth = np.argmax(lam.min(axis=2), axis=1)
    nearest = np.argmax(queries @ points.T, axis=1)
    assert np.any(~np.any(faces[truth] == nearest[:, None], axis=1))   # the hard case occurs
    locator = SphereLocator(points, faces)
    for neighbours in (1, 4):
        face, coords = locator.locate(queries, neighbours=neighbours)
        assert np.all(lam[np.arange(len(queries)), face].min(axis=1) >= -1e-12)
        combination = np.einsum("ik,ikd->id", coords, points[faces[face]])
        np.testing.assert_allclose(combination / np.linalg.norm(combination, axis=1)[:, None],
                                   queries, atol=1e-12)


def test_triangle_vertex_areas_sum_to_the_total_area(rng):
    points, faces = icosphere(2)
    surface = points * rng.uniform(0.5, 3.0, size=3) + rng.normal(scale=0.05, size=points.shape)
    # Heron's formula, independently of the cross product
    a, b, c = (np.linalg.norm(surface[faces[:, i]] - surface[faces[:, j]], axis=1)
               for i, j in ((0, 1), (1, 2), (2, 0)))
    s = (a + b + c) / 2
    total = np.sum(np.sqrt(s * (s - a) * (s - b) * (s - c)))
    areas = triangle_vertex_areas(surface, faces)
    assert areas.shape == (len(points),)
    assert areas.sum() == pytest.approx(total, rel=1e-10)
    assert np.all(areas > 0)


def test_triangle_vertex_areas_single_triangle_and_batches(rng):
    triangle = np.array([[0.0, 0, 0], [2, 0, 0], [0, 3, 0], [5, 5, 5]])   # last point unused
    areas = triangle_vertex_areas(triangle, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(areas, [1.0, 1.0, 1.0, 0.0])
    points, faces = icosphere(1)
    batch = np.stack([points * s for s in (1.0, 2.0, 0.5)])
    result = triangle_vertex_areas(batch, faces)
    assert result.shape == (3, len(points))
    np.testing.assert_allclose(result[1], 4 * result[0])
    np.testing.assert_allclose(result[2], 0.25 * result[0])


def test_jacobian_matches_finite_differences_along_the_sphere(rng):
    points, faces = icosphere(3)
    locator = SphereLocator(points, faces)
    values = rng.normal(size=(len(points), 3))
    queries = random_unit_vectors(rng, 200)
    face, coords = locator.locate(queries)
    # keep queries well inside their triangle so that a small step does not change face
    inside = coords.min(axis=1) > 0.05
    queries, face = queries[inside], face[inside]
    jacobian = locator.jacobian(values, face, queries)
    assert jacobian.shape == (len(queries), 3, 3)
    step = 1e-6
    for direction in random_unit_vectors(rng, 3):
        tangent = direction - (queries @ direction)[:, None] * queries
        moved = queries + step * tangent
        moved /= np.linalg.norm(moved, axis=1, keepdims=True)
        back = queries - step * tangent
        back /= np.linalg.norm(back, axis=1, keepdims=True)
        forward = locator.interpolate(values, face, locator.coordinates(face, moved) /
                                      locator.coordinates(face, moved).sum(1, keepdims=True))
        backward = locator.interpolate(values, face, locator.coordinates(face, back) /
                                       locator.coordinates(face, back).sum(1, keepdims=True))
        numeric = (forward - backward) / (2 * step)
        analytic = np.einsum("ndk,nk->nd", jacobian, tangent)
        np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6)
    # a radial motion of u does not move the sample
    np.testing.assert_allclose(np.einsum("ndk,nk->nd", jacobian, queries), 0.0, atol=1e-10)


def test_grid_order_renumbers_the_same_triangulation_in_grid_order(rng):
    """The renumbered mesh has the same triangles (as point triples, same orientation), and its
    faces come in the order of the grid point nearest to each."""
    points, triangles = icosphere(3)
    permutation = rng.permutation(len(points))               # a mesh numbered at random
    sphere = points[permutation]
    new_index = np.argsort(permutation)
    faces = new_index[triangles][rng.permutation(len(triangles))]
    grid, _ = icosphere(2)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    grid = grid @ q.T                                        # no ties between grid points
    order, renumbered = grid_order(sphere, faces, grid)
    assert sorted(order) == list(range(len(sphere)))
    moved = sphere[order]

    def point_triples(points, faces):
        corners = points[faces]                                # rotate each to its smallest corner
        first = np.argmin(corners[:, :, 0], axis=1)
        rolled = np.stack([np.roll(c, -f, axis=0) for c, f in zip(corners, first)])
        return rolled[np.lexsort(rolled.reshape(len(rolled), -1).T[::-1])]

    np.testing.assert_array_equal(point_triples(moved, renumbered), point_triples(sphere, faces))
    assert np.all(orientation(moved, renumbered) > 0)
    nearest = np.argmax(moved[renumbered].sum(axis=1) @ grid.T, axis=1)
    assert np.all(np.diff(nearest) >= 0)
    # vertices are numbered by first use: the first face uses 0, 1, 2
    assert sorted(renumbered[0]) == [0, 1, 2]


def test_index_dtype_is_int16_up_to_its_largest_index_then_int32():
    """Tables over at most 32,767 items (every index and the padding -1 fit) are int16."""
    assert index_dtype(1) is np.int16 and index_dtype(INT16_INDEX_LIMIT) is np.int16
    assert INT16_INDEX_LIMIT == 32767
    assert index_dtype(INT16_INDEX_LIMIT + 1) is np.int32 and index_dtype(10 ** 9) is np.int32
    with pytest.raises(ArgumentError, match="32-bit"):
        index_dtype(2 ** 31)


@pytest.mark.parametrize("mesh, itemsize", [
    (lambda: icosphere(3), 2),
    # 31,996 faces: face indices up to the top of int16's range
    (lambda: fibonacci_sphere(16000), 2),
    (lambda: icosphere(6), 4),          # 81,920 faces
])
def test_locator_index_tables_are_narrow_and_locate_as_int64_ones_do(rng, mesh, itemsize):
    """The locator a build keeps per case holds its three index tables, and gives the faces it
    locates (a part's hints), in 2 bytes an entry below 32,768 vertices and faces, 4 above; a
    walk over them, and a location by the nearest vertices, reach the same faces and coordinates
    as over the same tables in int64."""
    from mdlshapemodel.correspondence import hotloops
    from mdlshapemodel.correspondence.sampling import face_neighbours, vertex_face_table

    sphere, faces = mesh()
    locator = SphereLocator(sphere, faces)
    for table in (locator.faces, locator.neighbours, locator.vertex_faces):
        assert table.itemsize == itemsize
    assert locator.neighbours.nbytes == itemsize * 3 * len(faces)
    faces64 = np.asarray(faces, dtype=np.int64)
    neighbours64 = face_neighbours(faces64)
    np.testing.assert_array_equal(locator.neighbours, neighbours64)
    np.testing.assert_array_equal(locator.vertex_faces, vertex_face_table(faces64, len(sphere)))
    # hints among the highest-numbered faces, so that the indices walked are the largest, and
    # points a few triangles from them: some reached within the walk's steps, some not
    hint = rng.integers(max(len(faces) - 2000, 0), len(faces), 500)
    edge = np.sqrt(4.0 * np.pi / len(faces))
    points = sphere[faces64[hint]].mean(axis=1) + rng.normal(scale=3.0 * edge, size=(500, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    results = []
    for tables in ((locator.faces, locator.neighbours), (faces64, neighbours64)):
        face, coords = np.full(len(points), -1), np.zeros((len(points), 3))
        found = np.zeros(len(points), dtype=bool)
        hotloops.walk(locator.sphere, *tables, points, hint, 4, -1e-12, face, coords, found)
        results.append((face, coords, found))
    (face_narrow, coords_narrow, found_narrow), (face64, coords64, found64) = results
    assert found_narrow.any() and not found_narrow.all()
    np.testing.assert_array_equal(found_narrow, found64)
    np.testing.assert_array_equal(face_narrow, face64)
    np.testing.assert_array_equal(coords_narrow, coords64)
    assert face_narrow[found_narrow].max() > len(faces) - 200
    face, coords = locator.locate(points, hint)
    assert face.dtype == locator.faces.dtype         # kept as hints: narrow too
    np.testing.assert_array_equal(face[found_narrow], face_narrow[found_narrow])
    unhinted, unhinted_coords = locator.locate(points)
    np.testing.assert_array_equal(unhinted, face)
    np.testing.assert_allclose(unhinted_coords, coords, atol=1e-12)
    a, b, c = (sphere[faces64[face, k]] for k in range(3))
    corners = np.stack([a, b, c], axis=2)            # columns a, b, c
    lam = np.linalg.solve(corners, points[:, :, None])[:, :, 0]
    assert lam.min() > -1e-9


def _inverses_by_numpy(sphere, faces):
    """[a b c]^-1 of every face as numpy forms it: the rows b x c, c x a, a x b over a . (b x c)."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    rows = np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1)
    det = np.einsum("ij,ij->i", a, rows[:, 0])
    return rows / det[:, None, None]


def test_locator_computes_each_faces_inverse_as_numpy_does_bit_for_bit(rng):
    """The locator keeps no 3 x 3 matrix per face: the ones it computes where it locates a point
    are numpy's bit for bit, so the faces, coordinates and samples are too."""
    meshes = [icosphere(3), fibonacci_sphere(1500)]
    for n in (300, 4000):
        points = rng.normal(size=(n, 3))
        points /= np.linalg.norm(points, axis=1, keepdims=True)
        meshes.append((points, spherical_triangles(points)))
    for sphere, faces in meshes:
        locator = SphereLocator(sphere, faces)
        assert locator.faces.dtype == index_dtype(max(len(sphere), len(faces)))
        assert not any(isinstance(v, np.ndarray) and v.dtype == np.float64 and len(v) == len(faces)
                       for v in vars(locator).values())      # no table of floats per face
        expected = _inverses_by_numpy(np.asarray(sphere, dtype=np.float64), faces)
        np.testing.assert_array_equal(locator.inverses(np.arange(len(faces))), expected)
        chosen = rng.integers(0, len(faces), (50, 4))
        np.testing.assert_array_equal(locator.inverses(chosen), expected[chosen])
        u = rng.normal(size=(50, 1, 3))
        np.testing.assert_array_equal(locator.coordinates(chosen, u),
                                      np.einsum("...ij,...j->...i", expected[chosen], u))
