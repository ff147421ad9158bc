"""The simplex strategies (III-D1 multiresolution, III-D2 multiscale): many kernels, of all
examples, their amplitudes optimised together by the downhill simplex.

A trial amplitude is clipped into [0, A_max(kernel)], A_max being the largest amplitude that flips
no sampling-grid triangle when the kernel alone is applied to the positions at the start of the
level/iteration (``PartState.feasible_amplitude``); a trial whose *composed* kernels still flip a
grid triangle scores +inf, so every accepted warp is a homeomorphism on the grid. The kernels of
one level are composed in a fixed order (the order of their centres). F of a trial is computed from
the full covariance of the trial shapes, since all examples change at once.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from ...config import OptimisationSettings
from ...progress import OBJECTIVE, report
from ..objective import Objective
from ..state import CorrespondenceState, PartState
from ..trace import Stop, Trace
from ..warps import random_width
from .base import (PhasePoint, active_parts, begin_sweeps, end_of_iteration, recorder,
                   start_phase, stop_after_sweep, sweep_point)


def population_value(state: CorrespondenceState, shapes: np.ndarray,
                     raw: np.ndarray | None = None) -> float:
    """F of the population with *every* shape replaced by ``shapes`` (n_s, n_p, 3) (and the
    unposed samples by ``raw``, which a guided state needs)."""
    with state.trial_shapes(shapes, raw):
        return state.value()


@dataclass
class _KernelBlock:
    """The new kernels of part j of example i (composed in this order) and their amplitude bounds."""

    i: int
    j: int
    centers: list
    omegas: list
    upper: np.ndarray


class _SimplexOutOfTime(Exception):
    pass


def _block(state: CorrespondenceState, i: int, j: int, centers, omegas,
           max_amplitude: float, min_amplitude: float = 1e-7) -> _KernelBlock | None:
    """The kernels of part j of example i whose feasible amplitude is not negligible (None if none)."""
    part = state.examples[i].parts[j]
    upper = np.array([part.feasible_amplitude(c, w, max_amplitude) for c, w in zip(centers, omegas)])
    keep = upper > min_amplitude
    if not np.any(keep):
        return None
    return _KernelBlock(i, j, [c for c, k in zip(centers, keep) if k],
                  [float(w) for w, k in zip(omegas, keep) if k], upper[keep])


def _optimise_amplitudes(state: CorrespondenceState, blocks: list, current: float,
                         settings: OptimisationSettings, deadline: float, progress=None,
                         label: str = "", improved=None) -> float:
    """Downhill simplex over the amplitudes of all ``blocks`` at once; commits when F falls.

    ``improved`` as in :func:`optimise_amplitude`.

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
        raw = None if state.guides is None else state.raw_shapes()
        parts = []
        for i, ks in by_example.items():
            example = state.examples[i]
            replace = {}
            for k in ks:
                b = blocks[k]
                part = example.parts[b.j]
                kernels = [part.kernel(c, float(a), w) for c, w, a in
                           zip(b.centers, b.omegas, amplitudes[offsets[k]:offsets[k + 1]]) if a > 0]
                if not kernels:
                    continue
                positions = part.positions
                for kernel in kernels:
                    positions = kernel.apply(positions)
                if part.folds(positions):
                    return None, None, None
                points, hint = part.sample(positions)
                replace[b.j] = points
                parts.append((i, part, kernels, positions, points, hint))
            if replace:
                unposed = example.raw_points(replace)
                shapes[i] = example.pose.apply(unposed)
                if raw is not None:
                    raw[i] = unposed
        return shapes, raw, parts

    def objective(x: np.ndarray) -> float:
        shapes, raw, parts = trial_of(x)
        if shapes is None:
            return np.inf
        value = population_value(state, shapes, raw)
        if value < best["value"]:
            best["value"], best["trial"] = value, parts
            if improved is not None:
                improved(value)
        count[0] += 1
        if count[0] % 100 == 0:
            report(progress, None, f"{label}, {count[0]} evaluations, F = {best['value']:.3f}",
                       OBJECTIVE)
        if time.perf_counter() > deadline:
            raise _SimplexOutOfTime
        return value

    n = len(upper)
    simplex = np.vstack([np.zeros(n), np.diag(settings.simplex_step * upper)])
    max_evaluations = settings.simplex_evaluations or 200 * n
    try:
        minimize(objective, np.zeros(n), method="Nelder-Mead",
                 options={"initial_simplex": simplex, "maxfev": max_evaluations,
                          "xatol": 1e-4 * settings.max_amplitude, "fatol": 1e-6})
    except _SimplexOutOfTime:
        pass
    if best["trial"] is None:
        return current
    touched = set()
    for i, part, kernels, positions, points, hint in best["trial"]:
        for kernel in kernels[:-1]:
            part.accept(kernel)
        part.commit(kernels[-1], positions, points, hint)
        touched.add(i)
    for i in sorted(touched):
        state.commit_shape(i)
    return best["value"]


