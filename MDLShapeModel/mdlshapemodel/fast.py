"""The fast strategy: every example's reparameterization and pose optimised together, with gradients.

One *round* optimises, for all active examples at once, the coefficients of a smooth tangent
displacement field per part (:mod:`mdlshapemodel.fields`, bumps at the vertices of an icosphere of
one level) and the example's pose (rotation about its centroid, translation, log scale), by L-BFGS-B
with box bounds that keep every field a homeomorphism. The gradient of the objective with respect
to all of them comes from one evaluation of dF/dX (the shapes) chained through the pose, the surface
(dS/du of the barycentric interpolation) and the field. The round's maps are then composed into the
sample positions, the state is rebuilt (new area weights), and the next round starts at the same or
a finer level (coarse to fine), until the objective stops falling or the time is up.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

from .correspond import CorrespondenceState
from .fields import FieldBasis
from .pose import Pose, rotation_from_vector, weighted_centroid
from .strategies import stalled, start_phase


def gradient_at(state: CorrespondenceState, shapes: np.ndarray) -> tuple[float, np.ndarray]:
    """F and dF/dX (n_s, n_p, 3) for trial shapes of every example (the state is unchanged)."""
    with state.trial_shapes(shapes):
        return state.shape_gradient()


def _cross_matrix(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def right_jacobian(rotation_vector: np.ndarray) -> np.ndarray:
    """J_r(w) of SO(3): d(R(w) v)/dw = -R(w) [v]x J_r(w)."""
    angle = float(np.linalg.norm(rotation_vector))
    k = _cross_matrix(rotation_vector)
    if angle < 1e-8:
        return np.eye(3) - 0.5 * k
    return (np.eye(3) - (1 - np.cos(angle)) / angle ** 2 * k
            + (angle - np.sin(angle)) / angle ** 3 * k @ k)


class _Round:
    """The parameters of one round and the map from them to F and dF/dparameters."""

    def __init__(self, state: CorrespondenceState, active, level: int, support: float):
        self.state = state
        self.active = list(active)
        self.bases = {}     # (i, j) -> FieldBasis on the part's current positions
        self.slices = {}
        offset = 0
        bounds = []
        for i in self.active:
            for j, part in enumerate(state.examples[i].parts):
                basis = FieldBasis.icosphere_level(level, part.positions, support)
                self.bases[i, j] = basis
                size = 3 * basis.n_centres
                self.slices[i, j] = slice(offset, offset + size)
                offset += size
                limit = basis.max_coefficient() / np.sqrt(3.0)
                bounds += [(-limit, limit)] * size
            # pose: rotation vector (3), translation (3, in units of the shape size), log scale
            self.slices[i, "pose"] = slice(offset, offset + 7)
            offset += 7
            bounds += [(-0.5, 0.5)] * 3 + [(None, None)] * 3 + [(-0.2, 0.2)]
        self.size = offset
        self.bounds = bounds
        self.scale_of_length = state.target_size
        self.base_raw = {i: state.examples[i].raw_points() for i in self.active}
        posed = {i: state.examples[i].pose.apply(self.base_raw[i]) for i in self.active}
        self.centres = {i: weighted_centroid(posed[i], state.weights) for i in self.active}
        # the points about their centre at the start of the round, for the pose gradient
        self.about_centre = {i: posed[i] - self.centres[i] for i in self.active}

    def trial(self, x: np.ndarray):
        """Per active example: sampled points of its parts (with located faces and positions) and
        its pose, for parameters x."""
        trials = {}
        for i in self.active:
            example = self.state.examples[i]
            parts = []
            for j, part in enumerate(example.parts):
                c = x[self.slices[i, j]].reshape(-1, 3)
                positions, norms = self.bases[i, j].map(c)
                points, hint = part.sample(positions)
                parts.append((positions, points, hint, norms))
            trials[i] = (parts, self.pose_of(i, x[self.slices[i, "pose"]]))
        return trials

    def pose_of(self, i: int, p: np.ndarray) -> Pose:
        centre = self.centres[i]
        delta = Pose(float(np.exp(p[6])), rotation_from_vector(p[:3]),
                     p[3:6] * self.scale_of_length)
        about = Pose(1.0, np.eye(3), centre).compose(delta).compose(Pose(1.0, np.eye(3), -centre))
        return about.compose(self.state.examples[i].pose)

    def shapes(self, trials) -> np.ndarray:
        shapes = self.state.shapes.copy()
        for i, (parts, pose) in trials.items():
            shapes[i] = pose.apply(np.concatenate([points for _, points, _, _ in parts]))
        return shapes

    def gradient(self, x: np.ndarray, trials, shape_gradient: np.ndarray) -> np.ndarray:
        """dF/dx from dF/dX (n_s, n_p, 3)."""
        result = np.zeros(self.size)
        for i, (parts, pose) in trials.items():
            g = shape_gradient[i]
            # through the pose x = pose(y): dF/dy = s R^T g
            dy = pose.scale * g @ pose.rotation
            for j, (positions, points, hint, norms) in enumerate(parts):
                part = self.state.examples[i].parts[j]
                rows = self.state.part_slices[j]
                du = part.locator.jacobian_transpose(part.vertices, hint, positions, dy[rows])
                c = x[self.slices[i, j]].reshape(-1, 3)
                result[self.slices[i, j]] = self.bases[i, j].coefficient_gradient(
                    c, du, (positions, norms)).ravel()
            # pose parameters about the centroid: X = e^s R(w) (X0 - c) + c + size * t; with
            # v_k = X0_k - c and N = sum_k g_k v_k^T (3 x 3), every term is a contraction of N:
            # sum_k v_k x (R^T g_k) = axial part of R^T N, sum_k g_k . R v_k = <R, N>
            p = x[self.slices[i, "pose"]]
            rotation = rotation_from_vector(p[:3])
            scale = float(np.exp(p[6]))
            n = g.T @ self.about_centre[i]
            m = rotation.T @ n
            moment = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
            pose_gradient = np.empty(7)
            pose_gradient[:3] = scale * right_jacobian(p[:3]).T @ moment
            pose_gradient[3:6] = g.sum(axis=0) * self.scale_of_length
            pose_gradient[6] = scale * np.sum(rotation * n)
            result[self.slices[i, "pose"]] = pose_gradient
        return result

    def commit(self, trials):
        """Compose the round's maps into the sample positions and poses."""
        for i, (parts, pose) in trials.items():
            example = self.state.examples[i]
            for part, (positions, points, hint, _) in zip(example.parts, parts):
                part.positions, part.points, part.hint = positions, points, hint
            example.pose = pose
        self.state.rebuild()


