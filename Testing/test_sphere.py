"""Tests of bijective sphere maps and the alignment of parameterizations (docs/method.md section 5)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mdlshapemodel.errors import SphereMapError
from mdlshapemodel.correspondence.sampling import SphereLocator, icosphere
import mdlshapemodel.prepare.sphere as sphere_module
from mdlshapemodel.prepare.sphere import (FRAME_TWISTS, SphereMap, align_parameterizations,
                                         check_bijective, distortion, frame_turns, reference_frames,
                                  first_order_map, map_quality, minimise_distortion, orientation,
                                  principal_axes, solid_angles, sphere_map)
from synthetic import torus
from mdlshapemodel.prepare.multilevel import multilevel_map
from mdlshapemodel.prepare.surface import mask_to_surface, remesh, topology
from mdlshapemodel.correspondence.warps import apply_symmetric_theta


def determinants(sphere, faces):
    """det[a, b, c] per face, written out independently of the library."""
    a, b, c = (sphere[faces[:, k]] for k in range(3))
    return (a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
            - a[:, 1] * (b[:, 0] * c[:, 2] - b[:, 2] * c[:, 0])
            + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]))


def triangle_areas(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def mean_abs_log_area_ratio(vertices, faces, sphere):
    surface = triangle_areas(vertices, faces)
    chord = triangle_areas(sphere, faces)
    return float(np.mean(np.abs(np.log((chord / chord.sum()) / (surface / surface.sum())))))


def distortion_energy(vertices, faces, x, area_weight=4.0):
    """The energy minimise_distortion lowers, computed from Jacobians rather than cotangents.

    Surface triangles are scaled to a total area of 4 pi (area A per triangle); J maps a surface
    triangle linearly onto the chord triangle of ``x``; a = det[x0, x1, x2] / 2. The energy is
    sum A |J|_F^2 (1 + (A / a)^2) + area_weight * sum (a + A^2 / a).
    """
    s0, s1, s2 = (vertices[faces[:, k]] for k in range(3))
    area = triangle_areas(vertices, faces)
    scale2 = 4 * np.pi / area.sum()
    A = area * scale2
    es = np.stack([s1 - s0, s2 - s0], axis=2)                 # (m, 3, 2)
    g = np.einsum("mdi,mdj->mij", es, es) * scale2            # metric of the scaled surface
    t0, t1, t2 = (x[faces[:, k]] for k in range(3))
    et = np.stack([t1 - t0, t2 - t0], axis=2)
    h = np.einsum("mdi,mdj->mij", et, et)
    frobenius2 = np.einsum("mii->m", np.linalg.solve(g, h))   # |J|_F^2 = tr(G^-1 H)
    a = 0.5 * determinants(x, faces)
    return float(np.sum(A * frobenius2 * (1 + (A / a) ** 2)) + area_weight * np.sum(a + A * A / a))


def sample(sphere_map_, grid):
    """Surface points at the parameter values ``grid``."""
    locator = SphereLocator(sphere_map_.sphere, sphere_map_.faces)
    return locator.evaluate(sphere_map_.vertices, grid)[0]


def check_map(result, vertices, faces):
    assert np.all(determinants(result.sphere, faces) > 0)
    assert result.quality["flipped_triangles"] == 0
    assert check_bijective(result.sphere, faces) == 0
    np.testing.assert_allclose(np.linalg.norm(result.sphere, axis=1), 1.0, atol=1e-12)
    angles = solid_angles(result.sphere, faces)
    assert np.all(angles > 0)
    assert angles.sum() == pytest.approx(4 * np.pi, rel=1e-9)
    distortion_value = mean_abs_log_area_ratio(vertices, faces, result.sphere)
    assert distortion_value < 0.5
    assert result.quality["mean_abs_log_area_ratio"] == pytest.approx(distortion_value, rel=1e-9)
    np.testing.assert_array_equal(result.vertices, vertices)
    np.testing.assert_array_equal(result.faces, faces)


# --- sphere_map on real surfaces ---------------------------------------------------------------------

def test_sphere_map_of_an_ellipsoid_with_a_bump(bump_surface, bump_map):
    vertices, faces = bump_surface
    assert topology(vertices, faces).is_sphere_like
    check_map(bump_map, vertices, faces)
    assert bump_map.quality["p95_abs_log_area_ratio"] < 1.0


def test_sphere_map_of_a_dumbbell():
    """Two balls joined by a thick cylinder: strongly non-convex."""
    z, y, x = np.indices((24, 24, 50), dtype=float)
    left = (x - 12) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2 <= 8 ** 2
    right = (x - 37) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2 <= 8 ** 2
    bar = ((y - 11.5) ** 2 + (z - 11.5) ** 2 <= 4 ** 2) & (x >= 12) & (x <= 37)
    vertices, faces, _ = mask_to_surface(left | right | bar)
    # the surface is not star-shaped: the central projection of the surface itself folds
    centred = vertices - vertices.mean(axis=0)
    radial = centred / np.linalg.norm(centred, axis=1, keepdims=True)
    assert np.any(determinants(radial, faces) <= 0)
    result = sphere_map(vertices, faces)
    check_map(result, vertices, faces)


# --- Moebius balancing ---------------------------------------------------------------------------------

def test_mobius_is_an_orientation_preserving_bijection_of_the_sphere():
    from mdlshapemodel.prepare.sphere import mobius

    points, faces = icosphere(3)
    centre = np.array([0.3, -0.5, 0.2])
    moved = mobius(points, centre)
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
    assert np.all(determinants(moved, faces) > 0)
    assert check_bijective(moved, faces) == 0
    np.testing.assert_allclose(mobius(moved, -centre), points, atol=1e-12)
    np.testing.assert_allclose(mobius(points, np.zeros(3)), points, atol=1e-15)
    # conformal, not area-preserving: a strong one distorts the areas
    assert np.max(np.abs(distortion(points, faces, moved))) > 1.0


def test_balance_objective_gradient_matches_finite_differences(bump_surface, bump_map):
    from mdlshapemodel.prepare.sphere import balance_objective

    vertices, faces = bump_surface
    area = triangle_areas(vertices, faces)
    target = np.log(area / area.sum())
    for v in (np.zeros(3), np.array([0.4, -0.3, 0.8]), np.array([-2.0, 0.5, 0.1])):
        value, grad = balance_objective(v, bump_map.sphere, faces, target, 0.01)
        chord = triangle_areas(mobius_of(bump_map.sphere, v), faces)
        expected = np.mean(np.sqrt(np.log(chord / chord.sum() / np.exp(target)) ** 2 + 1e-4))
        assert value == pytest.approx(expected, rel=1e-10)
        numeric = [(balance_objective(v + e, bump_map.sphere, faces, target, 0.01)[0]
                    - balance_objective(v - e, bump_map.sphere, faces, target, 0.01)[0]) / 2e-6
                   for e in np.eye(3) * 1e-6]
        np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-8)


def mobius_of(points, v):
    from mdlshapemodel.prepare.sphere import mobius

    return mobius(points, v / np.sqrt(1 + v @ v))


def test_balance_area_undoes_a_moebius_distortion(bump_surface, bump_map):
    from mdlshapemodel.prepare.sphere import balance_area, mobius

    vertices, faces = bump_surface
    good = mean_abs_log_area_ratio(vertices, faces, bump_map.sphere)
    distorted = mobius(bump_map.sphere, np.array([0.5, 0.2, -0.3]))
    assert mean_abs_log_area_ratio(vertices, faces, distorted) > good + 0.5
    balanced = balance_area(vertices, faces, distorted)
    assert np.all(determinants(balanced, faces) > 0)
    assert mean_abs_log_area_ratio(vertices, faces, balanced) < good + 1e-3
    # already balanced: (almost) unchanged
    again = balance_area(vertices, faces, balanced)
    assert (mean_abs_log_area_ratio(vertices, faces, again)
            <= mean_abs_log_area_ratio(vertices, faces, balanced) + 1e-9)


# --- minimise_distortion -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def warped_start(bump_surface, bump_map):
    """A fold-free but badly distorted starting map: the good map warped by strong kernels."""
    rng = np.random.default_rng(3)
    sphere = bump_map.sphere
    for _ in range(4):
        sphere = apply_symmetric_theta(sphere, rng.normal(size=3), 0.8, 0.6)
    assert np.all(determinants(sphere, bump_surface[1]) > 0)
    return sphere


def test_energy_of_the_test_matches_its_definition_on_the_identity():
    """Sanity check of ``distortion_energy``: the unit icosphere mapped to itself has J = I on
    each (rescaled) triangle, so |J|_F^2 = 2 up to the 4 pi rescaling."""
    points, faces = icosphere(2)
    energy = distortion_energy(points, faces, points, area_weight=0.0)
    area = triangle_areas(points, faces)
    scale2 = 4 * np.pi / area.sum()
    a = 0.5 * determinants(points, faces)
    expected = np.sum(area * scale2 * (2 / scale2) * (1 + (area * scale2 / a) ** 2))
    assert energy == pytest.approx(expected, rel=1e-12)


def test_minimise_distortion_never_increases_the_energy_nor_flips(bump_surface, warped_start):
    vertices, faces = bump_surface
    energies = []
    for iterations in (0, 1, 2, 3, 5, 10, 30, 100):
        result = minimise_distortion(vertices, faces, warped_start, max_iterations=iterations)
        assert np.all(determinants(result, faces) > 0)
        np.testing.assert_allclose(np.linalg.norm(result, axis=1), 1.0, atol=1e-12)
        energies.append(distortion_energy(vertices, faces, result))
    assert energies[0] == pytest.approx(distortion_energy(vertices, faces, warped_start))
    assert np.all(np.diff(energies) <= 1e-9 * energies[0])
    assert energies[-1] < 0.8 * energies[0]
    final = minimise_distortion(vertices, faces, warped_start, max_iterations=100)
    assert (mean_abs_log_area_ratio(vertices, faces, final)
            < mean_abs_log_area_ratio(vertices, faces, warped_start))


def test_compiled_energy_matches_its_definition(bump_surface, warped_start, bump_map):
    """The single-pass (compiled) energy equals the Jacobian form of the test, and is infinite
    as soon as one triangle is flipped."""
    from mdlshapemodel.prepare.sphere import DistortionEnergy

    vertices, faces = bump_surface
    for area_weight in (0.0, 4.0):
        energy_of = DistortionEnergy(vertices, faces, area_weight)
        for x in (warped_start, bump_map.sphere):
            energy, grad = energy_of(x)
            assert energy == pytest.approx(distortion_energy(vertices, faces, x, area_weight),
                                           rel=1e-10)
            assert energy_of(x, gradient=False) == (energy, None)
            assert grad.shape == x.shape
    folded = bump_map.sphere.copy()
    i, j = faces[0, 0], faces[0, 1]
    folded[[i, j]] = folded[[j, i]]
    assert energy_of(folded) == (np.inf, None)


def test_energy_gradient_matches_finite_differences(bump_surface, warped_start, rng):
    from mdlshapemodel.prepare.sphere import DistortionEnergy

    vertices, faces = bump_surface
    energy_of = DistortionEnergy(vertices, faces, 4.0)
    _, grad = energy_of(warped_start)
    step = 1e-6
    # single coordinates, including the vertex with the largest gradient
    worst = np.unravel_index(np.argmax(np.abs(grad)), grad.shape)
    for index in [worst] + [(int(rng.integers(len(vertices))), int(rng.integers(3)))
                            for _ in range(5)]:
        e = np.zeros_like(warped_start)
        e[index] = step
        numeric = (energy_of(warped_start + e, gradient=False)[0]
                   - energy_of(warped_start - e, gradient=False)[0]) / (2 * step)
        assert grad[index] == pytest.approx(numeric, rel=1e-5, abs=1e-6 * np.abs(grad).max())
    # a random direction moving every vertex
    direction = rng.normal(size=warped_start.shape) * 1e-3
    numeric = (energy_of(warped_start + direction * 1e-3, gradient=False)[0]
               - energy_of(warped_start - direction * 1e-3, gradient=False)[0]) / 2e-3
    assert np.sum(grad * direction) == pytest.approx(numeric, rel=1e-6)


def test_the_preconditioner_factor_solves_its_matrix(bump_surface):
    from scipy import sparse

    from mdlshapemodel.prepare.sphere import DistortionEnergy, laplacian_factor
    from mdlshapemodel.prepare.sphere_kernels import solve_factor

    vertices, faces = bump_surface
    energy_of = DistortionEnergy(vertices, faces, 4.0)
    factor = laplacian_factor(energy_of.faces, energy_of.cot, energy_of.area, mass_weight=0.3)
    assert len(factor[3]) == len(vertices)
    # the matrix written out: L from the cotangents, a third of each triangle's area per corner
    n = len(vertices)
    matrix = np.zeros((n, n))
    for k in range(3):
        i, j = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        w = 0.5 * energy_of.cot[:, k]
        np.add.at(matrix, (i, j), -w)
        np.add.at(matrix, (j, i), -w)
        np.add.at(matrix, (i, i), w)
        np.add.at(matrix, (j, j), w)
        np.add.at(matrix, (faces[:, k], faces[:, k]), 0.3 * energy_of.area / 3)
    b = np.random.default_rng(5).normal(size=(n, 6))
    x = b.copy()
    solve_factor(*factor, x, np.empty_like(x))
    np.testing.assert_allclose(x, np.linalg.solve(matrix, b), rtol=1e-8, atol=1e-10)
    assert sparse.csr_matrix(matrix).nnz < 8 * n
    with pytest.raises(ValueError):
        solve_factor(*factor, b[:, :3].copy(), np.empty((n, 3)))


def test_preconditioning_reaches_the_same_minimum_in_fewer_iterations(bump_surface, warped_start):
    from mdlshapemodel.prepare.sphere import DistortionEnergy, laplacian_factor
    from mdlshapemodel.prepare.sphere_kernels import lbfgs, no_factor

    vertices, faces = bump_surface
    energy_of = DistortionEnergy(vertices, faces, 4.0)
    results = []
    for factor in (no_factor(), laplacian_factor(energy_of.faces, energy_of.cot,
                                                 energy_of.area)):
        x = np.array(warped_start)
        iterations = lbfgs(x, energy_of.faces, energy_of.cot, energy_of.area, 4.0, 10000,
                           1e-9, 5, factor, 20)
        assert np.all(determinants(x, faces) > 0)
        results.append((iterations, energy_of(x, gradient=False)[0]))
    (plain, plain_energy), (preconditioned, preconditioned_energy) = results
    assert preconditioned_energy == pytest.approx(plain_energy, rel=1e-6)
    assert preconditioned < plain / 2


def test_minimise_distortion_rejects_a_folded_start(bump_surface, bump_map):
    vertices, faces = bump_surface
    folded = bump_map.sphere.copy()
    i, j = faces[0, 0], faces[0, 1]
    folded[[i, j]] = folded[[j, i]]
    with pytest.raises(SphereMapError):
        minimise_distortion(vertices, faces, folded, max_iterations=5)


# --- checks ---------------------------------------------------------------------------------------------

def test_check_bijective_detects_flips(bump_map):
    faces = bump_map.faces
    assert check_bijective(bump_map.sphere, faces) == 0
    swapped = bump_map.sphere.copy()
    i, j = faces[10, 0], faces[10, 1]                 # two neighbouring vertices
    swapped[[i, j]] = swapped[[j, i]]
    expected = int(np.sum(determinants(swapped, faces) <= 0))
    assert expected > 0
    assert check_bijective(swapped, faces) == expected
    mirrored = bump_map.sphere * [1.0, 1.0, -1.0]
    assert check_bijective(mirrored, faces) == len(faces)
    quality = map_quality(bump_map.vertices, faces, swapped)
    assert quality["flipped_triangles"] == expected


def test_check_bijective_detects_a_double_cover():
    """Every triangle positive but the sphere covered twice: not a bijection."""
    points, faces = icosphere(1)
    with pytest.raises(SphereMapError, match="covers the sphere"):
        check_bijective(points, np.concatenate([faces, faces]))


def test_solid_angles():
    octant = np.eye(3)
    np.testing.assert_allclose(solid_angles(octant, np.array([[0, 1, 2]])), [np.pi / 2])
    np.testing.assert_allclose(solid_angles(octant, np.array([[0, 2, 1]])), [-np.pi / 2])
    points, faces = icosphere(2)
    assert solid_angles(points, faces).sum() == pytest.approx(4 * np.pi, rel=1e-12)
    np.testing.assert_array_equal(orientation(points, faces) > 0, True)


def test_distortion_is_zero_for_a_similar_map():
    points, faces = icosphere(2)
    np.testing.assert_allclose(distortion(points, faces, points), 0.0, atol=1e-12)
    np.testing.assert_allclose(distortion(points * 7.0 + 3.0, faces, points), 0.0, atol=1e-12)
    stretched = points * [3.0, 1.0, 1.0]
    values = distortion(stretched, faces, points)
    surface = triangle_areas(stretched, faces)
    chord = triangle_areas(points, faces)
    np.testing.assert_allclose(values, np.log(chord / chord.sum() / (surface / surface.sum())),
                               atol=1e-12)


# --- first-order maps and principal axes ---------------------------------------------------------------

def test_first_order_map_recovers_an_affine_image_of_the_sphere(rng):
    points, faces = icosphere(2)
    matrix = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    centre = rng.normal(size=3) * 10
    vertices = centre + points @ matrix.T
    fitted_centre, fitted_matrix = first_order_map(vertices, faces, points)
    np.testing.assert_allclose(fitted_centre, centre, atol=1e-10)
    np.testing.assert_allclose(fitted_matrix, matrix, atol=1e-10)


def test_principal_axes_of_a_rotated_ellipsoid(rng):
    points, faces = icosphere(3)
    rotation = Rotation.random(random_state=rng).as_matrix()
    shift = rng.normal(size=3) * 5
    vertices = (points * [5.0, 3.0, 1.5]) @ rotation.T + shift
    centre, axes = principal_axes(vertices, faces)
    np.testing.assert_allclose(centre, shift, atol=1e-10)        # the icosphere is symmetric
    assert np.linalg.det(axes) == pytest.approx(1.0)
    np.testing.assert_allclose(np.abs(axes.T @ rotation), np.eye(3), atol=1e-8)


def rod_with_a_knob(cross_section, rotation):
    """A long rod (principal axis x) of elliptic ``cross_section`` (y, z radii) with a knob near
    one end on the +y side, rotated by ``rotation``; (vertices, faces)."""
    sphere, faces = icosphere(4)
    vertices = sphere * [20.0, *cross_section]
    knob = np.exp(-np.sum((sphere - [0.6, 0.8, 0.0]) ** 2, axis=1) / 0.03)
    vertices = vertices + 4.0 * knob[:, None] * sphere
    return vertices @ rotation.T, faces


def test_reference_frames_find_the_twist_that_near_equal_axes_leave_open():
    # the cross-sections' longer axis is y in the reference and z in the case: their principal
    # axes differ by a quarter turn about the rod, their knobs do not
    twist = Rotation.from_rotvec([np.radians(35.0), 0.0, 0.0]).as_matrix()
    reference = rod_with_a_knob((4.0, 3.6), np.eye(3))
    case = rod_with_a_knob((3.6, 4.0), twist)
    frame = reference_frames([reference, case])[1]
    error = Rotation.from_matrix(frame @ twist).magnitude()      # the frame undoes the twist
    assert np.degrees(error) < 5.0



def round_rod_with_two_knobs(seed: int) -> tuple:
    """A rod (principal axis x) of round cross-section with knobs on its +y and -x,+z sides,
    its vertices moved by noise of 0.1 mm: the spread across the rod is nearly the same in
    every direction, so the noise, not the shape, sets its second and third principal axes."""
    sphere, faces = icosphere(4)
    vertices = sphere * [20.0, 4.0, 4.0]
    for centre in ([0.6, 0.8, 0.0], [-0.3, 0.0, 0.95]):
        knob = np.exp(-np.sum((sphere - centre) ** 2, axis=1) / 0.03)
        vertices = vertices + 3.0 * knob[:, None] * sphere
    return vertices + np.random.default_rng(seed).normal(scale=0.1, size=vertices.shape), faces


@pytest.mark.parametrize("seed", [0, 1])
def test_reference_frames_refine_the_nearest_candidate_by_closest_points(seed):
    # the candidates are 30 degrees apart about the rod from axes that the noise set: the
    # frame that undoes the turn lies between them, where the closest-point refinement ends
    turn = Rotation.from_rotvec([0.3, -0.5, 1.1 + seed]).as_matrix()
    reference = round_rod_with_two_knobs(100 + seed)
    vertices, faces = round_rod_with_two_knobs(seed)
    frame = reference_frames([reference, (vertices @ turn.T, faces)])[1]
    assert np.degrees(Rotation.from_matrix(frame @ turn).magnitude()) < 1.0


def test_frame_turns_are_every_proper_sign_choice_turned_each_rotation_once():
    turns = np.array(frame_turns())
    assert len(turns) == 2 * FRAME_TWISTS
    np.testing.assert_allclose(turns @ turns.transpose(0, 2, 1), np.broadcast_to(np.eye(3), turns.shape),
                               atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(turns), 1.0)
    # pairwise: no two the same rotation; the nearest pairs one twist step apart
    angles = [np.degrees(Rotation.from_matrix(a.T @ b).magnitude())
              for i, a in enumerate(turns) for b in turns[i + 1:]]
    assert min(angles) == pytest.approx(360.0 / FRAME_TWISTS)
    # each of the four proper sign choices of the axes is among them
    for signs in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1)):
        assert min(np.abs(turns - np.diag(signs)).max(axis=(1, 2))) < 1e-12


def bumpy_ellipsoids(seed: int) -> tuple:
    """A reference and a case (vertices, faces) that share an ellipsoid (10, 5, 4.5 mm) with four
    random bumps and differ by three random bumps each, the case turned by a random rotation
    (returned third)."""
    sphere, faces = icosphere(4)
    rng = np.random.default_rng(seed)

    def bumps(count, size):
        shift = np.zeros_like(sphere)
        for _ in range(count):
            centre = rng.normal(size=3)
            knob = np.exp(-np.sum((sphere - centre / np.linalg.norm(centre)) ** 2, axis=1) / 0.05)
            shift += rng.uniform(-size, size) * knob[:, None] * sphere
        return shift

    base = sphere * [10.0, 5.0, 4.5] + bumps(4, 3.0)
    reference, case = base + bumps(3, 2.5), base + bumps(3, 2.5)
    turn = Rotation.random(random_state=rng).as_matrix()
    return (reference, faces), (case @ turn.T, faces), turn


def test_reference_frames_refine_the_second_nearest_candidate_too(monkeypatch):
    # a case whose nearest candidate on the coarse points lies in the basin of a wrong frame: the
    # closest-point refinement of that one alone ends more than 10 degrees off, the second one's undoes
    # the turn up to what the cases' own bumps leave
    reference, case, turn = bumpy_ellipsoids(163)

    def error(frame):
        return np.degrees(Rotation.from_matrix(frame @ turn).magnitude())

    assert sphere_module.FRAME_REFINED >= 2
    assert error(reference_frames([reference, case])[1]) < 4.0
    monkeypatch.setattr(sphere_module, "FRAME_REFINED", 1)
    assert error(reference_frames([reference, case])[1]) > 10.0


# --- alignment of parameterizations -----------------------------------------------------------------

def test_align_parameterizations_undoes_a_parameter_rotation(bump_map, rng):
    parameter_rotation = Rotation.random(random_state=rng).as_matrix()
    rigid = Rotation.random(random_state=rng).as_matrix()
    shift = rng.normal(size=3) * 20
    moved = SphereMap(bump_map.vertices @ rigid.T + shift, bump_map.faces,
                      bump_map.sphere @ parameter_rotation, dict(bump_map.quality))
    before = moved.sphere.copy()
    aligned = align_parameterizations([bump_map, moved])
    np.testing.assert_array_equal(moved.sphere, before)          # inputs untouched
    assert aligned[0].quality["parameter_rotation_degrees"] == pytest.approx(0.0, abs=1e-5)
    np.testing.assert_allclose(aligned[0].sphere, bump_map.sphere, atol=1e-10)
    angle = np.degrees(Rotation.from_matrix(parameter_rotation).magnitude())
    assert aligned[1].quality["parameter_rotation_degrees"] == pytest.approx(angle, abs=1e-5)
    np.testing.assert_allclose(aligned[1].sphere, bump_map.sphere, atol=1e-8)
    # the same parameter values now give corresponding points (after undoing the rigid motion)
    grid, _ = icosphere(3)
    reference_points = sample(aligned[0], grid)
    moved_points = (sample(aligned[1], grid) - shift) @ rigid
    np.testing.assert_allclose(moved_points, reference_points, atol=1e-6)
    unaligned = (sample(moved, grid) - shift) @ rigid
    assert np.mean(np.linalg.norm(unaligned - reference_points, axis=1)) > 1.0


def test_align_parameterizations_of_two_subjects(bump_map):
    """A second subject (bump moved, 5% larger), mapped independently and with its parameter
    sphere turned at random: after alignment the same parameters give nearby points, whatever
    the turn was."""
    from mdlshapemodel.demo import bump_ellipsoid_mask

    mask = bump_ellipsoid_mask(shape=(22, 26, 36), semi_axes=(12.0, 7.0, 5.5), bump_radius=4.0,
                               bump_position=0.45, scale=1.05)
    other = sphere_map(*mask_to_surface(mask)[:2])
    grid, _ = icosphere(3)
    reference_points = sample(bump_map, grid)
    results = []
    for seed in range(3):
        turn = Rotation.random(random_state=np.random.default_rng(seed)).as_matrix()
        turned = SphereMap(other.vertices, other.faces, other.sphere @ turn, dict(other.quality))
        aligned = align_parameterizations([bump_map, turned])
        points = sample(aligned[1], grid)
        results.append(points)
        assert np.mean(np.linalg.norm(points - reference_points, axis=1)) < 1.5
    for points in results[1:]:
        np.testing.assert_allclose(points, results[0], atol=1e-6)


# --- the initial map that is fold-free by construction ---------------------------------------------

def long_ellipsoid():
    """A 20:1 ellipsoid of well-shaped triangles (about 1,500 vertices), on which the conformal
    map breaks down (it crowds the ends' points until their triangles degenerate)."""
    points, faces = icosphere(4)
    return remesh(points * [20.0, 1.0, 1.0], faces, edge_length=0.4)


def test_the_multilevel_map_is_fold_free_where_the_conformal_map_is_not():
    from mdlshapemodel.prepare.conformal import spherical_conformal_map

    vertices, faces = long_ellipsoid()
    conformal = spherical_conformal_map(vertices, faces)
    assert conformal is None or check_bijective(
        conformal / np.linalg.norm(conformal, axis=1, keepdims=True), faces) > 0
    sphere = multilevel_map(vertices, faces)
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.0)
    assert check_bijective(sphere, faces) == 0      # raises unless it covers the sphere once
    mapped = sphere_map(vertices, faces)
    assert mapped.quality["flipped_triangles"] == 0
    assert mapped.quality["mean_abs_log_area_ratio"] < 0.5


