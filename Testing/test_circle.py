"""Closed 2-D curves in the optimisation: circle warps, CurvePart, planar pose, the length weights,
records, and every strategy on resampled hands (correspondence/circle.py)."""


import numpy as np
import pytest

from mdlshapemodel.config import OptimisationSettings
from mdlshapemodel.correspondence.circle import (CIRCLE_WARP_KINDS, CircleField,
                                                 CircleFieldBasis, CircleKernel, CircleShift,
                                                 CurvePart, apply_circle_kernel, circle_grid,
                                                 curve_state)
from mdlshapemodel.geometry import align, generalized_procrustes
from mdlshapemodel.correspondence.state import replay_record, state_record
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.strategies.fast import FieldRound, gradient_at
from mdlshapemodel.correspondence.strategies.one_at_a_time import (optimise_shift,
                                                                    optimise_warp)
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.warps import (WARP_KINDS, apply_warps, make_warp,
                                                minimum_amplitude)
from mdlshapemodel.prepare.curve import curve_map, resample_curve, segment_lengths
from mdlshapemodel.prepare.curve_io import read_curve

from common import DATA, HANDS
from resuming import assert_same_record, optimised_with_checkpoints, resumed_from
from synthetic import build_objectives

needs_hands = pytest.mark.skipif(not HANDS, reason=f"shared hands not found at {DATA / 'hands2d'}")


def increasing_cyclically(positions) -> bool:
    steps = np.diff(positions, append=positions[0] + 2 * np.pi)
    return bool(np.all(steps > 0))


def blob(n=200, phase=0.0, bump=0.3):
    """A smooth star-shaped closed curve with one bump at angle ``phase``."""
    t = 2 * np.pi * np.arange(n) / n
    radius = 10 + 2 * np.cos(2 * t) + 10 * bump * np.exp(-8 * (1 - np.cos(t - phase)))
    return np.stack([radius * np.cos(t), radius * np.sin(t)], axis=1)


def blobs_state(count=5, n_points=32):
    rng = np.random.default_rng(1)
    curves = [resample_curve(blob(phase=0.3 * k, bump=0.2 + 0.05 * k), 150, rng.random())
              for k in range(count)]
    return curve_state(curves, [f"blob_{k}" for k in range(count)], n_points)


def hands_state(count=6, n_points=48, seed=0):
    """The first ``count`` shared hands, each resampled at arc length from a random start (they
    come in correspondence), as a curve state."""
    rng = np.random.default_rng(seed)
    curves = [resample_curve(read_curve(path), 300, rng.random()) for path in HANDS[:count]]
    return curve_state(curves, [path.stem for path in HANDS[:count]], n_points)


# ------------------------------------------------------------------------------------------------
# Warps of the circle


def test_circle_grid_is_equally_spaced_with_cyclic_segments():
    angles, segments = circle_grid(16)
    np.testing.assert_allclose(np.diff(angles), 2 * np.pi / 16)
    assert segments.shape == (16, 2) and segments[-1].tolist() == [15, 0]
    with pytest.raises(ValueError):
        circle_grid(4)


def test_circle_kernels_are_monotone_fix_centre_and_antipode_and_invert(rng):
    t = np.sort(rng.uniform(-2 * np.pi, 4 * np.pi, 3000))
    for _ in range(200):
        center, omega = rng.uniform(-10, 10), float(np.exp(rng.uniform(np.log(1e-3), 1.0)))
        low = minimum_amplitude(omega)
        amplitude = float(rng.choice([rng.uniform(0, 5), rng.uniform(0, 1e3),
                                      low + (1e-3 - low) * rng.random()]))
        kernel = CircleKernel(center, amplitude, omega)
        moved = kernel.apply(t)
        assert np.all(np.diff(moved) > 0)
        # a lift of a circle map: one turn on is one turn on
        np.testing.assert_allclose(kernel.apply(t + 2 * np.pi), moved + 2 * np.pi, atol=1e-9)
        fixed = np.array([center, center + np.pi])
        np.testing.assert_allclose(kernel.apply(fixed), fixed, atol=1e-9)
        np.testing.assert_allclose(kernel.inverse(moved), t, atol=1e-9)
    # a positive amplitude pushes points away from the centre (the samples thin out there), as
    # the sphere's kernel does
    assert 0.5 < apply_circle_kernel(np.array([0.5]), 0.0, 2.0, 0.3)[0] < np.pi


