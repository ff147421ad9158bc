"""The one-at-a-time strategies (III-D3, III-D4): examples in random order, one warp per step.

For each example of a sweep, a warp is drawn (the symmetric theta kernel by default; with
``warps`` beyond ``symmetric``, the kind is drawn uniformly among the Appendix's asymmetric theta
map, shear/twist and a global rotation of the parameter sphere) and its free parameter optimised by
bounded 1-D searches; with pose (III-D4), the example's pose is then optimised by the downhill
simplex. Every trial that turns a sampling triangle over is rejected.
"""

from __future__ import annotations

import time
from dataclasses import replace as changed

import numpy as np
from scipy.optimize import minimize, minimize_scalar

from ...config import WARPS, OptimisationSettings
from ...errors import ArgumentError
from ...geometry import Pose, pose_from_parameters, weighted_centroid
from ...progress import OBJECTIVE, report
from ..objective import Objective
from ..state import CorrespondenceState
from ..trace import Stop, Trace
from ..warps import (AsymmetricTheta, Rotation, ShearTwist, SymmetricTheta,
                     random_asymmetric_theta, random_shear_twist, random_unit_vector,
                     random_width)
from .base import (PhasePoint, begin_sweeps, improvements, rebuilt, recorder,
                   stop_after_sweep, sweep_point)

#: the warp kind (warps.WARP_KINDS) that each ``--warps`` option draws
KIND_OF_OPTION = {"symmetric": SymmetricTheta.kind, "asymmetric": AsymmetricTheta.kind,
                  "shear": ShearTwist.kind, "rotation": Rotation.kind}
OPTION_OF_KIND = {kind: option for option, kind in KIND_OF_OPTION.items()}


def optimise_amplitude(state: CorrespondenceState, i: int, j: int, kernel: SymmetricTheta,
                        current: float, max_amplitude: float, min_amplitude: float = 1e-7,
                        improved=None) -> float:
    """Best amplitude for one kernel of part j of example i; commits it when F falls.

    ``improved(value)``, if given, is called whenever a trial beats the best F so far."""
    example = state.examples[i]
    part = example.parts[j]
    cache = {}
    seen = improvements(current, improved)

    def objective(amplitude: float) -> float:
        trial = changed(kernel, amplitude=float(amplitude))
        positions, points, hint = part.propose(trial, check_folds=False)
        raw = example.raw_points({j: points})
        value = state.value(i, example.pose.apply(raw), raw)
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
    (F, warp, (positions, points, hint)) and passed to ``seen(F)`` (:func:`improvements`).
    Nothing is committed.
    """
    example = state.examples[i]
    part = example.parts[j]

    def objective(t: float) -> float:
        warp = warp_of(10.0 ** t if log_scale else float(t))
        proposal = part.propose(warp)
        if proposal is None:
            return np.inf
        raw = example.raw_points({j: proposal[1]})
        value = state.value(i, example.pose.apply(raw), raw)
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


def optimise_shift(state: CorrespondenceState, i: int, j: int, shift_of, current: float,
                   max_shift: float, improved=None) -> float:
    """Best shift of the origin in [-max_shift, max_shift] for curve part j of example i (bounded
    Brent search; ``shift_of(s)`` is the part's shift warp); commits it when F falls.

    The circle kernels fix two points each; a shift moves every sample along the curve at once,
    which they would need many steps for. It is searched at the example's current pose (III-D4
    then refits the pose): an origin far off, which Procrustes has partly absorbed as a
    rotation, is the initial alignment's to fix (:func:`~...prepare.curve.align_curve_origins`)."""
    found: list = []
    _search_warp(state, i, j, shift_of, (-max_shift, max_shift), False, 1e-3 * max_shift, 25,
                 found, improvements(current, improved))
    return _commit_best(state, i, j, found, current)


def _signed_bounds(part, move, cap: float, min_parameter: float) -> tuple | None:
    """[-low, high]: the unfolded range of a signed warp parameter within [-cap, cap], from one
    bisection per sign (:meth:`PartState.feasible_parameter`); None when both sides are negligible."""
    high = part.feasible_parameter(move, cap)
    low = part.feasible_parameter(lambda t: move(-t), cap)
    if max(low, high) <= min_parameter:
        return None
    return -low, high


