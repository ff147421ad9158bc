"""Optimisation strategies (section III-D), each recording a convergence trace.

Implemented here:

- ``none``: keep the initial correspondence (the equal-spacing / SPHARM-like baseline);
- ``one-at-a-time`` (III-D3): sweep the examples in random order; for each, draw a kernel position
  uniformly over the shape and a width from the positive half of N(0, sigma_G), and optimise that
  kernel's amplitude (bounded Brent search over log10 A, the paper's suggested 1-D alternative to
  the simplex);
- ``one-at-a-time-pose`` (III-D4): as above, then optimise the example's pose (rotation, translation,
  scale) with the downhill simplex;
- ``multiresolution`` (III-D1): level k = 0, 1, ... places kernels of width omega_1 / 2**k
  (omega_1 = 0.25, Table I) at the vertices of a coarse icosphere (12 at level 0, then the 30, 120,
  480, ... vertices that the next subdivision adds halfway between the earlier ones), the same
  positions in every active example and part; the amplitudes of one level, for all examples at
  once, are optimised by the downhill simplex and then fixed;
- ``multiscale`` (III-D2): each iteration draws one kernel per active example and part (position
  uniform over the surface by area, width from the positive half of N(0, sigma_G)) and optimises
  their amplitudes together by the downhill simplex; accepted kernels are fixed.

In the simplex strategies a trial amplitude is clipped into [0, A_max(kernel)], A_max being the
largest amplitude that flips no sampling-grid triangle when the kernel alone is applied to the
positions at the start of the level/iteration (``PartState.feasible_amplitude``); a trial whose
*composed* kernels still flip a grid triangle scores +inf (so every accepted warp is a
homeomorphism on the grid). The kernels of one level are composed in a fixed order (the order of
their centres). F of a trial is computed from the full covariance of the trial shapes
(:func:`_population_value`), since all examples change at once.

Each runs in two phases (III-B): the fixed-Delta objective (eq. 13) first, then the full objective
(eq. 14), each until convergence or its share of the time budget.

The trace has a row at the start of each phase and after each example (one-at-a-time) or
level/iteration (simplex strategies), plus the row after each rebuild. With
``OptimisationSettings.trace_improvements`` it also has a row whenever a trial inside a step (the
amplitude search, the pose simplex, the amplitude simplex) beats the best F so far, i.e. the value
that the step would commit if stopped there: convergence curves at the resolution of single
evaluations, which eq. (19) needs when one strategy is hundreds of times slower than another
(:mod:`mdlshapemodel.convergence`). Recording does not change the optimisation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from .correspond import CorrespondenceState, Kernel
from .mdl import Objective
from .pose import Pose, pose_from_parameters, weighted_centroid
from .sampling import icosphere
from .warps import apply_symmetric_theta, random_width

STRATEGIES = ("none", "one-at-a-time", "one-at-a-time-pose", "multiresolution", "multiscale",
              "fast")


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
    # the simplex strategies (III-D1, III-D2)
    omega_1: float = 0.25          # multiresolution: width of the level-0 kernels (Table I)
    max_levels: int = 4            # multiresolution: levels per phase (12, 30, 120, 480 kernels)
    simplex_step: float = 0.25     # initial simplex edge, as a fraction of each kernel's A_max
    simplex_evaluations: int = 0   # evaluations per simplex run; 0: 200 x its parameters
    # trace a row whenever a trial inside a step beats the best F so far (not only after each
    # example / iteration): convergence curves at the resolution of single evaluations
    trace_improvements: bool = False


def stalled(before: float, value: float, start_value: float, settings: OptimisationSettings
            ) -> bool:
    """Whether the last sweep gained less than ``tolerance`` times the phase's total gain."""
    return before - value <= settings.tolerance * max(start_value - value, 1e-12)


def _improvements(current: float, report):
    """Wrap ``report(value)`` (or None) to be called only when a trial beats the best so far."""
    if report is None:
        return lambda value: None
    best = [current]

    def seen(value: float):
        if value < best[0]:
            best[0] = value
            report(value)
    return seen


def _optimise_amplitude(state: CorrespondenceState, i: int, j: int, kernel: Kernel,
                        current: float, max_amplitude: float, min_amplitude: float = 1e-7,
                        improved=None) -> float:
    """Best amplitude for one kernel of part j of example i; commits it when F falls.

    ``improved(value)``, if given, is called whenever a trial beats the best F so far."""
    example = state.examples[i]
    part = example.parts[j]
    cache = {}
    seen = _improvements(current, improved)

    def objective(amplitude: float) -> float:
        trial = Kernel(kernel.center, kernel.omega, float(amplitude))
        positions, points, hint = part.propose_kernel(trial)
        shape = example.pose.apply(example.raw_points({j: points}))
        value = state.value(i, shape)
        cache[float(amplitude)] = (value, trial, positions, points, hint)
        seen(value)
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


