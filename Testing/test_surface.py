"""Tests of surfaces: topology checks, label map -> mesh, cleaning (docs/method.md section 5)."""

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from mdlshapemodel.errors import SurfaceError
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare.surface import (arrays_to_polydata, compact, contour_stride, decimate,
                                   drop_degenerate_faces,
                                   edges_of, face_areas, largest_component, mask_to_surface,
                                   merge_close_vertices, mesh_to_mask, orient_outwards,
                                   point_surface_distances,
                                   remesh, require_sphere_like, resample, signed_volume, topology)
from synthetic import torus
from mdlshapemodel.config import BuildConfig, MIN_SURFACE_VERTICES, target_vertices_for


def box(size=(1.0, 1.0, 1.0), offset=(0.0, 0.0, 0.0)):
    """An axis-aligned box as 12 triangles, oriented outwards independently of the library."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    corners = corners * size + offset
    faces = ConvexHull(corners).simplices.copy()
    centre = corners.mean(axis=0)
    for f in faces:
        a, b, c = corners[f]
        if np.cross(b - a, c - a) @ ((a + b + c) / 3 - centre) < 0:
            f[[1, 2]] = f[[2, 1]]
    return corners, faces


def ball_mask(shape, spacing, origin, centre_index, radius):
    """Voxels (z, y, x) whose physical centre lies in a ball; spacing and origin are (x, y, z)."""
    z, y, x = np.indices(shape, dtype=float)
    physical = [origin[k] + spacing[k] * i for k, i in enumerate((x, y, z))]
    centre = np.asarray(origin) + np.asarray(spacing) * centre_index
    return sum((p - c) ** 2 for p, c in zip(physical, centre)) <= radius ** 2


# --- topology ----------------------------------------------------------------------------------------

def test_icosphere_is_sphere_like():
    vertices, faces = icosphere(2)
    topo = topology(vertices, faces)
    assert topo.is_sphere_like and topo.is_closed_manifold and topo.consistently_oriented
    assert topo.euler_characteristic == 2
    assert (topo.n_vertices, topo.n_faces, topo.n_edges) == (162, 320, 480)
    assert topo.n_components == 1
    assert topo.describe() == ""
    assert require_sphere_like(vertices, faces).is_sphere_like


def test_torus_has_genus_one():
    vertices, faces = torus()
    topo = topology(vertices, faces)
    assert topo.euler_characteristic == 0
    assert topo.is_closed_manifold and topo.consistently_oriented and topo.n_components == 1
    assert not topo.is_sphere_like
    assert "genus 1" in topo.describe()
    with pytest.raises(SurfaceError, match="genus 1"):
        require_sphere_like(vertices, faces)


def test_mesh_with_a_hole():
    vertices, faces = icosphere(2)
    topo = topology(vertices, faces[1:])
    assert topo.n_boundary_edges == 3
    assert topo.euler_characteristic == 1
    assert not topo.is_closed_manifold and not topo.is_sphere_like
    assert "3 boundary edges" in topo.describe()
    with pytest.raises(SurfaceError, match="boundary edges"):
        require_sphere_like(vertices, faces[1:])


def test_two_disjoint_spheres():
    vertices, faces = icosphere(1)
    both_vertices = np.concatenate([vertices, vertices + [5.0, 0, 0]])
    both_faces = np.concatenate([faces, faces + len(vertices)])
    topo = topology(both_vertices, both_faces)
    assert topo.n_components == 2
    assert topo.euler_characteristic == 4
    assert topo.is_closed_manifold
    assert "2 disconnected components" in topo.describe()
    with pytest.raises(SurfaceError, match="2 disconnected components"):
        require_sphere_like(both_vertices, both_faces)


def test_three_triangles_sharing_an_edge_are_non_manifold():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], float)
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    topo = topology(vertices, faces)
    assert topo.n_nonmanifold_edges == 1
    assert topo.n_boundary_edges == 6
    assert "non-manifold" in topo.describe()
    # a fin glued to a closed sphere: one non-manifold edge, two boundary edges
    sphere, sphere_faces = icosphere(1)
    a, b = sphere_faces[0, :2]
    fin_vertices = np.concatenate([sphere, [[3.0, 3.0, 3.0]]])
    fin_faces = np.concatenate([sphere_faces, [[a, b, len(sphere)]]])
    topo = topology(fin_vertices, fin_faces)
    assert (topo.n_nonmanifold_edges, topo.n_boundary_edges) == (1, 2)
    with pytest.raises(SurfaceError, match="non-manifold"):
        require_sphere_like(fin_vertices, fin_faces)


def test_inconsistent_orientation_is_detected():
    vertices, faces = icosphere(1)
    faces = faces.copy()
    faces[3] = faces[3, ::-1]
    topo = topology(vertices, faces)
    assert topo.is_closed_manifold and topo.euler_characteristic == 2
    assert not topo.consistently_oriented and not topo.is_sphere_like
    assert "inconsistently oriented" in topo.describe()


def test_unused_vertices_and_empty_meshes():
    vertices, faces = icosphere(1)
    extra = np.concatenate([vertices, [[9.0, 9.0, 9.0]]])
    topo = topology(extra, faces)
    assert topo.n_vertices == len(vertices) and topo.is_sphere_like
    empty = topology(vertices, np.zeros((0, 3), dtype=int))
    assert empty.n_faces == 0 and not empty.is_sphere_like
    assert "empty" in empty.describe()


def test_non_finite_coordinates_are_rejected():
    vertices, faces = icosphere(1)
    for bad in (np.nan, np.inf):
        broken = vertices.copy()
        broken[5, 1] = bad
        with pytest.raises(SurfaceError, match="non-finite"):
            require_sphere_like(broken, faces)


def test_edges_of():
    edges = edges_of(np.array([[0, 1, 2], [2, 1, 3]]))
    np.testing.assert_array_equal(edges, [[0, 1], [2, 1], [1, 2], [1, 3], [2, 0], [3, 2]])


# --- volumes and orientation ------------------------------------------------------------------------

def test_signed_volume_of_boxes():
    vertices, faces = box()
    assert signed_volume(vertices, faces) == pytest.approx(1.0, abs=1e-14)
    vertices, faces = box(size=(2.0, 3.0, 0.5), offset=(10.0, -4.0, 7.0))
    assert signed_volume(vertices, faces) == pytest.approx(3.0, rel=1e-12)
    assert signed_volume(vertices, faces[:, ::-1]) == pytest.approx(-3.0, rel=1e-12)
    np.testing.assert_allclose(face_areas(vertices, faces).sum(), 2 * (6 + 1 + 1.5))


def test_orient_outwards_flips_inside_out_meshes():
    vertices, faces = icosphere(2)
    vertices = vertices * 2.0 + [1.0, 2.0, 3.0]
    inside_out = faces[:, [0, 2, 1]]
    assert signed_volume(vertices, inside_out) < 0
    fixed = orient_outwards(vertices, inside_out)
    assert signed_volume(vertices, fixed) > 0
    assert topology(vertices, fixed).consistently_oriented
    # outward normals: each face normal points away from the centre
    a, b, c = (vertices[fixed[:, k]] for k in range(3))
    normals = np.cross(b - a, c - a)
    assert np.all(np.einsum("ij,ij->i", normals, (a + b + c) / 3 - [1.0, 2.0, 3.0]) > 0)
    np.testing.assert_array_equal(orient_outwards(vertices, faces), faces)


# --- cleaning ---------------------------------------------------------------------------------------

def test_merge_close_vertices_rebuilds_an_stl_soup():
    points, faces = icosphere(2)
    points = points * 30.0 + [100.0, -50.0, 20.0]
    soup = points[faces].reshape(-1, 3)                  # every face has its own three vertices
    soup_faces = np.arange(len(soup)).reshape(-1, 3)
    assert not topology(soup, soup_faces).is_closed_manifold
    vertices, merged = merge_close_vertices(soup, soup_faces)
    assert len(vertices) == len(points)
    np.testing.assert_array_equal(vertices[merged], soup[soup_faces])  # same triangles
    assert topology(vertices, merged).is_sphere_like


def test_merge_close_vertices_keeps_distinct_vertices():
    points, faces = icosphere(2)
    vertices, merged = merge_close_vertices(points, faces)
    assert len(vertices) == len(points)
    np.testing.assert_array_equal(vertices[merged], points[faces])


def test_merge_close_vertices_merges_any_pair_closer_than_the_tolerance():
    """Two vertices 1e-12 apart (tolerance: 1e-9 x bounding-box diagonal = 1.4e-9) must merge,
    wherever they are; here they lie on both sides of a multiple of half the tolerance."""
    cell = 1e-9 * np.sqrt(2.0)                    # tolerance times the bounding-box diagonal
    x = (np.round(0.5 / cell) + 0.5) * cell - 0.4e-12
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                         [x, 0.0, 0.0], [x + 1e-12, 0.0, 0.0]])
    faces = np.array([[0, 1, 2], [3, 2, 0], [4, 1, 2]])
    assert np.linalg.norm(vertices[4] - vertices[3]) < 1e-3 * cell
    merged_vertices, _ = merge_close_vertices(vertices, faces)
    assert len(merged_vertices) == 4


def test_drop_degenerate_faces_and_compact():
    points, faces = icosphere(1)
    extra = np.concatenate([points, [[0.1, 0.2, 0.3], [5.0, 5.0, 5.0], [6.0, 6.0, 6.0],
                                     [7.0, 7.0, 7.0]]])
    n = len(points)
    bad = np.array([[0, 0, 1], [n, n, n], [n + 1, n + 2, n + 3]])   # repeated / collinear
    vertices, cleaned = drop_degenerate_faces(extra, np.concatenate([faces, bad]))
    assert len(cleaned) == len(faces) and len(vertices) == n
    assert topology(vertices, cleaned).is_sphere_like
    np.testing.assert_allclose(np.sort(face_areas(vertices, cleaned)),
                               np.sort(face_areas(points, faces)))
    sub_vertices, sub_faces = compact(extra, np.array([[n + 3, 2, n + 1]]))
    np.testing.assert_array_equal(sub_faces, [[2, 0, 1]])
    np.testing.assert_array_equal(sub_vertices, extra[[2, n + 1, n + 3]])


def test_largest_component_keeps_the_bigger_sphere():
    small, small_faces = icosphere(1)
    big, big_faces = icosphere(2)
    vertices = np.concatenate([small, big * 2 + 10.0])
    faces = np.concatenate([small_faces, big_faces + len(small)])
    kept_vertices, kept_faces = largest_component(vertices, faces)
    assert len(kept_faces) == len(big_faces) and len(kept_vertices) == len(big)
    np.testing.assert_allclose(kept_vertices.mean(axis=0), [10.0, 10.0, 10.0], atol=1e-12)
    assert topology(kept_vertices, kept_faces).is_sphere_like


def test_arrays_to_polydata():
    vertices, faces = icosphere(1)
    polydata = arrays_to_polydata(vertices, faces)
    assert polydata.GetNumberOfPoints() == len(vertices)
    assert polydata.GetNumberOfPolys() == len(faces)
    cell = polydata.GetCell(7)
    assert [cell.GetPointId(k) for k in range(3)] == list(faces[7])
    np.testing.assert_allclose(polydata.GetPoint(4), vertices[4])
    lines = arrays_to_polydata(vertices[:3], lines=np.array([[0, 1], [1, 2]]))
    assert lines.GetNumberOfLines() == 2 and lines.GetNumberOfPolys() == 0


def test_decimate_and_remesh_keep_a_sphere():
    points, faces = icosphere(4)
    points = points * 10.0
    vertices, decimated = decimate(points, faces, 600)
    assert 400 < len(vertices) < 800
    assert topology(vertices, decimated).is_sphere_like
    assert np.all(np.abs(np.linalg.norm(vertices, axis=1) - 10.0) < 0.3)
    vertices, remeshed = remesh(*icosphere(2), edge_length=0.1)
    assert topology(vertices, remeshed).is_sphere_like
    edges = np.unique(np.sort(edges_of(remeshed), axis=1), axis=0)
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    assert 0.06 < np.median(lengths) < 0.14
    assert np.all(np.abs(np.linalg.norm(vertices, axis=1) - 1.0) < 0.05)


def test_resample_coarsens_a_fine_surface_to_the_target_and_keeps_its_shape():
    # 40,962 vertices, 20 times the target: remeshed to it
    points, faces = icosphere(6)
    points = points * np.array([30.0, 10.0, 10.0])
    vertices, resampled = resample(points, faces, target_vertices=2000, edge_length=0.01)
    assert topology(vertices, resampled).is_sphere_like
    assert 1600 < len(vertices) < 2400
    assert np.mean(point_surface_distances(vertices, points, faces)) < 0.05
    # a surface already coarser than the target keeps the asked edge length
    coarse, coarse_faces = resample(*icosphere(3), target_vertices=5000, edge_length=0.1)
    edges = np.unique(np.sort(edges_of(coarse_faces), axis=1), axis=0)
    assert 0.07 < np.median(np.linalg.norm(coarse[edges[:, 0]] - coarse[edges[:, 1]], axis=1)) < 0.13


def test_the_surface_resolution_follows_the_sampling_grid_unless_set():
    default = BuildConfig()
    assert default.target_vertices == target_vertices_for(default.points_for(curves=False))
    assert BuildConfig(points=642).target_vertices == MIN_SURFACE_VERTICES
    assert BuildConfig(points=10242).target_vertices > BuildConfig(points=2562).target_vertices
    assert BuildConfig(points=10242, target_vertices=3000).target_vertices == 3000


def test_a_big_mask_gives_a_surface_of_about_the_target_size():
    z, y, x = np.mgrid[:90, :60, :60]
    mask = ((x - 30) / 25.0) ** 2 + ((y - 30) / 25.0) ** 2 + ((z - 45) / 40.0) ** 2 < 1
    fine, fine_faces, _ = mask_to_surface(mask, target_vertices=10 ** 6)   # edges of 1 voxel
    vertices, faces, info = mask_to_surface(mask, target_vertices=1500)
    assert len(fine) > 4 * 1500 and 1200 < info["n_vertices"] < 1800
    assert np.mean(point_surface_distances(vertices, fine, fine_faces)) < 0.1  # voxels
    # coarser still: edges of about 5 voxels, contoured on every second voxel
    assert contour_stride(mask, 1.0, 1500) == 1 and contour_stride(mask, 1.0, 500) == 2
    coarse, coarse_faces, info = mask_to_surface(mask, target_vertices=500)
    assert topology(coarse, coarse_faces).is_sphere_like and 400 < info["n_vertices"] < 600
    assert np.mean(point_surface_distances(coarse, fine, fine_faces)) < 0.2


def test_mesh_to_mask_fills_the_inside_and_round_trips():
    points, faces = icosphere(4)
    centre = np.array([3.3, -2.1, 7.6])
    mask, origin = mesh_to_mask(points * 10.0 + centre, faces, spacing=0.5)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) == {0, 1}
    assert not mask[0].any() and not mask[:, :, -1].any()          # the margin is empty
    assert mask.sum() * 0.5 ** 3 == pytest.approx(4 / 3 * np.pi * 1000, rel=0.03)
    vertices, _, _ = mask_to_surface(mask, spacing=(0.5,) * 3, origin=origin)
    radii = np.linalg.norm(vertices - centre, axis=1)
    assert abs(radii.mean() - 10.0) < 0.3


# --- label map -> surface ------------------------------------------------------------------------------

SPACING = (2.0, 1.0, 1.0)          # x, y, z (SimpleITK order); the array is (z, y, x)
ORIGIN = (-30.0, 5.0, 12.0)
CENTRE_INDEX = np.array([8.3, 14.6, 13.2])   # x, y, z voxel index of the ball centre
RADIUS = 9.0


@pytest.fixture(scope="module")
def ball():
    mask = ball_mask((30, 32, 18), SPACING, ORIGIN, CENTRE_INDEX, RADIUS)
    vertices, faces, info = mask_to_surface(mask, spacing=SPACING, origin=ORIGIN)
    return mask, vertices, faces, info


def test_ball_mask_gives_a_round_sphere_like_surface(ball):
    _, vertices, faces, info = ball
    centre = np.asarray(ORIGIN) + np.asarray(SPACING) * CENTRE_INDEX
    assert topology(vertices, faces).is_sphere_like
    assert info["n_vertices"] == len(vertices) and info["smoothing_sigma"] == 1.0
    radii = np.linalg.norm(vertices - centre, axis=1)
    assert abs(radii.mean() - RADIUS) < 0.5
    assert np.all(np.abs(radii - RADIUS) < 1.0)
    np.testing.assert_allclose(vertices.mean(axis=0), centre, atol=0.25)
    # round in physical space: the 2 mm voxels along x are taken into account
    extent = np.ptp(vertices, axis=0)
    assert np.ptp(extent) < 1.0
    np.testing.assert_allclose(extent, 2 * RADIUS, atol=1.2)


def test_ball_surface_is_outward_with_the_ball_volume(ball):
    mask, vertices, faces, _ = ball
    volume = signed_volume(vertices, faces)
    assert volume > 0
    assert volume == pytest.approx(4 / 3 * np.pi * RADIUS ** 3, rel=0.12)
    assert volume == pytest.approx(mask.sum() * np.prod(SPACING), rel=0.12)


@pytest.mark.parametrize("direction", [
    (0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),     # rotation by 90 degrees about z
    (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0),     # a reflection (left-handed image axes)
])
def test_direction_cosines(ball, direction):
    mask = ball[0]
    vertices, faces, _ = mask_to_surface(mask, spacing=SPACING, origin=ORIGIN, direction=direction)
    matrix = np.reshape(direction, (3, 3))
    centre = np.asarray(ORIGIN) + matrix @ (np.asarray(SPACING) * CENTRE_INDEX)
    np.testing.assert_allclose(vertices.mean(axis=0), centre, atol=0.25)
    radii = np.linalg.norm(vertices - centre, axis=1)
    assert abs(radii.mean() - RADIUS) < 0.5
    assert signed_volume(vertices, faces) > 0                    # still normals out
    assert topology(vertices, faces).is_sphere_like


def test_largest_of_two_balls_is_kept():
    mask = (ball_mask((24, 24, 44), (1.0, 1.0, 1.0), (0, 0, 0), np.array([11.0, 11.5, 11.5]), 8.0)
            | ball_mask((24, 24, 44), (1.0, 1.0, 1.0), (0, 0, 0), np.array([33.0, 11.5, 11.5]),
                        5.0))
    vertices, faces, _ = mask_to_surface(mask)
    assert topology(vertices, faces).is_sphere_like
    np.testing.assert_allclose(vertices.mean(axis=0), [11.0, 11.5, 11.5], atol=0.3)


def test_empty_and_too_thin_masks_raise():
    with pytest.raises(SurfaceError, match="empty"):
        mask_to_surface(np.zeros((10, 10, 10), dtype=bool))
    single = np.zeros((10, 10, 10), dtype=bool)
    single[5, 5, 5] = True
    with pytest.raises(SurfaceError):
        mask_to_surface(single)


def test_ring_mask_is_not_genus_zero():
    z, y, x = np.indices((16, 36, 36), dtype=float)
    major = np.hypot(x - 17.5, y - 17.5)
    ring = (major - 11.0) ** 2 + (z - 7.5) ** 2 <= 4.0 ** 2
    with pytest.raises(SurfaceError, match="genus 1"):
        mask_to_surface(ring)


def test_slicer_method_smooths_the_binary_surface_and_repairs_handles():
    """Slicer's conversion (flying edges on the binary mask + windowed sinc) keeps a box's size,
    and a diagonal voxel contact (a handle) is repaired by blurring, which the info reports."""
    from mdlshapemodel.prepare.surface import mask_to_surface, topology

    box = np.zeros((24, 24, 24), bool)
    box[6:18, 6:18, 6:18] = True
    vertices, faces, info = mask_to_surface(box, method="slicer", smoothing_factor=0.5)
    assert info["surface_method"] == "slicer" and info["smoothing_sigma"] == 0.0
    extent = np.ptp(vertices, axis=0)
    assert np.all(np.abs(extent - 12.0) < 1.0)        # 12 voxels: contour half-way to outside
    # a ring: genus 1 without blurring; closing the hole needs a blur that the ladder reaches
    ring = np.zeros((16, 30, 30), bool)
    yy, xx = np.mgrid[:30, :30]
    radius = np.hypot(yy - 14.5, xx - 14.5)
    ring[5:11] = (radius < 9) & (radius > 2.2)
    with pytest.raises(SurfaceError, match="genus 1"):
        mask_to_surface(ring, method="slicer", max_smoothing_sigma=0.0)
    vertices, faces, info = mask_to_surface(ring, method="slicer", max_smoothing_sigma=3.0)
    assert topology(vertices, faces).is_sphere_like
    assert info["smoothing_sigma"] > 0


def test_inconsistent_orientation_is_made_consistent():
    from mdlshapemodel.prepare.surface import make_orientation_consistent, orient_outwards, topology

    points, faces = icosphere(2)
    rng = np.random.default_rng(3)
    scrambled = faces.copy()
    flipped = rng.choice(len(faces), 37, replace=False)
    scrambled[flipped] = scrambled[flipped][:, [0, 2, 1]]
    assert not topology(points, scrambled).consistently_oriented
    repaired, count = make_orientation_consistent(points, scrambled)
    assert count in (37, len(faces) - 37)
    assert topology(points, repaired).is_sphere_like
    assert np.array_equal(orient_outwards(points, repaired), faces)


def test_mesh_with_scrambled_orientation_is_repaired_in_the_pipeline(tmp_path):
    from mdlshapemodel.config import BuildConfig
    from mdlshapemodel.prepare.io import write_polydata
    from mdlshapemodel.prepare import prepare_case

    points, faces = icosphere(3)
    points = points * np.array([20.0, 12.0, 9.0])
    scrambled = faces.copy()
    scrambled[::7] = scrambled[::7][:, [0, 2, 1]]
    write_polydata(tmp_path / "scrambled.stl", points, scrambled)
    case = prepare_case(str(tmp_path / "scrambled.stl"), BuildConfig(voxel_size=1.0))
    assert not hasattr(case, "reason"), getattr(case, "reason", "")
    assert "made the orientation of" in case.repair
    assert case.map.quality["flipped_triangles"] == 0


def test_fill_holes_is_scipy_s_binary_fill_holes():
    from scipy import ndimage

    from mdlshapemodel.prepare.surface import fill_holes

    rng = np.random.default_rng(11)
    for density in (0.2, 0.5, 0.7):             # many cavities, of all shapes, some at the border
        mask = rng.random((14, 17, 19)) < density
        np.testing.assert_array_equal(fill_holes(mask), ndimage.binary_fill_holes(mask))
    shell = np.zeros((9, 9, 9), dtype=bool)
    shell[1:8, 1:8, 1:8] = True
    shell[3:6, 3:6, 3:6] = False
    np.testing.assert_array_equal(fill_holes(shell)[1:8, 1:8, 1:8], True)
    np.testing.assert_array_equal(fill_holes(np.ones((3, 3, 3), dtype=bool)), True)
    np.testing.assert_array_equal(fill_holes(np.zeros((3, 3, 3), dtype=bool)), False)


@pytest.mark.parametrize("sigma", [0.0, 1.0, 1.5])
def test_the_blur_sampled_on_every_second_voxel_is_the_full_blur_sampled(sigma):
    from scipy import ndimage

    from mdlshapemodel.prepare.surface import blurred

    field = (np.random.default_rng(2).random((21, 18, 25)) < 0.4).astype(np.float32)
    full = ndimage.gaussian_filter(field, sigma) if sigma else field
    for step in (1, 2):
        sampled = blurred(field, sigma, step)
        assert sampled.dtype == np.float32
        np.testing.assert_array_equal(sampled, full[::step, ::step, ::step])   # bit for bit