def test_every_circle_warp_round_trips_through_its_vector_exactly(rng):
    basis = CircleFieldBasis(1, 2.0, circle_grid(40)[0])
    warps = [CircleKernel(rng.normal(), 0.7, 0.2), CircleShift(rng.normal()),
             CircleField(1, 2.0, 0.1, rng.uniform(-1, 1, 16) * basis.max_coefficient())]
    assert {w.kind for w in warps} == set(CIRCLE_WARP_KINDS) and set(CIRCLE_WARP_KINDS) <= \
        set(WARP_KINDS)
    t = circle_grid(40)[0]
    for warp in warps:
        again = WARP_KINDS[warp.kind].from_vector(warp.to_vector())
        assert np.array_equal(again.to_vector(), warp.to_vector())
        assert np.array_equal(again.apply(t), warp.apply(t))
        np.testing.assert_allclose(make_warp(warp.kind, warp.parameters()).apply(t),
                                   warp.apply(t), atol=0)
    np.testing.assert_allclose(warps[1].inverse(warps[1].apply(t)), t, atol=1e-14)


def test_circle_fields_within_their_bound_are_monotone(rng):
    t = circle_grid(500)[0]
    for level in range(4):
        basis = CircleFieldBasis(level, 2.0, t)
        bound = basis.max_coefficient()
        for _ in range(20):
            coefficients = rng.choice([-bound, bound], basis.n_centres)
            moved = basis.apply(coefficients, rng.normal())
            assert increasing_cyclically(moved)
            assert moved[-1] - moved[0] < 2 * np.pi
    # far beyond the bound a field folds
    basis = CircleFieldBasis(3, 2.0, t)
    assert not increasing_cyclically(basis.apply(np.tile([-50, 50], 32) * basis.max_coefficient()))


# ------------------------------------------------------------------------------------------------
# CurvePart and the state


def test_folds_detects_a_swapped_pair_and_accepts_lifts_and_wrapped_angles():
    part = CurvePart(curve_map(blob()), *circle_grid(24))
    positions = part.positions
    assert not part.folds(positions)
    assert not part.folds(positions + 7.0)                     # a shifted lift
    assert not part.folds(np.mod(positions + 3.0, 2 * np.pi))  # the same, wrapped
    swapped = positions.copy()
    swapped[[5, 6]] = swapped[[6, 5]]
    assert part.folds(swapped)
    assert part.folds(positions * 2)                          # winds twice


def test_samples_are_on_the_curve_in_order_with_z_zero():
    curve = blob()
    part = CurvePart(curve_map(curve), *circle_grid(50))
    assert part.points.shape == (50, 3) and np.all(part.points[:, 2] == 0)
    # every sample lies on the segment of the curve it was located in
    a = curve[part.hint]
    b = curve[(part.hint + 1) % len(curve)]
    cross = (b - a)[:, 0] * (part.points[:, 1] - a[:, 1]) - \
        (b - a)[:, 1] * (part.points[:, 0] - a[:, 0])
    assert np.all(np.abs(cross) < 1e-9)
    # equal arc length between consecutive samples
    assert np.all(np.diff(part.hint) >= 0)
    tangent = part.tangent(part.hint)
    np.testing.assert_allclose(np.linalg.norm(tangent[:, :2], axis=1),
                               segment_lengths(curve).sum() / (2 * np.pi), rtol=1e-12)


def test_the_curve_state_is_planar_with_length_weights():
    state = blobs_state()
    assert state.planar
    assert np.all(state.shapes[:, :, 2] == 0)
    for example in state.examples:
        assert np.allclose(example.pose.rotation[2], [0, 0, 1]) and example.pose.translation[2] == 0
    mean = state.shapes.mean(axis=0)
    lengths = np.linalg.norm(np.roll(mean, -1, axis=0) - mean, axis=1)
    expected = 0.5 * (lengths + np.roll(lengths, 1))
    np.testing.assert_allclose(state.weights, expected / expected.sum(), rtol=1e-12)
    assert state.triangles().shape == (32, 2)


