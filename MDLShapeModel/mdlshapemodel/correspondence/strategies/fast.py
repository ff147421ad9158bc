"""The fast strategy: every example's reparameterization and pose optimised together, with gradients.

One *round* optimises, for all active examples at once, the coefficients of a smooth tangent
displacement field per part (:mod:`mdlshapemodel.fields`, bumps at the vertices of an icosphere of
one level) and the example's pose (rotation about its centroid, translation, log scale), by a
projected L-BFGS (:mod:`.quasi_newton`) with box bounds that keep every field a homeomorphism.
The gradient of the objective with respect to all of them comes from one evaluation of dF/dX (the
shapes) chained through the pose, the surface (dS/du of the barycentric interpolation) and the
field. The round's maps are then composed into the sample positions, the state is rebuilt (new
area weights), and the next round starts at the same or a finer level (coarse to fine), until the
objective stops falling or the time is up.

The per-example steps of an evaluation (the field map, point location and surface Jacobian, and
their chain rule) run on ``settings.threads`` threads (:class:`~mdlshapemodel.parallel.Threads`),
each example on one thread with the same arithmetic: the result is the same on any number.
"""

from __future__ import annotations

import contextlib
import itertools
import time
from dataclasses import dataclass, replace

import numpy as np

from ...config import OptimisationSettings
from ...geometry import Pose, weighted_centroid
from ...parallel import Threads
from ...progress import OBJECTIVE, report
from .. import hotloops
from ..state import CorrespondenceState
from ..trace import Stop
from .base import PhasePoint, budget_spent, stalled, start_phase
from .blocks import BlockSet
from .spread import ExamplesOnCluster
from .quasi_newton import minimize_box, pair_dtype


#: The bound of the log scale of an example's pose in a round: 0, the size of every example stays
#: what the Procrustes alignment gave it. With its size free, F falls without limit by shrinking
#: most examples towards their centroids and growing a few (one mode of pure scale, every other
#: mode small): seen on a two-part population, whose sizes ended between 0.13 and 40 mm around a
#: mean of 11. The rescaling of the whole population (``CorrespondenceState.target_size``) keeps
#: only the mean's size.
POSE_SCALE_LIMIT = 0.0