def optimise_warp(state: CorrespondenceState, i: int, j: int, kind: str, current: float,
                   settings: OptimisationSettings, rng: np.random.Generator,
                   min_amplitude: float = 1e-7, improved=None) -> float:
    """One step of the one-at-a-time strategies on part j of example i with a warp of ``kind``.

    - ``symmetric``: a random kernel (centre uniform over the surface, omega from sigma_G), its
      amplitude optimised by :func:`optimise_amplitude`, as in the paper; on a curve (a part
      with a ``shift``) the circle kernel, then a shift of the origin (:func:`optimise_shift`);
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
        kernel = part.kernel(part.random_surface_parameter(rng), 0.0,
                             random_width(rng, settings.sigma_g))
        value = optimise_amplitude(state, i, j, kernel, current, settings.max_amplitude,
                                   min_amplitude, improved)
        shift = getattr(part, "shift", None)      # curves: a shift of the origin too
        if shift is not None:
            value = optimise_shift(state, i, j, shift, value, settings.max_angle, improved)
        return value
    found: list = []
    seen = improvements(current, improved)
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
        raise ArgumentError(f"unknown warp kind {kind!r}; choose from {', '.join(WARPS)}")
    return _commit_best(state, i, j, found, current)


def warp_counts(state: CorrespondenceState) -> dict:
    """How many warps of each ``--warps`` kind (config.WARPS) were accepted, over every example
    and part."""
    counts = dict.fromkeys(WARPS, 0)
    for example in state.examples:
        for part in example.parts:
            for kind, count in part.warp_counts().items():
                if kind in OPTION_OF_KIND:
                    counts[OPTION_OF_KIND[kind]] += count
    return counts


def optimise_pose(state: CorrespondenceState, i: int, current: float, max_evaluations: int,
                   improved=None) -> float:
    """Downhill simplex over example i's pose (rotation about its centroid, translation, and
    scale unless the state keeps sizes, ``state.scaling`` False: ``--no-scaling``); for a planar
    state (curves) rotation about z and translation in x and y only.

    ``improved`` as in :func:`optimise_amplitude`."""
    example = state.examples[i]
    raw = example.raw_points()
    base = example.pose
    centre = weighted_centroid(base.apply(raw), state.weights)
    size = state.target_size

    # the parameters the simplex moves (of rotation vector, translation, log scale): in the
    # plane only for a planar state, and the log scale (the 7th) unless the state keeps sizes
    free = np.array(([2, 3, 4] if state.planar else [0, 1, 2, 3, 4, 5])
                    + ([6] if state.scaling else []))

    def pose_of(parameters: np.ndarray) -> Pose:
        vector = np.zeros(7)
        vector[free] = parameters
        delta = pose_from_parameters(vector)
        # rotate and scale about the shape's centroid, then translate
        about = Pose(1.0, np.eye(3), centre).compose(delta).compose(Pose(1.0, np.eye(3), -centre))
        return about.compose(base)

    seen = improvements(current, improved)

    def objective(parameters: np.ndarray) -> float:
        value = state.value(i, pose_of(parameters).apply(raw), raw)
        seen(value)
        return value

    step = np.array([0.02, 0.02, 0.02, 0.02 * size, 0.02 * size, 0.02 * size, 0.01])[free]
    simplex = np.vstack([np.zeros(len(free)), np.diag(step)])
    result = minimize(objective, np.zeros(len(free)), method="Nelder-Mead",
                      options={"initial_simplex": simplex, "maxfev": max_evaluations,
                               "xatol": 1e-6, "fatol": 1e-6})
    if result.fun < current:
        example.pose = pose_of(result.x)
        state.commit_shape(i)
        return float(result.fun)
    return current


def one_at_a_time(state: CorrespondenceState, objective: Objective, settings: OptimisationSettings,
                  rng: np.random.Generator, trace: Trace, phase: str, deadline: float,
                  progress=None, checkpoint=None, active=None, resume: PhasePoint | None = None,
                  *, with_pose: bool = False) -> float:
    """Optimise one example at a time (III-D3/III-D4) until convergence or ``deadline``.

    ``active``: indices of the examples to optimise (default all); the others stay as they are.

    Converged means: for ``patience`` consecutive sweeps, the sweep lowered F by less than
    ``tolerance`` times the total decrease of this phase so far. Why the phase ended goes to
    ``trace.stopped_by``: converged, the deadline, or ``max_sweeps`` sweeps.

    ``checkpoint(point)`` after every sweep; ``resume`` (a :class:`PhasePoint`, with the state and
    the random generator of that moment) carries on from there.
    """
    kinds = tuple(settings.warps)
    unknown = [kind for kind in kinds if kind not in WARPS]
    if not kinds or unknown:
        raise ArgumentError(f"warps: {list(kinds)!r} must be one or more of {', '.join(WARPS)}")
    if state.planar and kinds != ("symmetric",):
        raise ArgumentError(f"warps: {list(kinds)!r}: closed 2-D curves take the symmetric kernel "
                         "only (asymmetric, shear and rotation are warps of the sphere)")
    active = np.arange(state.n_shapes) if active is None else np.asarray(active)
    sweeps = begin_sweeps(state, objective, trace, phase, deadline, settings, resume)
    value = sweeps.value
    if sweeps.over is not None:
        trace.stopped_by = sweeps.over
        return value
    for sweep in range(sweeps.first, settings.max_sweeps + 1):
        before = value
        improved = recorder(state, trace, phase, sweep, settings)
        for i in rng.permutation(active):
            example = state.examples[i]
            for j in rng.permutation(len(example.parts)):
                # with the symmetric kernel alone, no draw of the kind (the paper's strategy,
                # and the same random stream as before warps could be chosen)
                kind = kinds[0] if len(kinds) == 1 else kinds[int(rng.integers(len(kinds)))]
                value = optimise_warp(state, i, j, kind, value, settings, rng,
                                       improved=improved)
            if with_pose:
                value = optimise_pose(state, i, value, settings.pose_evaluations, improved)
            trace.record(state, value, phase, sweep)
            report(progress, None, f"{phase}: sweep {sweep}, F = {value:.3f}", OBJECTIVE)
            if time.perf_counter() > deadline:
                break
        value = rebuilt(state, trace, phase, sweep, checkpoint,
                        sweep_point(phase, sweep, before, sweeps, settings))
        stop = stop_after_sweep(sweeps, before, value, deadline, settings)
        if stop is not None:
            break
    else:
        stop = Stop.SWEEP_LIMIT
    trace.stopped_by = stop
    return value


def one_at_a_time_pose(state: CorrespondenceState, objective: Objective,
                       settings: OptimisationSettings, rng: np.random.Generator, trace: Trace,
                       phase: str, deadline: float, progress=None, checkpoint=None,
                       active=None, resume: PhasePoint | None = None) -> float:
    """III-D4: :func:`one_at_a_time` with the example's pose optimised after each warp."""
    return one_at_a_time(state, objective, settings, rng, trace, phase, deadline, progress,
                         checkpoint, active, resume, with_pose=True)
