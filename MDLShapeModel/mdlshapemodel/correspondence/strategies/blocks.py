"""The fast strategy's per-example work: the field blocks of a round and the set of them that one
process holds.

A round of the fast strategy (:class:`~.fast.FieldRound`) moves every active example by a field
per part and a pose. What depends on one example alone, its parts' field maps, point location and
surface Jacobians (:meth:`SphereBlock.sample`), their chain rule (:meth:`SphereBlock.gradient`),
fold checks and commits, is done by a :class:`BlockSet` of consecutive active examples: in the
build's own process one set holds them all (on threads); with ``--scheduler`` each Dask worker
holds one set (:mod:`.spread`). The same functions run in both places, so the numbers are the
same.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ArgumentError
from ...parallel import Threads
from .. import hotloops
from ..circle import CircleField, CircleFieldBasis
from ..fields import FieldBasis
from ..warps import FieldWarp

#: the pose parameters of an example in a round (:class:`~.fast.FieldRound`): a rotation vector,
#: a translation and a log scale, after its parts' field coefficients
POSE_SIZE = 7


class SphereBlock:
    """One sphere part of one active example in a round: its field basis (bumps at the vertices
    of an icosphere of ``level``, 3 coefficients each) and where its coefficients (in x, set by
    the round) and points (``row`` of the active examples, ``rows`` of the shape vector) are.

    A block does a part's share of an evaluation: :meth:`sample` (field map, point location,
    surface Jacobian), :meth:`gradient` (their chain rule), :meth:`folds` and :meth:`settled`.
    A :class:`BlockSet` picks the block class by the part's ``kind`` (:data:`FIELD_BLOCKS`)."""

    def __init__(self, row: int, part, rows: slice, level: int, support: float):
        self.row, self.part, self.rows = row, part, rows
        self.level, self.support = level, support
        self.basis = FieldBasis.icosphere_level(level, part.positions, support)
        self.size = 3 * self.basis.n_centres
        self.coefficients = slice(0, self.size)
        self.hint = part.hint           # the faces last located: the next walk starts there

    def limits(self) -> np.ndarray:
        """The bound of each coefficient's absolute value (a homeomorphism within them)."""
        return np.full(self.size, self.basis.max_coefficient() / np.sqrt(3.0))

    def sample(self, x: np.ndarray, raw: np.ndarray) -> tuple:
        """The field map at x, located on the surface: phi, |m|, faces, dS/du; the samples go
        into ``raw``."""
        part, basis = self.part, self.basis
        n = len(basis.points)
        phi, norms = np.empty((n, 3)), np.empty(n)
        face, jac = np.empty(n, dtype=part.faces.dtype), np.empty((n, 3, 3))
        found = np.empty(n, dtype=np.bool_)
        sampled = raw[self.row, self.rows]
        w = basis.weights
        hotloops.field_sample(w.indptr, w.indices, w.data, basis.points,
                              x[self.coefficients].reshape(-1, 3), part.locator.sphere,
                              part.locator.neighbours, part.faces, part.vertices, self.hint,
                              8, phi, norms, face, sampled, jac, found)
        missed = np.flatnonzero(~found)
        if len(missed):     # walked too far: locate these among the faces near them
            face[missed], coords = part.locator.locate(phi[missed])
            sampled[missed] = part.locator.interpolate(part.vertices, face[missed], coords)
            jac[missed] = part.locator.jacobian(part.vertices, face[missed], phi[missed])
        self.hint = face
        return phi, norms, face, jac

    def gradient(self, located: tuple, scale: float, rotation: np.ndarray,
                 shape_gradient: np.ndarray) -> np.ndarray:
        """dF/d(coefficients) from dF/dX of the block's points, posed by ``scale`` and
        ``rotation``."""
        phi, norms, _, jac = located
        w = self.basis.weights
        return hotloops.field_sample_gradient(
            w.indptr, w.indices, w.data, self.basis.points, phi, norms, jac, scale, rotation,
            shape_gradient, self.basis.n_centres).ravel()

    @staticmethod
    def earlier(located: tuple) -> tuple:
        """What a trial keeps once a later one is sampled: its fold check and commit need phi
        and the faces, not dS/du (72 bytes a point), which only its gradient, asked for right
        after its sampling, needs."""
        return located[:3] + (None,)

    def folds(self, located: tuple) -> bool:
        return self.part.folds(located[0])

    def settled(self, located: tuple, x: np.ndarray, raw: np.ndarray) -> tuple:
        """What committing the block's map at x gives its part (the arguments of its
        ``commit``): the map recorded as a :class:`FieldWarp`, the positions, samples and
        faces."""
        phi, _, face, _ = located
        warp = FieldWarp(self.level, self.support, x[self.coefficients].reshape(-1, 3).copy())
        return warp, phi, raw[self.row, self.rows].copy(), face