def test_the_multilevel_map_does_not_depend_on_the_vertex_numbering():
    # the simplification removes every vertex but four and re-inserts them all: with the
    # vertices numbered in another order the map still covers the sphere once, fold-free, and
    # the mesh given is left as it was
    vertices, faces = long_ellipsoid()
    faces = np.array(faces, dtype=np.int64)
    order = np.random.default_rng(11).permutation(len(vertices))
    renumbered = np.empty_like(order)
    renumbered[order] = np.arange(len(order))
    given_vertices, given_faces = vertices[order], renumbered[faces]
    kept = given_vertices.copy(), given_faces.copy()
    sphere = multilevel_map(given_vertices, given_faces)
    np.testing.assert_array_equal(given_vertices, kept[0])
    np.testing.assert_array_equal(given_faces, kept[1])
    np.testing.assert_allclose(np.linalg.norm(sphere, axis=1), 1.0)
    assert np.all(determinants(sphere, given_faces) > 0)
    assert check_bijective(sphere, given_faces) == 0


def test_the_multilevel_map_needs_only_the_topology():
    # garbage geometry (random points, some of them coincident) on the triangles of a sphere
    points, faces = icosphere(3)
    vertices = np.random.default_rng(3).normal(size=points.shape)
    vertices[:20] = vertices[0]
    sphere = multilevel_map(vertices, faces)
    assert check_bijective(sphere, faces) == 0