def gradient_at(state: CorrespondenceState, shapes: np.ndarray,
                raw: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """F and dF/dX (n_s, n_p, 3) for trial shapes of every example (and their unposed samples
    ``raw``, which a guided state needs; the state is unchanged)."""
    with state.trial_shapes(shapes, raw):
        return state.shape_gradient()


def _cross_matrices(vectors: np.ndarray) -> np.ndarray:
    """[v]x for each row of (n, 3)."""
    k = np.zeros((len(vectors), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -vectors[:, 2], vectors[:, 1], -vectors[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = vectors[:, 2], -vectors[:, 1], vectors[:, 0]
    return k


def rotations_and_jacobians(vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For rotation vectors w (n, 3): R(w) = I + sin(a)/a K + (1 - cos a)/a^2 K^2 (Rodrigues) and
    the right Jacobian of SO(3), J_r(w) = I - (1 - cos a)/a^2 K + (a - sin a)/a^3 K^2, with
    K = [w]x and a = |w|; d(R(w) v)/dw = -R(w) [v]x J_r(w). Series near a = 0."""
    angle = np.linalg.norm(vectors, axis=1)
    small = angle < 1e-4
    a = np.where(small, 1.0, angle)
    a2 = angle ** 2
    sin_a = np.where(small, 1.0 - a2 / 6.0, np.sin(a) / a)
    cos_a = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(a)) / a ** 2)
    cubic = np.where(small, 1.0 / 6.0 - a2 / 120.0, (a - np.sin(a)) / a ** 3)
    k = _cross_matrices(vectors)
    k2 = k @ k
    eye = np.eye(3)[None]
    rotations = eye + sin_a[:, None, None] * k + cos_a[:, None, None] * k2
    jacobians = eye - cos_a[:, None, None] * k + cubic[:, None, None] * k2
    return rotations, jacobians


@dataclass
class _Trial:
    """What the parameters x of a round give (see :meth:`FieldRound.trial`)."""

    x: np.ndarray             # the parameters
    number: int               # the trial's number, under which its sampling is kept where
                              # the blocks are (:class:`~.blocks.BlockSet`)
    raw: np.ndarray           # (n_active, n_p, 3) the unposed samples
    about: np.ndarray | None  # the samples posed as at the start, centred on their centroid
    rotation: np.ndarray      # (n_active, 3, 3) R(w)
    jacobian: np.ndarray      # (n_active, 3, 3) J_r(w)
    scale: np.ndarray         # (n_active,) e^sigma
    shapes: np.ndarray | None  # (n_s, n_p, 3) every example's shape, the active ones moved
    pose: np.ndarray          # (n_active, 7) the pose parameters of x
    unposed: np.ndarray | None   # (n_s, n_p, 3) every example's unposed samples (guided states)


@dataclass(frozen=True)
class Stretch:
    """One :class:`~.blocks.BlockSet` of a round: its active examples' ``rows`` and its
    ``parameters`` in x."""

    rows: slice
    parameters: slice


class ExamplesHere:
    """Where a round's per-example work runs by default: one :class:`~.blocks.BlockSet` of
    every active example, in this process on ``threads``, on the state's own parts.

    The interface of :class:`~.spread.ExamplesOnCluster`: :meth:`open` a round, :meth:`each`
    to call a method of every set with its arguments, :meth:`commit`.
    """

    def __init__(self, state: CorrespondenceState, threads: Threads | None = None):
        self.state, self.threads = state, threads or Threads(1)
        self.sets = []

    def open(self, active: np.ndarray, level: int, support: float, pose_limits) -> list:
        """The round's block sets made; returns (rows, :class:`~.blocks.Layout`) of each."""
        parts = [self.state.examples[i].parts for i in active]
        self.sets = [BlockSet(parts, self.state.part_slices, level, support, pose_limits,
                              self.threads)]
        return [(slice(0, len(active)), self.sets[0].layout)]

    def each(self, method: str, arguments: list) -> list:
        """``[set.method(*a) for set, a in zip(sets, arguments)]``."""
        return [getattr(one, method)(*a) for one, a in zip(self.sets, arguments)]

    def commit(self, trial: int, parameters: list):
        """Commit ``trial`` (each set's stretch of x in ``parameters``) to the parts."""
        self.each("commit", [(trial, x) for x in parameters])


class FieldRound:
    """The parameters of one round and the map from them to F and dF/dparameters.

    x holds, per active example, the field coefficients of each part (3 per bump on a sphere;
    1 per bump and a shift on a curve: the part's block, :data:`~.blocks.FIELD_BLOCKS`) and 7
    pose parameters: a rotation vector w and a log scale sigma about the example's centroid c at
    the start of the round, and a translation t in units of the shape size L:
    X = e^sigma R(w) (P(y) - c) + c + L t, with P the example's pose and y its unposed samples.
    A planar state's bounds hold w_x, w_y and t_z at zero (rotation about z, in-plane moves).

    The per-example work (sampling, chain rule, fold checks, commits) is done by ``examples``
    (default :class:`ExamplesHere` on ``threads``; :class:`~.spread.ExamplesOnCluster` on Dask
    workers); the poses, the shapes and their gradient are done here.
    """

    def __init__(self, state: CorrespondenceState, active, level: int, support: float,
                 threads: Threads | None = None, examples=None):
        self.state = state
        self.examples = examples if examples is not None else ExamplesHere(state, threads)
        self.level, self.support = level, support
        self.active = np.array(list(active), dtype=np.int64)
        # the log scale is held at 0: an example's size is not free to lower F
        # (POSE_SCALE_LIMIT); a planar state turns about z and moves in x and y only
        pose_limits = ([0.0, 0.0, 0.5, np.inf, np.inf, 0.0, POSE_SCALE_LIMIT] if state.planar
                       else [0.5, 0.5, 0.5, np.inf, np.inf, np.inf, POSE_SCALE_LIMIT])
        self.stretches, limits, pose_index, offset = [], [], [], 0
        for rows, layout in self.examples.open(self.active, level, support, pose_limits):
            self.stretches.append(Stretch(rows, slice(offset, offset + layout.size)))
            limits.append(layout.limit)
            pose_index.append(layout.pose_index + offset)
            offset += layout.size
        self.size = offset
        self.limit = np.concatenate(limits)     # |x| <= limit, element by element
        self.pose_index = np.concatenate(pose_index)
        self.scale_of_length = state.target_size
        poses = [state.examples[i].pose for i in self.active]
        self.scale0 = np.array([p.scale for p in poses])
        self.rotation0 = np.array([p.rotation for p in poses]).reshape(-1, 3, 3)
        self.translation0 = np.array([p.translation for p in poses]).reshape(-1, 3)
        self.centres = np.array([weighted_centroid(state.shapes[i], state.weights)
                                 for i in self.active]).reshape(-1, 3)
        self._numbers = itertools.count()

    def trial(self, x: np.ndarray, keep=None) -> _Trial:
        """Everything that parameters x give: see :meth:`gradient` and :meth:`commit`. The
        sampling of the earlier trials in ``keep`` (their numbers) stays where the blocks are,
        that of the others goes (None: every one stays)."""
        number = next(self._numbers)
        keep = range(number) if keep is None else keep
        raws = self.examples.each("sample", [(number, x[s.parameters], keep)
                                             for s in self.stretches])
        raw = raws[0] if len(raws) == 1 else np.concatenate(raws)
        p = x[self.pose_index]
        rotation, jacobian = rotations_and_jacobians(p[:, :3])
        scale = np.exp(p[:, 6])
        # about the centre: v = P(y) - c; X = e^sigma R(w) v + c + L t
        about = hotloops.apply_poses(raw, self.scale0, self.rotation0,
                                     self.translation0 - self.centres)
        posed = hotloops.apply_poses(about, scale, rotation,
                                     self.centres + self.scale_of_length * p[:, 3:6])
        everyone = len(self.active) == self.state.n_shapes and np.array_equal(
            self.active, np.arange(self.state.n_shapes))
        if everyone:
            shapes = posed          # every example moves (a round of the whole population)
        else:
            shapes = self.state.shapes.copy()
            shapes[self.active] = posed
        unposed = None
        if self.state.guides is not None and everyone:
            unposed = raw
        elif self.state.guides is not None:
            unposed = self.state.raw_shapes()
            unposed[self.active] = raw
        return _Trial(x=np.array(x, copy=True), number=number, raw=raw, about=about,
                      rotation=rotation, jacobian=jacobian, scale=scale, shapes=shapes, pose=p,
                      unposed=unposed)

    def gradient(self, trial: _Trial, shape_gradient: np.ndarray) -> np.ndarray:
        """dF/dx from dF/dX (n_s, n_p, 3) and, for a guided state, the landmark term's gradient
        with respect to the unposed samples (which moves the fields, not the poses)."""
        g = shape_gradient[self.active]
        rotation, scale = trial.rotation, trial.scale
        # the samples y of example i are posed by scale e^sigma s0 and rotation R(w) R0
        total_scale = scale * self.scale0
        total_rotation = rotation @ self.rotation0
        g_fields = g
        guides = self.state.guides
        if guides is not None:
            # dC/dy as the dF/dX that the blocks' chain rule (y -> X = s R y + t) turns into it
            pulled = guides.gradients(trial.unposed)[self.active]
            g_fields = g.copy()
            g_fields[:, guides.indices] += (np.einsum("aij,alj->ali", total_rotation, pulled)
                                            / total_scale[:, None, None])
        parts = self.examples.each("gradient", [
            (trial.number, total_scale[s.rows], total_rotation[s.rows], g_fields[s.rows])
            for s in self.stretches])
        result = parts[0] if len(parts) == 1 else np.concatenate(parts)
        # the pose: with N = sum_k g_k v_k^T (3 x 3) every term is a contraction of N:
        # sum_k v_k x (R^T g_k) = axial part of R^T N, sum_k g_k . R v_k = <R, N>
        n = g.transpose(0, 2, 1) @ trial.about
        m = rotation.transpose(0, 2, 1) @ n
        moment = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                           m[:, 1, 0] - m[:, 0, 1]], axis=1)
        pose = np.empty((len(self.active), 7))
        pose[:, :3] = scale[:, None] * np.einsum("aij,ai->aj", trial.jacobian, moment)
        pose[:, 3:6] = g.sum(axis=1) * self.scale_of_length
        pose[:, 6] = scale * np.einsum("aij,aij->a", rotation, n)
        result[self.pose_index] = pose
        return result

    def folds(self, trial: _Trial) -> bool:
        return any(self.examples.each("folds", [(trial.number,)] * len(self.stretches)))

    def commit(self, trial: _Trial):
        """Compose the round's maps into the sample positions (each recorded as a
        :class:`~..warps.FieldWarp` or :class:`~..circle.CircleField`, which re-applied to the positions at the
        start of the round gives the same positions bit for bit) and the poses."""
        self.examples.commit(trial.number, [trial.x[s.parameters] for s in self.stretches])
        rotation, scale, p = trial.rotation, trial.scale, trial.pose
        for row, i in enumerate(self.active):
            centre = self.centres[row]
            delta = Pose(float(scale[row]), rotation[row],
                         p[row, 3:6] * self.scale_of_length)
            about = Pose(1.0, np.eye(3), centre).compose(delta).compose(
                Pose(1.0, np.eye(3), -centre))
            example = self.state.examples[i]
            example.pose = about.compose(example.pose)
        self.state.rebuild()


class _RoundOutOfTime(Exception):
    pass


def optimise_round(state: CorrespondenceState, objective, active, level: int,
                   max_iterations: int = OptimisationSettings.round_iterations,
                   support: float = 2.0,
                   deadline: float = float("inf"), threads: Threads | None = None,
                   examples=None,
                   curvature_pairs: str = OptimisationSettings.curvature_pairs) -> float:
    """One projected L-BFGS round at one field level; returns F after it.

    At ``deadline`` the round stops and keeps the best point it has evaluated. The per-example
    work runs on ``threads`` here, or where ``examples`` has it (:class:`FieldRound`).
    ``curvature_pairs``: the precision of the quasi-Newton pairs (:func:`.pair_dtype`).
    """
    state.objective = objective
    round_ = FieldRound(state, active, level, support, threads, examples)
    cache = {}

    def best() -> tuple:
        """The number of the best trial so far: the only earlier sampling kept."""
        return (cache["best"][2].number,) if "best" in cache else ()

    def fun(x):
        if "best" in cache and time.perf_counter() > deadline:
            raise _RoundOutOfTime
        trial = round_.trial(x, best())
        value, shape_gradient = gradient_at(state, trial.shapes, trial.unposed)
        state.evaluations += 1
        if "best" not in cache or value < cache["best"][0]:
            # kept for the fold check and the commit, which need its number, x and pose: not
            # its posed shapes, which the evaluations after it would hold beside their own
            cache["best"] = (value, trial.x, replace(trial, about=None, shapes=None,
                                                     unposed=None))
        return value, round_.gradient(trial, shape_gradient)

    start_value = fun(np.zeros(round_.size))[0]
    try:
        # the symmetric box |x| <= limit (lower None: no vector of lower bounds held)
        minimize_box(fun, np.zeros(round_.size), None, round_.limit, max_iterations,
                     ftol=1e-9, gtol=1e-10,
                     pairs_dtype=pair_dtype(curvature_pairs, round_.size))
    except _RoundOutOfTime:
        pass
    value, x, trial = cache["best"]
    # the bounds make every field a homeomorphism of the sphere; a grid triangle can still turn
    # over where a bump is narrow for the grid: then take a shorter step
    folded = value < start_value and round_.folds(trial)
    for _ in range(4):
        if not folded:
            break
        x = 0.5 * x
        trial = round_.trial(x, ())
        value = gradient_at(state, trial.shapes, trial.unposed)[0]
        state.evaluations += 1
        folded = value < start_value and round_.folds(trial)
    if value < start_value and not folded:
        round_.commit(trial)
    else:
        state.rebuild()
    return float(state.value())


#: the fast strategy's field levels, coarse to fine, and its rounds per level at most
FIELD_LEVELS = (0, 1, 2, 3)
ROUNDS_PER_LEVEL = 3


def most_rounds(settings: OptimisationSettings, levels=FIELD_LEVELS,
                rounds_per_level: int = ROUNDS_PER_LEVEL, at: dict | None = None,
                made: int = 0) -> int:
    """The most rounds a phase of :func:`optimise_fast` can make: ``settings.field_passes``
    passes over ``levels``, each level at most ``rounds_per_level`` rounds; from the round at
    ``at`` on (its pass, level index and round in the level; None: the phase's start), that
    round included; and at most ``settings.max_sweeps`` in the phase, ``made`` of which are
    made.

    Examples
    --------
    >>> from mdlshapemodel.config import OptimisationSettings
    >>> settings = OptimisationSettings(field_passes=3)
    >>> most_rounds(settings), most_rounds(settings, at={"pass": 2, "level": 3, "round": 1})
    (36, 2)
    """
    at = at or {"pass": 0, "level": 0, "round": 0}
    per_pass = len(levels) * rounds_per_level
    schedule = ((rounds_per_level - at["round"])
                + (len(levels) - at["level"] - 1) * rounds_per_level
                + (settings.field_passes - at["pass"] - 1) * per_pass)
    return min(schedule, settings.max_sweeps - made)


def optimise_fast(state: CorrespondenceState, objective, settings, rng, trace,
                  phase: str, deadline: float, progress=None, checkpoint=None, active=None,
                  resume: PhasePoint | None = None, levels=FIELD_LEVELS,
                  rounds_per_level: int = ROUNDS_PER_LEVEL, cluster=None) -> float:
    """Coarse-to-fine rounds until the gain stalls (``settings.tolerance``), ``deadline`` or
    ``settings.max_sweeps`` rounds. At each level, rounds go on until one gains less than the
    tolerance (then the next level starts), at most ``rounds_per_level``. The pass over the levels
    is repeated, at most ``settings.field_passes`` times in all, while a whole pass gains more
    than the tolerance: after the fine levels have moved the points, the coarse fields can move
    whole regions again.

    After every round ``checkpoint(point)`` gets a :class:`PhasePoint` (pass, level and round;
    the F at the start of the phase and of the pass, before and after the round); given one as
    ``resume``, with the state of that moment, the phase carries on exactly from there.
    ``trace.stopped_by`` says why the phase ended (a limit reached after the last round of the
    schedule counts as the limit: that round may have been cut short). Each round's report
    says the most rounds the phase can still make (``rounds_left``, :func:`most_rounds` from
    the next round on, 0 where the phase is over).

    ``cluster``, a ``distributed.Client``: the rounds' per-example work runs on its workers,
    which hold their examples for the phase (:class:`~.spread.ExamplesOnCluster`); the same
    result.
    """
    active = range(state.n_shapes) if active is None else active
    if objective.kind == "fixed" and objective.free_below_delta:
        # Case 3 of the fixed-Delta cost (a mode spanning less than Delta is free) is a step of
        # about n_s ln(8 pi) / 2 nats in the mode's range: a quasi-Newton line search that crosses
        # it fails (seen with 82 hippocampi, where the smallest modes reach Delta). The paper's
        # eq. 13 codes every mode, continuously: this phase minimises that (its own objective,
        # which holds its own pool of threads for the phase)
        with replace(objective, free_below_delta=False).pooled() as coded:
            return optimise_fast(state, coded, settings, rng, trace, phase, deadline, progress,
                                 checkpoint, active, resume, levels, rounds_per_level, cluster)

    def following(at: dict, values: dict) -> dict | None:
        """The loop position after the round at ``at`` (None: the phase is over)."""
        start = values["start"]
        if (at["round"] + 1 < rounds_per_level
                and not stalled(values["before"], values["value"], start, settings)):
            return {**at, "round": at["round"] + 1}
        if at["level"] + 1 < len(levels):
            return {**at, "level": at["level"] + 1, "round": 0}
        if (at["pass"] + 1 < settings.field_passes
                and not stalled(values["pass_start"], values["value"], start, settings)):
            return {"pass": at["pass"] + 1, "level": 0, "round": 0}
        return None

    if resume is None:
        value = start_phase(state, objective, trace, phase)
        sweep, at = 0, {"pass": 0, "level": 0, "round": 0}
        values = {"start": value, "pass_start": value}
    else:
        state.objective = objective
        sweep, values, value = resume.sweep, dict(resume.values), resume.values["value"]
        trace.stopped_by = budget_spent(deadline, sweep, settings)
        if trace.stopped_by is not None:
            return value
        at = following(resume.counters, values)
        if at is not None and at["pass"] != resume.counters["pass"]:
            values["pass_start"] = value
    with contextlib.ExitStack() as stack:
        threads = stack.enter_context(Threads(settings.threads))
        examples = (None if cluster is None or at is None else
                    stack.enter_context(ExamplesOnCluster(cluster, state, active, threads)))
        while at is not None:
            sweep += 1
            values["before"] = value
            value = optimise_round(state, objective, active, levels[at["level"]],
                                   max_iterations=settings.round_iterations,
                                   deadline=deadline, threads=threads, examples=examples,
                                   curvature_pairs=settings.curvature_pairs)
            values["value"] = value
            trace.record(state, value, phase, sweep)
            upcoming = following(at, values)
            rounds_left = (0 if upcoming is None else
                           most_rounds(settings, levels, rounds_per_level, upcoming, sweep))
            report(progress, None, f"{phase}: level {levels[at['level']]}, round {sweep}, "
                                   f"F = {value:.3f}", OBJECTIVE, rounds_left)
            if checkpoint is not None:
                checkpoint(PhasePoint(phase, sweep, dict(at), dict(values)))
            trace.stopped_by = budget_spent(deadline, sweep, settings)
            if trace.stopped_by is not None:
                return value
            previous, at = at, upcoming
            if at is not None and at["pass"] != previous["pass"]:
                values["pass_start"] = value
        trace.stopped_by = Stop.CONVERGED
        return value
