"""Tests of the symmetric theta transformation (paper eq. 8-12, docs/method.md section 3)."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.fields import FieldBasis
from mdlshapemodel.correspondence.sampling import icosphere
from mdlshapemodel.correspondence.warps import (apply_symmetric_theta, minimum_amplitude, random_unit_vector,
                                 random_width, symmetric_theta, symmetric_theta_derivative)

AMPLITUDES = [0.0, 0.1, 0.5, 1.0, 3.0, 10.0]
WIDTHS = [1e-3, 0.01, 0.05, 0.25, 1.0, 3.0]
THETA = np.linspace(0.0, np.pi, 20001)


def orientation(points, faces):
    a, b, c = (points[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c))


def random_unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("omega", WIDTHS)
@pytest.mark.parametrize("amplitude", AMPLITUDES)
def test_end_points_fixed_and_strictly_increasing(amplitude, omega):
    f = symmetric_theta(THETA, amplitude, omega)
    assert f[0] == pytest.approx(0.0, abs=1e-12)
    assert f[-1] == pytest.approx(np.pi, abs=1e-12)
    assert np.all(np.diff(f) > 0)
    assert np.all(symmetric_theta_derivative(THETA, amplitude, omega) > 0)
    assert np.all((f >= -1e-12) & (f <= np.pi + 1e-12))


@pytest.mark.parametrize("omega", WIDTHS)
@pytest.mark.parametrize("amplitude", [0.3, 2.0, minimum_amplitude(0.7) * 0.9])
def test_derivative_matches_finite_differences(amplitude, omega):
    theta = np.linspace(0.02, np.pi - 0.02, 400)
    h = 1e-6
    numeric = (symmetric_theta(theta + h, amplitude, omega)
               - symmetric_theta(theta - h, amplitude, omega)) / (2 * h)
    np.testing.assert_allclose(symmetric_theta_derivative(theta, amplitude, omega), numeric,
                               rtol=1e-4, atol=1e-6)


def test_derivative_integrates_to_pi():
    """f' = pi * rho with rho a probability density on [0, pi] (eq. 9)."""
    for amplitude, omega in [(0.5, 0.1), (4.0, 0.5), (1.0, 2.0)]:
        theta = np.linspace(0, np.pi, 200001)
        total = np.trapezoid(symmetric_theta_derivative(theta, amplitude, omega), theta)
        assert total == pytest.approx(np.pi, rel=1e-6)


def test_zero_amplitude_is_the_identity(rng):
    for omega in WIDTHS:
        np.testing.assert_allclose(symmetric_theta(THETA, 0.0, omega), THETA, atol=1e-15)
    points = random_unit_vectors(rng, 100)
    moved = apply_symmetric_theta(points, rng.normal(size=3), 0.0, 0.3)
    np.testing.assert_array_equal(moved, points)


@pytest.mark.parametrize("omega", [0.01, 0.2, 1.0, 3.0])
def test_minimum_amplitude_is_the_monotonicity_limit(omega):
    """Just above the limit f still increases everywhere; just below it decreases near theta = 0."""
    limit = minimum_amplitude(omega)
    a = np.exp(-omega)
    assert limit == pytest.approx(-(1 - a) / (1 + a), rel=1e-14)
    # at the limit, f'(0) = 0: the Cauchy term peaks at theta = 0
    assert symmetric_theta_derivative(0.0, limit, omega) == pytest.approx(0.0, abs=1e-12)
    # a fine grid near theta = 0, where f' is smallest (spacing well above rounding noise of arccos)
    theta = np.concatenate([np.linspace(0, 0.2 * omega, 201)[:-1], THETA[THETA >= 0.2 * omega]])
    above = limit * (1 - 1e-2)
    below = limit * (1 + 1e-2)
    f_above = symmetric_theta(theta, above, omega)
    assert np.all(np.diff(f_above) > 0)
    assert np.all(symmetric_theta_derivative(theta, above, omega) > 0)
    f_below = symmetric_theta(theta, below, omega)
    assert np.any(np.diff(f_below) < 0)
    assert symmetric_theta_derivative(0.0, below, omega) < 0


def test_apply_keeps_points_on_their_great_circle_through_the_centre(rng):
    points = random_unit_vectors(rng, 500)
    for _ in range(5):
        centre = rng.normal(size=3) * rng.uniform(0.1, 10)       # need not be a unit vector
        unit_centre = centre / np.linalg.norm(centre)
        amplitude, omega = rng.uniform(0, 3), rng.uniform(0.01, 2)
        moved = apply_symmetric_theta(points, centre, amplitude, omega)
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
        # point, centre and moved point are coplanar with the origin
        coplanar = np.einsum("ij,ij->i", points, np.cross(moved, np.broadcast_to(unit_centre,
                                                                                    points.shape)))
        np.testing.assert_allclose(coplanar, 0.0, atol=1e-12)
        # ... on the same side of the centre (psi unchanged), at the new angle f(theta)
        tangent_before = points - np.outer(points @ unit_centre, unit_centre)
        tangent_after = moved - np.outer(moved @ unit_centre, unit_centre)
        assert np.all(np.einsum("ij,ij->i", tangent_before, tangent_after) > 0)
        theta = np.arccos(np.clip(points @ unit_centre, -1, 1))
        new_theta = np.arccos(np.clip(moved @ unit_centre, -1, 1))
        np.testing.assert_allclose(new_theta, symmetric_theta(theta, amplitude, omega), atol=1e-7)
        assert points.shape == moved.shape


