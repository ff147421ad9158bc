"""The fast strategy's coarse grid: optimised on fewer sample points, carried over to the build's."""

from __future__ import annotations

import pickle
from dataclasses import replace

import numpy as np
import pytest

from mdlshapemodel.config import BuildConfig, OptimisationSettings
from mdlshapemodel.correspondence.coarse import carry_over, coarse_grid_applies, coarse_view
from mdlshapemodel.correspondence.fields import FieldBasis
from mdlshapemodel.correspondence.sampling import sphere_grid
from mdlshapemodel.correspondence.state import (CorrespondenceState, FixedExample, replay_record,
                                                state_record)
from mdlshapemodel.correspondence.strategies import measured_state, optimise
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.warps import FieldWarp, apply_warps
from mdlshapemodel.errors import ConfigError, InternalError
from mdlshapemodel.parallel import Threads

from resuming import assert_same_record, optimised_with_checkpoints, resumed_from
from synthetic import build_objectives, small_state

STAGED = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=0.5, coarse_points=42,
                              max_sweeps=6)


def test_a_coarse_view_samples_the_same_surfaces_on_its_own_grid():
    state = small_state(points=162)
    coarse = coarse_view(state, 42)
    assert coarse.n_points == 42 and coarse.n_shapes == state.n_shapes
    for example, source in zip(coarse.examples, state.examples):
        part, fine = example.parts[0], source.parts[0]
        assert part.vertices is fine.vertices and part.locator is fine.locator   # shared
        assert np.array_equal(part.positions, part.grid) and len(part.grid) == 42
        # the samples lie on the example's surface where the sphere map sends the grid
        assert np.allclose(part.points, part.sample(part.grid)[0])
    assert coarse.target_size == state.target_size
    assert fine.positions.shape == (162, 3)            # the state's own parts are untouched


def test_carrying_over_gives_the_fine_grid_the_coarse_maps_and_poses():
    state = small_state(points=162)
    coarse = coarse_view(state, 42)
    rng = np.random.default_rng(2)
    for example in coarse.examples:   # a map per part, as a round of the fast strategy commits
        part = example.parts[0]
        basis = FieldBasis.icosphere_level(1, part.positions, 2.0)
        coefficients = rng.uniform(-0.3, 0.3, (basis.n_centres, 3)) * basis.max_coefficient()
        warp = FieldWarp(1, 2.0, coefficients)
        moved = warp.apply(part.positions)
        part.commit(warp, moved, *part.sample(moved))
        example.pose.translation = example.pose.translation + rng.normal(0, 0.1, 3)
    coarse.evaluations = 17
    with Threads(2) as threads:
        assert carry_over(coarse, state, threads) == 0
    assert state.evaluations == 17
    for example, source in zip(state.examples, coarse.examples):
        part = example.parts[0]
        assert part.warps == source.parts[0].warps
        assert np.array_equal(part.positions, apply_warps(part.grid, part.warps))
        assert np.allclose(part.points, part.sample(part.positions)[0])
    # the poses are the coarse ones up to the rescaling every rebuild applies
    ratio = [e.pose.scale / s.pose.scale for e, s in zip(state.examples, coarse.examples)]
    assert np.allclose(ratio, ratio[0])


def test_a_state_set_aside_during_the_coarse_stage_is_carried_over_the_same_bit_for_bit():
    """set_aside drops the samples and X that carry_over makes again: the state carried over
    after it equals, array for array, one that kept them."""
    kept, aside = small_state(points=162), small_state(points=162)
    views = []
    for state in (kept, aside):
        coarse = coarse_view(state, 42)
        moves = np.random.default_rng(3)
        for example in coarse.examples:
            part = example.parts[0]
            basis = FieldBasis.icosphere_level(1, part.positions, 2.0)
            warp = FieldWarp(1, 2.0, moves.uniform(-0.3, 0.3, (basis.n_centres, 3))
                             * basis.max_coefficient())
            moved = warp.apply(part.positions)
            part.commit(warp, moved, *part.sample(moved))
        views.append(coarse)
    aside.set_aside()
    assert aside.shapes is None
    assert all(e.parts[0].points is None for e in aside.examples)
    assert all(e.parts[0].locator is not None for e in aside.examples)   # the surfaces stay
    for coarse, state in zip(views, (kept, aside)):
        carry_over(coarse, state)
    assert_same_record(state_record(aside), state_record(kept))
    np.testing.assert_array_equal(aside.shapes, kept.shapes)
    np.testing.assert_array_equal(aside.weights, kept.weights)
    for mine, theirs in zip(aside.examples, kept.examples):
        np.testing.assert_array_equal(mine.parts[0].hint, theirs.parts[0].hint)
        np.testing.assert_array_equal(mine.parts[0].points, theirs.parts[0].points)


def _field_warps(part, rng, levels=(0, 1, 2)) -> list:
    """Field warps within their bounds on ``part``'s grid, one per level."""
    warps = []
    for level in levels:
        basis = FieldBasis.icosphere_level(level, part.grid, 2.0)
        warps.append(FieldWarp(level, 2.0, rng.uniform(-0.3, 0.3, (basis.n_centres, 3))
                               * basis.max_coefficient()))
    return warps


