"""Convergence-rate comparison of strategies (section IV-A, eq. 19): f_A(t) = a + b f_B(alpha t)."""

import math
import warnings

import numpy as np
import pytest

from mdlshapemodel.prepare import io
from mdlshapemodel.model.convergence import (common_grid, compare_strategies, fit_alpha, mean_curve,
                                       read_trace, scaling_gradient, scaling_study, trace_curve)
from mdlshapemodel.errors import InputError
from mdlshapemodel.correspondence.trace import Trace


def f_b(t, tau=20.0):
    """Reference convergence curve: 100 exp(-t / tau) + 5."""
    return 100.0 * np.exp(-np.asarray(t, dtype=float) / tau) + 5.0


def noisy_trials(rng, n, alpha, a=0.0, b=1.0, end=200.0, samples=600, noise=0.3, spread=0.1):
    """Trials of a strategy whose mean curve is a + b f_B(alpha t) in expectation.

    Each trial runs at its own speed (time scale exp(N(0, spread))) and has additive noise; the
    speeds have the same distribution for every strategy, so the mean curves of two strategies
    satisfy eq. (19) with the given alpha, a and b.
    """
    trials = []
    for _ in range(n):
        t = np.sort(rng.uniform(0.0, end, samples))
        t[0], t[-1] = 0.0, end
        speed = math.exp(rng.normal(0.0, spread))
        trials.append((t, a + b * f_b(alpha * speed * t) + rng.normal(0.0, noise, samples)))
    return trials


# ----------------------------------------------------------------------------------------------
# fit_alpha on single curves


@pytest.mark.parametrize("alpha", [0.3, 1.0, 4.0])
@pytest.mark.parametrize("criterion", ["relative", "absolute"])
def test_exact_relation_recovers_alpha_a_b(alpha, criterion):
    t = np.linspace(0.0, 200.0, 2001)
    fit, a, b, residual = fit_alpha(t, 3.0 + 0.5 * f_b(alpha * t), t, f_b(t), criterion=criterion)
    assert fit == pytest.approx(alpha, rel=1e-5)
    assert a == pytest.approx(3.0, abs=1e-3)
    assert b == pytest.approx(0.5, rel=1e-4)
    assert residual < 1e-6


def test_alpha_above_one_means_a_converges_faster():
    """The paper's convention: A at t matches B at alpha t, so alpha > 1 when A is faster."""
    t = np.linspace(0.0, 200.0, 2001)
    faster = f_b(4.0 * t)  # reaches at t what f_B reaches at 4 t
    assert np.all(faster[1:] < f_b(t)[1:])
    alpha, a, b, _ = fit_alpha(t, faster, t, f_b(t))
    assert alpha == pytest.approx(4.0, rel=1e-5)
    slower, _, _, _ = fit_alpha(t, f_b(t), t, faster)
    assert slower == pytest.approx(0.25, rel=1e-5)


def test_swapping_the_curves_inverts_the_relation():
    t = np.linspace(0.0, 150.0, 1201)
    values_a = 3.0 + 0.5 * f_b(2.5 * t)
    alpha, a, b, _ = fit_alpha(t, values_a, t, f_b(t))
    inverse, a_inv, b_inv, _ = fit_alpha(t, f_b(t), t, values_a)
    assert inverse == pytest.approx(1.0 / alpha, rel=1e-6)
    assert b_inv == pytest.approx(1.0 / b, rel=1e-4)
    assert a_inv == pytest.approx(-a / b, abs=1e-3)


@pytest.mark.parametrize("alpha", [0.3, 1.0, 4.0])
def test_partial_overlap_when_b_is_shorter(alpha):
    """B measured only on [5, 40] while A runs to 200: only the overlap counts."""
    t_a = np.linspace(0.0, 200.0, 2001)
    t_b = np.linspace(5.0, 40.0, 351)
    fit, a, b, _ = fit_alpha(t_a, 3.0 + 0.5 * f_b(alpha * t_a), t_b, f_b(t_b))
    assert fit == pytest.approx(alpha, rel=1e-5)
    assert a == pytest.approx(3.0, abs=1e-3)
    assert b == pytest.approx(0.5, rel=1e-4)


def test_partial_overlap_when_a_is_shorter():
    t_a = np.linspace(0.0, 30.0, 301)
    t_b = np.linspace(0.0, 300.0, 3001)
    fit, a, b, _ = fit_alpha(t_a, 1.0 + 2.0 * f_b(3.0 * t_a), t_b, f_b(t_b))
    assert fit == pytest.approx(3.0, rel=1e-5)
    assert a == pytest.approx(1.0, abs=1e-3)
    assert b == pytest.approx(2.0, rel=1e-4)


