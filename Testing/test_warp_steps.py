"""The one-at-a-time strategies with the Appendix warps and the global rotation (``--warps``)."""

import json

import numpy as np
import pytest

from mdlshapemodel.config import BuildConfig
from mdlshapemodel.errors import ConfigError
from mdlshapemodel.prepare.sphere import orientation
from mdlshapemodel.config import WARPS, OptimisationSettings
from mdlshapemodel.correspondence.strategies import optimise
from mdlshapemodel.correspondence.strategies.one_at_a_time import optimise_warp, warp_counts
from mdlshapemodel.correspondence.trace import Trace
from mdlshapemodel.correspondence.warps import ShearTwist

from common import run_cli
from synthetic import build_objectives, small_state, write_population


def unfolded(state) -> bool:
    return all(np.all(orientation(p.positions, triangles) > 0)
               for e in state.examples for p, (_, triangles) in zip(e.parts, state.grids))


def replay(warp, positions):
    return warp.apply(positions)


def run(warps, seed=0, sweeps=2, strategy="one-at-a-time", **options):
    state = small_state()
    settings = OptimisationSettings(strategy=strategy, max_time=1e6, max_sweeps=sweeps,
                                    fixed_fraction=0.0, pose_evaluations=20, warps=warps,
                                    **options)
    trace = Trace()
    final = optimise(state, build_objectives(state), settings, np.random.default_rng(seed), trace)
    return state, trace, final


@pytest.mark.parametrize("kind", WARPS)
def test_each_kind_alone_is_used_lowers_the_objective_and_never_folds(kind):
    state, trace, final = run((kind,))
    counts = warp_counts(state)
    assert counts[kind] > 0
    assert all(n == 0 for k, n in counts.items() if k != kind)
    assert final < trace.rows[0][3]
    assert unfolded(state)
    # the accepted warps are what moved the samples: replaying them on the grid gives the positions
    grid, _ = state.grids[0]
    for example in state.examples:
        positions = grid
        for warp in example.parts[0].warps:
            positions = replay(warp, positions)
        np.testing.assert_allclose(positions, example.parts[0].positions, atol=1e-12)


def test_all_kinds_together_are_each_drawn_and_the_pose_strategy_works_with_them():
    state, trace, final = run(WARPS, seed=0, sweeps=3, strategy="one-at-a-time-pose")
    # the state's record of accepted warps: every kind among them (each has probability 1/4
    # per step), at most one per example and sweep
    counts = warp_counts(state)
    assert set(counts) == set(WARPS) and all(counts.values()), counts
    assert sum(counts.values()) <= 3 * state.n_shapes
    assert final < trace.rows[0][3]
    assert unfolded(state)


def stepping(kind):
    """A small state on eq. 14, its F, a generator and settings drawing only ``kind``."""
    state = small_state()
    state.objective = build_objectives(state)[1]
    return state, state.value(), np.random.default_rng(3), OptimisationSettings(warps=(kind,))


@pytest.mark.parametrize("kind", WARPS)
def test_a_step_never_raises_f_and_leaves_the_state_consistent(kind):
    state, value, rng, settings = stepping(kind)
    for step in range(3 * state.n_shapes):
        i = step % state.n_shapes
        new = optimise_warp(state, i, 0, kind, value, settings, rng)
        assert new <= value
        assert state.value() == pytest.approx(new, rel=1e-9)  # the state holds what was returned
        value = new
    assert unfolded(state)


@pytest.mark.parametrize("kind", WARPS)
def test_each_kind_reports_its_improvements_down_to_the_committed_value(kind):
    """``improved`` hears every trial that beats the best F so far, of every warp kind, ending at
    the value the step commits; a step that commits nothing reports nothing."""
    state, value, rng, settings = stepping(kind)
    accepted = 0
    for step in range(3 * state.n_shapes):
        heard = []
        new = optimise_warp(state, step % state.n_shapes, 0, kind, value, settings, rng,
                             improved=heard.append)
        if new < value:
            accepted += 1
            assert heard and heard[-1] == new
            assert np.all(np.diff([value] + heard) < 0)
        else:
            assert heard == []
        value = new
    assert accepted > 0


