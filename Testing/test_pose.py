"""Tests of similarity transforms and weighted (generalized) Procrustes alignment."""

import numpy as np
import pytest
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from mdlshapemodel.geometry import (Pose, align, centroid_size, generalized_procrustes,
                                pose_from_parameters, rotation_from_vector, weighted_centroid)


def random_rotation(rng):
    return Rotation.random(random_state=rng).as_matrix()


def random_weights(rng, n):
    w = rng.uniform(0.1, 3.0, size=n)
    return w / w.sum()


def random_pose(rng, scaling=True):
    return Pose(float(rng.uniform(0.5, 2.0)) if scaling else 1.0, random_rotation(rng),
                rng.normal(scale=5.0, size=3))


def weighted_residual(points, target, weights):
    return float(np.sum(weights * np.sum((points - target) ** 2, axis=1)))


# --- rotations ---------------------------------------------------------------------------------------

def test_rotation_from_vector_is_a_proper_rotation_by_the_right_angle(rng):
    for _ in range(50):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0, np.pi)
        rotation = rotation_from_vector(axis * angle)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(rotation @ axis, axis, atol=1e-14)          # axis is fixed
        # a vector perpendicular to the axis turns by ``angle``, counter-clockwise about the axis
        perpendicular = np.cross(axis, rng.normal(size=3))
        perpendicular /= np.linalg.norm(perpendicular)
        turned = rotation @ perpendicular
        assert np.arccos(np.clip(turned @ perpendicular, -1, 1)) == pytest.approx(angle, abs=1e-7)
        assert np.cross(perpendicular, turned) @ axis >= -1e-14
        np.testing.assert_allclose(rotation, Rotation.from_rotvec(axis * angle).as_matrix(),
                                   atol=1e-14)


def test_rotation_from_vector_simple_cases():
    np.testing.assert_array_equal(rotation_from_vector(np.zeros(3)), np.eye(3))
    quarter = rotation_from_vector([0, 0, np.pi / 2])
    np.testing.assert_allclose(quarter @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rotation_from_vector([np.pi, 0, 0]), np.diag([1, -1, -1]),
                               atol=1e-15)


def test_pose_from_parameters(rng):
    parameters = rng.normal(size=7)
    pose = pose_from_parameters(parameters)
    assert pose.scale == pytest.approx(np.exp(parameters[6]))
    np.testing.assert_allclose(pose.rotation, Rotation.from_rotvec(parameters[:3]).as_matrix(),
                               atol=1e-14)
    np.testing.assert_array_equal(pose.translation, parameters[3:6])
    identity = pose_from_parameters(np.zeros(7))
    points = rng.normal(size=(10, 3))
    np.testing.assert_allclose(identity.apply(points), points)


# --- Pose algebra -------------------------------------------------------------------------------------

def test_pose_apply_is_scale_rotate_translate(rng):
    pose = random_pose(rng)
    points = rng.normal(size=(20, 3))
    expected = np.array([pose.scale * pose.rotation @ p + pose.translation for p in points])
    np.testing.assert_allclose(pose.apply(points), expected, atol=1e-12)