def test_step_curves_of_evaluation_counts():
    """Objective after each evaluation, held until the next one (kind="step")."""
    k = np.arange(0.0, 2001.0)

    def slow(t):
        return f_b(t, tau=200.0)

    for alpha in (0.5, 2.0):
        fit, a, b, _ = fit_alpha(k, 3.0 + 0.5 * slow(alpha * k), k, slow(k), kind="step")
        assert fit == pytest.approx(alpha, rel=5e-3)
        assert b == pytest.approx(0.5, rel=5e-3)


def test_repeated_times_keep_the_last_value():
    t = np.linspace(0.0, 200.0, 801)
    values = f_b(2.0 * t)
    # a rebuild records a second value at the same time: only the later one counts
    t_rep = np.insert(t, 100, t[100])
    v_rep = np.insert(values, 100, values[100] + 50.0)  # the earlier value is off
    assert fit_alpha(t_rep, v_rep, t, f_b(t))[0] == pytest.approx(2.0, rel=1e-4)


def test_alpha_at_a_bound_warns():
    t = np.linspace(0.0, 200.0, 2001)
    with pytest.warns(RuntimeWarning, match="end of the search range"):
        alpha, _, _, _ = fit_alpha(t, f_b(4.0 * t), t, f_b(t), bounds=(0.1, 2.0))
    assert alpha == pytest.approx(2.0, rel=1e-6)


def test_bad_curves_are_refused():
    t = np.linspace(0.0, 10.0, 50)
    with pytest.raises(ValueError, match="times but"):
        fit_alpha(t, f_b(t)[:-1], t, f_b(t))
    with pytest.raises(ValueError, match="non-decreasing"):
        fit_alpha(t[::-1], f_b(t), t, f_b(t))
    with pytest.raises(ValueError, match="bounds"):
        fit_alpha(t, f_b(t), t, f_b(t), bounds=(2.0, 1.0))
    with pytest.raises(ValueError, match="kind"):
        fit_alpha(t, f_b(t), t, f_b(t), kind="cubic")
    # B only defined at times no alpha in the bounds can reach from A's range
    far = np.linspace(1e4, 2e4, 50)
    with pytest.raises(ValueError, match="overlap"):
        fit_alpha(t[:10] * 0.01, f_b(t[:10]), far, f_b(far), bounds=(1e-3, 1e3))


# ----------------------------------------------------------------------------------------------
# mean curves


def test_mean_curve_and_common_grid():
    curves = [(np.array([0.0, 10.0]), np.array([10.0, 0.0])),
              (np.array([2.0, 4.0, 8.0]), np.array([6.0, 4.0, 2.0]))]
    grid = common_grid(curves, n=5)
    np.testing.assert_allclose(grid, [2.0, 3.5, 5.0, 6.5, 8.0])
    at = np.array([1.0, 3.0, 6.0, 9.0])
    np.testing.assert_allclose(mean_curve(curves, at), [np.nan, (7.0 + 5.0) / 2, (4.0 + 3.0) / 2,
                                                        np.nan])
    np.testing.assert_allclose(mean_curve(curves, at, kind="step"),
                               [np.nan, (10.0 + 6.0) / 2, (10.0 + 4.0) / 2, np.nan])
    # a run that stopped (converged) keeps its last value
    np.testing.assert_allclose(mean_curve(curves, at, hold_last=True)[-1], (1.0 + 2.0) / 2)
    assert common_grid(curves, n=3, hold_last=True)[-1] == 10.0
    with pytest.raises(ValueError, match="share no time"):
        common_grid([(np.array([0.0, 1.0]), np.ones(2)), (np.array([2.0, 3.0]), np.ones(2))])


def test_log_spaced_common_grid():
    curves = [(np.array([0.0, 1.0, 10.0, 100.0]), np.ones(4)),
              (np.array([0.0, 2.0, 50.0]), np.ones(3))]
    grid = common_grid(curves, n=5, spacing="log")
    assert grid[0] == 0.0 and grid[1] == 2.0 and grid[-1] == pytest.approx(50.0)
    ratios = grid[2:] / grid[1:-1]
    np.testing.assert_allclose(ratios, ratios[0])
    assert common_grid(curves, n=5, spacing="log", hold_last=True)[-1] == pytest.approx(100.0)
    with pytest.raises(ValueError, match="non-negative"):
        common_grid([(np.array([-1.0, 1.0]), np.ones(2))], spacing="log")
    with pytest.raises(ValueError, match="spacing"):
        common_grid(curves, spacing="quadratic")
    with pytest.raises(ValueError, match="more than their first step"):
        common_grid([(np.array([0.0, 5.0]), np.ones(2)), (np.array([0.0, 1.0, 3.0]), np.ones(3))],
                    spacing="log")