def test_apply_fixes_the_centre_and_its_antipode(rng):
    centre = random_unit_vector(rng)
    points = np.stack([centre, -centre, random_unit_vector(rng)])
    moved = apply_symmetric_theta(points, centre, 2.0, 0.1)
    np.testing.assert_allclose(moved[0], centre, atol=1e-15)
    np.testing.assert_allclose(moved[1], -centre, atol=1e-15)
    assert not np.allclose(moved[2], points[2])
    # the input is not modified
    np.testing.assert_array_equal(points[0], centre)


def test_kernel_moves_points_away_from_its_centre(rng):
    """A > 0 expands the neighbourhood of P: every point's angle from P grows (f(theta) >= theta)."""
    theta = np.linspace(0, np.pi, 1001)
    for amplitude, omega in [(0.5, 0.2), (2.0, 1.0), (1.0, 0.01)]:
        assert np.all(symmetric_theta(theta, amplitude, omega) >= theta - 1e-12)


@pytest.mark.parametrize("seed", range(10))
def test_composed_kernels_flip_no_icosphere_triangle(seed):
    """eq. 12: a composition of random kernels keeps every triangle of an icosphere positive.

    Kernels are kept wider than a few triangles (omega >= 0.3 on a level-3 icosphere): the discrete
    test can only see the homeomorphism when triangles are small compared with the kernels.
    """
    rng = np.random.default_rng(seed)
    points, faces = icosphere(3)
    assert np.all(orientation(points, faces) > 0)
    moved = points
    for _ in range(8):
        moved = apply_symmetric_theta(moved, rng.normal(size=3), rng.uniform(0.0, 1.0),
                                      rng.uniform(0.3, 2.0))
    assert np.all(orientation(moved, faces) > 0)
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
    # distinct points stay distinct
    assert len(np.unique(np.round(moved, 9), axis=0)) == len(points)


