"""Optimisation strategies (section III-D), each recording a convergence trace.

Implemented here:

- ``none``: keep the initial correspondence (the equal-spacing / SPHARM-like baseline);
- ``one-at-a-time`` (III-D3): sweep the examples in random order; for each, draw a kernel position
  uniformly over the shape and a width from the positive half of N(0, sigma_G), and optimise that
  kernel's amplitude (bounded Brent search over log10 A, the paper's suggested 1-D alternative to
  the simplex);
- ``one-at-a-time-pose`` (III-D4): as above, then optimise the example's pose (rotation, translation,
  scale) with the downhill simplex.

Each runs in two phases (III-B): the fixed-Delta objective (eq. 13) first, then the full objective
(eq. 14), each until convergence or its share of the time budget.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from .correspond import CorrespondenceState, Kernel
from .mdl import Objective
from .pose import Pose, pose_from_parameters, weighted_centroid
from .warps import random_width

STRATEGIES = ("none", "one-at-a-time", "one-at-a-time-pose")


class Cancelled(Exception):
    """Raised by a progress callback to stop a long operation; the state so far is kept."""


@dataclass
class Trace:
    """Convergence trace: one row per optimisation step."""

    start_wall: float = field(default_factory=time.perf_counter)
    start_cpu: float = field(default_factory=time.process_time)
    rows: list = field(default_factory=list)

    def record(self, state: CorrespondenceState, value: float, phase: str, sweep: int):
        self.rows.append((time.perf_counter() - self.start_wall, time.process_time() - self.start_cpu,
                          state.evaluations, float(value), phase, sweep))

    HEADER = ("wall_seconds", "cpu_seconds", "evaluations", "objective", "phase", "sweep")


@dataclass
class OptimisationSettings:
    """The knobs of the one-at-a-time strategies (filled from the build configuration)."""

    strategy: str = "one-at-a-time-pose"
    sigma_g: float = 1.0 / 32.0
    max_amplitude: float = 1.0
    max_time: float = 600.0
    fixed_fraction: float = 0.7
    tolerance: float = 0.001
    patience: int = 3
    max_sweeps: int = 10_000
    pose_evaluations: int = 80


def _optimise_amplitude(state: CorrespondenceState, i: int, j: int, kernel: Kernel,
                        current: float, max_amplitude: float, min_amplitude: float = 1e-7
                        ) -> float:
    """Best amplitude for one kernel of part j of example i; commits it when F falls."""
    example = state.examples[i]
    part = example.parts[j]
    cache = {}

    def objective(amplitude: float) -> float:
        trial = Kernel(kernel.center, kernel.omega, float(amplitude))
        positions, points, hint = part.propose_kernel(trial)
        shape = example.pose.apply(example.raw_points({j: points}))
        value = state.value(i, shape)
        cache[float(amplitude)] = (value, trial, positions, points, hint)
        return value

    upper = part.feasible_amplitude(kernel.center, kernel.omega, max_amplitude)
    if upper <= min_amplitude:
        return current
    # Useful amplitudes span decades (a narrow kernel displaces every point by about
    # A (pi - theta) / (1 + A)), so the search is over log10 A.
    minimize_scalar(lambda t: objective(10.0 ** t), method="bounded",
                    bounds=(np.log10(min_amplitude), np.log10(upper)),
                    options={"xatol": 0.02, "maxiter": 25})
    best_value, trial, positions, points, hint = min(cache.values(), key=lambda item: item[0])
    if best_value < current and trial.amplitude > 0:
        part.commit(trial, positions, points, hint)
        state.commit_shape(i)
        return best_value
    return current


def _optimise_pose(state: CorrespondenceState, i: int, current: float, max_evaluations: int
                   ) -> float:
    """Downhill simplex over example i's pose (rotation about its centroid, translation, scale)."""
    example = state.examples[i]
    raw = example.raw_points()
    base = example.pose
    centre = weighted_centroid(base.apply(raw), state.weights)
    size = state.target_size

    def pose_of(parameters: np.ndarray) -> Pose:
        delta = pose_from_parameters(parameters)
        # rotate and scale about the shape's centroid, then translate
        about = Pose(1.0, np.eye(3), centre).compose(delta).compose(Pose(1.0, np.eye(3), -centre))
        return about.compose(base)

    def objective(parameters: np.ndarray) -> float:
        return state.value(i, pose_of(parameters).apply(raw))

    step = np.array([0.02, 0.02, 0.02, 0.02 * size, 0.02 * size, 0.02 * size, 0.01])
    simplex = np.vstack([np.zeros(7), np.diag(step)])
    result = minimize(objective, np.zeros(7), method="Nelder-Mead",
                      options={"initial_simplex": simplex, "maxfev": max_evaluations,
                               "xatol": 1e-6, "fatol": 1e-6})
    if result.fun < current:
        example.pose = pose_of(result.x)
        state.commit_shape(i)
        return float(result.fun)
    return current