def test_the_multilevel_map_refuses_a_torus():
    with pytest.raises(SphereMapError, match="tetrahedron"):
        multilevel_map(*torus())


def test_bfgs_finds_the_minimum_of_small_smooth_functions():
    from mdlshapemodel.prepare.sphere import bfgs

    matrix = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    centre = np.array([1.0, -2.0, 0.5])

    def quadratic(x):
        return 0.5 * (x - centre) @ matrix @ (x - centre), matrix @ (x - centre)

    np.testing.assert_allclose(bfgs(quadratic, np.zeros(3)), centre, atol=1e-6)

    def rosenbrock(x):
        value = sum(100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2)
        gradient = np.zeros_like(x)
        gradient[:-1] = -400 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2 * (1 - x[:-1])
        gradient[1:] += 200 * (x[1:] - x[:-1] ** 2)
        return value, gradient

    np.testing.assert_allclose(bfgs(rosenbrock, np.array([-1.2, 1.0, 0.8]), gtol=1e-9),
                               np.ones(3), atol=1e-5)
    # at the minimum already: unchanged
    np.testing.assert_array_equal(bfgs(quadratic, centre), centre)


def test_the_sphere_map_of_a_raw_contour_full_of_slivers_is_bijective():
    # the contour of a blurred mask before remeshing: slivers and nearly degenerate triangles,
    # whose cotangents reach hundreds (a hostile input for the energy and its preconditioner)
    from mdlshapemodel.prepare.surface import orient_outwards
    from test_remesh import raw_contour

    z, y, x = np.indices((26, 30, 44), dtype=float)
    mask = (((x - 21.5) / 17) ** 2 + ((y - 14.5) / 9) ** 2 + ((z - 12.5) / 7) ** 2 <= 1) | (
        ((x - 30) ** 2 + (y - 20) ** 2 + (z - 12.5) ** 2) <= 25)
    vertices, faces = raw_contour(mask)
    faces = orient_outwards(vertices, faces)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    assert area.min() < 1e-3 * np.median(area)                          # slivers there are
    result = sphere_map(vertices, faces)
    check_map(result, vertices, faces)