def test_composed_kernels_preserve_orientation_locally_at_all_widths(rng):
    """The continuous map has a positive Jacobian everywhere, even for narrow, strong kernels.

    Tiny triangles (1e-6 rad) around random points keep their orientation under a composition of
    kernels with widths down to 0.01 and amplitudes up to 5.
    """
    base = random_unit_vectors(rng, 3000)
    helper = random_unit_vectors(rng, 3000)
    t1 = np.cross(base, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(base, t1)
    eps = 1e-6
    corners = [base, base + eps * t1, base + eps * t2]
    corners = [c / np.linalg.norm(c, axis=1, keepdims=True) for c in corners]
    assert np.all(np.einsum("ij,ij->i", corners[0], np.cross(corners[1], corners[2])) > 0)
    for _ in range(6):
        centre, amplitude = rng.normal(size=3), rng.uniform(0, 5)
        omega = float(np.exp(rng.uniform(np.log(0.01), np.log(3.0))))
        corners = [apply_symmetric_theta(c, centre, amplitude, omega) for c in corners]
    det = np.einsum("ij,ij->i", corners[0], np.cross(corners[1], corners[2]))
    assert np.all(det > 0)


def test_random_helpers(rng):
    vectors = np.array([random_unit_vector(rng) for _ in range(2000)])
    np.testing.assert_allclose(np.linalg.norm(vectors, axis=1), 1.0)
    assert np.all(np.abs(vectors.mean(axis=0)) < 0.1)          # roughly uniform
    widths = np.array([random_width(rng, 1 / 32) for _ in range(4000)])
    assert np.all(widths >= 1e-4)
    # half-normal: mean sigma sqrt(2/pi)
    assert widths.mean() == pytest.approx(np.sqrt(2 / np.pi) / 32, rel=0.05)


# ------------------------------------------------------------------------------------------------
# Appendix transformations (asymmetric theta, shear/twist), global rotation and the common interface

from mdlshapemodel.correspondence.circle import CIRCLE_WARP_KINDS  # noqa: E402
from mdlshapemodel.geometry import rotation_from_vector  # noqa: E402
from mdlshapemodel.correspondence.sampling import sphere_grid  # noqa: E402
from mdlshapemodel.prepare.sphere import orientation as sphere_orientation, solid_angles  # noqa: E402
from mdlshapemodel.correspondence.warps import (WARP_KINDS, AsymmetricTheta, Rotation, ShearTwist,  # noqa: E402
                                 SymmetricTheta, apply_asymmetric_theta,
                                 apply_psi_modulated_theta, apply_rotation, apply_shear_twist,
                                 apply_warp, apply_warps, asymmetric_amplitude, asymmetric_theta,
                                 invert_warps, make_warp, maximum_asymmetric_amplitude,
                                 minimum_asymmetric_amplitude, perpendicular, polar_coordinates,
                                 polar_frame, random_asymmetric_theta, random_rotation,
                                 random_shear_twist, random_symmetric_theta, shear_twist_angle,
                                 theta_map, theta_map_inverse, with_amplitude,
                                 wrapped_cauchy_cdf)

GRID_POINTS, GRID_TRIANGLES = sphere_grid(2562)


def wrap_angle(angle):
    return (angle + np.pi) % (2 * np.pi) - np.pi


def peak_amplitude(peak, b):
    """A0 whose A(psi') of eq. 29 peaks at ``peak``."""
    return peak * np.sinh(b) / 2


def assert_fold_free_and_onto(moved, triangles=GRID_TRIANGLES):
    """No flipped triangle, distinct points, and the spherical triangles cover the sphere once."""
    assert np.all(sphere_orientation(moved, triangles) > 0)
    assert len(np.unique(np.round(moved, 9), axis=0)) == len(moved)
    assert np.sum(solid_angles(moved, triangles)) == pytest.approx(4 * np.pi, rel=1e-9)


def tiny_triangles(rng, n, eps):
    """Corners (3 arrays (n, 3)) of positive triangles of size ``eps`` at random points."""
    base = random_unit_vectors(rng, n)
    t1 = np.cross(base, random_unit_vectors(rng, n))
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(base, t1)
    corners = [base, base + eps * t1, base + eps * t2]
    return [c / np.linalg.norm(c, axis=1, keepdims=True) for c in corners]


def small_orientation(a, b, c):
    """det[a, b, c] evaluated from differences, accurate for tiny triangles."""
    return np.einsum("ij,ij->i", a, np.cross(b - a, c - a))


# --- polar coordinates ----------------------------------------------------------------------------

def test_polar_frame_and_coordinates(rng):
    centre = rng.normal(size=3) * 3
    reference = rng.normal(size=3)
    p, e1, e2 = polar_frame(centre, reference)
    np.testing.assert_allclose(np.stack([p, e1, e2]) @ np.stack([p, e1, e2]).T, np.eye(3),
                               atol=1e-15)
    np.testing.assert_allclose(np.cross(e1, e2), p, atol=1e-15)      # right-handed about P
    assert (reference @ e1) > 0 and abs(reference @ e2) < 1e-12
    theta = rng.uniform(0, np.pi, 300)
    psi = rng.uniform(-np.pi, np.pi, 300)
    points = (np.cos(theta)[:, None] * p + np.sin(theta)[:, None]
              * (np.cos(psi)[:, None] * e1 + np.sin(psi)[:, None] * e2))
    theta_back, psi_back = polar_coordinates(points, centre, reference)
    np.testing.assert_allclose(theta_back, theta, atol=1e-12)
    np.testing.assert_allclose(wrap_angle(psi_back - psi), 0.0, atol=1e-10)
    with pytest.raises(ValueError):
        polar_frame(centre, -2 * centre)
    with pytest.raises(ValueError):
        polar_frame(np.zeros(3), reference)
    np.testing.assert_allclose(perpendicular(centre) @ p, 0.0, atol=1e-15)


# --- the theta map of eq. 10, accurate form and inverse ------------------------------------------

@pytest.mark.parametrize("omega", WIDTHS)
def test_theta_map_equals_eq_10(omega):
    for amplitude in [0.0, 0.5, 3.0, minimum_amplitude(omega) * 0.9]:
        np.testing.assert_allclose(theta_map(THETA, amplitude, omega),
                                   symmetric_theta(THETA, amplitude, omega), atol=1e-7)
    cdf = wrapped_cauchy_cdf(THETA, omega)
    assert cdf[0] == 0.0 and cdf[-1] == pytest.approx(np.pi, abs=1e-15)
    # derivative of the CDF is the wrapped Cauchy density
    a = np.exp(-omega)
    theta = np.linspace(0.05, np.pi - 0.05, 300)
    h = 1e-5
    numeric = (wrapped_cauchy_cdf(theta + h, omega)
               - wrapped_cauchy_cdf(theta - h, omega)) / (2 * h)
    np.testing.assert_allclose(numeric, (1 - a * a) / (1 + a * a - 2 * a * np.cos(theta)),
                               rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("omega", [0.01, 0.3, 3.0])
def test_theta_map_inverse(omega):
    theta = np.linspace(0, np.pi, 5001)
    amplitudes = np.linspace(minimum_amplitude(omega) * 0.99, 50.0, theta.size)
    forward = theta_map(theta, amplitudes, omega)
    np.testing.assert_allclose(theta_map_inverse(forward, amplitudes, omega), theta, atol=1e-11)
    assert theta_map_inverse(0.0, 2.0, omega) == pytest.approx(0.0, abs=1e-15)
    assert theta_map_inverse(np.pi, 2.0, omega) == pytest.approx(np.pi, abs=1e-15)


# --- asymmetric theta transformation (Appendix eq. 27-29) ---------------------------------------

@pytest.mark.parametrize("b", [0.01, 0.3, 1.0, 5.0])
def test_asymmetric_amplitude_is_eq_29_with_minimum_zero(b):
    psi = np.linspace(-np.pi, np.pi, 4001)
    psi0, a0 = 0.7, 2.5
    beta = np.exp(-b)
    literal = a0 * ((1 - beta ** 2) / (1 + beta ** 2 - 2 * beta * np.cos(psi - psi0))
                    - (1 - beta ** 2) / (1 + beta) ** 2)
    values = asymmetric_amplitude(psi, a0, psi0, b)
    np.testing.assert_allclose(values, literal, rtol=1e-9, atol=1e-12 * literal.max())
    assert np.all(values >= 0)
    assert asymmetric_amplitude(psi0 + np.pi, a0, psi0, b) == pytest.approx(0.0, abs=1e-12)
    maximum = maximum_asymmetric_amplitude(a0, b)
    assert maximum == pytest.approx(a0 * 4 * beta / (1 - beta ** 2), rel=1e-12)
    assert asymmetric_amplitude(psi0, a0, psi0, b) == pytest.approx(maximum, rel=1e-12)
    assert values.max() <= maximum * (1 + 1e-12)
    # smooth and 2 pi-periodic
    np.testing.assert_allclose(asymmetric_amplitude(psi + 2 * np.pi, a0, psi0, b), values,
                               rtol=1e-9, atol=1e-12 * maximum)


@pytest.mark.parametrize("b", [0.05, 0.5, 3.0])
@pytest.mark.parametrize("omega", [0.01, 0.2, 1.0, 3.0])
def test_asymmetric_theta_strictly_increasing_for_every_psi(omega, b):
    theta = np.concatenate([np.linspace(0, 0.2 * omega, 201)[:-1], THETA[THETA >= 0.2 * omega]])
    psi0 = -1.2
    for a0 in [0.5, 10.0, 1000.0, minimum_asymmetric_amplitude(omega, b) * 0.99]:
        for psi in np.linspace(-np.pi, np.pi, 13).tolist() + [psi0]:
            f = asymmetric_theta(theta, psi, a0, omega, psi0, b)
            assert f[0] == pytest.approx(0.0, abs=1e-12)
            assert f[-1] == pytest.approx(np.pi, abs=1e-12)
            assert np.all(np.diff(f) > 0)


@pytest.mark.parametrize("b", [0.05, 0.5, 3.0])
@pytest.mark.parametrize("omega", [0.05, 0.5, 3.0])
def test_minimum_asymmetric_amplitude_is_the_limit(omega, b):
    """Below the bound f decreases near theta = 0 on the side psi0; the bound is sharp there."""
    limit = minimum_asymmetric_amplitude(omega, b)
    assert limit < 0
    assert maximum_asymmetric_amplitude(limit, b) == pytest.approx(minimum_amplitude(omega))
    theta = np.linspace(0, 0.2 * omega, 201)
    psi0 = 0.3
    assert np.all(np.diff(asymmetric_theta(theta, psi0, limit * 0.99, omega, psi0, b)) > 0)
    assert np.any(np.diff(asymmetric_theta(theta, psi0, limit * 1.01, omega, psi0, b)) < 0)
    warp = AsymmetricTheta([0, 0, 1], [1, 0, 0], limit * 0.99, omega, psi0, b)
    assert warp.is_valid()
    assert not with_amplitude(warp, limit * 1.01).is_valid()


def test_asymmetric_theta_moves_points_along_great_circles_through_the_centre(rng):
    points = random_unit_vectors(rng, 1000)
    for _ in range(5):
        centre, reference = rng.normal(size=3), rng.normal(size=3)
        a0, omega = rng.uniform(0, 5), rng.uniform(0.05, 2)
        psi0, b = rng.uniform(-np.pi, np.pi), rng.uniform(0.05, 2)
        moved = apply_asymmetric_theta(points, centre, reference, a0, omega, psi0, b)
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
        theta, psi = polar_coordinates(points, centre, reference)
        new_theta, new_psi = polar_coordinates(moved, centre, reference)
        np.testing.assert_allclose(wrap_angle(new_psi - psi), 0.0, atol=1e-9)   # psi unchanged
        np.testing.assert_allclose(new_theta, asymmetric_theta(theta, psi, a0, omega, psi0, b),
                                   atol=1e-12)
        # the opposite side (psi' = pi) does not move at all; the side psi0 moves most
        change = np.abs(new_theta - theta)
        opposite = np.abs(wrap_angle(psi - psi0 - np.pi)) < 0.02
        assert np.all(change[opposite] < 1e-3 * max(change.max(), 1e-300) + 1e-12)


def test_asymmetric_theta_reduces_to_symmetric_theta_for_constant_modulation(rng):
    points = random_unit_vectors(rng, 1000)
    for _ in range(5):
        centre, reference = rng.normal(size=3), rng.normal(size=3)
        amplitude, omega = rng.uniform(0, 5), rng.uniform(0.01, 3)
        # a constant A(psi) is exactly the symmetric transformation (eq. 10)
        constant = apply_psi_modulated_theta(points, centre, reference,
                                             lambda psi: amplitude, omega)
        symmetric = apply_symmetric_theta(points, centre, amplitude, omega)
        np.testing.assert_allclose(constant, symmetric, atol=1e-7)
        # on each half great circle psi = const, the asymmetric map is the symmetric one with
        # amplitude A(psi') of eq. 29
        psi0, b, a0 = rng.uniform(-np.pi, np.pi), rng.uniform(0.05, 3), rng.uniform(0, 5)
        p, e1, e2 = polar_frame(centre, reference)
        psi = rng.uniform(-np.pi, np.pi)
        theta = np.linspace(0, np.pi, 400)
        meridian = (np.cos(theta)[:, None] * p
                    + np.sin(theta)[:, None] * (np.cos(psi) * e1 + np.sin(psi) * e2))
        on_meridian = apply_asymmetric_theta(meridian, centre, reference, a0, omega, psi0, b)
        symmetric = apply_symmetric_theta(meridian, centre,
                                          float(asymmetric_amplitude(psi, a0, psi0, b)), omega)
        np.testing.assert_allclose(on_meridian, symmetric, atol=1e-7)


def test_asymmetric_theta_zero_amplitude_is_the_identity_and_poles_are_fixed(rng):
    points = random_unit_vectors(rng, 200)
    centre, reference = random_unit_vector(rng), random_unit_vector(rng)
    moved = apply_asymmetric_theta(points, centre, reference, 0.0, 0.3, 1.0, 0.5)
    np.testing.assert_array_equal(moved, points)
    assert moved is not points
    # a vanishing subsidiary Cauchy (b -> infinity) leaves every point in place
    np.testing.assert_allclose(apply_asymmetric_theta(points, centre, reference, 5.0, 0.3, 1.0,
                                                      40.0), points, atol=1e-12)
    poles = np.stack([centre, -centre])
    np.testing.assert_allclose(apply_asymmetric_theta(poles, centre, reference, 5.0, 0.3, 1.0, 0.5),
                               poles, atol=1e-15)
    # continuous at P: points at distance 1e-8 from P stay within f'(0)_max * 1e-8 of it
    offsets = random_unit_vectors(rng, 50)
    offsets -= np.outer(offsets @ centre, centre)
    offsets /= np.linalg.norm(offsets, axis=1, keepdims=True)
    near = np.cos(1e-8) * centre + np.sin(1e-8) * offsets
    moved_near = apply_asymmetric_theta(near, centre, reference, 5.0, 0.3, 1.0, 0.5)
    a = np.exp(-0.3)
    slope = (1 + maximum_asymmetric_amplitude(5.0, 0.5) * (1 + a) / (1 - a)) \
        / (1 + maximum_asymmetric_amplitude(5.0, 0.5))
    distance = np.arctan2(np.linalg.norm(np.cross(moved_near, centre), axis=1), moved_near @ centre)
    assert np.all(distance <= slope * 1e-8 * (1 + 1e-6))
    assert np.all(distance > 0)


# omega, b, A0: the extremes of the amplitude range that a 2562-point grid (edges ~0.075 rad)
# resolves: A(psi') peaking at 30 or 10 and A0 at 50% / 90% of the negative bound
ASYMMETRIC_GRID_CASES = [(1.0, 0.5, peak_amplitude(30, 0.5)), (3.0, 1.0, peak_amplitude(30, 1.0)),
                         (0.5, 0.3, peak_amplitude(10, 0.3)),
                         (0.3, 0.5, 0.5 * minimum_asymmetric_amplitude(0.3, 0.5)),
                         (3.0, 3.0, 0.9 * minimum_asymmetric_amplitude(3.0, 3.0))]


@pytest.mark.parametrize("omega, b, a0", ASYMMETRIC_GRID_CASES)
def test_asymmetric_theta_flips_no_grid_triangle_and_inverts(omega, b, a0):
    assert_fold_free_and_onto(GRID_POINTS)
    for seed in range(5):
        rng = np.random.default_rng(seed)
        warp = AsymmetricTheta(rng.normal(size=3), rng.normal(size=3), a0, omega,
                               rng.uniform(0, 2 * np.pi), b)
        assert warp.is_valid()
        moved = warp.apply(GRID_POINTS)
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
        assert not np.allclose(moved, GRID_POINTS)
        assert_fold_free_and_onto(moved)
        np.testing.assert_allclose(warp.inverse(moved), GRID_POINTS, atol=1e-10)
        np.testing.assert_allclose(warp.apply(warp.inverse(GRID_POINTS)), GRID_POINTS, atol=1e-10)


# --- shear and twist (Appendix eq. 30-31) --------------------------------------------------------

@pytest.mark.parametrize("width", [0.01, 0.3, 2.0])
def test_shear_twist_angle_is_eq_31(width):
    theta = np.linspace(0, np.pi, 1001)
    gamma = np.exp(-width)
    for amplitude, theta0 in [(1.0, 0.0), (-3.0, 1.1), (0.5, np.pi)]:
        literal = (amplitude / (2 * np.pi)) * (1 - gamma ** 2) \
            / (1 + gamma ** 2 - 2 * gamma * np.cos(theta - theta0))
        np.testing.assert_allclose(shear_twist_angle(theta, amplitude, width, theta0), literal,
                                   rtol=1e-9)
        assert shear_twist_angle(theta0, amplitude, width, theta0) == pytest.approx(
            amplitude / (2 * np.pi * np.tanh(width / 2)), rel=1e-12)
    # B is the integral of g over a full period
    s = np.linspace(-np.pi, np.pi, 400001)
    assert np.trapezoid(shear_twist_angle(s, 2.0, width, 0.3), s) == pytest.approx(2.0, rel=1e-6)


def test_shear_twist_keeps_theta_and_adds_g_to_psi(rng):
    points = random_unit_vectors(rng, 1000)
    for _ in range(6):
        centre, reference = rng.normal(size=3), rng.normal(size=3)
        amplitude, width = rng.uniform(-20, 20), float(np.exp(rng.uniform(np.log(0.01), 1)))
        theta0 = rng.uniform(0, np.pi)
        moved = apply_shear_twist(points, centre, amplitude, width, theta0)
        np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
        theta, psi = polar_coordinates(points, centre, reference)
        new_theta, new_psi = polar_coordinates(moved, centre, reference)
        np.testing.assert_allclose(new_theta, theta, atol=1e-12)                   # theta kept
        np.testing.assert_allclose(
            wrap_angle(new_psi - psi - shear_twist_angle(theta, amplitude, width, theta0)), 0.0,
            atol=1e-9)
        # the inverse is psi -> psi - g(theta), i.e. amplitude -B
        np.testing.assert_allclose(apply_shear_twist(moved, centre, amplitude, width, theta0,
                                                     inverse=True), points, atol=1e-12)
        np.testing.assert_allclose(apply_shear_twist(moved, centre, -amplitude, width, theta0),
                                   points, atol=1e-12)


def test_shear_twist_zero_amplitude_identity_and_continuity_at_the_poles(rng):
    points = random_unit_vectors(rng, 200)
    centre = random_unit_vector(rng)
    np.testing.assert_array_equal(apply_shear_twist(points, centre, 0.0, 0.1, 1.0), points)
    poles = np.stack([centre, -centre])
    # g(0) and g(pi) are not zero here, yet the poles are fixed ...
    assert shear_twist_angle(0.0, 7.0, 0.5, 0.2) > 1
    np.testing.assert_allclose(apply_shear_twist(poles, centre, 7.0, 0.5, 0.2), poles, atol=1e-15)
    # ... and points near a pole stay equally near it (rotated about it by about g(0))
    offsets = random_unit_vectors(rng, 50)
    offsets -= np.outer(offsets @ centre, centre)
    offsets /= np.linalg.norm(offsets, axis=1, keepdims=True)
    for pole in [centre, -centre]:
        near = np.cos(1e-7) * pole + np.sin(1e-7) * offsets
        moved = apply_shear_twist(near, centre, 7.0, 0.5, 0.2)
        np.testing.assert_allclose(np.linalg.norm(moved - pole, axis=1),
                                   np.linalg.norm(near - pole, axis=1), rtol=1e-6)


@pytest.mark.parametrize("width, amplitude", [(3.0, 30.0), (1.0, 10.0), (0.5, 2.0)])
def test_shear_twist_flips_no_grid_triangle_and_inverts(width, amplitude):
    """Twists of up to about 5 rad (peak g) across bands resolved by the 2562-point grid."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        for sign in [1, -1]:
            warp = ShearTwist(rng.normal(size=3), sign * amplitude, width, rng.uniform(0, np.pi))
            assert warp.is_valid()
            moved = warp.apply(GRID_POINTS)
            np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
            assert_fold_free_and_onto(moved)
            np.testing.assert_allclose(warp.inverse(moved), GRID_POINTS, atol=1e-12)
            # area preserving (Jacobian 1): the grid's total area and its triangles' sum agree
            np.testing.assert_allclose(np.sum(solid_angles(moved, GRID_TRIANGLES)),
                                       np.sum(solid_angles(GRID_POINTS, GRID_TRIANGLES)),
                                       rtol=1e-12)


# --- global rotation ------------------------------------------------------------------------------

def test_rotation_equals_the_matrix_rotation(rng):
    from scipy.spatial.transform import Rotation as ScipyRotation
    points = random_unit_vectors(rng, 300)
    for _ in range(5):
        vector = rng.normal(size=3) * rng.uniform(0, 3)
        rotated = apply_rotation(points, vector)
        np.testing.assert_allclose(rotated, (rotation_from_vector(vector) @ points.T).T, atol=1e-14)
        np.testing.assert_allclose(rotated, ScipyRotation.from_rotvec(vector).apply(points),
                                   atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(rotated, axis=1), 1.0, atol=1e-14)
        np.testing.assert_allclose(apply_rotation(rotated, vector, inverse=True), points,
                                   atol=1e-14)
        # points on the axis are fixed
        axis = vector / np.linalg.norm(vector)
        np.testing.assert_allclose(apply_rotation(axis[None], vector)[0], axis, atol=1e-14)
    np.testing.assert_array_equal(apply_rotation(points, np.zeros(3)), points)
    moved = apply_rotation(GRID_POINTS, [0.3, -2.0, 1.0])
    assert_fold_free_and_onto(moved)


# --- the common interface and compositions --------------------------------------------------------

def example_warps(rng):
    return [SymmetricTheta(rng.normal(size=3), 0.8, 0.7),
            AsymmetricTheta(rng.normal(size=3), rng.normal(size=3), 2.0, 0.8, 1.0, 0.6),
            ShearTwist(rng.normal(size=3), 4.0, 1.0, 1.2),
            Rotation(rng.normal(size=3))]


def test_apply_warp_by_name_matches_the_functions(rng):
    points = random_unit_vectors(rng, 300)
    centre, reference = random_unit_vector(rng), random_unit_vector(rng)
    np.testing.assert_allclose(
        apply_warp(points, "symmetric_theta", {"center": centre, "amplitude": 1.5, "omega": 0.4}),
        apply_symmetric_theta(points, centre, 1.5, 0.4), atol=0)
    np.testing.assert_allclose(
        apply_warp(points, "asymmetric_theta", {"center": centre, "reference_direction": reference,
                                                "amplitude": 1.5, "omega": 0.4, "psi0": 2.0,
                                                "b": 0.3}),
        apply_asymmetric_theta(points, centre, reference, 1.5, 0.4, 2.0, 0.3), atol=1e-15)
    np.testing.assert_allclose(
        apply_warp(points, "shear_twist", {"center": centre, "amplitude": -2.0, "width": 0.3,
                                           "theta0": 1.0}),
        apply_shear_twist(points, centre, -2.0, 0.3, 1.0), atol=1e-15)
    np.testing.assert_allclose(apply_warp(points, "rotation", {"rotation_vector": [0.1, 0.2, 0.3]}),
                               apply_rotation(points, [0.1, 0.2, 0.3]), atol=0)
    coefficients = rng.normal(size=(12, 3)) * 1e-3
    np.testing.assert_allclose(
        apply_warp(points, "field", {"level": 0, "support": 2.0, "coefficients": coefficients}),
        FieldBasis.icosphere_level(0, points, 2.0).apply(coefficients), atol=0)
    assert set(WARP_KINDS) == {"symmetric_theta", "asymmetric_theta", "shear_twist", "rotation",
                               "field", *CIRCLE_WARP_KINDS}
    with pytest.raises(ValueError):
        apply_warp(points, "bogus", {})
    # parameters() rebuild the same warp
    for warp in example_warps(rng):
        again = make_warp(warp.kind, warp.parameters())
        np.testing.assert_allclose(again.apply(points), warp.apply(points), atol=1e-15)


def test_bounds_and_validity(rng):
    centre = random_unit_vector(rng)
    symmetric = SymmetricTheta(centre * 4, 1.0, 0.5)
    np.testing.assert_allclose(symmetric.center, centre)
    assert symmetric.bounds()["amplitude"][0] == minimum_amplitude(0.5)
    assert symmetric.is_valid()
    assert not with_amplitude(symmetric, minimum_amplitude(0.5) * 1.01).is_valid()
    assert not SymmetricTheta(centre, 1.0, -0.1).is_valid()
    assert not SymmetricTheta(centre, np.nan, 0.5).is_valid()
    asymmetric = AsymmetricTheta(centre, perpendicular(centre), -0.01, 0.5, 0.0, 0.3)
    assert asymmetric.is_valid()
    assert not AsymmetricTheta(centre, perpendicular(centre), 1.0, 0.5, 0.0, 0.0).is_valid()
    with pytest.raises(ValueError):
        AsymmetricTheta(centre, centre, 1.0, 0.5, 0.0, 0.3)
    assert ShearTwist(centre, -1e6, 0.1, 7.0).is_valid()
    assert not ShearTwist(centre, 1.0, 0.0, 1.0).is_valid()
    assert Rotation([0, 0, 10.0]).is_valid()
    assert Rotation([0, 0, 10.0]).bounds() == {}


@pytest.mark.parametrize("seed", range(5))
def test_composition_of_all_kinds_is_fold_free_and_invertible(seed):
    rng = np.random.default_rng(seed)
    warps = example_warps(rng) + example_warps(rng)
    moved = apply_warps(GRID_POINTS, warps)
    np.testing.assert_allclose(np.linalg.norm(moved, axis=1), 1.0, atol=1e-12)
    assert_fold_free_and_onto(moved)
    np.testing.assert_allclose(invert_warps(moved, warps), GRID_POINTS, atol=1e-9)
    # apply_warps applies warps[0] first
    step = GRID_POINTS
    for warp in warps:
        step = warp.apply(step)
    np.testing.assert_array_equal(step, moved)


EXTREME_WARPS = [
    lambda rng: AsymmetricTheta(rng.normal(size=3), rng.normal(size=3), 1000.0, 0.01,
                                rng.uniform(0, 6), 0.01),
    lambda rng: AsymmetricTheta(rng.normal(size=3), rng.normal(size=3),
                                0.999 * minimum_asymmetric_amplitude(0.05, 0.05), 0.05,
                                rng.uniform(0, 6), 0.05),
    lambda rng: AsymmetricTheta(rng.normal(size=3), rng.normal(size=3), 50.0, 3.0,
                                rng.uniform(0, 6), 10.0),
    lambda rng: ShearTwist(rng.normal(size=3), 2.0, 0.05, rng.uniform(0, np.pi)),
    lambda rng: ShearTwist(rng.normal(size=3), -1000.0, 3.0, rng.uniform(0, np.pi)),
    lambda rng: Rotation(rng.normal(size=3) * 10),
]


@pytest.mark.parametrize("make", EXTREME_WARPS)
def test_extreme_parameters_preserve_orientation_locally(make, rng):
    """The continuous maps have a positive Jacobian even at extreme parameters.

    Tiny triangles (1e-9 rad) around random points keep their orientation and the map inverts.
    Continuously every amplitude is allowed for the shear; the twist is limited here (peak g about
    13 rad at width 0.05) only because a triangle sheared into a sliver thinner than the rounding
    error of the rotation angle can no longer be resolved in floating point.
    """
    corners = tiny_triangles(rng, 4000, 1e-9)
    assert np.all(small_orientation(*corners) > 0)
    warp = make(rng)
    assert warp.is_valid()
    moved = [warp.apply(c) for c in corners]
    assert np.all(small_orientation(*moved) > 0)
    for before, after in zip(corners, moved):
        np.testing.assert_allclose(np.linalg.norm(after, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(warp.inverse(after), before, atol=1e-8)


# --- random draws -------------------------------------------------------------------------------

def test_random_warp_draws(rng):
    sigma = 1 / 32
    symmetric = [random_symmetric_theta(rng, sigma) for _ in range(2000)]
    asymmetric = [random_asymmetric_theta(rng, sigma) for _ in range(4000)]
    shears = [random_shear_twist(rng, sigma) for _ in range(4000)]
    for warps in (symmetric, asymmetric, shears):
        assert all(w.is_valid() and w.amplitude == 0.0 for w in warps)
    half_normal_mean = np.sqrt(2 / np.pi) * sigma
    assert np.mean([w.omega for w in symmetric]) == pytest.approx(half_normal_mean, rel=0.06)
    assert np.mean([w.omega for w in asymmetric]) == pytest.approx(half_normal_mean, rel=0.05)
    assert np.mean([w.width for w in shears]) == pytest.approx(half_normal_mean, rel=0.05)
    psi0 = np.array([w.psi0 for w in asymmetric])
    assert psi0.min() >= 0 and psi0.max() < 2 * np.pi
    assert psi0.mean() == pytest.approx(np.pi, rel=0.03)
    b = np.array([w.b for w in asymmetric])
    assert b.min() >= 0.1 and b.max() <= 2.0
    assert np.log(b).mean() == pytest.approx(0.5 * (np.log(0.1) + np.log(2.0)), abs=0.05)
    cos_theta0 = np.cos([w.theta0 for w in shears])
    assert cos_theta0.mean() == pytest.approx(0.0, abs=0.03)
    assert np.mean(cos_theta0 ** 2) == pytest.approx(1 / 3, abs=0.02)
    centres = np.array([w.center for w in shears])
    assert np.all(np.abs(centres.mean(axis=0)) < 0.05)
    given = np.array([0.0, 0.0, 2.0])
    np.testing.assert_allclose(random_asymmetric_theta(rng, sigma, center=given).center,
                               [0, 0, 1])
    # a new warp (amplitude zero) is the identity
    points = random_unit_vectors(rng, 50)
    for warp in (symmetric[0], asymmetric[0], shears[0]):
        np.testing.assert_array_equal(warp.apply(points), points)


def test_random_rotations(rng):
    matrices = np.array([rotation_from_vector(random_rotation(rng).rotation_vector)
                         for _ in range(4000)])
    # Haar measure: E[R] = 0, and the angle has density (1 - cos t) / pi on [0, pi]
    assert np.all(np.abs(matrices.mean(axis=0)) < 0.04)
    angles = np.array([np.linalg.norm(random_rotation(rng).rotation_vector) for _ in range(4000)])
    assert angles.max() <= np.pi + 1e-12
    assert angles.mean() == pytest.approx(np.pi / 2 + 2 / np.pi, rel=0.03)
    small = np.array([np.linalg.norm(random_rotation(rng, 0.05).rotation_vector)
                      for _ in range(4000)])
    assert small.mean() == pytest.approx(np.sqrt(2 / np.pi) * 0.05, rel=0.05)
