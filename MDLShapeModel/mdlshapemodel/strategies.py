"""Optimisation strategies (section III-D), each recording a convergence trace.

Implemented here:

- ``none``: keep the initial correspondence (the equal-spacing / SPHARM-like baseline);
- ``one-at-a-time`` (III-D3): sweep the examples in random order; for each, draw a kernel position
  uniformly over the shape and a width from the positive half of N(0, sigma_G), and optimise that
  kernel's amplitude (bounded Brent search over log10 A, the paper's suggested 1-D alternative to
  the simplex); with ``warps`` beyond ``symmetric``, each step first draws the kind of warp
  uniformly: the Appendix's asymmetric theta map or shear/twist, or a global rotation of the
  parameter sphere, its free parameter(s) optimised by 1-D bounded searches
  (:func:`_optimise_warp`);
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
from dataclasses import replace as changed

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from .correspond import CorrespondenceState, Kernel
from .mdl import Objective
from .pose import Pose, pose_from_parameters, weighted_centroid
from .sampling import icosphere
from .warps import (Rotation, apply_symmetric_theta, random_asymmetric_theta, random_shear_twist,
                    random_unit_vector, random_width)

STRATEGIES = ("none", "one-at-a-time", "one-at-a-time-pose", "multiresolution", "multiscale",
              "fast")
# Warp kinds a one-at-a-time step can draw: the symmetric theta kernel (III-A), the Appendix's
# asymmetric theta transformation and shear/twist, and a global rotation of the parameter sphere.
WARPS = ("symmetric", "asymmetric", "shear", "rotation")
WARP_STRATEGIES = ("one-at-a-time", "one-at-a-time-pose")


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
    # the one-at-a-time strategies: warp kinds drawn (uniformly) per step, see _optimise_warp
    warps: tuple = ("symmetric",)
    max_angle: float = np.pi / 4   # largest rotation, and peak shear/twist angle, of one step
    shear_sigma: float = 0.25      # shear/twist band widths c: positive half of N(0, this)


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


def _search_warp(state: CorrespondenceState, i: int, j: int, warp_of, bounds: tuple,
                 log_scale: bool, xatol: float, maxiter: int, found: list, seen):
    """Bounded Brent search of F over one parameter t of a warp of part j of example i.

    ``warp_of(t)`` is the warp at parameter t (10**t when ``log_scale``); every trial that flips a
    grid triangle scores +inf and is never kept. Each unfolded trial is appended to ``found`` as
    (F, warp, (positions, points, hint)) and passed to ``seen(F)`` (:func:`_improvements`).
    Nothing is committed.
    """
    example = state.examples[i]
    part = example.parts[j]

    def objective(t: float) -> float:
        warp = warp_of(10.0 ** t if log_scale else float(t))
        proposal = part.propose_warp(warp)
        if proposal is None:
            return np.inf
        value = state.value(i, example.pose.apply(example.raw_points({j: proposal[1]})))
        found.append((value, warp, proposal))
        seen(value)
        return value

    minimize_scalar(objective, method="bounded", bounds=bounds,
                    options={"xatol": xatol, "maxiter": maxiter})


def _commit_best(state: CorrespondenceState, i: int, j: int, found: list, current: float
                 ) -> float:
    """Commit the best trial of ``found`` when it lowers F; return the new F."""
    if not found:
        return current
    value, warp, proposal = min(found, key=lambda item: item[0])
    if value < current:
        state.examples[i].parts[j].commit(warp, *proposal)
        state.commit_shape(i)
        return value
    return current


def _signed_bounds(part, move, cap: float, min_parameter: float) -> tuple | None:
    """[-low, high]: the unfolded range of a signed warp parameter within [-cap, cap], from one
    bisection per sign (:meth:`PartState.feasible_parameter`); None when both sides are negligible."""
    high = part.feasible_parameter(move, cap)
    low = part.feasible_parameter(lambda t: move(-t), cap)
    if max(low, high) <= min_parameter:
        return None
    return -low, high


def _optimise_warp(state: CorrespondenceState, i: int, j: int, kind: str, current: float,
                   settings: OptimisationSettings, rng: np.random.Generator,
                   min_amplitude: float = 1e-7, improved=None) -> float:
    """One step of the one-at-a-time strategies on part j of example i with a warp of ``kind``.

    - ``symmetric``: a random kernel (centre uniform over the surface, omega from sigma_G), its
      amplitude optimised by :func:`_optimise_amplitude`, as in the paper;
    - ``asymmetric`` (Appendix eq. 27-29): centre and omega drawn as for the symmetric kernel,
      psi0 uniform, b log-uniform on [0.1, 2] (:func:`warps.random_asymmetric_theta`); A0 >= 0 is
      searched over log10 A0 up to the amplitude whose peak A(psi0) = ``max_amplitude`` (or less,
      so that no grid triangle flips); if that lowers F, psi0 is then searched over +-pi at the
      best A0;
    - ``shear`` (Appendix eq. 30-31): axis point uniform over the surface, band centre theta0 with
      cos theta0 uniform, band width c from the positive half of N(0, ``shear_sigma``); the signed
      amplitude B is searched (linearly) over the range in which the peak twist angle is at most
      ``max_angle`` and no grid triangle flips;
    - ``rotation``: a global rotation of the part's parameter sphere about a random axis (uniform
      on the sphere), its signed angle searched over [-max_angle, max_angle]. One axis per step:
      over the steps the random axes cover all three angles.

    Every trial that flips a grid triangle is rejected; the best trial is committed only if it
    lowers F. Returns the new F.
    """
    part = state.examples[i].parts[j]
    positions = part.positions
    if kind == "symmetric":
        kernel = Kernel(part.random_surface_parameter(rng), random_width(rng, settings.sigma_g),
                        0.0)
        return _optimise_amplitude(state, i, j, kernel, current, settings.max_amplitude,
                                   min_amplitude, improved)
    found: list = []
    seen = _improvements(current, improved)
    if kind == "asymmetric":
        base = random_asymmetric_theta(rng, settings.sigma_g,
                                       center=part.random_surface_parameter(rng))
        cap = settings.max_amplitude * np.sinh(base.b) / 2.0   # peak amplitude = max_amplitude
        upper = part.feasible_parameter(
            lambda a: changed(base, amplitude=a).apply(positions), cap)
        if upper <= min_amplitude:
            return current
        _search_warp(state, i, j, lambda a: changed(base, amplitude=a),
                     (np.log10(min_amplitude), np.log10(upper)), True, 0.02, 25, found, seen)
        value, best, _ = min(found, key=lambda item: item[0], default=(np.inf, None, None))
        if value < current:
            _search_warp(state, i, j, lambda d: changed(best, psi0=best.psi0 + d),
                         (-np.pi, np.pi), False, 0.02, 15, found, seen)
    elif kind == "shear":
        base = random_shear_twist(rng, settings.shear_sigma,
                                  center=part.random_surface_parameter(rng))
        # peak twist angle B / (2 pi tanh(c / 2)) at most max_angle
        cap = settings.max_angle * 2.0 * np.pi * np.tanh(base.width / 2.0)
        bounds = _signed_bounds(part, lambda b: changed(base, amplitude=b).apply(positions), cap,
                                min_amplitude * cap)
        if bounds is None:
            return current
        _search_warp(state, i, j, lambda b: changed(base, amplitude=b), bounds, False,
                     1e-3 * (bounds[1] - bounds[0]), 25, found, seen)
    elif kind == "rotation":
        axis = random_unit_vector(rng)
        bounds = _signed_bounds(part, lambda t: Rotation(axis * t).apply(positions),
                                settings.max_angle, min_amplitude * settings.max_angle)
        if bounds is None:
            return current
        _search_warp(state, i, j, lambda t: Rotation(axis * t), bounds, False,
                     1e-3 * (bounds[1] - bounds[0]), 25, found, seen)
    else:
        raise ValueError(f"unknown warp kind {kind!r}; choose from {', '.join(WARPS)}")
    return _commit_best(state, i, j, found, current)


def warp_counts(state: CorrespondenceState) -> dict:
    """How many warps of each kind were accepted, over every example and part."""
    names = {"symmetric_theta": "symmetric", "asymmetric_theta": "asymmetric",
             "shear_twist": "shear", "rotation": "rotation"}
    counts = dict.fromkeys(WARPS, 0)
    for example in state.examples:
        for part in example.parts:
            for warp in part.kernels:
                counts[names[warp.kind] if hasattr(warp, "kind") else "symmetric"] += 1
    return counts


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
    kinds = tuple(settings.warps)
    unknown = [kind for kind in kinds if kind not in WARPS]
    if not kinds or unknown:
        raise ValueError(f"warps: {list(kinds)!r} must be one or more of {', '.join(WARPS)}")
    value = start_value = start_phase(state, objective, trace, phase)
    quiet_sweeps = 0
    active = np.arange(state.n_shapes) if active is None else np.asarray(active)
    for sweep in range(1, settings.max_sweeps + 1):
        before = value
        improved = _recorder(state, trace, phase, sweep, settings)
        for i in rng.permutation(active):
            example = state.examples[i]
            for j in rng.permutation(len(example.parts)):
                # with the symmetric kernel alone, no draw of the kind (the paper's strategy,
                # and the same random stream as before warps could be chosen)
                kind = kinds[0] if len(kinds) == 1 else kinds[int(rng.integers(len(kinds)))]
                value = _optimise_warp(state, i, j, kind, value, settings, rng,
                                       improved=improved)
            if with_pose:
                value = _optimise_pose(state, i, value, settings.pose_evaluations, improved)
            trace.record(state, value, phase, sweep)
            if progress is not None:
                progress(None, f"{phase}: sweep {sweep}, F = {value:.3f}")
            if time.perf_counter() > deadline:
                break
        value = _rebuilt(state, trace, phase, sweep, checkpoint)
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
    """Record the step's F, report it, then :func:`_rebuilt` (as between the sweeps of
    one_at_a_time); returns F after the rebuild."""
    trace.record(state, value, phase, sweep)
    if progress is not None:
        progress(None, f"{label}: F = {value:.3f}")
    return _rebuilt(state, trace, phase, sweep, checkpoint)


def _rebuilt(state: CorrespondenceState, trace: Trace, phase: str, sweep: int, checkpoint
             ) -> float:
    """Between sweeps / iterations: area weights on the new mean and fresh sums (no drift), F
    recorded, the state checkpointed; returns F after the rebuild."""
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