def one_at_a_time(state: CorrespondenceState, objective: Objective, settings: OptimisationSettings,
                  rng: np.random.Generator, trace: Trace, phase: str, deadline: float,
                  with_pose: bool, progress=None, checkpoint=None, active=None) -> float:
    """Optimise one example at a time (III-D3/III-D4) until convergence or ``deadline``.

    ``active``: indices of the examples to optimise (default all); the others stay as they are.

    Converged means: for ``patience`` consecutive sweeps, the sweep lowered F by less than
    ``tolerance`` times the total decrease of this phase so far.
    """
    state.objective = objective
    state.rebuild()
    value = state.value()
    start_value = value
    trace.record(state, value, phase, 0)
    quiet_sweeps = 0
    active = np.arange(state.n_shapes) if active is None else np.asarray(active)
    for sweep in range(1, settings.max_sweeps + 1):
        before = value
        for i in rng.permutation(active):
            example = state.examples[i]
            for j in rng.permutation(len(example.parts)):
                part = example.parts[j]
                kernel = Kernel(part.random_surface_parameter(rng),
                                random_width(rng, settings.sigma_g), 0.0)
                value = _optimise_amplitude(state, i, j, kernel, value, settings.max_amplitude)
            if with_pose:
                value = _optimise_pose(state, i, value, settings.pose_evaluations)
            trace.record(state, value, phase, sweep)
            if progress is not None:
                progress(None, f"{phase}: sweep {sweep}, F = {value:.3f}")
            if time.perf_counter() > deadline:
                break
        # new sweep: area weights on the new mean, fresh sums (no drift)
        state.rebuild()
        value = state.value()
        trace.record(state, value, phase, sweep)
        if checkpoint is not None:
            checkpoint()
        if time.perf_counter() > deadline:
            break
        gained = before - value
        total = start_value - value
        quiet_sweeps = quiet_sweeps + 1 if gained <= settings.tolerance * max(total, 1e-12) else 0
        if quiet_sweeps >= settings.patience:
            break
    return value


def optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
             rng: np.random.Generator, trace: Trace, progress=None, checkpoint=None,
             active=None) -> float:
    """Run ``settings.strategy``: the fixed-Delta phase, then the full objective.

    ``objectives`` is (fixed, integrated); ``active`` the indices of the examples to optimise
    (default all). Returns the final value of the full objective.
    Raises :class:`Cancelled` (from ``progress``) with the state left consistent.

    BLAS runs single-threaded meanwhile: the objective's linear algebra is on n_s x n_s matrices,
    where threaded BLAS costs more than it gains (measured: a 40 x 40 eigh takes 0.2 ms on one
    thread and 7 ms on two when another process is busy on the second core).
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _optimise(state, objectives, settings, rng, trace, progress, checkpoint, active)


def _optimise(state: CorrespondenceState, objectives: tuple, settings: OptimisationSettings,
              rng: np.random.Generator, trace: Trace, progress, checkpoint, active) -> float:
    fixed, integrated = objectives
    start = time.perf_counter()
    if settings.strategy == "none":
        state.objective = integrated
        value = state.value()
        trace.record(state, value, "integrated", 0)
        return value
    if settings.strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {settings.strategy!r}")
    with_pose = settings.strategy == "one-at-a-time-pose"
    state.objective = integrated
    initial_value = state.value()
    initial = state.snapshot()
    try:
        if settings.fixed_fraction > 0:
            one_at_a_time(state, fixed, settings, rng, trace, "fixed",
                          start + settings.fixed_fraction * settings.max_time, with_pose,
                          progress, checkpoint, active)
        value = one_at_a_time(state, integrated, settings, rng, trace, "integrated",
                              start + settings.max_time, with_pose, progress, checkpoint, active)
    finally:
        state.objective = integrated
    if value > initial_value:
        # The fixed-Delta phase optimises another function; with a short budget the full
        # objective may end above its start. Never return a worse correspondence than the start.
        state.restore(initial)
        value = state.value()
        trace.record(state, value, "restored-initial", trace.rows[-1][5] if trace.rows else 0)
    return value