def _optimise_pose(state: CorrespondenceState, i: int, current: float, max_evaluations: int,
                   improved=None) -> float:
    """Downhill simplex over example i's pose (rotation about its centroid, translation, scale).

    ``improved`` as in :func:`_optimise_amplitude`."""
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

    seen = _improvements(current, improved)

    def objective(parameters: np.ndarray) -> float:
        value = state.value(i, pose_of(parameters).apply(raw))
        seen(value)
        return value

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


def _recorder(state: CorrespondenceState, trace: Trace, phase: str, sweep: int,
              settings: OptimisationSettings):
    """``improved(value)`` recording a trace row, if ``settings.trace_improvements``; else None."""
    if not settings.trace_improvements:
        return None
    return lambda value: trace.record(state, value, phase, sweep)


def one_at_a_time(state: CorrespondenceState, objective: Objective, settings: OptimisationSettings,
                  rng: np.random.Generator, trace: Trace, phase: str, deadline: float,
                  with_pose: bool, progress=None, checkpoint=None, active=None) -> float:
    """Optimise one example at a time (III-D3/III-D4) until convergence or ``deadline``.

    ``active``: indices of the examples to optimise (default all); the others stay as they are.

    Converged means: for ``patience`` consecutive sweeps, the sweep lowered F by less than
    ``tolerance`` times the total decrease of this phase so far.
    """
    value = start_value = start_phase(state, objective, trace, phase)
    quiet_sweeps = 0
    active = np.arange(state.n_shapes) if active is None else np.asarray(active)
    for sweep in range(1, settings.max_sweeps + 1):
        before = value
        improved = _recorder(state, trace, phase, sweep, settings)
        for i in rng.permutation(active):
            example = state.examples[i]
            for j in rng.permutation(len(example.parts)):
                part = example.parts[j]
                kernel = Kernel(part.random_surface_parameter(rng),
                                random_width(rng, settings.sigma_g), 0.0)
                value = _optimise_amplitude(state, i, j, kernel, value, settings.max_amplitude,
                                            improved=improved)
            if with_pose:
                value = _optimise_pose(state, i, value, settings.pose_evaluations, improved)
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
        quiet_sweeps = quiet_sweeps + 1 if stalled(before, value, start_value, settings) else 0
        if quiet_sweeps >= settings.patience:
            break
    return value

# ------------------------------------------------------------------------------------------------
# The simplex strategies (III-D1, III-D2): many kernels, of all examples, optimised together


def _population_value(state: CorrespondenceState, shapes: np.ndarray) -> float:
    """F of the population with *every* shape replaced by ``shapes`` (n_s, n_p, 3)."""
    with state.trial_shapes(shapes):
        return state.value()


@dataclass
class _Block:
    """The new kernels of part j of example i (composed in this order) and their amplitude bounds."""

    i: int
    j: int
    centers: list
    omegas: list
    upper: np.ndarray


class _OutOfTime(Exception):
    pass


def _block(state: CorrespondenceState, i: int, j: int, centers, omegas,
           max_amplitude: float, min_amplitude: float = 1e-7) -> _Block | None:
    """The kernels of part j of example i whose feasible amplitude is not negligible (None if none)."""
    part = state.examples[i].parts[j]
    upper = np.array([part.feasible_amplitude(c, w, max_amplitude) for c, w in zip(centers, omegas)])
    keep = upper > min_amplitude
    if not np.any(keep):
        return None
    return _Block(i, j, [c for c, k in zip(centers, keep) if k],
                  [float(w) for w, k in zip(omegas, keep) if k], upper[keep])