def multiresolution_levels(omega_1: float, levels: int) -> list:
    """[(omega, centres)] of III-D1: level k has kernels of width omega_1 / 2**k at the vertices that
    the k-th subdivision of the icosahedron adds (level 0: its 12 vertices), i.e. halfway between
    the kernels of the earlier levels."""
    return [(omega_1 / 2.0 ** k, PartState.kernel_centres(k)) for k in range(levels)]


def multiresolution(state: CorrespondenceState, objective: Objective,
                    settings: OptimisationSettings, rng: np.random.Generator, trace: Trace,
                    phase: str, deadline: float, progress=None, checkpoint=None, active=None,
                    resume: PhasePoint | None = None) -> float:
    """III-D1: one downhill simplex per level over the amplitudes of that level's kernels in all
    active examples and parts; the level's amplitudes are then fixed. Stops after
    ``min(max_levels, max_sweeps)`` levels or at ``deadline`` (the ``sweep`` of the trace is the
    level, from 1): converged once all ``max_levels`` are done (``trace.stopped_by``).
    Deterministic: ``rng`` is not used. ``checkpoint(point)`` after every level; ``resume``
    carries on after the level it names."""
    parts = active_parts(state, active)
    widths = [settings.omega_1 / 2.0 ** k for k in range(min(settings.max_levels,
                                                              settings.max_sweeps))]
    # the schedule's end: all its levels, unless max_sweeps cut it shorter
    scheduled = Stop.CONVERGED if len(widths) == settings.max_levels else Stop.SWEEP_LIMIT
    done = 0 if resume is None else resume.sweep
    if resume is None:
        value = start_phase(state, objective, trace, phase)
    else:
        state.objective = objective
        value = resume.values["value"]
        if done < len(widths) and time.perf_counter() > deadline:
            trace.stopped_by = Stop.TIME_LIMIT
            return value
    for level, omega in enumerate(widths, start=1):
        if level <= done:
            continue
        blocks = []
        for i, j in parts:
            # the part's own centres: the icosphere's on a sphere, the circle's on a curve
            centers = state.examples[i].parts[j].kernel_centres(level - 1)
            blocks.append(_block(state, i, j, centers, [omega] * len(centers),
                                 settings.max_amplitude))
        blocks = [b for b in blocks if b is not None]
        label = f"{phase}: level {level} ({sum(len(b.upper) for b in blocks)} kernels, " \
                f"omega = {omega:g})"
        value = _optimise_amplitudes(state, blocks, value, settings, deadline, progress, label,
                                     recorder(state, trace, phase, level, settings))
        value = end_of_iteration(state, trace, phase, level, value, label, progress, checkpoint,
                                 lambda after: PhasePoint(phase, level, {}, {"value": after}))
        if time.perf_counter() > deadline:
            # the level may have been cut short: even the last is not a finished schedule
            trace.stopped_by = Stop.TIME_LIMIT
            return value
    trace.stopped_by = scheduled
    return value


def multiscale(state: CorrespondenceState, objective: Objective, settings: OptimisationSettings,
               rng: np.random.Generator, trace: Trace, phase: str, deadline: float,
               progress=None, checkpoint=None, active=None,
               resume: PhasePoint | None = None) -> float:
    """III-D2: each iteration draws one kernel per active example and part (centre uniform over the
    surface by area, width from the positive half of N(0, sigma_G)) and optimises their amplitudes
    together by the downhill simplex; accepted kernels are fixed.

    Converged as in :func:`one_at_a_time`, an iteration playing the part of a sweep: for
    ``patience`` consecutive iterations, the gain was below ``tolerance`` times the total gain of
    this phase; or ``max_sweeps`` iterations, or ``deadline`` (``trace.stopped_by`` says which).
    ``checkpoint(point)`` after every iteration; ``resume`` (with the state and random generator
    of that moment) carries on.
    """
    parts = active_parts(state, active)
    sweeps = begin_sweeps(state, objective, trace, phase, deadline, settings, resume)
    value = sweeps.value
    if sweeps.over is not None:
        trace.stopped_by = sweeps.over
        return value
    for iteration in range(sweeps.first, settings.max_sweeps + 1):
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
                                     recorder(state, trace, phase, iteration, settings))
        value = end_of_iteration(state, trace, phase, iteration, value, label, progress,
                                  checkpoint, sweep_point(phase, iteration, before, sweeps,
                                                          settings))
        stop = stop_after_sweep(sweeps, before, value, deadline, settings)
        if stop is not None:
            break
    else:
        stop = Stop.SWEEP_LIMIT
    trace.stopped_by = stop
    return value