def finely_sampled_trials(rng, n, slowdown, end, a=0.0, b=1.0, noise=0.1, spread=0.1):
    """Trials of a strategy ``slowdown`` times slower than f_B, sampled evenly in log t."""
    trials = []
    for _ in range(n):
        t = np.concatenate([[0.0], np.geomspace(1e-3 * slowdown, end, 800)])
        speed = math.exp(rng.normal(0.0, spread))
        trials.append((t, a + b * f_b(speed * t / slowdown) + rng.normal(0.0, noise, t.size)))
    return trials


def test_log_grid_measures_a_strategy_hundreds_of_times_slower():
    """B is 200 times slower than A and its run covers only A's first 25 time units (A's curve
    runs to 2000): a regular grid over A's run has two points there and the fit is pinned far
    from the truth; a log-spaced grid resolves A's early curve and recovers alpha = 200."""
    rng = np.random.default_rng(4)
    trials_a = finely_sampled_trials(rng, 6, 1.0, 2000.0)
    trials_b = finely_sampled_trials(rng, 6, 200.0, 5000.0, a=7.0, b=2.0)
    log = compare_strategies(trials_a, trials_b, n_bootstrap=40, rng=0, spacing="log",
                             n_grid=300)
    assert abs(log["alpha"] - 200.0) < 3 * log["alpha_se"]
    assert log["alpha_se"] < 0.1 * 200.0
    assert log["b"] == pytest.approx(0.5, rel=0.05)
    linear = compare_strategies(trials_a, trials_b, n_bootstrap=5, rng=0, n_grid=200)
    assert abs(linear["alpha"] - 200.0) > 50.0


# ----------------------------------------------------------------------------------------------
# bootstrap over trials


@pytest.mark.parametrize("alpha", [0.5, 3.0])
def test_bootstrap_se_covers_the_true_alpha(alpha):
    rng = np.random.default_rng(19)
    trials_a = noisy_trials(rng, 8, alpha, a=3.0, b=0.5)
    trials_b = noisy_trials(rng, 8, 1.0)
    result = compare_strategies(trials_a, trials_b, n_bootstrap=100, rng=1, n_grid=400)
    assert result["bootstrap"].shape == (100,)
    assert result["n_a"] == result["n_b"] == 8
    assert result["alpha_se"] > 0
    assert result["alpha_se"] == pytest.approx(np.std(result["bootstrap"], ddof=1))
    assert abs(result["alpha"] - alpha) < 3 * result["alpha_se"]
    assert result["b"] == pytest.approx(0.5, rel=0.1)
    assert result["alpha_se"] < 0.1 * alpha


def test_bootstrap_se_matches_the_spread_over_replications():
    """The bootstrap SE estimates the sd of alpha over independent sets of trials."""
    estimates, ses = [], []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        result = compare_strategies(noisy_trials(rng, 6, 2.0, samples=300, noise=1.0, spread=0.15),
                                    noisy_trials(rng, 6, 1.0, samples=300, noise=1.0, spread=0.15),
                                    n_bootstrap=30, rng=seed)
        estimates.append(result["alpha"])
        ses.append(result["alpha_se"])
    spread = np.std(estimates, ddof=1)
    assert 0.5 < np.mean(ses) / spread < 2.0
    assert abs(np.mean(estimates) - 2.0) < 3 * spread / math.sqrt(len(estimates))


def test_relative_criterion_has_no_spurious_extreme_alpha():
    """Noisy, coarsely sampled trials where the per-point squared residual (the paper's sum,
    normalised by the number of points) lets a few bootstrap samples jump to alpha ~ 47: a short,
    nearly straight start of A matched to all of B with b -> 0. The relative criterion does not."""
    rng = np.random.default_rng(9)
    trials_a = noisy_trials(rng, 8, 0.3, a=3.0, b=0.5, samples=150, noise=1.0, spread=0.15)
    trials_b = noisy_trials(rng, 8, 1.0, samples=150, noise=1.0, spread=0.15)
    relative = compare_strategies(trials_a, trials_b, n_bootstrap=30, rng=9)
    assert relative["bootstrap"].max() < 0.4
    assert abs(relative["alpha"] - 0.3) < 3 * relative["alpha_se"] < 0.1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        absolute = compare_strategies(trials_a, trials_b, n_bootstrap=30, rng=9,
                                      criterion="absolute")
    assert absolute["alpha"] == pytest.approx(relative["alpha"], rel=0.01)
    assert absolute["bootstrap"].max() > 10


