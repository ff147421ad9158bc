"""The fast strategy's coarse grid: the correspondence is optimised on fewer sample points per part
(``coarse_points``, 642 by default) than the model is sampled at (``points``), and its maps are
then carried over to the model's grid.

A reparameterization is a composition of maps of the sphere (warps), not a set of point
positions, so the maps found on the coarse grid apply unchanged to the model's grid. An evaluation
on the coarse grid costs about n_p(coarse) / n_p of one on the model's grid (the per-point field
sampling and chain rule, and the O(n_s^2 n_p) Gram matrix and gradient, all scale with n_p).

Eq. 14 is then the description length of the training set sampled at the coarse grid's points,
and a build reports it there (:func:`coarse_view` of the initial and of the final state). On the
model's grid its value differs: the smallest of the n_s - 1 modes there also hold the variation
between the coarse points, which the optimisation does not see and which eq. 14's log terms
weigh heavily when n_s is large. Measured (docs/benchmarks.md), a further phase on the model's
grid lowers eq. 14 there without changing generalization or specificity, so there is none.
"""

from __future__ import annotations

import numpy as np

from ..errors import ArgumentError
from ..parallel import Threads
from .sampling import sphere_grid
from .state import CorrespondenceState, Example, FixedExample


def coarse_grid_applies(state: CorrespondenceState, n_points: int) -> bool:
    """Whether a coarse stage of ``n_points`` points per part can run on ``state``: every example
    has sphere parts to reparameterize (not given correspondences, not curves) and every part's
    grid has more than ``n_points`` points."""
    return (n_points > 0 and state.n_shapes > 0
            and all(isinstance(example, Example) and example.parts
                    and all(part.kind == "sphere" for part in example.parts)
                    for example in state.examples)
            and all(len(points) > n_points for points, _ in state.grids))


def coarse_view(state: CorrespondenceState, n_points: int,
                carry: bool = False) -> CorrespondenceState:
    """The same correspondence sampled at ``n_points`` per part (:func:`.sampling.sphere_grid`),
    with the same poses, rebuilt (area weights of the coarse grid, rescaled to ``state``'s target
    size): eq. 14 of the view is eq. 14 of ``state`` on the coarse grid.

    Sphere parts are resampled with their warps (they share the surfaces, sphere maps and
    locators of ``state``'s); a part that keeps no warps, only its positions, is sampled at the
    first of them (:meth:`~.state.PartState.take_first_positions`). An example whose
    correspondence is given (:class:`FixedExample`, e.g. the CPD baseline's) keeps the points of
    each part where its grid starts with the coarse grid (nested icospheres: 642 in 2562);
    raises ValueError where it does not. The landmark guides carry over where their sample
    points are among the coarse grid's (ValueError else).

    ``carry``: the view is to be optimised and carried over (:func:`carry_over`); where every
    grid of ``state`` starts with the coarse grid, each view part moves its part's grid along
    (:meth:`~.state.PartState.carry`) and keeps no warps."""
    grid, cells = sphere_grid(n_points)
    carry = carry and all(len(points) > n_points and np.array_equal(points[:n_points], grid)
                          for points, _ in state.grids)
    examples = []
    for example in state.examples:
        if isinstance(example, FixedExample):
            if not all(len(points) >= n_points and np.array_equal(points[:n_points], grid)
                       for points, _ in state.grids):
                raise ArgumentError(f"the grid of {n_points} points is not the first points of "
                                 "the state's grids: a given correspondence has no samples there")
            points = np.concatenate([example.points[part][:n_points]
                                     for part in state.part_slices])
            examples.append(FixedExample(example.name, points))
        else:
            parts = [part.on_grid(grid, cells) for part in example.parts]
            if carry:
                for view, part in zip(parts, example.parts):
                    view.carry(part)
            examples.append(Example(example.name, parts))
    guides = None
    if state.guides is not None:     # the guided points are among the coarse grid's
        guides = state.guides.on_rows(np.concatenate([np.arange(part.start, part.start + n_points)
                                                      for part in state.part_slices]))
    coarse = CorrespondenceState(examples, [(grid, cells)] * len(state.grids), state.objective,
                                 scaling=state.scaling, planar=state.planar, guides=guides,
                                 smoothness=state.smoothness)
    coarse.target_size = state.target_size
    for view, example in zip(coarse.examples, state.examples):
        view.pose = example.pose.copy()
    coarse.rebuild()
    coarse.evaluations = state.evaluations
    return coarse


def carry_over(coarse: CorrespondenceState, state: CorrespondenceState,
               threads: Threads | None = None) -> int:
    """Give ``state`` the correspondence of its :func:`coarse_view`: every example's pose and
    every part's map on ``state``'s grid (the positions the view's part carried along,
    :meth:`~.state.PartState.take_carried`, or its warps re-applied,
    :meth:`~.state.PartState.replay_unfolded`), then rebuild it. Returns how many warps were
    left out because they turned a triangle of the finer grid over (none, in practice: a finer
    grid resolves a map better)."""
    jobs = [(i, j) for i, example in enumerate(state.examples) for j in range(len(example.parts))]
    dropped = [0] * len(jobs)

    def replay(indices):
        for k in indices:
            i, j = jobs[k]
            source, part = coarse.examples[i].parts[j], state.examples[i].parts[j]
            if source.carried is not None:
                dropped[k] = part.take_carried(source.carried)
            else:
                dropped[k] = len(source.warps) - part.replay_unfolded(source.warps)

    (threads or Threads(1)).over(len(jobs), replay)
    for example, source in zip(state.examples, coarse.examples):
        example.pose = source.pose.copy()
    state.evaluations = coarse.evaluations
    state.rebuild()
    return sum(dropped)
