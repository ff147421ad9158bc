"""Tests of the symmetric theta transformation (paper eq. 8-12, METHOD.md section 3)."""

import numpy as np
import pytest

from mdlshapemodel.sampling import icosphere
from mdlshapemodel.warps import (apply_symmetric_theta, minimum_amplitude, random_unit_vector,
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
