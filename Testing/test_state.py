"""The optimisation state: incremental covariance, objective bookkeeping, homeomorphism."""

import numpy as np
import pytest

from mdlshapemodel.correspondence.warps import SymmetricTheta
from mdlshapemodel.correspondence.objective import Objective
from mdlshapemodel.geometry import Pose, centroid_size, rotation_from_vector
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.prepare.sphere import orientation
from mdlshapemodel.prepare.surface import face_areas

from synthetic import build_objectives, small_state


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
    s.objective = build_objectives(s)[1]
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
            kernel = SymmetricTheta(part.random_surface_parameter(rng), 0.2, 0.3)
            part.commit(kernel, *part.propose(kernel, check_folds=False))
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
            kernel = SymmetricTheta(centre, amplitude, omega)
            part.commit(kernel, *part.propose(kernel, check_folds=False))
        assert np.all(orientation(part.positions, triangles) > 0)
        np.testing.assert_allclose(np.linalg.norm(part.positions, axis=1), 1.0, atol=1e-12)


def test_random_surface_parameter_is_uniform_over_the_surface(state):
    """Kernel centres are drawn by surface area: their surface points cover both halves evenly."""
    part = state.examples[0].parts[0]
    rng = np.random.default_rng(0)
    from mdlshapemodel.correspondence.sampling import SphereLocator

    locator = SphereLocator(part.sphere, part.faces)
    centres = np.array([part.random_surface_parameter(rng) for _ in range(2000)])
    points, _ = locator.evaluate(part.vertices, centres)
    from mdlshapemodel.prepare.surface import face_areas

    areas = face_areas(part.vertices, part.faces)
    centroids = part.vertices[part.faces].mean(axis=1)
    median_x = np.median(part.vertices[:, 0])
    expected = areas[centroids[:, 0] < median_x].sum() / areas.sum()
    observed = np.mean(points[:, 0] < median_x)
    assert observed == pytest.approx(expected, abs=0.04)


# --- the gradient dF/dX ------------------------------------------------------------------------

def trial_value(state, i, shape):
    """F with example i's posed points replaced (no evaluation counted)."""
    return state.objective(state.covariance(i, shape))


def derivative_along(state, i, direction, shape=None, step=1e-6):
    """Richardson-extrapolated central difference of F along ``direction`` on example i.

    The step is small: F has kinks (a mode's variance crossing a limit of the integrated
    objective) that can lie within 1e-5 of the largest coordinate of a state; with the sphere
    maps of the small population, example 4 has one (the gradient agrees with differences of
    steps 1e-6 to 1e-8 to 1e-7 relative, not with steps of 1e-5 and 2e-5)."""
    base = state.shapes[i] if shape is None else shape
    scale = step * np.abs(state.shapes).max()

    def central(h):
        return (trial_value(state, i, base + h * direction)
                - trial_value(state, i, base - h * direction)) / (2 * h)
    return (4 * central(scale) - central(2 * scale)) / 3


def test_shape_gradient_matches_finite_differences(state):
    rng = np.random.default_rng(7)
    for objective in build_objectives(state)[::-1]:
        state.objective = objective
        value, grad = state.shape_gradient()
        assert value == pytest.approx(state.value(), rel=1e-12)
        assert grad.shape == state.shapes.shape
        for i in (0, 2, 4):
            direction = rng.normal(size=state.shapes[i].shape)       # all points of example i
            numeric = derivative_along(state, i, direction)
            assert np.sum(grad[i] * direction) == pytest.approx(numeric, rel=1e-6)
            for _ in range(3):                                       # single coordinates
                k, d = int(rng.integers(state.n_points)), int(rng.integers(3))
                direction = np.zeros_like(state.shapes[i])
                direction[k, d] = 1.0
                numeric = derivative_along(state, i, direction)
                assert grad[i, k, d] == pytest.approx(numeric, rel=1e-5,
                                                      abs=1e-7 * np.abs(grad).max())


def test_example_gradient_matches_shape_gradient_and_trial_shapes(state):
    rng = np.random.default_rng(8)
    for objective in build_objectives(state)[::-1]:
        state.objective = objective
        value, grad = state.shape_gradient()
        for i in range(state.n_shapes):
            value_i, grad_i = state.example_gradient(i)
            assert value_i == pytest.approx(value, rel=1e-12)
            np.testing.assert_allclose(grad_i, grad[i], atol=1e-12 * np.abs(grad).max())
        # at a trial shape of example 3 (as value(i, shape) evaluates it)
        trial = state.shapes[3] + rng.normal(scale=0.2, size=state.shapes[3].shape)
        value_t, grad_t = state.example_gradient(3, trial)
        assert value_t == pytest.approx(trial_value(state, 3, trial), rel=1e-12)
        direction = rng.normal(size=trial.shape)
        numeric = derivative_along(state, 3, direction, shape=trial)
        assert np.sum(grad_t * direction) == pytest.approx(numeric, rel=1e-6)


