"""The state records every accepted reparameterization, for every strategy, and a record (the
build's checkpoint) re-applied to a fresh state gives the same correspondence bit for bit."""


import numpy as np
import pytest
from scipy.spatial.transform import Rotation as SpatialRotation

from mdlshapemodel.config import OptimisationSettings
from mdlshapemodel.correspondence.circle import CIRCLE_WARP_KINDS
from mdlshapemodel.correspondence.state import PartState, replay_record, state_record
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.warps import (WARP_KINDS, AsymmetricTheta, FieldWarp, Rotation,
                                                ShearTwist, SymmetricTheta, apply_warps)
from mdlshapemodel.folders import load_checkpoint, save_checkpoint
from mdlshapemodel.outputs import warp_summary

from synthetic import build_objectives, small_state

STRATEGY_KINDS = {
    "fast": {"field"},
    "one-at-a-time-pose": {"symmetric_theta", "asymmetric_theta", "shear_twist", "rotation"},
    "multiresolution": {"symmetric_theta"},
    "multiscale": {"symmetric_theta"},
}


def optimised(strategy):
    state = small_state()
    # the second case's parameterization turned 20 degrees off the aligned one, so that every
    # strategy has a misalignment to undo whatever the initial alignment leaves
    part = state.examples[1].parts[0]
    turn = SpatialRotation.from_rotvec([0.0, 0.0, np.radians(20.0)]).as_matrix()
    state.examples[1].parts[0] = PartState(part.vertices, part.faces, part.sphere @ turn,
                                           part.grid, part.grid_triangles)
    state.refresh()
    options = dict(max_time=1e6, max_sweeps=3, fixed_fraction=0.0, pose_evaluations=20,
                   simplex_evaluations=300, simplex_step=0.1)
    if strategy == "one-at-a-time-pose":
        options["warps"] = ("symmetric", "asymmetric", "shear", "rotation")
    settings = OptimisationSettings(strategy=strategy, **options)
    final = optimise(state, build_objectives(state), settings, np.random.default_rng(4), Trace())
    return state, final


@pytest.mark.parametrize("strategy", sorted(STRATEGY_KINDS))
def test_every_strategy_records_the_warps_that_make_its_positions(strategy):
    state, final = optimised(strategy)
    kinds = {w.kind for e in state.examples for p in e.parts for w in p.warps}
    assert kinds and kinds <= STRATEGY_KINDS[strategy]
    for example in state.examples:
        for part in example.parts:
            # the recorded warps, applied to the grid, are the sample positions bit for bit
            assert np.array_equal(apply_warps(part.grid, part.warps), part.positions)
            # the counts cases.csv reports are those of the recorded warps
            listed = {kind: [w.kind for w in part.warps].count(kind) for kind in WARP_KINDS}
            assert part.warp_counts() == listed
        summary = warp_summary(example)
        assert summary == " ".join(f"{k}:{n}" for k, n in example.parts[0].warp_counts().items()
                                   if n)


@pytest.mark.parametrize("strategy", ["fast", "one-at-a-time-pose"])
def test_a_checkpoint_replayed_on_a_fresh_state_is_the_same_state(strategy, tmp_path):
    state, final = optimised(strategy)
    path = tmp_path / "checkpoint.npz"
    save_checkpoint(path, state)
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.npz"]   # no temporary left
    fresh = small_state()
    fresh.objective = state.objective
    before = fresh.value()
    replay_record(fresh, load_checkpoint(path))
    assert fresh.value() == state.value() == final != before
    assert np.array_equal(fresh.shapes, state.shapes)
    assert np.array_equal(fresh.gram, state.gram)
    for a, b in zip(state.examples, fresh.examples):
        assert np.array_equal(a.pose.rotation, b.pose.rotation) and a.pose.scale == b.pose.scale
        assert np.array_equal(a.parts[0].positions, b.parts[0].positions)


def test_a_record_with_int64_faces_resumes_with_the_parts_own_index_type(tmp_path):
    """A checkpoint whose located faces (the parts' walk hints) are int64, as older builds
    wrote them, gives parts whose hints are in their tables' narrow type, with the same values."""
    state, _ = optimised("fast")
    record = state_record(state)
    hints = [key for key in record if key.startswith("hint_")]
    assert hints and all(record[key].dtype == np.int16 for key in hints)
    path = tmp_path / "old.npz"
    np.savez(path, **{key: (value.astype(np.int64) if key in hints else value)
                      for key, value in record.items()})
    fresh = small_state()
    replay_record(fresh, np.load(path))
    for example, original in zip(fresh.examples, state.examples):
        part = example.parts[0]
        assert part.hint.dtype == part.faces.dtype == np.int16
        assert np.array_equal(part.hint, original.parts[0].hint)


def test_a_record_of_other_cases_is_refused():
    state, _ = optimised("fast")
    record = state_record(state)
    record["names"] = np.array(["x"] * state.n_shapes)
    with pytest.raises(ValueError, match="other cases"):
        replay_record(small_state(), record)


def test_every_warp_kind_round_trips_through_its_vector_exactly(rng):
    center = rng.normal(size=3)
    warps = [SymmetricTheta(center, 0.4, 0.3),
             AsymmetricTheta(center, rng.normal(size=3), 0.5, 0.2, 1.0, 0.7),
             ShearTwist(center, 0.8, 0.4, 1.2), Rotation(rng.normal(size=3) * 0.3),
             FieldWarp(1, 2.0, rng.normal(size=(42, 3)) * 1e-3)]
    # (the circle's kinds: Testing/test_circle.py)
    assert {w.kind for w in warps} == set(WARP_KINDS) - set(CIRCLE_WARP_KINDS)
    points = rng.normal(size=(50, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    for warp in warps:
        again = type(warp).from_vector(warp.to_vector())
        assert np.array_equal(again.to_vector(), warp.to_vector())
        assert np.array_equal(again.apply(points), warp.apply(points))
    with pytest.raises(ValueError):
        SymmetricTheta.from_vector(np.zeros(4))