def test_planar_procrustes_rotates_a_mirrored_shape_and_never_reflects_it():
    shape = np.column_stack([blob(80, bump=0.5), np.zeros(80)])
    mirrored = shape * [-1, 1, 1]
    weights = np.full(80, 1 / 80)
    # in 3-D the best proper rotation of a mirror image is a half turn out of the plane
    flipped = align(mirrored, shape, weights, planar=False)
    assert flipped.rotation[2, 2] < 0
    pose = align(mirrored, shape, weights, planar=True)
    assert np.linalg.det(pose.rotation) == pytest.approx(1.0)
    np.testing.assert_allclose(pose.rotation[2], [0, 0, 1], atol=0)
    assert np.all(pose.apply(mirrored)[:, 2] == 0)
    # the rotation found is the best one about z: a finite-difference check of optimality
    rotated = np.column_stack([blob(80, bump=0.5) @ np.array([[0.6, -0.8], [0.8, 0.6]]).T,
                               np.zeros(80)])
    best = align(rotated, shape, weights, scaling=False, planar=True)
    np.testing.assert_allclose(best.apply(rotated), shape, atol=1e-9)
    aligned, poses = generalized_procrustes(np.stack([shape, mirrored, rotated]), weights,
                                            planar=True)
    assert np.all(aligned[:, :, 2] == 0)
    assert all(np.linalg.det(p.rotation) > 0 and p.rotation[2, 2] == 1 for p in poses)


def test_a_curve_state_replays_from_its_record():
    state = blobs_state()
    _, integrated = build_objectives(state)
    state.objective = integrated
    value = state.value()
    settings = OptimisationSettings()
    rng = np.random.default_rng(5)
    for i in range(state.n_shapes):
        value = optimise_warp(state, i, 0, "symmetric", value, settings, rng)
    kinds = {w.kind for e in state.examples for w in e.parts[0].warps}
    assert kinds and kinds <= {"circle_kernel", "circle_shift"}
    state.refresh()                 # K from scratch, as a replayed state has it
    record = state_record(state)
    fresh = blobs_state()
    fresh.objective = integrated
    replay_record(fresh, record)
    for a, b in zip(state.examples, fresh.examples):
        assert np.array_equal(a.parts[0].positions, b.parts[0].positions)
        assert np.array_equal(a.parts[0].points, b.parts[0].points)
    assert fresh.value() == state.value()


def test_a_shift_step_undoes_a_misplaced_origin():
    rng = np.random.default_rng(4)
    curves = [blob(bump=0.3 + 0.02 * rng.normal()) * rng.uniform(0.95, 1.05, 2)
              for _ in range(5)]
    curves[2] = np.roll(curves[2], 12, axis=0)                 # origin 12 / 200 of a turn on
    state = curve_state(curves, [f"c{k}" for k in range(5)], 40, align_origins=False)
    # Procrustes turns the misplaced curve to fit its wrong correspondence; a shift is searched
    # at a fixed pose (the -pose strategy refits the pose after it): give it its true pose
    state.examples[2].pose = state.examples[0].pose.copy()
    state.rebuild()
    state.objective = build_objectives(state)[1]
    value = state.value()
    part = state.examples[2].parts[0]
    new = optimise_shift(state, 2, 0, part.shift, value, np.pi / 4)
    assert new < value
    assert [w.kind for w in part.warps] == ["circle_shift"]
    # its parameter 0 is the old point 188 (of 200): a shift by the arc length of the last 12
    # segments brings the samples back to the others' points
    lengths = segment_lengths(curves[2])
    expected = 2 * np.pi * lengths[:12].sum() / lengths.sum()
    assert part.warps[0].shift == pytest.approx(expected, abs=0.02)


def test_curves_refuse_the_warps_of_the_sphere():
    state = blobs_state()
    settings = OptimisationSettings(strategy="one-at-a-time", warps=("symmetric", "shear"),
                                    max_sweeps=1)
    with pytest.raises(ValueError, match="symmetric kernel only"):
        optimise(state, build_objectives(state), settings, np.random.default_rng(0), Trace())


# ------------------------------------------------------------------------------------------------
# The fast strategy's gradient and every strategy on hands