class _OutOfTime(Exception):
    pass


def optimise_round(state: CorrespondenceState, objective, active, level: int,
                   max_iterations: int = 30, support: float = 2.0,
                   deadline: float = float("inf")) -> float:
    """One L-BFGS-B round at one field level; returns F after it.

    At ``deadline`` the round stops and keeps the best point it has evaluated.
    """
    state.objective = objective
    round_ = _Round(state, active, level, support)
    cache = {}

    def fun(x):
        if "best" in cache and time.perf_counter() > deadline:
            raise _OutOfTime
        trials = round_.trial(x)
        value, shape_gradient = gradient_at(state, round_.shapes(trials))
        state.evaluations += 1
        cache["last"] = (value, x.copy(), trials)
        if "best" not in cache or value < cache["best"][0]:
            cache["best"] = (value, x.copy(), trials)
        return value, round_.gradient(x, trials, shape_gradient)

    start_value = fun(np.zeros(round_.size))[0]
    try:
        minimize(fun, np.zeros(round_.size), jac=True, method="L-BFGS-B", bounds=round_.bounds,
                 options={"maxiter": max_iterations, "ftol": 1e-9, "gtol": 1e-10})
    except _OutOfTime:
        pass
    value, x, trials = cache["best"]
    # the bounds make every field a homeomorphism of the sphere; a grid triangle can still turn
    # over where a bump is narrow for the grid: then take a shorter step
    folded = value < start_value and _folds(state, trials)
    for _ in range(4):
        if not folded:
            break
        x = 0.5 * x
        trials = round_.trial(x)
        value = gradient_at(state, round_.shapes(trials))[0]
        state.evaluations += 1
        folded = value < start_value and _folds(state, trials)
    if value < start_value and not folded:
        round_.commit(trials)
    else:
        state.rebuild()
    return float(state.value())


def _folds(state: CorrespondenceState, trials) -> bool:
    for i, (parts, _) in trials.items():
        for part, (positions, _, _, _) in zip(state.examples[i].parts, parts):
            if part.folds(positions):
                return True
    return False


def optimise_fast(state: CorrespondenceState, objective, settings, trace,
                  phase: str, deadline: float, progress=None, checkpoint=None, active=None,
                  levels=(0, 1, 2, 3), rounds_per_level: int = 3) -> float:
    """Coarse-to-fine rounds until the gain stalls (``settings.tolerance``), ``deadline`` or
    ``settings.max_sweeps`` rounds. At each level, rounds go on until one gains less than the
    tolerance (then the next level starts), at most ``rounds_per_level``."""
    active = range(state.n_shapes) if active is None else active
    if objective.kind == "fixed" and objective.free_below_delta:
        # Case 3 of the fixed-Delta cost (a mode spanning less than Delta is free) is a step of
        # about n_s ln(8 pi) / 2 nats in the mode's range: a quasi-Newton line search that crosses
        # it fails (seen with 82 hippocampi, where the smallest modes reach Delta). The paper's
        # eq. 13 codes every mode, continuously: this phase minimises that.
        objective = replace(objective, free_below_delta=False)
    value = start_value = start_phase(state, objective, trace, phase)
    sweep = 0
    for level in levels:
        for _ in range(rounds_per_level):
            sweep += 1
            before = value
            value = optimise_round(state, objective, active, level, deadline=deadline)
            trace.record(state, value, phase, sweep)
            if progress is not None:
                progress(None, f"{phase}: level {level}, round {sweep}, F = {value:.3f}")
            if checkpoint is not None:
                checkpoint()
            if time.perf_counter() > deadline or sweep >= settings.max_sweeps:
                return value
            if stalled(before, value, start_value, settings):
                break   # this level has stopped paying: go finer
    return value