def test_a_carried_grid_gives_the_fine_parts_what_replaying_the_warps_gives_bit_for_bit():
    replayed, carried = small_state(points=162), small_state(points=162)
    views = {"replayed": coarse_view(replayed, 42), "carried": coarse_view(carried, 42, carry=True)}
    for view in views.values():
        rng = np.random.default_rng(5)
        for example in view.examples:
            part = example.parts[0]
            for warp in _field_warps(part, rng):
                moved = warp.apply(part.positions)
                part.commit(warp, moved, *part.sample(moved))
    assert all(e.parts[0].warps is None and e.parts[0].carried is not None
               for e in views["carried"].examples)
    assert all(len(e.parts[0].warps) == 3 and e.parts[0].carried is None
               for e in views["replayed"].examples)
    # a copy sent to another process (pickled) leaves the carrying to the state's own part
    copied = pickle.loads(pickle.dumps(views["carried"].examples[0].parts[0]))
    assert copied.carried is None and copied.warp_counts()["field"] == 3
    # the checkpoint of the stage holds positions, not field coefficients
    record = state_record(views["carried"])
    assert not any(key.startswith("warp_values") for key in record)
    resumed = coarse_view(small_state(points=162), 42, carry=True)
    replay_record(resumed, record)
    for mine, theirs in zip(resumed.examples, views["carried"].examples):
        np.testing.assert_array_equal(mine.parts[0].carried.positions,
                                      theirs.parts[0].carried.positions)
        assert mine.parts[0].carried.counts == {"field": 3}
    # a checkpoint that lists the warps (a view that kept them) moves the carried grid by them
    listed = coarse_view(small_state(points=162), 42, carry=True)
    replay_record(listed, state_record(views["replayed"]))
    for mine, theirs in zip(listed.examples, views["carried"].examples):
        np.testing.assert_array_equal(mine.parts[0].carried.positions,
                                      theirs.parts[0].carried.positions)
        np.testing.assert_array_equal(mine.parts[0].positions, theirs.parts[0].positions)
    assert carry_over(views["replayed"], replayed) == 0
    assert carry_over(views["carried"], carried) == 0
    for mine, theirs in zip(carried.examples, replayed.examples):
        part, expected = mine.parts[0], theirs.parts[0]
        assert part.warps is None and part.warp_counts() == expected.warp_counts()
        np.testing.assert_array_equal(part.positions, expected.positions)
        np.testing.assert_array_equal(part.points, expected.points)
        np.testing.assert_array_equal(part.hint, expected.hint)
    # its coarse view (where a build measures F) takes the first positions: the same bits as
    # the warps replayed on the coarse grid
    for mine, theirs in zip(coarse_view(carried, 42).examples,
                            coarse_view(replayed, 42).examples):
        np.testing.assert_array_equal(mine.parts[0].positions, theirs.parts[0].positions)
        np.testing.assert_array_equal(mine.parts[0].points, theirs.parts[0].points)
    # a record of the carried-over state replays its positions
    fresh = small_state(points=162)
    replay_record(fresh, state_record(carried))
    assert_same_record(state_record(fresh), state_record(carried))
    with pytest.raises(InternalError, match="first points"):
        carried.examples[0].parts[0].on_grid(*sphere_grid(100))


def test_a_carried_grid_leaves_out_a_warp_that_turns_its_triangle_over_and_those_after_it():
    state = small_state(points=162)
    view = coarse_view(state, 42, carry=True)
    part, fine = view.examples[0].parts[0], state.examples[0].parts[0]
    basis = FieldBasis.icosphere_level(2, fine.grid, 2.0)
    gentle = FieldWarp(2, 2.0, np.full((basis.n_centres, 3), 0.2 * basis.max_coefficient()))
    violent = FieldWarp(2, 2.0, np.random.default_rng(0).normal(0, 2.0, (basis.n_centres, 3)))
    for warp in (gentle, violent, gentle):
        moved = warp.apply(part.positions)
        part.commit(warp, moved, *part.sample(moved))
    assert fine.take_carried(part.carried) == 2
    np.testing.assert_array_equal(fine.positions, gentle.apply(fine.grid))
    assert fine.warp_counts()["field"] == 1 and not fine.folds(fine.positions)


def test_a_warp_that_turns_a_fine_grid_triangle_over_is_left_out_with_the_ones_after_it():
    state = small_state(points=162)
    part = state.examples[0].parts[0]
    basis = FieldBasis.icosphere_level(2, part.grid, 2.0)
    gentle = FieldWarp(2, 2.0, np.full((basis.n_centres, 3), 0.2 * basis.max_coefficient()))
    violent = FieldWarp(2, 2.0, np.random.default_rng(0).normal(0, 2.0, (basis.n_centres, 3)))
    assert part.folds(violent.apply(gentle.apply(part.grid)))
    assert part.replay_unfolded([gentle, violent, gentle]) == 1
    assert part.warps == [gentle] and not part.folds(part.positions)