def test_the_fast_gradient_on_a_curve_state_matches_finite_differences(rng):
    state = blobs_state()
    state.objective = build_objectives(state)[1]
    round_ = FieldRound(state, range(state.n_shapes), 1, 2.0)
    x = rng.uniform(-0.3, 0.3, round_.size) * np.minimum(round_.limit, 1.0)
    trial = round_.trial(x)
    value, shape_gradient = gradient_at(state, trial.shapes)
    gradient = round_.gradient(trial, shape_gradient)
    free = np.flatnonzero(round_.limit > 0)
    assert len(free) < round_.size          # the out-of-plane pose parameters are held at zero
    for k in rng.choice(free, 25, replace=False):
        step = 1e-6 * max(1.0, abs(x[k]))
        up, down = x.copy(), x.copy()
        up[k] += step
        down[k] -= step
        numeric = (gradient_at(state, round_.trial(up).shapes)[0]
                   - gradient_at(state, round_.trial(down).shapes)[0]) / (2 * step)
        assert gradient[k] == pytest.approx(numeric, rel=2e-3, abs=2e-3 * np.abs(gradient).max())


@needs_hands
@pytest.mark.parametrize("strategy", ["fast", "one-at-a-time", "one-at-a-time-pose", "multiscale",
                                      "multiresolution"])
def test_every_strategy_lowers_the_objective_on_hands_without_folding(strategy):
    state = hands_state()
    settings = OptimisationSettings(strategy=strategy, max_time=1e6, max_sweeps=2,
                                    pose_evaluations=30, fixed_fraction=0.0, max_levels=2,
                                    simplex_evaluations=150)
    trace = Trace()
    final = optimise(state, build_objectives(state), settings, np.random.default_rng(0), trace)
    assert final < trace.rows[0][3]
    assert np.all(state.shapes[:, :, 2] == 0)
    assert any(example.parts[0].warps for example in state.examples)
    for example in state.examples:
        part = example.parts[0]
        assert not part.folds(part.positions) and increasing_cyclically(part.positions)
        assert part.positions[-1] - part.positions[0] < 2 * np.pi
        assert np.allclose(example.pose.rotation[2], [0, 0, 1])
        # the recorded warps, applied to the grid, are the sample positions bit for bit
        assert np.array_equal(apply_warps(part.grid, part.warps), part.positions)


def test_a_two_part_curve_state_is_optimised_with_one_pose_per_example():
    rng = np.random.default_rng(2)
    curves = [[resample_curve(blob(phase=0.2 * k), 120, rng.random()),
               resample_curve(blob(phase=1.0 + 0.1 * k, bump=0.1) * 0.5 + [40, 0], 120,
                              rng.random())] for k in range(5)]
    state = curve_state(curves, [f"pair_{k}" for k in range(5)], [32, 16])
    assert state.planar and state.n_points == 48 and state.triangles().shape == (48, 2)
    assert state.triangles()[32:].min() == 32                  # the second part's segments
    np.testing.assert_allclose(state.weights.sum(), 1.0)
    settings = OptimisationSettings(strategy="fast", max_time=1e6, max_sweeps=3,
                                    fixed_fraction=0.0)
    trace = Trace()
    final = optimise(state, build_objectives(state), settings, np.random.default_rng(0), trace)
    assert final < trace.rows[0][3]
    for example in state.examples:
        assert [p.kind for p in example.parts] == ["circle", "circle"]
        assert all(increasing_cyclically(p.positions) for p in example.parts)


@pytest.mark.parametrize("strategy, sweeps", [("fast", 10_000), ("one-at-a-time-pose", 3),
                                              ("multiscale", 3)])
def test_a_curve_optimisation_resumed_from_a_checkpoint_ends_as_the_uninterrupted_one(strategy,
                                                                                       sweeps):
    settings = OptimisationSettings(strategy=strategy, max_time=1e6, max_sweeps=sweeps,
                                    fixed_fraction=0.5, simplex_evaluations=60,
                                    pose_evaluations=30)
    state = blobs_state()
    final, _, saved = optimised_with_checkpoints(state, settings)
    assert len(saved) >= 3
    resumed = blobs_state()
    value, _ = resumed_from(resumed, settings, saved[len(saved) // 2])
    assert value == final
    assert_same_record(state_record(resumed), state_record(state))