def _optimise_amplitudes(state: CorrespondenceState, blocks: list, current: float,
                         settings: OptimisationSettings, deadline: float, progress=None,
                         label: str = "", improved=None) -> float:
    """Downhill simplex over the amplitudes of all ``blocks`` at once; commits when F falls.

    ``improved`` as in :func:`_optimise_amplitude`.

    Trial amplitudes are clipped into [0, A_max] per kernel; a trial whose composed kernels flip a
    grid triangle of its part scores +inf. Stops at the simplex's own tolerance, after
    ``settings.simplex_evaluations`` evaluations (0: 200 per parameter) or at ``deadline``; the best
    trial seen is kept. Returns the new value of F.
    """
    if not blocks:
        return current
    upper = np.concatenate([b.upper for b in blocks])
    offsets = np.cumsum([0] + [len(b.upper) for b in blocks])
    by_example: dict = {}
    for k, b in enumerate(blocks):
        by_example.setdefault(b.i, []).append(k)
    best = {"value": current, "trial": None}
    count = [0]

    def trial_of(x: np.ndarray):
        amplitudes = np.clip(x, 0.0, upper)
        shapes = state.shapes.copy()
        parts = []
        for i, ks in by_example.items():
            example = state.examples[i]
            replace = {}
            for k in ks:
                b = blocks[k]
                part = example.parts[b.j]
                kernels = [Kernel(c, w, float(a)) for c, w, a in
                           zip(b.centers, b.omegas, amplitudes[offsets[k]:offsets[k + 1]]) if a > 0]
                if not kernels:
                    continue
                positions = part.positions
                for kernel in kernels:
                    positions = apply_symmetric_theta(positions, kernel.center, kernel.amplitude,
                                                      kernel.omega)
                if part.folds(positions):
                    return None, None
                points, hint = part.sample(positions)
                replace[b.j] = points
                parts.append((i, part, kernels, positions, points, hint))
            if replace:
                shapes[i] = example.pose.apply(example.raw_points(replace))
        return shapes, parts

    def objective(x: np.ndarray) -> float:
        shapes, parts = trial_of(x)
        if shapes is None:
            return np.inf
        value = _population_value(state, shapes)
        if value < best["value"]:
            best["value"], best["trial"] = value, parts
            if improved is not None:
                improved(value)
        count[0] += 1
        if progress is not None and count[0] % 100 == 0:
            progress(None, f"{label}, {count[0]} evaluations, F = {best['value']:.3f}")
        if time.perf_counter() > deadline:
            raise _OutOfTime
        return value

    n = len(upper)
    simplex = np.vstack([np.zeros(n), np.diag(settings.simplex_step * upper)])
    max_evaluations = settings.simplex_evaluations or 200 * n
    try:
        minimize(objective, np.zeros(n), method="Nelder-Mead",
                 options={"initial_simplex": simplex, "maxfev": max_evaluations,
                          "xatol": 1e-4 * settings.max_amplitude, "fatol": 1e-6})
    except _OutOfTime:
        pass
    if best["trial"] is None:
        return current
    touched = set()
    for i, part, kernels, positions, points, hint in best["trial"]:
        part.kernels.extend(kernels[:-1])
        part.commit(kernels[-1], positions, points, hint)
        touched.add(i)
    for i in sorted(touched):
        state.commit_shape(i)
    return best["value"]


def _active_parts(state: CorrespondenceState, active) -> list:
    active = range(state.n_shapes) if active is None else sorted(int(i) for i in active)
    return [(i, j) for i in active for j in range(len(state.examples[i].parts))]


def start_phase(state: CorrespondenceState, objective: Objective, trace: Trace, phase: str
                ) -> float:
    """Set the phase's objective, rebuild the state, record and return the starting F."""
    state.objective = objective
    state.rebuild()
    value = state.value()
    trace.record(state, value, phase, 0)
    return value


def _end_of_iteration(state: CorrespondenceState, trace: Trace, phase: str, sweep: int,
                      value: float, label: str, progress, checkpoint) -> float:
    """Record the step's F, report it, then new area weights on the new mean and fresh sums (as
    between the sweeps of one_at_a_time); returns F after the rebuild."""
    trace.record(state, value, phase, sweep)
    if progress is not None:
        progress(None, f"{label}: F = {value:.3f}")
    state.rebuild()
    value = state.value()
    trace.record(state, value, phase, sweep)
    if checkpoint is not None:
        checkpoint()
    return value


def multiresolution_levels(omega_1: float, levels: int) -> list:
    """[(omega, centres)] of III-D1: level k has kernels of width omega_1 / 2**k at the vertices that
    the k-th subdivision of the icosahedron adds (level 0: its 12 vertices), i.e. halfway between
    the kernels of the earlier levels."""
    result = []
    previous = 0
    for k in range(levels):
        points, _ = icosphere(k)
        result.append((omega_1 / 2.0 ** k, points[previous:]))
        previous = len(points)
    return result