def test_the_staged_optimisation_runs_both_objectives_on_the_coarse_grid_and_carries_them_over():
    state = small_state(points=162)
    objectives = build_objectives(state)
    start = measured_state(state, STAGED, objective=objectives[1]).value()
    trace = Trace()
    final = optimise(state, objectives, STAGED, np.random.default_rng(0), trace)
    phases = list(dict.fromkeys(row.phase for row in trace.rows))
    assert phases == ["coarse fixed", "coarse integrated"]
    assert final < start
    # the value returned is eq. 14 of the carried-over state, measured on the coarse grid
    assert final == pytest.approx(measured_state(state, STAGED, objective=objectives[1]).value(),
                                  rel=1e-9)
    # every part's map is the positions its coarse part carried, counted by kind, no warps
    for example in state.examples:
        part = example.parts[0]
        assert part.warps is None and part.warp_counts()["field"] > 0
        assert not np.array_equal(part.positions, part.grid)
        assert np.allclose(part.points, part.sample(part.positions)[0])
    assert [row.evaluations for row in trace.rows] == sorted(row.evaluations for row in trace.rows)


def test_the_objective_is_measured_where_the_optimisation_starts_from():
    state = small_state(points=162)
    objectives = build_objectives(state)
    settings = replace(STAGED, fixed_fraction=0.0, max_sweeps=1)
    view = measured_state(state, settings, objective=objectives[1])
    assert view.n_points == 42 and measured_state(state, replace(settings, coarse_points=0)) is state
    trace = Trace()
    optimise(state, objectives, settings, np.random.default_rng(0), trace)
    first = trace.rows[0]
    assert (first.phase, first.sweep) == ("coarse integrated", 0)
    assert first.objective == pytest.approx(view.value(), rel=1e-12)


def test_a_coarse_view_keeps_the_poses_and_the_given_points_of_a_nested_grid():
    state = small_state(points=162)
    rng = np.random.default_rng(3)
    for example in state.examples:
        example.pose.translation = example.pose.translation + rng.normal(0, 0.2, 3)
    state.rebuild()
    view = coarse_view(state, 42)
    for example, source in zip(view.examples, state.examples):
        assert np.allclose(example.pose.rotation, source.pose.rotation)
    given = CorrespondenceState([FixedExample(e.name, e.raw_points()) for e in state.examples],
                                state.grids)
    fixed_view = coarse_view(given, 42)
    grid, _ = sphere_grid(42)
    assert np.array_equal(grid, state.grids[0][0][:42])      # nested icospheres
    for example, source in zip(fixed_view.examples, given.examples):
        assert np.array_equal(example.points, source.points[:42])
    fibonacci = CorrespondenceState([FixedExample(e.name, e.raw_points()[:100])
                                     for e in state.examples], [sphere_grid(100)])
    with pytest.raises(ValueError, match="not the first points"):
        coarse_view(fibonacci, 42)


def test_no_coarse_stage_where_it_cannot_help():
    state = small_state(points=162)
    assert coarse_grid_applies(state, 42) and not coarse_grid_applies(state, 162)
    assert not coarse_grid_applies(state, 0)
    for settings in (OptimisationSettings(strategy="fast", max_time=1e6, max_sweeps=2,
                                          coarse_points=0),                 # switched off
                     OptimisationSettings(strategy="one-at-a-time", max_time=1e6, max_sweeps=1,
                                          coarse_points=42)):                # not the fast one
        trace = Trace()
        fresh = small_state(points=162)
        optimise(fresh, build_objectives(fresh), settings, np.random.default_rng(0), trace)
        assert not any(row.phase.startswith("coarse") for row in trace.rows)
        assert "integrated" in {row.phase for row in trace.rows}
    with pytest.raises(ConfigError, match="coarse_points"):
        BuildConfig(coarse_points=5).validate()


def test_resumed_from_any_checkpoint_of_either_stage_it_ends_as_the_uninterrupted_run():
    state = small_state(points=162)
    final, trace, saved = optimised_with_checkpoints(state, STAGED)
    expected = state_record(state)
    phases = [point.phase for point, *_ in saved]
    assert {"coarse fixed", "coarse integrated"} <= set(phases)
    # the first checkpoint of each phase, the last of the coarse integrated one, and the end
    chosen = [saved[phases.index("coarse fixed")], saved[phases.index("coarse integrated")],
              saved[len(phases) - 1 - phases[::-1].index("coarse integrated")], saved[-1]]
    for entry in chosen:
        resumed = small_state(points=162)
        value, resumed_trace = resumed_from(resumed, STAGED, entry)
        assert value == final, (entry[0].phase, entry[0].sweep)
        assert_same_record(state_record(resumed), expected)
        assert [r[2:] for r in resumed_trace.rows] == [r[2:] for r in trace.rows]


def test_the_staged_optimisation_gives_the_same_correspondence_on_any_number_of_threads():
    records = []
    for threads in (1, 3):
        state = small_state(points=162)
        settings = OptimisationSettings(strategy="fast", max_time=1e6, fixed_fraction=0.5,
                                        coarse_points=42, max_sweeps=4, threads=threads)
        optimise(state, build_objectives(state), settings, np.random.default_rng(0), Trace())
        records.append(state_record(state))
    assert_same_record(*records)