def test_shape_gradient_respects_the_invariances_of_f(state):
    """F is unchanged by translating, rotating or scaling all examples together (centring, the
    rotation invariance of D' and the rescaling to the target mean size): the gradient has no
    component along those motions, although it is far from zero."""
    for objective in build_objectives(state)[::-1]:
        state.objective = objective
        _, grad = state.shape_gradient()
        points = state.shapes - state.shapes.mean(axis=(0, 1))
        size = np.linalg.norm(grad) * np.linalg.norm(points)
        assert np.linalg.norm(grad) > 1e-3
        np.testing.assert_allclose(grad.sum(axis=(0, 1)), 0.0, atol=1e-12 * np.abs(grad).sum())
        assert abs(np.sum(grad * points)) < 1e-12 * size                           # scale
        np.testing.assert_allclose(np.cross(points, grad).sum(axis=(0, 1)), 0.0,
                                   atol=1e-12 * size)                               # rotation



def test_translating_one_example(state):
    """dF/dt_i = 2 sum_j M_ij c_j (c_j: weighted centroid of example j, M = f^2 H Gd H): zero
    while all examples share their weighted centroid (as after Procrustes), not otherwise."""
    centroids = np.einsum("k,ikd->id", state.weights, state.shapes)
    np.testing.assert_allclose(centroids - centroids[0], 0.0, atol=1e-7)   # Procrustes tolerance
    _, grad = state.shape_gradient()
    np.testing.assert_allclose(grad.sum(axis=1), 0.0, atol=1e-7 * np.abs(grad).sum())
    shifted = state.shapes[1] + np.array([0.3, -0.2, 0.1])
    _, grad_shifted = state.example_gradient(1, shifted)
    translation = grad_shifted.sum(axis=0)
    assert np.linalg.norm(translation) > 1e-3 * np.abs(grad_shifted).sum()
    for d in range(3):
        direction = np.zeros_like(shifted)
        direction[:, d] = 1.0
        numeric = derivative_along(state, 1, direction, shape=shifted)
        assert translation[d] == pytest.approx(numeric, rel=1e-6)


def test_scaling_term_of_the_gradient(state):
    """Scaling every example by (1 + t) leaves F unchanged only because of the rescaling factor:
    along that motion the data term and the scale term of the gradient cancel."""
    state.objective = build_objectives(state)[0]
    _, grad = state.shape_gradient()
    _, grad_cov = state.objective.gradient(state.covariance())
    amount = float(np.sum(grad_cov * state.covariance()))
    data = grad - state.scale_gradient(state.sum_shapes, amount)[None]
    along = np.sum(data * state.shapes)
    assert abs(along) > 1e-3 * np.linalg.norm(data) * np.linalg.norm(state.shapes)
    assert np.sum(grad * state.shapes) == pytest.approx(0.0, abs=1e-9 * abs(along))


def test_trial_shapes_replace_every_shape_and_restore_the_state():
    state = small_state()
    state.objective = Objective("fixed", 30.0, delta=0.1)
    before = state.value()
    gram = state.gram.copy()
    trial = state.shapes * 1.1 + 0.3
    trial[2] = state.shapes[2]
    with state.trial_shapes(trial):
        replaced = state.value()
    np.testing.assert_array_equal(state.gram, gram)
    assert state.value() == before
    one = state.shapes.copy()  # one shape replaced: the same F as the incremental covariance
    one[1] = trial[1]
    with state.trial_shapes(one):
        assert state.value() == pytest.approx(state.objective(state.covariance()), rel=1e-12)
        full = state.value()
    assert full == pytest.approx(state.value(1, trial[1]), rel=1e-9)
    assert replaced != before


def test_released_sampling_keeps_the_correspondence_and_refuses_to_move_points():
    state = small_state()
    shapes, aligned, weights = state.raw_shapes(), state.aligned_shapes(), state.weights.copy()
    state.release_sampling()
    np.testing.assert_array_equal(state.raw_shapes(), shapes)
    np.testing.assert_array_equal(state.aligned_shapes(), aligned)
    np.testing.assert_array_equal(state.weights, weights)
    part = state.examples[0].parts[0]
    with pytest.raises(RuntimeError, match="release_sampling"):
        part.sample(part.positions)


def test_a_part_holds_one_narrow_copy_of_its_triangles(state):
    """A part's triangles are its locator's table (one array, in the locator's index type), the
    same surface as given: renumbered vertices, same triangles."""
    part = state.examples[0].parts[0]
    assert part.faces is part.locator.faces
    assert part.faces.dtype == np.int16
    areas = np.sort(face_areas(part.vertices, part.faces))
    from mdlshapemodel.correspondence.state import PartState

    again = PartState(part.vertices, part.faces.astype(np.int64), part.sphere, part.grid,
                      part.grid_triangles)
    assert again.faces is again.locator.faces and again.faces.dtype == np.int16
    assert np.array_equal(np.sort(face_areas(again.vertices, again.faces)), areas)
