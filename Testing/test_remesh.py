"""The compiled isotropic remesher (prepare/remesh.py): closed genus-0 surfaces of edges near the
target, on the input surface, the same output for the same input; non-manifold input refused."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.prepare.remesh import HIGH, LOW, remesh_isotropic
from mdlshapemodel.prepare.surface import (edges_of, mask_to_surface, point_surface_distances,
                                           topology)

from common import HIPPOCAMPI


def edge_lengths(vertices, faces):
    edges = np.unique(np.sort(edges_of(faces), axis=1), axis=0)
    return np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)


def minimum_angles(vertices, faces):
    a, b, c = (vertices[faces[:, k]] for k in range(3))

    def angle(p, q, r):
        u, w = q - p, r - p
        cosine = np.sum(u * w, axis=1) / np.linalg.norm(u, axis=1) / np.linalg.norm(w, axis=1)
        return np.degrees(np.arccos(np.clip(cosine, -1, 1)))

    return np.minimum(np.minimum(angle(a, b, c), angle(b, c, a)), angle(c, a, b))


def check_remeshed(result, source, target):
    vertices, faces = result
    assert topology(vertices, faces).is_sphere_like
    lengths = edge_lengths(vertices, faces)
    assert 0.85 * target < np.median(lengths) < 1.15 * target
    assert np.percentile(lengths, 2) > 0.5 * LOW * target
    assert np.percentile(lengths, 98) < 1.2 * HIGH * target
    # every vertex is on the input surface
    assert np.max(point_surface_distances(vertices, *source)) < 1e-9 * (1 + np.abs(source[0]).max())
    return vertices, faces


def test_coarsening_and_refining_a_sphere():
    points, faces = icosphere(4)                         # edges of about 0.08
    coarse = check_remeshed(remesh_isotropic(points, faces, 0.3), (points, faces), 0.3)
    assert len(coarse[0]) < len(points) / 5
    # refining an ellipsoid from coarse triangles: the arrays grow several times on the way
    points, faces = icosphere(1)
    points = points * [3.0, 1.0, 1.0]
    fine = check_remeshed(remesh_isotropic(points, faces, 0.1, iterations=8), (points, faces), 0.1)
    assert len(fine[0]) > 50 * len(points)


def test_remeshing_keeps_the_triangles_regular_and_the_valences_near_six():
    points, faces = icosphere(5)
    points = points * [20.0, 8.0, 6.0]
    vertices, triangles = check_remeshed(remesh_isotropic(points, faces, 1.0), (points, faces),
                                         1.0)
    angles = minimum_angles(vertices, triangles)
    assert np.percentile(angles, 1) > 35 and np.median(angles) > 50
    valence = np.bincount(triangles.ravel())
    assert np.mean(valence == 6) > 0.7 and valence.min() >= 3


def raw_contour(mask):
    """The surface mask_to_surface makes of ``mask`` before it is remeshed: the contour of the
    blurred mask, with slivers where the isosurface passes near voxels."""
    from mdlshapemodel.prepare import surface

    captured = []
    original = surface.resample
    surface.resample = lambda v, f, t, e: captured.append((v, f)) or (v, f)
    try:
        mask_to_surface(mask)
    finally:
        surface.resample = original
    return captured[0]


def test_a_contour_of_slivers_becomes_well_shaped():
    z, y, x = np.mgrid[:30, :36, :44]
    mask = (((x - 22) / 17.0) ** 2 + ((y - 18) / 11.0) ** 2 + ((z - 15) / 8.0) ** 2) < 1
    contour = raw_contour(mask)
    assert np.percentile(minimum_angles(*contour), 5) < 10
    vertices, triangles = check_remeshed(remesh_isotropic(*contour, 1.0), contour, 1.0)
    assert minimum_angles(vertices, triangles).min() > 20


def test_the_same_input_gives_the_same_mesh():
    points, faces = icosphere(4)
    points = points * [10.0, 5.0, 4.0] + np.sin(7 * points) * 0.2
    first = remesh_isotropic(points, faces, 0.5)
    second = remesh_isotropic(points.copy(), faces.copy(), 0.5)
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)


def test_a_mesh_that_is_not_a_closed_manifold_is_refused():
    points, faces = icosphere(2)
    assert remesh_isotropic(points, faces[1:], 0.3) is None                  # a hole
    turned = np.vstack([faces[:1, [0, 2, 1]], faces[1:]])
    assert remesh_isotropic(points, turned, 0.3) is None                     # one face turned
    extra = np.vstack([points, [[5.0, 5.0, 5.0]]])
    assert remesh_isotropic(extra, faces, 0.3) is None                       # an unused vertex
    doubled = np.vstack([faces, faces + len(points)])
    assert remesh_isotropic(np.vstack([points, points + 3.0]), doubled, 0.3) is not None


def test_a_remeshed_sphere_is_a_closed_consistently_oriented_genus_0_mesh():
    """Every edge of the result is run once in each direction by its two triangles, every
    vertex is used, the Euler characteristic is 2 and the triangles face outward."""
    points, faces = icosphere(2)
    vertices, triangles = remesh_isotropic(points, faces, 0.25)
    directed = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    pairs = {tuple(edge) for edge in directed.tolist()}
    assert len(pairs) == len(directed)                                 # each direction once
    assert all((b, a) in pairs for a, b in pairs)                      # and its reverse
    assert np.array_equal(np.unique(triangles), np.arange(len(vertices)))
    assert len(vertices) - len(directed) // 2 + len(triangles) == 2
    corners = vertices[triangles]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.all(np.einsum("fd,fd->f", normal, corners.mean(axis=1)) > 0)


@pytest.mark.skipif(not HIPPOCAMPI.is_dir(), reason="the shared hippocampus data is not here")
def test_hippocampus_surfaces_remesh_to_the_target_resolution():
    from mdlshapemodel.prepare.io import read_label_map
    from mdlshapemodel.prepare.surface import mask_components

    label_map = read_label_map(str(HIPPOCAMPI / "hippocampus_003.nii.gz"), [1, 2])
    mask, _ = mask_components(label_map.mask)
    vertices, faces, info = mask_to_surface(mask, target_vertices=5124)
    assert 1500 < info["n_vertices"] < 2500
    lengths = edge_lengths(vertices, faces)
    assert 0.9 < np.median(lengths) < 1.1                             # voxels: the edge length
    assert np.percentile(minimum_angles(vertices, faces), 1) > 35
