"""The optimisation state: incremental covariance, objective bookkeeping, homeomorphism."""

import numpy as np
import pytest

from mdlshapemodel.correspond import Kernel
from mdlshapemodel.mdl import Objective
from mdlshapemodel.pose import Pose, centroid_size, rotation_from_vector
from mdlshapemodel.sampling import sphere_grid
from mdlshapemodel.sphere import orientation

from synthetic import small_state


def full_covariance(shapes, weights, target_size):
    """D' computed from scratch, on the population rescaled to the target mean size."""
    mean = shapes.mean(axis=0)
    factor = target_size / centroid_size(mean, weights)
    centred = (shapes - mean) * factor
    flat = (centred * np.sqrt(weights)[None, :, None]).reshape(len(shapes), -1)
    return flat @ flat.T


@pytest.fixture
def state():
    s = small_state()
    data_range = float(np.max(np.ptp(s.aligned_shapes().reshape(-1, 3), axis=0)))
    s.objective = Objective("integrated", data_range, delta_min=1e-4, delta_max=0.5)
    return s


def test_initial_alignment_keeps_target_size(state):
    mean = state.aligned_shapes().mean(axis=0)
    assert centroid_size(mean, state.weights) == pytest.approx(state.target_size, rel=1e-9)
    assert np.sum(state.weights) == pytest.approx(1.0)
    assert np.all(state.weights > 0)


def test_trial_covariance_matches_recomputation(state):
    rng = np.random.default_rng(3)
    i = 2
    trial = state.shapes[i] + rng.normal(scale=0.3, size=state.shapes[i].shape)
    shapes = state.shapes.copy()
    shapes[i] = trial
    expected = full_covariance(shapes, state.weights, state.target_size)
    np.testing.assert_allclose(state.covariance(i, trial), expected, atol=1e-9 * np.abs(expected).max())
    assert state.value(i, trial) == pytest.approx(state.objective(expected), rel=1e-10)


def test_commits_keep_incremental_gram_exact(state):
    rng = np.random.default_rng(5)
    for step in range(6):
        i = int(rng.integers(state.n_shapes))
        example = state.examples[i]
        if step % 2:
            part = example.parts[0]
            kernel = Kernel(part.random_surface_parameter(rng), 0.3, 0.2)
            part.commit(kernel, *part.propose_kernel(kernel))
        else:
            example.pose = Pose(1.05, rotation_from_vector([0.05, -0.02, 0.03]),
                                np.array([0.5, 0.0, -0.2])).compose(example.pose)
        state.commit_shape(i)
    incremental = state.covariance()
    shapes = np.stack([e.pose.apply(e.raw_points()) for e in state.examples])
    expected = full_covariance(shapes, state.weights, state.target_size)
    np.testing.assert_allclose(incremental, expected, atol=1e-9 * np.abs(expected).max())


def test_objective_ignores_global_scale_of_poses(state):
    """Shrinking every example cannot lower F: F is measured at the fixed mean size."""
    before = state.value()
    for example in state.examples:
        example.pose = Pose(0.5, np.eye(3), np.zeros(3)).compose(example.pose)
    state.rebuild(update_weights=False)
    assert state.value() == pytest.approx(before, rel=1e-9)


def test_kernels_keep_sample_grid_a_homeomorphism(state):
    """After many random kernels the warped grid triangles are all positively oriented."""
    rng = np.random.default_rng(11)
    _, triangles = sphere_grid(162)
    for example in state.examples:
        part = example.parts[0]
        for _ in range(30):
            centre, omega = part.random_surface_parameter(rng), float(rng.uniform(0.005, 2.0))
            amplitude = part.feasible_amplitude(centre, omega, float(rng.uniform(0.0, 1.0)))
            kernel = Kernel(centre, omega, amplitude)
            part.commit(kernel, *part.propose_kernel(kernel))
        assert np.all(orientation(part.positions, triangles) > 0)
        np.testing.assert_allclose(np.linalg.norm(part.positions, axis=1), 1.0, atol=1e-12)


def test_random_surface_parameter_is_uniform_over_the_surface(state):
    """Kernel centres are drawn by surface area: their surface points cover both halves evenly."""
    part = state.examples[0].parts[0]
    rng = np.random.default_rng(0)
    from mdlshapemodel.sampling import SphereLocator

    locator = SphereLocator(part.sphere, part.faces)
    centres = np.array([part.random_surface_parameter(rng) for _ in range(2000)])
    points, _ = locator.evaluate(part.vertices, centres)
    from mdlshapemodel.surface import face_areas

    areas = face_areas(part.vertices, part.faces)
    centroids = part.vertices[part.faces].mean(axis=1)
    median_x = np.median(part.vertices[:, 0])
    expected = areas[centroids[:, 0] < median_x].sum() / areas.sum()
    observed = np.mean(points[:, 0] < median_x)
    assert observed == pytest.approx(expected, abs=0.04)