def test_bootstrap_is_reproducible_with_a_seed():
    rng = np.random.default_rng(5)
    trials_a = noisy_trials(rng, 5, 2.0, samples=200)
    trials_b = noisy_trials(rng, 4, 1.0, samples=200)
    first = compare_strategies(trials_a, trials_b, n_bootstrap=20, rng=42)
    again = compare_strategies(trials_a, trials_b, n_bootstrap=20, rng=np.random.default_rng(42))
    other = compare_strategies(trials_a, trials_b, n_bootstrap=20, rng=43)
    np.testing.assert_array_equal(first["bootstrap"], again["bootstrap"])
    assert first["alpha"] == other["alpha"]  # the estimate itself uses every trial
    assert not np.array_equal(first["bootstrap"], other["bootstrap"])


def test_paired_bootstrap():
    rng = np.random.default_rng(6)
    trials_a = noisy_trials(rng, 5, 2.0, samples=200)
    trials_b = noisy_trials(rng, 5, 1.0, samples=200)
    result = compare_strategies(trials_a, trials_b, n_bootstrap=20, rng=0, paired=True)
    assert result["alpha_se"] > 0
    # a strategy compared with itself, pair by pair, never differs from itself
    same = compare_strategies(trials_a, trials_a, n_bootstrap=10, rng=0, paired=True)
    np.testing.assert_allclose(same["bootstrap"], 1.0, rtol=1e-6)
    # independent draws of the two members of a pair: a genuine spread
    assert compare_strategies(trials_a, trials_a, n_bootstrap=10, rng=0)["alpha_se"] > 0
    with pytest.raises(ValueError, match="equal counts"):
        compare_strategies(trials_a, trials_b[:3], n_bootstrap=2, paired=True)


# ----------------------------------------------------------------------------------------------
# scaling with n_s (Tables II-III)


def test_scaling_gradient_recovers_an_exact_line():
    n_s = np.array([15, 20, 25, 30, 35])
    se = np.full(5, 0.05)
    line = scaling_gradient(n_s, 0.5 + 0.1 * n_s, se)
    assert line["gradient"] == pytest.approx(0.1, rel=1e-12)
    assert line["intercept"] == pytest.approx(0.5, rel=1e-12)
    # weighted least squares with known errors: SE = sigma / sqrt(sum (n - mean n)^2)
    assert line["gradient_se"] == pytest.approx(0.05 / math.sqrt(250.0), rel=1e-12)
    assert line["chi2"] == pytest.approx(0.0, abs=1e-20)
    assert line["dof"] == 3


def test_scaling_gradient_se_is_calibrated():
    rng = np.random.default_rng(7)
    n_s = np.array([15.0, 20, 25, 30, 35])
    se = np.array([0.02, 0.04, 0.05, 0.08, 0.1])  # larger sets, noisier alphas
    fits = [scaling_gradient(n_s, 0.2 + 0.05 * n_s + rng.normal(0.0, se), se)
            for _ in range(4000)]
    gradients = np.array([f["gradient"] for f in fits])
    assert fits[0]["gradient_se"] == pytest.approx(np.std(gradients), rel=0.05)
    assert np.mean(gradients) == pytest.approx(0.05, abs=3 * np.std(gradients) / math.sqrt(4000))
    covered = np.mean(np.abs(gradients - 0.05) < 2 * fits[0]["gradient_se"])
    assert 0.93 < covered < 0.97
    # the weights matter: the precise points pull the line
    unweighted = scaling_gradient(n_s, 0.2 + 0.05 * n_s + np.array([0, 0, 0, 0, 0.5]), se)
    assert abs(unweighted["gradient"] - 0.05) < 0.01


def test_scaling_gradient_without_standard_errors():
    n_s = np.array([15.0, 25, 35])
    line = scaling_gradient(n_s, [1.0, 2.1, 2.9])
    slope, intercept = np.polyfit(n_s, [1.0, 2.1, 2.9], 1)
    assert (line["gradient"], line["intercept"]) == pytest.approx((slope, intercept))
    assert line["gradient_se"] > 0
    with pytest.raises(ValueError, match="distinct"):
        scaling_gradient([15, 15], [1.0, 2.0], [0.1, 0.1])
    with pytest.raises(ValueError, match="positive"):
        scaling_gradient([15, 25], [1.0, 2.0], [0.1, 0.0])