def multiresolution(state: CorrespondenceState, objective: Objective,
                    settings: OptimisationSettings, trace: Trace, phase: str, deadline: float,
                    progress=None, checkpoint=None, active=None) -> float:
    """III-D1: one downhill simplex per level over the amplitudes of that level's kernels in all
    active examples and parts; the level's amplitudes are then fixed. Stops after
    ``min(max_levels, max_sweeps)`` levels or at ``deadline`` (the ``sweep`` of the trace is the
    level, from 1)."""
    value = start_phase(state, objective, trace, phase)
    parts = _active_parts(state, active)
    levels = multiresolution_levels(settings.omega_1, min(settings.max_levels, settings.max_sweeps))
    for level, (omega, centers) in enumerate(levels, start=1):
        blocks = [_block(state, i, j, centers, [omega] * len(centers), settings.max_amplitude)
                  for i, j in parts]
        blocks = [b for b in blocks if b is not None]
        label = f"{phase}: level {level} ({sum(len(b.upper) for b in blocks)} kernels, " \
                f"omega = {omega:g})"
        value = _optimise_amplitudes(state, blocks, value, settings, deadline, progress, label,
                                     _recorder(state, trace, phase, level, settings))
        value = _end_of_iteration(state, trace, phase, level, value, label, progress, checkpoint)
        if time.perf_counter() > deadline:
            break
    return value


def multiscale(state: CorrespondenceState, objective: Objective, settings: OptimisationSettings,
               rng: np.random.Generator, trace: Trace, phase: str, deadline: float,
               progress=None, checkpoint=None, active=None) -> float:
    """III-D2: each iteration draws one kernel per active example and part (centre uniform over the
    surface by area, width from the positive half of N(0, sigma_G)) and optimises their amplitudes
    together by the downhill simplex; accepted kernels are fixed.

    Converged as in :func:`one_at_a_time`, an iteration playing the part of a sweep: for
    ``patience`` consecutive iterations, the gain was below ``tolerance`` times the total gain of
    this phase; or ``max_sweeps`` iterations, or ``deadline``.
    """
    value = start_value = start_phase(state, objective, trace, phase)
    parts = _active_parts(state, active)
    quiet = 0
    for iteration in range(1, settings.max_sweeps + 1):
        before = value
        blocks = []
        for i, j in parts:
            part = state.examples[i].parts[j]
            center = part.random_surface_parameter(rng)
            omega = random_width(rng, settings.sigma_g)
            block = _block(state, i, j, [center], [omega], settings.max_amplitude)
            if block is not None:
                blocks.append(block)
        label = f"{phase}: iteration {iteration}"
        value = _optimise_amplitudes(state, blocks, value, settings, deadline, progress, label,
                                     _recorder(state, trace, phase, iteration, settings))
        value = _end_of_iteration(state, trace, phase, iteration, value, label, progress,
                                  checkpoint)
        if time.perf_counter() > deadline:
            break
        quiet = quiet + 1 if stalled(before, value, start_value, settings) else 0
        if quiet >= settings.patience:
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
        raise ValueError(f"unknown strategy {settings.strategy!r}; "
                         f"choose one of {', '.join(STRATEGIES)}")

    def phase(objective, name, deadline):
        if settings.strategy == "multiresolution":
            return multiresolution(state, objective, settings, trace, name, deadline, progress,
                                   checkpoint, active)
        if settings.strategy == "fast":
            from .fast import optimise_fast

            return optimise_fast(state, objective, settings, trace, name, deadline, progress,
                                 checkpoint, active)
        if settings.strategy == "multiscale":
            return multiscale(state, objective, settings, rng, trace, name, deadline, progress,
                              checkpoint, active)
        return one_at_a_time(state, objective, settings, rng, trace, name, deadline,
                             settings.strategy == "one-at-a-time-pose", progress, checkpoint,
                             active)

    state.objective = integrated
    initial_value = state.value()
    initial = state.snapshot()
    try:
        if settings.fixed_fraction > 0:
            phase(fixed, "fixed", start + settings.fixed_fraction * settings.max_time)
        value = phase(integrated, "integrated", start + settings.max_time)
    finally:
        state.objective = integrated
    if value > initial_value:
        # The fixed-Delta phase optimises another function; with a short budget the full
        # objective may end above its start. Never return a worse correspondence than the start.
        state.restore(initial)
        value = state.value()
        trace.record(state, value, "restored-initial", trace.rows[-1][5] if trace.rows else 0)
    return value