class CurveBlock:
    """One curve part (:class:`~..circle.CurvePart`) of one active example in a round: the map
    t -> t + s + v(t) of :class:`~..circle.CircleFieldBasis` at ``level`` (8 * 2**level bumps,
    one scalar coefficient each) and the shift s of the origin, last. The interface of
    :class:`SphereBlock`.

    Chain rule: X_k = scale R S(phi_k) + ..., dS/dphi = the polyline's tangent T_k (constant on
    each segment), so dF/da_j = sum_k g_j(t_k) q_k and dF/ds = sum_k q_k with
    q_k = scale (R^T dF/dX_k) . T_k.
    """

    def __init__(self, row: int, part, rows: slice, level: int, support: float):
        self.row, self.part, self.rows = row, part, rows
        self.level, self.support = level, support
        self.basis = CircleFieldBasis(level, support, part.positions)
        self.size = self.basis.n_centres + 1
        self.coefficients = slice(0, self.size)

    def limits(self) -> np.ndarray:
        """|a_j| within :meth:`CircleFieldBasis.max_coefficient`; a shift of at most 1/8 turn
        per round (any shift is a homeomorphism: this only keeps the steps local)."""
        return np.append(np.full(self.basis.n_centres, self.basis.max_coefficient()),
                         np.pi / 4.0)

    def sample(self, x: np.ndarray, raw: np.ndarray) -> tuple:
        """phi, the curve segments and dS/dphi at x; the samples go into ``raw``."""
        values = x[self.coefficients]
        phi = self.basis.apply(values[:-1], values[-1])
        raw[self.row, self.rows], segments = self.part.sample(phi)
        return phi, segments, self.part.tangent(segments)

    def gradient(self, located: tuple, scale: float, rotation: np.ndarray,
                 shape_gradient: np.ndarray) -> np.ndarray:
        along = scale * np.einsum("kd,kd->k", shape_gradient @ rotation, located[2])
        return np.append(self.basis.weights.T @ along, along.sum())

    @staticmethod
    def earlier(located: tuple) -> tuple:
        """What a trial keeps once a later one is sampled: phi and the segments, not the
        tangents, which only its gradient needs."""
        return located[:2] + (None,)

    def folds(self, located: tuple) -> bool:
        return self.part.folds(located[0])

    def settled(self, located: tuple, x: np.ndarray, raw: np.ndarray) -> tuple:
        """What committing the block's map at x gives its part: the map recorded as a
        :class:`CircleField`, the positions, samples and segments."""
        phi, segments, _ = located
        values = x[self.coefficients]
        warp = CircleField(self.level, self.support, float(values[-1]), values[:-1].copy())
        return warp, phi, raw[self.row, self.rows].copy(), segments


#: the field block of each kind of part (``part.kind``)
FIELD_BLOCKS = {"sphere": SphereBlock, "circle": CurveBlock}


@dataclass(frozen=True)
class Layout:
    """Where a :class:`BlockSet`'s parameters lie in its stretch of a round's x: ``size`` of
    them, ``limit`` the bound of each one's absolute value, ``pose_index`` (rows, 7) the pose
    parameters of each of its examples."""

    size: int
    limit: np.ndarray
    pose_index: np.ndarray