def test_scaling_study_relative_to_a_reference():
    """Strategies slower than the reference by alpha = c + g n_s: the gradients come back."""
    rng = np.random.default_rng(8)
    reference = noisy_trials(rng, 5, 1.0, samples=300)
    truth = {"multiscale": (0.5, 0.2), "one-at-a-time": (0.8, 0.03)}
    runs = {name: {n: noisy_trials(rng, 5, 1.0 / (c + g * n), a=1.0, b=2.0, samples=300,
                                   end=200.0 * (c + g * n))
                   for n in (15, 25, 35)}
            for name, (c, g) in truth.items()}
    study = scaling_study(reference, runs, n_bootstrap=30, rng=3)
    for name, (c, g) in truth.items():
        entry = study[name]
        np.testing.assert_array_equal(entry["n_shapes"], [15, 25, 35])
        expected = c + g * entry["n_shapes"]
        assert np.all(np.abs(entry["alpha"] - expected) < 4 * entry["alpha_se"])
        assert entry["alpha"][0] > 1  # slower than the reference: higher alpha, poorer rate
        assert abs(entry["gradient"] - g) < 4 * entry["gradient_se"]
    assert study["multiscale"]["gradient"] > 3 * study["one-at-a-time"]["gradient"]


# ----------------------------------------------------------------------------------------------
# convergence.csv


def trace_rows(alpha=1.0, a=0.0, b=1.0, steps=400):
    """Rows of a convergence trace in Trace.HEADER order: a fixed phase then the integrated one."""
    rows = []
    for k in range(steps):
        cpu = 0.25 * k
        phase = "fixed" if k < 40 else "integrated"
        value = 1e3 - k if phase == "fixed" else a + b * float(f_b(alpha * cpu))
        rows.append((0.3 * k, cpu, 7 * k, value, phase, k // 10))
    rows.append((0.3 * steps, 0.25 * steps, 7 * steps, 1e4, "coarse integrated", steps // 10))
    return rows


def test_trace_curve_reads_convergence_csv(tmp_path):
    path = tmp_path / "convergence.csv"
    rows = trace_rows()
    io.write_csv(path, Trace.HEADER, rows)
    read = io.read_csv(path)
    times, values = trace_curve(read, time="evaluations", phase="integrated")
    np.testing.assert_array_equal(times, [7.0 * k for k in range(40, 400)])
    np.testing.assert_allclose(values, [r[3] for r in rows[40:400]])
    times, values = trace_curve(read)  # every row, CPU seconds
    assert times.size == len(rows) and values[-1] == 1e4
    np.testing.assert_allclose(times[:3], [0.0, 0.25, 0.5])
    times, _ = trace_curve(read, time="wall_seconds", phase=("fixed", "coarse integrated"))
    assert times.size == 41
    # Trace.rows themselves (tuples in HEADER order) give the same curve
    for got, want in zip(trace_curve(rows, phase="integrated"), trace_curve(read, phase="integrated")):
        np.testing.assert_allclose(got, want)
    np.testing.assert_allclose(read_trace(path)[0], trace_curve(read, phase="integrated")[0])


def test_trace_curve_refuses_bad_traces(tmp_path):
    rows = trace_rows(steps=60)
    with pytest.raises(ValueError, match="time must be"):
        trace_curve(rows, time="seconds")
    with pytest.raises(InputError, match="phase pose"):
        trace_curve(rows, phase="pose")
    with pytest.raises(InputError, match="decreases"):
        trace_curve(rows[::-1])
    path = tmp_path / "convergence.csv"
    io.write_csv(path, ("cpu_seconds", "phase"), [(0.0, "fixed")])
    with pytest.raises(InputError, match="no column"):
        read_trace(path, phase=None)


def test_alpha_from_two_convergence_files(tmp_path):
    """End to end: two runs' convergence.csv files, integrated phase, CPU time."""
    io.write_csv(tmp_path / "a.csv", Trace.HEADER, trace_rows(alpha=2.0, a=4.0, b=0.25))
    io.write_csv(tmp_path / "b.csv", Trace.HEADER, trace_rows(alpha=1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        alpha, a, b, _ = fit_alpha(*read_trace(tmp_path / "a.csv"),
                                   *read_trace(tmp_path / "b.csv"))
    assert alpha == pytest.approx(2.0, rel=1e-3)
    assert (a, b) == pytest.approx((4.0, 0.25), rel=1e-2)
