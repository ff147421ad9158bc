"""Coarse to fine in sample points: the fast strategy's first stage optimises the correspondence
on a coarser grid of sample points on the same surfaces, then carries its maps over to the build's
grid and finishes there.

A reparameterization is a composition of maps of the sphere (warps), not a set of point
positions, so the maps found on the coarse grid apply unchanged to the build's grid. An evaluation
on the coarse grid costs about n_p(coarse) / n_p of one on the build's grid (the per-point field
sampling and chain rule, and the O(n_s^2 n_p) Gram matrix and gradient, all scale with n_p).
The description length on the coarse grid approximates the one on the build's grid (the area
weights of eq. 17 make both integrals over the mean surface), so the large-scale part of the
search is done there and the build's grid only refines it.
"""

from __future__ import annotations

from ..parallel import Threads
from .sampling import sphere_grid
from .state import CorrespondenceState, Example


def coarse_grid_applies(state: CorrespondenceState, n_points: int) -> bool:
    """Whether a coarse stage of ``n_points`` points per part can run on ``state``: every example
    has sphere parts to reparameterize (not given correspondences, not curves) and every part's
    grid has more than ``n_points`` points."""
    return (n_points > 0 and state.n_shapes > 0
            and all(isinstance(example, Example) and example.parts
                    and all(part.kind == "sphere" for part in example.parts)
                    for example in state.examples)
            and all(len(points) > n_points for points, _ in state.grids))


def coarse_view(state: CorrespondenceState, n_points: int) -> CorrespondenceState:
    """The same examples sampled at ``n_points`` per part (:func:`.sampling.sphere_grid`), with
    their current warps, aligned afresh (Procrustes) and rescaled to ``state``'s target size.
    The parts share the surfaces, sphere maps and locators of ``state``'s."""
    grid, cells = sphere_grid(n_points)
    examples = [Example(example.name, [part.on_grid(grid, cells) for part in example.parts])
                for example in state.examples]
    coarse = CorrespondenceState(examples, [(grid, cells)] * len(state.grids), state.objective,
                                 scaling=state.scaling, planar=state.planar)
    coarse.target_size = state.target_size
    coarse.rebuild()
    coarse.evaluations = state.evaluations
    return coarse


def carry_over(coarse: CorrespondenceState, state: CorrespondenceState,
               threads: Threads | None = None) -> int:
    """Give ``state`` the correspondence of its :func:`coarse_view`: every example's pose and
    every part's warps (re-applied to ``state``'s grid, :meth:`~.state.PartState.replay_unfolded`),
    then rebuild it. Returns how many warps were left out because they turned a triangle of the
    finer grid over (none, in practice: a finer grid resolves a map better)."""
    jobs = [(i, j) for i, example in enumerate(state.examples) for j in range(len(example.parts))]
    dropped = [0] * len(jobs)

    def replay(indices):
        for k in indices:
            i, j = jobs[k]
            warps = coarse.examples[i].parts[j].warps
            dropped[k] = len(warps) - state.examples[i].parts[j].replay_unfolded(warps)

    (threads or Threads(1)).over(len(jobs), replay)
    for example, source in zip(state.examples, coarse.examples):
        example.pose = source.pose.copy()
    state.evaluations = coarse.evaluations
    state.rebuild()
    return sum(dropped)