def test_compose_and_inverse_are_consistent(rng):
    points = rng.normal(size=(30, 3))
    for _ in range(10):
        first, second = random_pose(rng), random_pose(rng)
        composed = second.compose(first)
        np.testing.assert_allclose(composed.apply(points), second.apply(first.apply(points)),
                                   atol=1e-12)
        inverse = first.inverse()
        np.testing.assert_allclose(inverse.apply(first.apply(points)), points, atol=1e-12)
        np.testing.assert_allclose(first.apply(inverse.apply(points)), points, atol=1e-12)
        identity = first.compose(inverse)
        assert identity.scale == pytest.approx(1.0)
        np.testing.assert_allclose(identity.rotation, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(identity.translation, 0.0, atol=1e-12)
        # (B o A)^-1 = A^-1 o B^-1
        np.testing.assert_allclose(composed.inverse().apply(points),
                                   first.inverse().compose(second.inverse()).apply(points),
                                   atol=1e-12)


def test_copy_is_independent(rng):
    pose = random_pose(rng)
    copy = pose.copy()
    copy.rotation[0, 0] += 1.0
    copy.translation[0] += 1.0
    assert not np.allclose(copy.rotation, pose.rotation)
    assert not np.allclose(copy.translation, pose.translation)


# --- align ---------------------------------------------------------------------------------------------

def test_centroid_and_centroid_size(rng):
    points = rng.normal(size=(40, 3))
    weights = random_weights(rng, 40)
    centre = np.sum(points * weights[:, None], axis=0)
    np.testing.assert_allclose(weighted_centroid(points, weights), centre)
    size = np.sqrt(np.sum(weights * np.sum((points - centre) ** 2, axis=1)))
    assert centroid_size(points, weights) == pytest.approx(size)
    assert centroid_size(3 * points + 7, weights) == pytest.approx(3 * size)


@pytest.mark.parametrize("scaling", [True, False])
def test_align_recovers_a_known_transform_exactly(rng, scaling):
    for _ in range(10):
        source = rng.normal(size=(50, 3)) * [3.0, 2.0, 1.0]
        weights = random_weights(rng, 50)
        truth = random_pose(rng, scaling)
        target = truth.apply(source)
        pose = align(source, target, weights, scaling=scaling)
        assert pose.scale == pytest.approx(truth.scale, rel=1e-10)
        np.testing.assert_allclose(pose.rotation, truth.rotation, atol=1e-10)
        np.testing.assert_allclose(pose.translation, truth.translation, atol=1e-9)
        np.testing.assert_allclose(pose.apply(source), target, atol=1e-9)


def test_align_without_scaling_keeps_unit_scale(rng):
    source = rng.normal(size=(30, 3))
    weights = random_weights(rng, 30)
    truth = Pose(2.5, random_rotation(rng), rng.normal(size=3))
    pose = align(source, truth.apply(source), weights, scaling=False)
    assert pose.scale == 1.0
    # the best rigid fit to a scaled copy still has the right rotation; centroids coincide
    np.testing.assert_allclose(pose.rotation, truth.rotation, atol=1e-10)
    np.testing.assert_allclose(weighted_centroid(pose.apply(source), weights),
                               weighted_centroid(truth.apply(source), weights), atol=1e-10)


def test_align_is_the_weighted_least_squares_optimum(rng):
    """With noise and non-uniform weights no nearby similarity transform does better."""
    source = rng.normal(size=(40, 3)) * [2.0, 1.0, 0.5]
    weights = random_weights(rng, 40)
    target = random_pose(rng).apply(source) + rng.normal(scale=0.3, size=source.shape)
    for scaling in (True, False):
        pose = align(source, target, weights, scaling=scaling)
        best = weighted_residual(pose.apply(source), target, weights)

        def residual(p):
            candidate = Pose(float(np.exp(p[6])) if scaling else 1.0,
                             rotation_from_vector(p[:3]) @ pose.rotation,
                             pose.translation + p[3:6])
            return weighted_residual(candidate.apply(source), target, weights)

        start = np.zeros(7)
        start[6] = np.log(pose.scale)
        refined = minimize(residual, start, method="Nelder-Mead",
                           options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 20000})
        assert best <= refined.fun + 1e-10
        for _ in range(20):
            assert best <= residual(start + rng.normal(scale=1e-3, size=7)) + 1e-14