class BlockSet:
    """The field blocks of consecutive active examples of a round, and the trials sampled on
    them.

    Its stretch of the round's x holds, per example, each part's coefficients
    (:data:`FIELD_BLOCKS`) and then :data:`POSE_SIZE` pose parameters, bounded by ``pose_limits``.
    Each trial's sampling is kept under its number, for its fold check or commit, until a later
    :meth:`sample` is told not to keep it; the gradient is of the trial sampled last (the blocks'
    ``earlier``: what the others keep).

    Parameters
    ----------
    examples : list of list of parts
        Each example's parts, in the order of the set's rows.
    part_slices : list of slice
        The rows of each part in an example's shape (``CorrespondenceState.part_slices``).
    level, support : int, float
        The fields' level and support (:class:`SphereBlock`).
    pose_limits : sequence of 7 floats
        The bounds of each example's pose parameters.
    threads : Threads, optional
        Threads for the per-block loops (each block on one thread: the same result on any
        number).
    """

    def __init__(self, examples: list, part_slices: list, level: int, support: float,
                 pose_limits, threads: Threads | None = None):
        self.threads = threads or Threads(1)
        self.n_rows = len(examples)
        self.n_points = part_slices[-1].stop
        parts = [(row, j, part) for row, own in enumerate(examples) for j, part in enumerate(own)]
        self.parts = [(row, j) for row, j, _ in parts]
        self.blocks = [None] * len(parts)

        def make(indices):
            for b in indices:
                row, j, part = parts[b]
                self.blocks[b] = FIELD_BLOCKS[part.kind](row, part, part_slices[j], level,
                                                         support)

        self.threads.over(len(parts), make)
        offset, limits, pose_index = 0, [], []
        for b, (block, (row, _, _)) in enumerate(zip(self.blocks, parts)):
            block.coefficients = slice(offset, offset + block.size)
            offset += block.size
            limits.append(block.limits())
            if b + 1 == len(parts) or parts[b + 1][0] != row:   # the example's last part
                pose_index.append(np.arange(offset, offset + POSE_SIZE))
                offset += POSE_SIZE
                limits.append(np.asarray(pose_limits, dtype=np.float64))
        self.layout = Layout(offset, np.concatenate(limits),
                             np.array(pose_index, dtype=np.int64).reshape(-1, POSE_SIZE))
        self.trials = {}        # trial number -> (per block: what its sample() gave, raw)
        self.newest = None      # the trial sampled last

    def sample(self, trial: int, x: np.ndarray, keep=()) -> np.ndarray:
        """The unposed samples (rows, n_p, 3) of the set's stretch ``x`` of a round's
        parameters, kept as ``trial``; the trials other than those in ``keep`` are dropped."""
        # the trials not kept dropped, and the kept ones' gradient data, before this one is
        # sampled: they are never held beside it
        self.trials = {k: ([block.earlier(one) for block, one in zip(self.blocks, kept)], samples)
                       for k, (kept, samples) in self.trials.items() if k in keep}
        raw = np.empty((self.n_rows, self.n_points, 3))
        located = [None] * len(self.blocks)

        def sample(indices):
            for b in indices:
                located[b] = self.blocks[b].sample(x, raw)

        self.threads.over(len(self.blocks), sample)
        self.trials[trial] = (located, raw)
        self.newest = trial
        return raw

    def gradient(self, trial: int, scale: np.ndarray, rotation: np.ndarray,
                 shape_gradient: np.ndarray) -> np.ndarray:
        """dF/d(coefficients) of the set's stretch (zero at the pose parameters) from dF/dX
        (rows, n_p, 3) of its examples at ``trial``, whose samples are posed by ``scale`` (rows,)
        and ``rotation`` (rows, 3, 3)."""
        if trial != self.newest:
            raise ArgumentError(f"the gradient is of the trial sampled last ({self.newest}), "
                                f"not of trial {trial}")
        located = self.trials[trial][0]
        result = np.zeros(self.layout.size)

        def chain(indices):
            for b in indices:
                block = self.blocks[b]
                result[block.coefficients] = block.gradient(
                    located[b], scale[block.row], rotation[block.row],
                    shape_gradient[block.row, block.rows])

        self.threads.over(len(self.blocks), chain)
        return result

    def folds(self, trial: int) -> bool:
        """Whether a grid triangle of any part turns over at ``trial``."""
        located = self.trials[trial][0]
        return any(block.folds(one) for block, one in zip(self.blocks, located))

    def commit(self, trial: int, x: np.ndarray) -> list:
        """Commit ``trial`` (sampled at ``x``) to the set's parts; returns, per part, (row, part
        index, what its ``commit`` was given), for other copies of the parts."""
        located, raw = self.trials[trial]
        settled = [None] * len(self.blocks)

        def commit(indices):
            # on the threads: a part that carries a finer grid moves it as it commits
            for b in indices:
                arguments = self.blocks[b].settled(located[b], x, raw)
                self.blocks[b].part.commit(*arguments)
                settled[b] = (*self.parts[b], arguments)

        self.threads.over(len(self.blocks), commit)
        return settled