def test_warps_that_would_fold_the_grid_are_never_accepted():
    state = small_state()
    part = state.examples[0].parts[0]
    # a quarter-turn twist of a band much narrower than the grid spacing, centred on the ring
    # through a neighbour of the axis point, moves that neighbour alone: triangles turn over
    axis = part.positions[0]
    theta0 = float(np.sort(np.arccos(np.clip(part.positions @ axis, -1, 1)))[1])
    width = 0.01
    folding = ShearTwist(axis, np.pi / 2 * 2 * np.pi * np.tanh(width / 2), width, theta0)
    assert part.folds(folding.apply(part.positions))
    assert part.propose(folding) is None
    # with such bands and large angles allowed, every accepted shear still leaves the grid unfolded
    state, _, _ = run(("shear",), seed=2, sweeps=2, shear_sigma=0.005, max_angle=3.0)
    assert unfolded(state)


class RecordingGenerator:
    """A random generator that records which of its methods are called."""

    def __init__(self, seed):
        self.rng = np.random.default_rng(seed)
        self.calls = set()

    def __getattr__(self, name):
        self.calls.add(name)
        return getattr(self.rng, name)


def test_symmetric_alone_is_the_default_and_draws_no_kind():
    """Only the symmetric kernel: no draw of the kind, so the random stream (and every result of
    a seed) is that of the strategy before other warps could be chosen."""
    assert OptimisationSettings().warps == ("symmetric",)
    assert BuildConfig().warps == ["symmetric"]
    for warps, drawn in ((("symmetric",), False), (("symmetric", "rotation"), True)):
        state = small_state()
        settings = OptimisationSettings(strategy="one-at-a-time", max_time=1e6, max_sweeps=1,
                                        fixed_fraction=0.0, warps=warps)
        rng = RecordingGenerator(0)
        optimise(state, build_objectives(state), settings, rng, Trace())
        assert ("integers" in rng.calls) == drawn


def test_unknown_kind_is_rejected_by_the_strategy():
    with pytest.raises(ValueError, match="warps.*symmetric, asymmetric, shear, rotation"):
        run(("twirl",))


@pytest.mark.parametrize("warps, strategy", [(["twirl"], "one-at-a-time-pose"),
                                             ([], "one-at-a-time-pose"),
                                             (["shear", "shear"], "one-at-a-time"),
                                             (["symmetric", "rotation"], "multiscale")])
def test_config_validation_names_the_field(warps, strategy):
    with pytest.raises(ConfigError, match="^warps: "):
        BuildConfig(warps=warps, strategy=strategy).validate()


def test_config_round_trip_keeps_the_warps():
    config = BuildConfig(warps=["symmetric", "asymmetric", "rotation"],
                         strategy="one-at-a-time-pose").validate()
    assert BuildConfig.from_dict(config.to_dict()).warps == ["symmetric", "asymmetric", "rotation"]
    assert BuildConfig.from_dict({}).warps == ["symmetric"]  # configs written before the option


@pytest.mark.slow
def test_cli_passes_the_warps_to_the_build(tmp_path):
    """The real command line's small builds: config.json holds the warps as given (spaces
    dropped), or the default."""
    inputs = write_population(tmp_path / "inputs", 3)
    small = ["--points", "42", "--max-sweeps", "1", "--baselines", "", "--evaluation-modes", "1",
             "--specificity-samples", "20", "--surface-samples", "2", "--workers", "1", "-q"]
    for output, options, expected in (
            ("given", ["--strategy", "one-at-a-time-pose", "--warps", "symmetric, shear,rotation"],
             ["symmetric", "shear", "rotation"]),
            ("default", [], ["symmetric"])):
        result = run_cli("build", *inputs, "-o", tmp_path / output, *small, *options)
        assert result.returncode == 0, result.stderr
        assert json.loads((tmp_path / output / "config.json").read_text())["warps"] == expected


def test_cli_rejects_bad_warps_with_exit_code_2(tmp_path):
    def build(*options):
        return run_cli("build", tmp_path, "-o", tmp_path / "out", *options, timeout=120)

    unknown = build("--warps", "symmetric,twirl")
    assert unknown.returncode == 2
    assert "unknown warp kind 'twirl'" in unknown.stderr and "Traceback" not in unknown.stderr
    for strategy in ("multiresolution", "fast"):
        wrong_strategy = build("--warps", "rotation", "--strategy", strategy)
        assert wrong_strategy.returncode == 2
        assert "warps:" in wrong_strategy.stderr and "Traceback" not in wrong_strategy.stderr