def test_align_never_returns_a_reflection(rng):
    source = rng.normal(size=(25, 3)) * [3.0, 2.0, 1.0]
    weights = random_weights(rng, 25)
    mirrored = source * [1.0, 1.0, -1.0]           # the best orthogonal fit is a reflection
    for target in (mirrored, random_pose(rng).apply(mirrored)):
        pose = align(source, target, weights)
        assert np.linalg.det(pose.rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(pose.rotation @ pose.rotation.T, np.eye(3), atol=1e-12)
    # planar shapes: reflection and rotation fit equally well; still a rotation
    flat = source * [1.0, 1.0, 0.0]
    pose = align(flat, flat * [1.0, -1.0, 1.0], weights)
    assert np.linalg.det(pose.rotation) == pytest.approx(1.0)


def test_align_honours_the_weights(rng):
    """Points with zero weight do not influence the fit."""
    source = rng.normal(size=(20, 3))
    truth = random_pose(rng)
    target = truth.apply(source)
    target[:5] += rng.normal(scale=10.0, size=(5, 3))     # outliers ...
    weights = np.ones(20)
    weights[:5] = 0.0                                      # ... with no weight
    weights /= weights.sum()
    pose = align(source, target, weights)
    np.testing.assert_allclose(pose.rotation, truth.rotation, atol=1e-10)
    assert pose.scale == pytest.approx(truth.scale, rel=1e-10)


# --- generalized Procrustes ---------------------------------------------------------------------------

@pytest.mark.parametrize("scaling", [True, False])
def test_gpa_of_transformed_copies_gives_identical_shapes(rng, scaling):
    base = rng.normal(size=(60, 3)) * [4.0, 2.0, 1.0]
    weights = random_weights(rng, 60)
    poses = [random_pose(rng, scaling) for _ in range(7)]
    shapes = np.stack([p.apply(base) for p in poses])
    aligned, found = generalized_procrustes(shapes, weights, scaling=scaling)
    assert aligned.shape == shapes.shape
    for x in aligned[1:]:
        np.testing.assert_allclose(x, aligned[0], atol=1e-8)
    # default size: the mean centroid size of the inputs
    target = np.mean([centroid_size(x, weights) for x in shapes])
    sizes = [centroid_size(x, weights) for x in aligned]
    assert np.mean(sizes) == pytest.approx(target, rel=1e-10)
    np.testing.assert_allclose(weighted_centroid(aligned.mean(axis=0), weights), 0.0, atol=1e-9)
    # returned poses map each input onto its aligned shape
    for pose, x, y in zip(found, shapes, aligned):
        np.testing.assert_allclose(pose.apply(x), y, atol=1e-9)
        assert np.linalg.det(pose.rotation) == pytest.approx(1.0)
    # the aligned shape is the base shape up to a similarity
    back = align(base, aligned[0], weights)
    np.testing.assert_allclose(back.apply(base), aligned[0], atol=1e-8)


def test_gpa_target_size(rng):
    """The result scales with ``target_size``; the mean of noisy copies is centred, about that size."""
    base = rng.normal(size=(40, 3))
    weights = random_weights(rng, 40)
    shapes = np.stack([random_pose(rng).apply(base + rng.normal(scale=0.05, size=base.shape))
                       for _ in range(6)])
    aligned, _ = generalized_procrustes(shapes, weights, target_size=3.0)
    doubled, _ = generalized_procrustes(shapes, weights, target_size=6.0)
    np.testing.assert_allclose(doubled, 2 * aligned, atol=1e-9)
    mean = aligned.mean(axis=0)
    # least-squares scaling shrinks each shape slightly towards the size-3 reference
    assert centroid_size(mean, weights) == pytest.approx(3.0, rel=1e-2)
    for x in aligned:
        np.testing.assert_allclose(weighted_centroid(x, weights), 0.0, atol=1e-9)
        assert centroid_size(x, weights) == pytest.approx(3.0, rel=1e-2)


def test_gpa_result_is_a_fixed_point(rng):
    """Aligned noisy copies are much closer to their mean than the raw ones, and aligning each
    input to the (centred, size-normalised) mean of the result reproduces the result."""
    base = rng.normal(size=(50, 3)) * [3.0, 1.5, 1.0]
    weights = random_weights(rng, 50)
    shapes = np.stack([random_pose(rng).apply(base + rng.normal(scale=0.05, size=base.shape))
                       for _ in range(8)])
    aligned, _ = generalized_procrustes(shapes, weights, iterations=200, tolerance=1e-14)
    target = np.mean([centroid_size(x, weights) for x in shapes])
    mean = aligned.mean(axis=0)
    spread = np.mean([weighted_residual(x, mean, weights) for x in aligned])
    raw_spread = np.mean([weighted_residual(x, shapes.mean(axis=0), weights) for x in shapes])
    assert spread < 1e-2 * raw_spread
    reference = mean - weighted_centroid(mean, weights)
    reference *= target / centroid_size(reference, weights)
    for x, y in zip(shapes, aligned):
        np.testing.assert_allclose(align(x, reference, weights).apply(x), y, atol=1e-6)
